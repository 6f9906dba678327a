"""A frame's target: colour, view distance and depth of one size (made again when the size
changes), its label twin for datasets, and how the picture comes back: at once, through a ring
of pixel-pack buffers a frame or more later, or not at all (a window shows the target).

A frame that comes back is drawn upside down in clip space (``TopDownCamera``), so the GL's rows
are the picture's, top first: the read-back lands in the array returned as it is, with no flip
on the CPU (on a GPU the flip's two copies and the driver's allocations were most of a 1080p
frame). A window's frames keep the GL's own orientation (it shows the target)."""

from __future__ import annotations

import collections
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, Protocol, TypeVar

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.lod.camera import Camera
from lodscape.render import labels

__all__ = ["FrameTarget", "GLObject", "TopDownCamera", "as_rgb", "clip_y"]

Rgb = tuple[float, float, float]
_ALL = (True, True, True, True)
_NONE = (False, False, False, False)


@dataclass(frozen=True)
class TopDownCamera(Camera):
    """A camera whose clip space is upside down (y negated): what a frame that is read back is
    drawn with, so that the GL's first row is the picture's top. Everything drawn through
    ``view_projection`` follows; what works from window coordinates (``gl_FragCoord``) takes
    ``clip_y``'s sign, and the front faces are clockwise (``FrameTarget.begin``)."""

    def projection(self) -> NDArray[np.float64]:
        p = super().projection()
        p[1] = -p[1]
        return p


def clip_y(camera: Camera) -> float:
    """-1 where ``camera`` draws upside down in clip space (a frame read back), else 1."""
    return -1.0 if isinstance(camera, TopDownCamera) else 1.0


class GLObject(Protocol):
    """What a renderer frees: any moderngl object."""

    def release(self) -> None: ...


_T = TypeVar("_T", bound=GLObject)


class _Track(Protocol):
    """Counts a GL object made (the renderer's ``live_objects``) and hands it back."""

    def __call__(self, obj: _T) -> _T: ...


@dataclass(eq=False)
class _Target:
    size: tuple[int, int]
    color: moderngl.Renderbuffer
    dist: moderngl.Renderbuffer | moderngl.Texture
    depth: moderngl.Renderbuffer
    fbo: moderngl.Framebuffer
    #: The colour attachment alone (what a window's framebuffer can be copied from).
    colour_fbo: moderngl.Framebuffer | None = None


