"""Fly over a scene in a notebook: ``scene.widget()`` (``pip install 'lodscape[jupyter]'``).

The kernel renders headlessly (the scene's own EGL context) and sends each picture to the
browser as JPEG; the browser sends back what the user does: the keys held (W/S forward and
back, A/D sideways, Q/E down and up, arrows turn and tilt, as in ``lodscape view``), mouse drags
(look around) and the wheel (speed). The browser asks for the next picture only when the last
has come, so a slow kernel drops input rate, never piles up frames.

    w = scene.widget(width=640, height=400)
    w                       # in a cell: the view; click it, then fly
    w.fly(["w"], dt=2.0)    # the same from Python: two seconds forward
    w.camera, w.picture     # where it is, and the last Picture (RGB, distance)
"""

from __future__ import annotations

import io
import math
import threading
from collections.abc import Iterable
from typing import Any

import anywidget
import numpy as np
import traitlets

from lodscape.errors import CameraError, LodscapeError
from lodscape.lod.camera import Camera
from lodscape.view import Motion, faster, fly_step, look

__all__ = ["SceneWidget"]

_ESM = """
function render({ model, el }) {
  const img = document.createElement("img");
  img.tabIndex = 0;
  img.draggable = false;
  img.className = "lodscape-view";
  const bar = document.createElement("div");
  bar.className = "lodscape-status";
  el.append(img, bar);
  let url = null;
  let busy = false;
  const show = () => {
    const data = model.get("frame");  // a DataView over the message's buffer
    if (data && data.byteLength) {
      const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
      const blob = new Blob([bytes], { type: "image/jpeg" });
      if (url) URL.revokeObjectURL(url);
      url = URL.createObjectURL(blob);
      img.src = url;
    }
    bar.textContent = model.get("status");
  };
  model.on("change:frame", show);
  model.on("change:status", show);
  model.on("change:frame_id", () => { busy = false; });
  show();
  const flying = new Set(["w", "a", "s", "d", "q", "e",
    "arrowleft", "arrowright", "arrowup", "arrowdown"]);
  const held = new Set();
  let dx = 0, dy = 0, wheel = 0, dragging = false;
  let last = performance.now();
  img.addEventListener("keydown", (e) => {
    const k = e.key.toLowerCase();
    if (flying.has(k)) { held.add(k); e.preventDefault(); }
  });
  img.addEventListener("keyup", (e) => { held.delete(e.key.toLowerCase()); });
  img.addEventListener("blur", () => held.clear());
  img.addEventListener("mousedown", (e) => { dragging = true; img.focus(); e.preventDefault(); });
  window.addEventListener("mouseup", () => { dragging = false; });
  img.addEventListener("mousemove", (e) => {
    if (dragging) { dx += e.movementX; dy += e.movementY; }
  });
  img.addEventListener("wheel", (e) => { wheel += -Math.sign(e.deltaY); e.preventDefault(); },
    { passive: false });
  const tick = () => {
    const now = performance.now();
    if (busy) return;
    if (held.size === 0 && dx === 0 && dy === 0 && wheel === 0) { last = now; return; }
    model.send({ type: "input", keys: [...held], dt: Math.min((now - last) / 1000, 0.25),
                 dx: dx, dy: dy, wheel: wheel });
    busy = true;
    last = now;
    dx = 0; dy = 0; wheel = 0;
  };
  const timer = setInterval(tick, 33);
  return () => { clearInterval(timer); if (url) URL.revokeObjectURL(url); };
}
export default { render };
"""

_CSS = """
.lodscape-view { display: block; cursor: grab; outline: none; }
.lodscape-view:focus { box-shadow: 0 0 0 2px #4a90d9; }
.lodscape-status { font: 12px monospace; color: #555; padding: 2px 0; }
"""


