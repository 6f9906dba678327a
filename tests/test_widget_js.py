"""The widget's browser side (its ES module) run by Node against a stand-in DOM and model: keys
held become input messages, a next message waits for the frame, released keys stop them."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

pytest.importorskip("anywidget")

HARNESS = r"""
import mod from "./widget.mjs";
const made = [];
function element(tag) {
  const handlers = {};
  const el = {
    tag, handlers, children: [], style: {},
    addEventListener(ev, f) { (handlers[ev] ||= []).push(f); },
    append(...c) { this.children.push(...c); },
    focus() {},
    fire(ev, data) { for (const f of handlers[ev] || []) f({ preventDefault() {}, ...data }); },
  };
  made.push(el);
  return el;
}
globalThis.document = { createElement: element };
globalThis.window = { addEventListener() {} };
globalThis.URL = { createObjectURL: () => "blob:frame", revokeObjectURL() {} };
const state = { frame: new DataView(new Uint8Array([1, 2, 3]).buffer), status: "ready" };
const listeners = {};
const sent = [];
const model = {
  get: (k) => state[k],
  on: (ev, f) => (listeners[ev] ||= []).push(f),
  send: (m) => sent.push(m),
};
const el = element("div");
const stop = mod.render({ model, el });
const img = el.children[0];
const wait = (ms) => new Promise((r) => setTimeout(r, ms));
const out = {};
out.src = img.src;
img.fire("keydown", { key: "W" });
await wait(120);
out.first = sent.slice();           // one message: the frame has not come yet
for (const f of listeners["change:frame_id"]) f();
await wait(80);
out.second = sent.length;           // the frame came: the next input goes
img.fire("keyup", { key: "w" });
for (const f of listeners["change:frame_id"]) f();
await wait(120);
out.after_release = sent.length;    // nothing held, nothing moved: no message
img.fire("mousedown", {});
img.fire("mousemove", { movementX: 30, movementY: -4 });
await wait(80);
out.drag = sent[sent.length - 1];
stop();
console.log(JSON.stringify(out));
process.exit(0);
"""


def test_the_browser_side_sends_input_one_frame_at_a_time(tmp_path: Path) -> None:
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node.js is not installed")
    from lodscape.widget import _ESM

    (tmp_path / "widget.mjs").write_text(_ESM)
    (tmp_path / "harness.mjs").write_text(HARNESS)
    proc = subprocess.run(
        [node, "harness.mjs"], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["src"] == "blob:frame"
    assert len(out["first"]) == 1
    first = out["first"][0]
    assert first["type"] == "input"
    assert first["keys"] == ["w"]
    assert 0.0 <= first["dt"] <= 0.25
    assert out["second"] == 2
    assert out["after_release"] == 2
    assert out["drag"]["dx"] == 30
    assert out["drag"]["dy"] == -4
    assert out["drag"]["keys"] == []
