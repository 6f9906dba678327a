"""The interactive viewer (``lodscape view``): a window (moderngl-window on pyglet) in which the
scene streams and draws as the camera flies.

Keys: W/S forward and back, A/D sideways, Q/E down and up, arrows turn and pitch, mouse drag
looks around, the wheel sets the speed; T wireframe, L level-of-detail colours, C back-face
culling, G fractal detail (raster sources), P screenshot, K save the camera, Esc quits. A HUD
shows frames per second, tiles, triangles, resident MiB, the largest screen-space error and how
far tiles fall back.

Camera files are JSON (lon, lat, alt, heading, pitch, roll, fov_y): ``lodscape render --camera``
reads them too.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from lodscape.errors import CameraError, LodscapeError
from lodscape.lod.camera import Camera

__all__ = ["Motion", "Viewable", "faster", "fly_step", "load_camera", "look", "save_camera", "view"]

CAMERA_FIELDS = ("lon", "lat", "alt", "heading", "pitch", "roll", "fov_y")


def save_camera(path: str | Path, camera: Camera) -> None:
    """Write a camera file (JSON; atomic)."""
    p = Path(path)
    data = {k: float(getattr(camera, k)) for k in CAMERA_FIELDS}
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(p)


def load_camera(path: str | Path, width: int, height: int) -> Camera:
    """A camera file's camera at the given viewport; a one-line error names a bad file."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise LodscapeError(f"{p}: no such camera file") from None
    except (OSError, ValueError) as exc:
        raise LodscapeError(f"{p}: not a camera file ({exc})") from None
    if not isinstance(data, dict) or not all(k in data for k in ("lon", "lat", "alt")):
        raise LodscapeError(f"{p}: a camera file needs lon, lat and alt")
    try:
        kw = {k: float(data[k]) for k in CAMERA_FIELDS if k in data}
    except (TypeError, ValueError):
        raise LodscapeError(f"{p}: camera values must be numbers") from None
    return Camera(width=width, height=height, **kw)  # type: ignore[arg-type]


_HUD_VERTEX = """
#version 330
in vec2 in_pos;
out vec2 v_uv;
uniform vec4 u_rect;   // x, y, w, h in clip space
void main() {
    v_uv = vec2(in_pos.x, 1.0 - in_pos.y);
    gl_Position = vec4(u_rect.xy + in_pos * u_rect.zw, 0.0, 1.0);
}
"""
_HUD_FRAGMENT = """
#version 330
uniform sampler2D u_text;
in vec2 v_uv;
out vec4 f_color;
void main() { f_color = texture(u_text, v_uv); }
"""


class Viewable(Protocol):
    """What the window asks of what it shows: a terrain ``Scene`` and the QTM ``Globe`` both
    answer it."""

    def use_context(self, ctx: Any) -> None:
        """Draw in the window's OpenGL context (before the first frame); the frames stay in
        the renderer's target, none read back."""
        ...

    def render(self, camera: Camera) -> Any: ...

    @property
    def renderer(self) -> Any:
        """What drew the last frame: its ``colour_framebuffer``, ``wireframe`` and
        ``lod_colours``."""
        ...

    @property
    def terrain_mode(self) -> str: ...

    def ground_height(self, lon: float, lat: float) -> float | None: ...

    def hud_stats(self) -> dict[str, Any]:
        """The last frame's figures: tiles, triangles, resident_mb, max_sse_px, fallback_max."""
        ...

    def toggle_culling(self) -> bool | None:
        """Flip back-face culling; the new setting, or None where there is none."""
        ...

    def close(self) -> None: ...


@dataclass
class _State:
    camera: Camera
    speed: float
    keys: set[int] = field(default_factory=set)
    fps: float = 0.0
    frames: int = 0
    screenshots: int = 0
    message: str = ""
    message_until: float = 0.0

    def say(self, msg: str) -> None:
        self.message, self.message_until = msg, time.perf_counter() + 2.5