class SceneWidget(anywidget.AnyWidget):  # type: ignore[misc]
    """A scene's view in a notebook cell that the user flies through (see the module)."""

    _esm = _ESM
    _css = _CSS
    #: The current picture, JPEG.
    frame = traitlets.Bytes(b"").tag(sync=True)
    #: Counts pictures sent (the browser's cue to send its next input).
    frame_id = traitlets.Int(0).tag(sync=True)
    #: One line under the picture: where the camera is, the speed, the frame's figures.
    status = traitlets.Unicode("").tag(sync=True)
    #: Metres per second of a held key (the wheel: ×1.25 a notch).
    speed = traitlets.Float(100.0)

    def __init__(
        self,
        scene: Any,
        camera: Camera | None = None,
        *,
        width: int = 640,
        height: int = 400,
        quality: int = 85,
    ) -> None:
        super().__init__()
        if width < 1 or height < 1:
            raise ValueError(f"Expected a positive size, got {width}x{height}")
        self.scene = scene
        if camera is None:
            camera = scene.default_camera(width, height)
        self._camera = camera.moved(width=width, height=height)
        self.quality = int(quality)
        self.picture: Any = None
        ground = scene.ground_height(self._camera.lon, self._camera.lat)
        self.speed = max(self._camera.alt - (ground if ground is not None else 0.0), 20.0)
        #: One input (or draw) at a time, whichever thread a message comes on.
        self._lock = threading.RLock()
        self.on_msg(self._on_msg)
        self.draw()

    @property
    def camera(self) -> Camera:
        return self._camera

    @camera.setter
    def camera(self, camera: Camera) -> None:
        self._camera = camera.moved(width=self._camera.width, height=self._camera.height)
        self.draw()

    def fly(
        self,
        keys: Iterable[str] = (),
        dt: float = 0.1,
        dx: float = 0.0,
        dy: float = 0.0,
        wheel: float = 0.0,
    ) -> Camera:
        """What the browser sends, from Python: ``keys`` held for ``dt`` seconds (browser key
        names: "w", "ArrowLeft"…), a drag of (dx, dy) pixels, ``wheel`` notches; then draw."""
        if not 0.0 <= dt <= 10.0:
            raise ValueError(f"Expected 0 <= dt <= 10 seconds, got {dt}")
        with self._lock:
            self.speed = faster(self.speed, wheel)
            cam = look(self._camera, dx, dy) if dx or dy else self._camera
            self._camera = fly_step(
                cam, Motion.of_keys(keys), self.speed, dt, self.scene.ground_height
            )
            self.draw()
            return self._camera

    def draw(self) -> None:
        """Render the camera and send the picture (and the status line) to the browser (the
        scene's GL work on its own thread: any thread may call this)."""
        with self._lock:
            self._draw()

    def _draw(self) -> None:
        from PIL import Image

        message = ""
        try:
            try:
                pic = self.scene.show(self._camera)
            except CameraError:
                # under the ground (the viewer does the same): lift and try once more
                ground = self.scene.ground_height(self._camera.lon, self._camera.lat)
                self._camera = self._camera.moved(alt=(ground or 0.0) + 50.0)
                pic = self.scene.show(self._camera)
        except LodscapeError as exc:
            message = f"  ! {exc}"
        else:
            self.picture = pic
            buf = io.BytesIO()
            Image.fromarray(np.ascontiguousarray(pic.rgb), "RGB").save(
                buf, "JPEG", quality=self.quality
            )
            self.frame = buf.getvalue()
        c = self._camera
        self.status = (
            f"lon {c.lon:.5f} lat {c.lat:.5f} alt {c.alt:,.0f} m  heading {c.heading:.0f}° "
            f"pitch {c.pitch:.0f}°  speed {self.speed:,.0f} m/s{message}"
        )
        self.frame_id += 1

    def _on_msg(self, _widget: Any, content: Any, _buffers: Any) -> None:
        if not isinstance(content, dict) or content.get("type") != "input":
            return
        try:
            keys = [str(k) for k in content.get("keys", [])]
            dt, dx, dy, wheel = (float(content.get(k, 0.0)) for k in ("dt", "dx", "dy", "wheel"))
            ok = all(math.isfinite(v) for v in (dt, dx, dy, wheel))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            self.frame_id += 1  # a malformed message: release the browser, draw nothing
            return
        self.fly(keys, min(max(dt, 0.0), 0.25), dx, dy, wheel)