class FrameTarget:
    """Where a renderer's frames are drawn (``frame.Target``'s GL side). GL objects are made
    and freed through ``track`` and ``free`` (the renderer's count), on the thread ``use``
    checks."""

    def __init__(
        self,
        ctx: moderngl.Context,
        track: _Track,
        free: Callable[[GLObject], None],
        use: Callable[[], None],
        *,
        background: Rgb,
        log_depth: bool,
    ) -> None:
        self.ctx = ctx
        self._track = track
        self._free = free
        self._use = use
        #: The clear colour where nothing is drawn.
        self.background = background
        #: A frame with the globe: the terrain scene's pixels are marked by their alpha (1).
        self.log_depth = log_depth
        self._target: _Target | None = None
        self._labels_target: _Target | None = None
        #: False: ``draw`` leaves the picture in ``framebuffer`` and returns empty arrays.
        self.read_back = True
        #: False: ``draw`` reads the picture only, and returns an empty (0, 0) distance.
        self.read_depth = True
        #: N > 0: the picture is read into a ring of N pixel-pack buffers, and ``draw`` returns
        #: the one read N - 1 frames before (empty until then; ``drain`` gives the rest), so
        #: the GL may copy frame N while the next renders (paper 001's triple buffering).
        self.ring = 0
        self._ring: collections.deque[tuple[moderngl.Buffer, int, int]] = collections.deque()
        self._ring_free: list[tuple[moderngl.Buffer, int]] = []
        #: The frame begun draws upside down in clip space (it is read back: ``TopDownCamera``).
        self.flipped = False
        #: The last camera ``camera`` turned upside down, and what it made (each pass asks).
        self._top_down: tuple[Camera, TopDownCamera] | None = None
        #: Log-depth frames: pixels of the last picture read back that the terrain and the
        #: city drew (the globe's have alpha 0); through the read ring, of the picture that
        #: came back.
        self.covered = 0

    def fbo(self, labelled: bool = False) -> moderngl.Framebuffer:
        """The framebuffer of the frame begun (its label twin with ``labelled``)."""
        got = self.label_framebuffer if labelled else self.framebuffer
        if got is None:
            raise RuntimeError("no frame begun")
        return got

    @property
    def framebuffer(self) -> moderngl.Framebuffer | None:
        """The last frame's colour + distance target."""
        return None if self._target is None else self._target.fbo

    @property
    def label_framebuffer(self) -> moderngl.Framebuffer | None:
        """The label pass's target (normals and labels, distance), once it was begun."""
        return None if self._labels_target is None else self._labels_target.fbo

    @property
    def colour_framebuffer(self) -> moderngl.Framebuffer | None:
        """The last frame's colour alone, as a framebuffer a window's can be copied from."""
        t = self._target
        if t is None:
            return None
        if t.colour_fbo is None:
            t.colour_fbo = self._track(self.ctx.framebuffer([t.color]))
        return t.colour_fbo

    @property
    def attachments(self) -> tuple[moderngl.Renderbuffer, moderngl.Texture]:
        """The colour attachment and the distance texture of the frame being drawn (what a
        pass drawn before the terrain works with)."""
        t = self._target
        if t is None or not isinstance(t.dist, moderngl.Texture):
            raise RuntimeError("no frame target yet")
        return t.color, t.dist

    def begin(
        self, camera: Camera, *, background: Rgb | None = None, labelled: bool = False
    ) -> moderngl.Framebuffer:
        """Start a frame of ``camera``'s size: the target cleared to ``background`` (the
        target's own when None), its distance to +inf; the target's framebuffer, bound."""
        self._use()
        # a frame read back is drawn top row first (no flip on the CPU); the winding follows
        self.flipped = labelled or self.read_back
        self.ctx.front_face = "cw" if self.flipped else "ccw"
        if labelled:
            fbo = self._label_target_for(camera.width, camera.height)
            bg: tuple[float, float, float, float] = (0.0, 0.0, 0.0, float(labels.SKY))
        else:
            fbo = self._target_for(camera.width, camera.height).fbo
            # a frame with the globe marks the terrain scene's pixels by their alpha (1)
            alpha = 0.0 if self.log_depth else 1.0
            bg = (*(self.background if background is None else as_rgb(background)), alpha)
        fbo.use()
        # glClear writes one value to every colour attachment: mask each in turn instead
        # (the stubs type color_mask for one attachment; moderngl takes one mask per attachment)
        fbo.color_mask = (_ALL, _NONE)  # type: ignore[assignment]
        fbo.clear(*bg, depth=1.0)
        fbo.color_mask = (_NONE, _ALL)  # type: ignore[assignment]
        fbo.clear(float("inf"), 0.0, 0.0, 0.0)
        fbo.color_mask = (_ALL, _ALL)  # type: ignore[assignment]
        return fbo

    def end(
        self, camera: Camera, labelled: bool = False
    ) -> tuple[NDArray[Any], NDArray[np.float32]]:
        """End the frame: its picture and distance read back (once; into the read ring when
        ``ring``; not at all when ``read_back`` is off, a window showing the target)."""
        self._use()
        fbo = self.fbo(labelled)
        self.ctx.wireframe = False
        self.ctx.front_face = "ccw"
        h, w = camera.height, camera.width
        if labelled:
            got = np.empty((h, w, 4), np.float32)
            fbo.read_into(got, components=4, attachment=0, dtype="f4")
            return got, self._read_dist(fbo, h, w)
        if not self.read_back:
            # a window shows the framebuffer itself (``framebuffer``): nothing comes back
            return np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), np.float32)

        no_depth = np.zeros((0, 0), np.float32)
        if self.ring > 0:
            self._ring.append((self._pack(fbo, w, h), w, h))
            late = self.drain(keep=self.ring - 1)
            return (late[0] if late else np.zeros((0, 0, 3), np.uint8)), no_depth
        # the rows come top first (``begin``): read straight into the arrays returned
        if self.log_depth:
            # the same read with the alpha: the pixels the terrain scene drew, globe aside
            rgba = np.empty((h, w, 4), np.uint8)
            fbo.read_into(rgba, components=4, attachment=0, alignment=1)
            self.covered = int(np.count_nonzero(rgba[..., 3] > 127))
            rgb = np.ascontiguousarray(rgba[..., :3])
        else:
            rgb = np.empty((h, w, 3), np.uint8)
            fbo.read_into(rgb, components=3, attachment=0, alignment=1)
        if not self.read_depth:
            return rgb, no_depth
        return rgb, self._read_dist(fbo, h, w)

    @staticmethod
    def _read_dist(fbo: moderngl.Framebuffer, h: int, w: int) -> NDArray[np.float32]:
        dist = np.empty((h, w), np.float32)
        fbo.read_into(dist, components=1, attachment=1, alignment=1, dtype="f4")
        return dist

    def camera(self, camera: Camera) -> Camera:
        """``camera`` as the frame begun draws it: upside down in clip space where it is read
        back (``TopDownCamera``), as it is in a window's frame."""
        if not self.flipped or isinstance(camera, TopDownCamera):
            return camera
        made = self._top_down
        if made is None or made[0] is not camera:
            top = camera.posed_as(
                TopDownCamera(**{f.name: getattr(camera, f.name) for f in fields(camera)})
            )
            self._top_down = made = (camera, top)
        return made[1]

    @property
    def pending(self) -> int:
        """Pictures in the read ring not yet returned."""
        return len(self._ring)

    def drain(self, keep: int = 0) -> list[NDArray[np.uint8]]:
        """The pictures still in the read ring, oldest first, leaving the newest ``keep``."""
        out = []
        n = self._components
        while len(self._ring) > keep:
            buf, w, h = self._ring.popleft()
            got = np.empty((h, w, n), np.uint8)  # top row first (``begin``)
            buf.read_into(got)
            if n == 4:  # the terrain scene's pixels of the picture that comes back
                self.covered = int(np.count_nonzero(got[..., 3] > 127))
            out.append(np.ascontiguousarray(got[..., :3]))
            self._ring_free.append((buf, w * h * n))
        return out

    @property
    def _components(self) -> int:
        """Read-backs take the alpha too in log-depth frames (it marks the terrain's pixels)."""
        return 4 if self.log_depth else 3

    def _pack(self, fbo: moderngl.Framebuffer, w: int, h: int) -> moderngl.Buffer:
        """Start reading the picture into a pixel-pack buffer (the GL copies asynchronously)."""
        size = w * h * self._components
        for buf, n in [e for e in self._ring_free if e[1] != size]:
            self._ring_free.remove((buf, n))
            self._free(buf)
        if self._ring_free:
            buf, _ = self._ring_free.pop()
        else:
            buf = self._track(self.ctx.buffer(reserve=size))
        fbo.read_into(buf, components=self._components, attachment=0, alignment=1)
        return buf

    # --- lifetime ---------------------------------------------------------------------------

    def _target_for(self, width: int, height: int) -> _Target:
        target = self._target
        if target is not None and target.size == (width, height):
            return target
        if target is not None:
            self._free_target(target)
        size = (width, height)
        color = self._track(self.ctx.renderbuffer(size, 4))
        # a texture: a pass drawn after another may read the distances it left (the globe's
        # imagery reads the globe's)
        dist = self._track(self.ctx.texture(size, 1, dtype="f4"))
        dist.filter = (moderngl.NEAREST, moderngl.NEAREST)
        depth = self._track(self.ctx.depth_renderbuffer(size))
        fbo = self._track(self.ctx.framebuffer([color, dist], depth))
        self._target = _Target(size, color, dist, depth, fbo)
        return self._target

    def _label_target_for(self, width: int, height: int) -> moderngl.Framebuffer:
        """The label pass's target: RGBA32F (normal, label), the distance, a depth buffer."""
        got = self._labels_target
        if got is not None and got.size == (width, height):
            return got.fbo
        if got is not None:
            self._free_target(got)
        size = (width, height)
        color = self._track(self.ctx.renderbuffer(size, 4, dtype="f4"))
        dist = self._track(self.ctx.renderbuffer(size, 1, dtype="f4"))
        depth = self._track(self.ctx.depth_renderbuffer(size))
        fbo = self._track(self.ctx.framebuffer([color, dist], depth))
        self._labels_target = _Target(size, color, dist, depth, fbo)
        return fbo

    def _free_target(self, target: _Target) -> None:
        # moderngl re-binds its idea of the bound framebuffer after creating or reading objects;
        # left pointing at a deleted name that is GL_INVALID_OPERATION, so bind name 0 first
        self.ctx.detect_framebuffer(0).use()
        if target.colour_fbo is not None:
            self._free(target.colour_fbo)
        for obj in (target.fbo, target.color, target.dist, target.depth):
            self._free(obj)

    def close(self) -> None:
        """Free the targets and the read ring's buffers."""
        for target in (self._target, self._labels_target):
            if target is not None:
                self._free_target(target)
        self._target = self._labels_target = None
        for buf in [b for b, _, _ in self._ring] + [b for b, _ in self._ring_free]:
            self._free(buf)
        self._ring.clear()
        self._ring_free.clear()


def as_rgb(colour: Any) -> Rgb:
    """A colour as three floats 0..1; a ValueError for anything else."""
    values = tuple(float(c) for c in colour)
    if len(values) != 3:
        raise ValueError(f"expected an RGB colour of three numbers 0..1, got {colour!r}")
    return values[0], values[1], values[2]