def _open_window(camera: Camera, title: str, gpu: bool) -> Any:
    """A pyglet window through moderngl-window (OpenGL 4.1 for the GPU terrain mode, 3.3 where
    that is refused); a one-line error where none opens."""
    import moderngl_window
    from moderngl_window.conf import settings

    settings.WINDOW["class"] = "moderngl_window.context.pyglet.Window"
    settings.WINDOW["size"] = (camera.width, camera.height)
    settings.WINDOW["title"] = title
    settings.WINDOW["vsync"] = False
    settings.WINDOW["resizable"] = True
    settings.WINDOW["gl_version"] = (4, 1) if gpu else (3, 3)
    try:
        return moderngl_window.create_window_from_settings()
    except Exception as exc:  # pyglet raises its own classes per platform
        if not gpu:
            raise LodscapeError(f"cannot open a window: {exc}") from None
    settings.WINDOW["gl_version"] = (3, 3)
    try:
        return moderngl_window.create_window_from_settings()
    except Exception as exc:
        raise LodscapeError(f"cannot open a window: {exc}") from None


class _Hud:
    """The text in the window's top left corner: a texture remade only when the text changes."""

    def __init__(self, ctx: Any) -> None:
        self.ctx = ctx
        self.prog = ctx.program(vertex_shader=_HUD_VERTEX, fragment_shader=_HUD_FRAGMENT)
        quad = ctx.buffer(np.array([0, 0, 1, 0, 0, 1, 1, 1], np.float32).tobytes())
        self.vao = ctx.vertex_array(self.prog, [(quad, "2f", "in_pos")])
        self.tex: Any = None
        self.text = ""

    def draw(self, text: str, w: int, h: int) -> None:
        import moderngl

        if text != self.text or self.tex is None:
            self.text = text
            from PIL import Image, ImageDraw

            lines = text.split("\n")
            img = Image.new(
                "RGBA", (8 * max(len(s) for s in lines) + 8, 14 * len(lines) + 6), (0, 0, 0, 140)
            )
            dr = ImageDraw.Draw(img)
            for i, line in enumerate(lines):
                dr.text((4, 3 + 14 * i), line, fill=(255, 255, 255, 255))
            if self.tex is not None:
                self.tex.release()
            self.tex = self.ctx.texture(img.size, 4, img.tobytes())
            self.tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        tw, th = self.tex.size
        rect: Any = self.prog["u_rect"]
        rect.value = (-1.0, 1.0 - 2.0 * th / h, 2.0 * tw / w, 2.0 * th / h)
        self.ctx.enable_only(moderngl.BLEND)
        self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        self.tex.use(0)
        self.vao.render(moderngl.TRIANGLE_STRIP)


def _hud_text(st: _State, scene: Viewable) -> str:
    stats = scene.hud_stats()
    text = (
        f"{st.fps:5.1f} fps  tiles {stats.get('tiles', 0)}  "
        f"triangles {int(stats.get('triangles', 0)):,}  "
        f"resident {float(stats.get('resident_mb', 0.0)):.1f} MiB  "
        f"max SSE {float(stats.get('max_sse_px', 0.0)):.2f} px  "
        f"fallback {stats.get('fallback_max', 0)}  [{scene.terrain_mode}]"
    )
    if time.perf_counter() < st.message_until:
        text += "\n" + st.message
    return text


