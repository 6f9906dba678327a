"""Notebooks: the docs notebook executed on a real kernel, and the widget driven as a browser
drives it (comm messages over the kernel's sockets)."""

from __future__ import annotations

import base64
import io
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import lodscape
from lodscape.data import sample_dem_path
from lodscape.errors import LodscapeError
from lodscape.view import Motion, fly_step, look

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("anywidget")

DOCS = Path(__file__).resolve().parent.parent / "docs" / "notebook.ipynb"


def test_the_docs_notebook_runs_on_a_real_kernel(tmp_path: Path) -> None:
    nb = nbformat.read(DOCS, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    pngs = [o.data["image/png"] for o in outputs if "image/png" in o.get("data", {})]
    assert len(pngs) == 2  # the scene, then the picture
    sizes = [Image.open(io.BytesIO(base64.b64decode(p))).size for p in pngs]
    assert sizes == [(640, 400), (640, 400)]
    views = [o for o in outputs if "application/vnd.jupyter.widget-view+json" in o.get("data", {})]
    assert len(views) == 1
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "of the view is ground" in text
    # the widget's state is saved with the notebook (a browser opening it shows the view)
    state = nb.metadata.get("widgets", {}).get("application/vnd.jupyter.widget-state+json", {})
    assert state, "the notebook keeps no widget state"


def _kernel():  # type: ignore[no-untyped-def]
    from jupyter_client.manager import start_new_kernel

    return start_new_kernel(kernel_name="python3")


def _run(kc, code: str) -> str:  # type: ignore[no-untyped-def]
    out: list[str] = []

    def hook(msg) -> None:  # type: ignore[no-untyped-def]
        if msg["msg_type"] == "stream":
            out.append(msg["content"]["text"])
        elif msg["msg_type"] == "error":
            out.append("\n".join(msg["content"]["traceback"]))

    reply = kc.execute_interactive(code, output_hook=hook, timeout=120)
    assert reply["content"]["status"] == "ok", "".join(out)
    return "".join(out)


def _updates(kc, comm_id: str, until: float) -> list[tuple[dict, list[bytes]]]:  # type: ignore[no-untyped-def]
    """The widget's state updates on iopub until one carries a new frame_id."""
    got = []
    while time.monotonic() < until:
        try:
            msg = kc.get_iopub_msg(timeout=max(until - time.monotonic(), 0.1))
        except Exception:
            break
        c = msg["content"]
        if msg["msg_type"] == "comm_msg" and c.get("comm_id") == comm_id:
            data = c["data"]
            if data.get("method") in ("update", "echo_update"):
                got.append((data, msg.get("buffers", [])))
                if "frame_id" in data["state"]:
                    return got
    return got


def test_the_widget_flies_on_what_the_browser_sends(tmp_path: Path) -> None:
    km, kc = _kernel()
    try:
        _run(
            kc,
            "import json, lodscape\n"
            "from lodscape.data import sample_dem_path\n"
            "scene = lodscape.open(sample_dem_path())\n"
            "w = scene.widget(width=320, height=200)\n"
            "display(w)\n"
            "c = w.camera\n"
            "print(json.dumps({'id': w.model_id, 'lon': c.lon, 'lat': c.lat,"
            " 'heading': c.heading, 'frame_id': w.frame_id}))\n",
        )
        first = json.loads(_run(kc, "print(json.dumps({'id': w.model_id}))"))
        comm_id = first["id"]
        before = json.loads(
            _run(kc, "c = w.camera; print(json.dumps({'lat': c.lat, 'heading': c.heading}))")
        )

        def send(content: dict) -> None:
            msg = kc.session.msg(
                "comm_msg",
                {"comm_id": comm_id, "data": {"method": "custom", "content": content}},
            )
            kc.shell_channel.send(msg)

        # the browser: W held for a quarter second, then a drag to the right
        send({"type": "input", "keys": ["w"], "dt": 0.25, "dx": 0, "dy": 0, "wheel": 0})
        ups = _updates(kc, comm_id, time.monotonic() + 60)
        assert ups
        assert "frame_id" in ups[-1][0]["state"]
        frames = [(d, b) for d, b in ups if any(p == ["frame"] for p in d.get("buffer_paths", []))]
        assert frames, "no picture came with the update"
        data, buffers = frames[-1]
        idx = next(i for i, p in enumerate(data["buffer_paths"]) if p == ["frame"])
        img = Image.open(io.BytesIO(bytes(buffers[idx])))
        assert img.format == "JPEG"
        assert img.size == (320, 200)
        send({"type": "input", "keys": [], "dt": 0.0, "dx": 80, "dy": 0, "wheel": 0})
        assert _updates(kc, comm_id, time.monotonic() + 60)
        # nonsense from a browser is answered (the browser waits for it) and moves nothing
        send({"type": "input", "keys": ["w"], "dt": "soon"})
        assert _updates(kc, comm_id, time.monotonic() + 60)
        after = json.loads(
            _run(
                kc,
                "c = w.camera; print(json.dumps({'lat': c.lat, 'heading': c.heading,"
                " 'frame_id': w.frame_id}))",
            )
        )
    finally:
        kc.stop_channels()
        km.shutdown_kernel(now=True)
    # the overview looks north: forward is north, and the drag turned 80 px x 0.25°
    assert after["lat"] > before["lat"]
    assert math.isclose((after["heading"] - before["heading"]) % 360.0, 20.0, abs_tol=1e-6)
    assert after["frame_id"] == 4


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    s = lodscape.open(sample_dem_path())
    yield s
    s.close()


def test_the_widget_from_python_moves_as_the_viewer_does(scene) -> None:  # type: ignore[no-untyped-def]
    w = scene.widget(width=200, height=120)
    start = w.camera
    assert (start.width, start.height) == (200, 120)
    assert Image.open(io.BytesIO(w.frame)).size == (200, 120)
    cam = w.fly(["W", "ArrowLeft"], dt=0.2, dx=10, dy=-4, wheel=1)
    want = fly_step(
        look(start, 10, -4),
        Motion(forward=1, turn=-1),
        w.speed,
        0.2,
        scene.ground_height,
    )
    assert cam == want
    np.testing.assert_array_equal(w.picture.rgb, scene.render(cam)[0])
    assert w.frame_id == 2
    assert "speed" in w.status
    # opposite keys cancel; unknown keys are ignored
    assert Motion.of_keys(["w", "s", "x", "Enter"]) == Motion()
    with pytest.raises(ValueError, match="dt"):
        w.fly(["w"], dt=-1.0)


def test_a_scene_without_the_extra_says_what_to_install(scene, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setitem(sys.modules, "anywidget", None)
    monkeypatch.delitem(sys.modules, "lodscape.widget", raising=False)
    with pytest.raises(LodscapeError, match=r"lodscape\[jupyter\]"):
        scene.widget()


def test_comm_messages_from_other_threads_draw(scene) -> None:  # type: ignore[no-untyped-def]
    """ipykernel 7 hands comm messages to the widget on another thread than the cell's that
    drew the first frame; the scene's GL work goes to its own thread, so every message draws
    (it raised "a Renderer must be used from the thread that created it" and the view froze,
    with no error shown). Two threads at once, as a key held while the cell runs on."""
    import threading

    w = scene.widget(width=160, height=100)
    first = w.frame
    errors: list[BaseException] = []

    def send(keys: list[str], n: int) -> None:
        try:
            for _ in range(n):
                w._on_msg(w, {"type": "input", "keys": keys, "dt": 0.05}, [])
        except BaseException as exc:
            errors.append(exc)

    threads = [
        threading.Thread(target=send, args=(["w"], 4)),
        threading.Thread(target=send, args=(["ArrowLeft"], 4)),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    assert w.frame_id == 1 + 8  # the first frame and one per message
    assert "!" not in w.status
    assert w.frame != first
    # and the cell's thread still renders the same scene
    rgb, _ = scene.render(w.camera)
    np.testing.assert_array_equal(rgb, w.picture.rgb)