class _Controller:
    """Keys and mouse onto the camera and the scene: the viewer's state between frames."""

    def __init__(
        self,
        window: Any,
        scenes: dict[str, Any],
        start: str,
        camera: Camera,
        screenshot_dir: Path,
        camera_file: Path | None,
    ) -> None:
        self.window = window
        self.keys = window.keys
        self.scenes = scenes
        self.active = start
        self.scene: Viewable = scenes[start]
        self.screenshot_dir = screenshot_dir
        self.camera_file = camera_file
        ground = self.scene.ground_height(camera.lon, camera.lat)
        start_agl = camera.alt - (ground if ground is not None else 0.0)
        self.st = _State(camera, speed=max(start_agl, 20.0))
        window.key_event_func = self.on_key
        window.mouse_drag_event_func = self.on_drag
        window.mouse_scroll_event_func = self.on_scroll

    def screenshot(self) -> Path:
        rend = self.scene.renderer
        fbo = rend.colour_framebuffer if rend is not None else None
        if fbo is None:
            raise LodscapeError("no frame yet")
        w, h = fbo.size
        rgb = np.frombuffer(fbo.read(components=3, attachment=0, alignment=1), np.uint8)
        rgb = rgb.reshape(h, w, 3)[::-1]
        from PIL import Image

        self.screenshot_dir.mkdir(parents=True, exist_ok=True)
        self.st.screenshots += 1
        path = self.screenshot_dir / f"lodscape-{self.st.screenshots:04d}.png"
        tmp = path.with_name(path.name + ".tmp.png")
        Image.fromarray(np.ascontiguousarray(rgb)).save(tmp)
        tmp.replace(path)
        return path

    def on_key(self, key: int, action: Any, modifiers: Any) -> None:
        keys, st = self.keys, self.st
        if action == keys.ACTION_RELEASE:
            st.keys.discard(key)
            return
        if action != keys.ACTION_PRESS:
            return
        st.keys.add(key)
        rend = self.scene.renderer
        if key == keys.ESCAPE:
            self.window.close()
        elif key == keys.P:
            st.say(f"saved {self.screenshot().name}")
        elif key == keys.K:
            if self.camera_file is None:
                st.say("no --camera-file to save to")
            else:
                save_camera(self.camera_file, st.camera)
                st.say(f"saved the camera to {self.camera_file.name}")
        elif key == keys.T and rend is not None:
            rend.wireframe = not rend.wireframe
            st.say(f"wireframe {'on' if rend.wireframe else 'off'}")
        elif key == keys.L and rend is not None:
            rend.lod_colours = not rend.lod_colours
            st.say(f"level colours {'on' if rend.lod_colours else 'off'}")
        elif key == keys.C:
            on = self.scene.toggle_culling()
            if on is not None:
                st.say(f"back-face culling {'on' if on else 'off'}")
        elif key == keys.G:
            self.switch_detail()

    def switch_detail(self) -> None:
        """The G key: the other of the plain and the fractal-detail scene, made when first
        asked for."""
        other = "detail" if self.active == "plain" else "plain"
        made = self.scenes.get(other)
        if made is None:
            self.st.say("fractal detail needs a raster source")
            return
        if callable(made):
            try:
                made = made()
            except LodscapeError as exc:
                self.scenes.pop(other)
                self.st.say(str(exc))
                return
            made.use_context(self.window.ctx)
            self.scenes[other] = made
        self.scene, self.active = made, other
        self.st.say(f"fractal detail {'on' if other == 'detail' else 'off'}")

    def on_drag(self, x: int, y: int, dx: int, dy: int) -> None:
        self.st.camera = look(self.st.camera, dx, dy)

    def on_scroll(self, x: float, y: float) -> None:
        self.st.speed = faster(self.st.speed, y)
        self.st.say(f"speed {self.st.speed:,.0f} m/s")

    def move(self, dt: float) -> None:
        k, keys = self.st.keys, self.keys
        self.st.camera = fly_step(
            self.st.camera,
            Motion(
                forward=(keys.W in k) - (keys.S in k),
                right=(keys.D in k) - (keys.A in k),
                up=(keys.E in k) - (keys.Q in k),
                turn=(keys.RIGHT in k) - (keys.LEFT in k),
                tilt=(keys.UP in k) - (keys.DOWN in k),
            ),
            self.st.speed,
            dt,
            self.scene.ground_height,
        )


#: The keys (lower-case letters, ``ArrowLeft``…) that push each way, as a browser names them.
BROWSER_KEYS: dict[str, tuple[str, int]] = {
    "w": ("forward", 1),
    "s": ("forward", -1),
    "d": ("right", 1),
    "a": ("right", -1),
    "e": ("up", 1),
    "q": ("up", -1),
    "arrowright": ("turn", 1),
    "arrowleft": ("turn", -1),
    "arrowup": ("tilt", 1),
    "arrowdown": ("tilt", -1),
}


@dataclass(frozen=True)
class Motion:
    """Which way the flying keys push, each -1, 0 or 1: W/S forward, D/A right, E/Q up,
    arrows turn right/left and tilt up/down."""

    forward: int = 0
    right: int = 0
    up: int = 0
    turn: int = 0
    tilt: int = 0

    @classmethod
    def of_keys(cls, keys: Any) -> Motion:
        """The motion of the held keys (browser names, any case; unknown keys are ignored)."""
        push = {"forward": 0, "right": 0, "up": 0, "turn": 0, "tilt": 0}
        for key in keys:
            way = BROWSER_KEYS.get(str(key).lower())
            if way is not None:
                push[way[0]] += way[1]
        return cls(**{k: max(-1, min(1, v)) for k, v in push.items()})


def look(camera: Camera, dx: float, dy: float) -> Camera:
    """A mouse drag of (dx, dy) pixels: a quarter degree of heading and pitch per pixel."""
    return camera.moved(
        heading=(camera.heading + 0.25 * dx) % 360.0,
        pitch=float(np.clip(camera.pitch - 0.25 * dy, -89.0, 89.0)),
    )


def faster(speed: float, notches: float) -> float:
    """The wheel: ×1.25 a notch, kept within 0.5 m/s .. 2,000 km/s."""
    return float(np.clip(speed * 1.25**notches, 0.5, 2e6))


def fly_step(
    camera: Camera,
    motion: Motion,
    speed: float,
    dt: float,
    ground_height: Any = None,
) -> Camera:
    """The camera after ``dt`` seconds of ``motion`` at ``speed`` m/s (turning 60°/s, tilting
    40°/s), kept 2 m above ``ground_height(lon, lat)``, or above the ellipsoid where that
    gives none."""
    c = camera
    h, p = math.radians(c.heading), math.radians(c.pitch)
    fwd = np.array([math.sin(h) * math.cos(p), math.cos(h) * math.cos(p), math.sin(p)])
    right = np.array([math.cos(h), -math.sin(h), 0.0])
    d = fwd * motion.forward + right * motion.right
    d[2] += motion.up
    step = d * speed * dt
    # east/north metres to degrees at the camera
    lat = c.lat + math.degrees(step[1] / 6_371_000.0)
    lon = c.lon + math.degrees(step[0] / (6_371_000.0 * max(math.cos(math.radians(c.lat)), 1e-6)))
    lat = float(np.clip(lat, -85.0, 85.0))
    alt = c.alt + step[2]
    if ground_height is not None:
        # outside the data the ellipsoid is drawn: kept above it too (a held key flew the
        # notebook's view 27 km under it)
        g = ground_height(lon, lat)
        alt = max(alt, (0.0 if g is None else g) + 2.0)
    return c.moved(
        lon=(lon + 180.0) % 360.0 - 180.0,
        lat=lat,
        alt=alt,
        heading=(c.heading + motion.turn * 60.0 * dt) % 360.0,
        pitch=float(np.clip(c.pitch + motion.tilt * 40.0 * dt, -89.0, 89.0)),
    )


def view(
    scenes: dict[str, Any],
    camera: Camera,
    *,
    screenshot_dir: Path,
    camera_file: Path | None = None,
    exit_after: float | None = None,
    title: str = "lodscape",
    start: str = "plain",
) -> dict[str, Any]:
    """Open a window on ``scenes[start]`` (a ``Viewable``; the other of "plain" and "detail", a
    viewable or a factory of one, is what the G key switches to) and fly until Esc, the window
    closing, or ``exit_after`` seconds. Returns what happened (frames, screenshots, the last
    camera)."""
    window = _open_window(camera, title, scenes[start].terrain_mode == "gpu")
    ctx = window.ctx
    scenes[start].use_context(ctx)
    control = _Controller(window, scenes, start, camera, screenshot_dir, camera_file)
    st = control.st
    hud = _Hud(ctx)
    started = last_t = time.perf_counter()
    fps_t, fps_n = started, 0
    error: BaseException | None = None
    try:
        while not window.is_closing:
            now = time.perf_counter()
            dt, last_t = min(now - last_t, 0.25), now
            if exit_after is not None and now - started > exit_after:
                break
            control.move(dt)
            w, h = window.buffer_size
            cam = replace(st.camera, width=max(w, 1), height=max(h, 1))
            scene = control.scene
            try:
                scene.render(cam)
            except CameraError:
                st.camera = st.camera.moved(alt=st.camera.alt + 50.0)
                continue
            rend = scene.renderer
            # a scene in the window's context reads nothing back (``use_context``)
            colour = rend.colour_framebuffer if rend is not None else None
            if colour is not None:
                ctx.copy_framebuffer(window.fbo, colour)
            window.use()
            hud.draw(_hud_text(st, scene), w, h)
            window.swap_buffers()
            st.frames += 1
            fps_n += 1
            if now - fps_t > 0.5:
                st.fps, fps_t, fps_n = fps_n / (now - fps_t), now, 0
    except BaseException as exc:
        error = exc
    finally:
        for s in scenes.values():
            if not callable(s):
                s.close()
        window.destroy()
    if error is not None:
        raise error
    return {"frames": st.frames, "screenshots": st.screenshots, "camera": st.camera}
