"""The globe pass (paper 002): a QTM mesh in Earth-centred coordinates, drawn relative to the
camera in float32 (the subtraction made in float64 on the CPU, so orbit and street level are
equally steady), textured from an equirectangular image by each facet's own longitudes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.frame.globe import ImageryDraw
from lodscape.lod.camera import Camera
from lodscape.lod.globe import GlobeMesh, pole_longitudes
from lodscape.render._context import make_current
from lodscape.render._depth import LOG_DEPTH_GLSL
from lodscape.render._shaders import shader

__all__ = ["GlobePass"]


_VERTEX = shader("globe_vertex.glsl")
_FRAGMENT = shader("globe_fragment.glsl").replace("LOG_DEPTH_GLSL", LOG_DEPTH_GLSL)

#: Imagery tiles over the globe (``lodscape.lod.mercator``), each a patch of the surface lifted
#: a little above it (by its cells' sag) and widened a little past its edges, so that together
#: they cover every pixel of the globe's own surface: a patch's fragment is kept where it is
#: the visible surface (no farther than the globe's at that pixel, which hides the far side of
#: the Earth and what hills hide), and where it lies inside its own tile; among patches the
#: nearest wins.
_IMAGERY_VERTEX = shader("globe_imagery_vertex.glsl")
_IMAGERY_FRAGMENT = shader("globe_imagery_fragment.glsl")


def relief_shade(p: NDArray[np.float64], latlon: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per triangle (positions ``p``, (T, 3, 3); lat/lon with the poles' longitudes set, as
    ``pole_longitudes`` gives), a hillshade factor: light from the north-west, 45° up, in the
    triangle's own east/north/up frame, relative to level ground (1 on the bare ellipsoid,
    brighter on slopes facing the light, darker away from it), so a DEM's relief shows on any
    image."""
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(n, axis=1)
    lat = np.radians(latlon[..., 0].mean(axis=1))
    lon = np.radians(latlon[..., 1].mean(axis=1))
    up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], 1)
    east = np.stack([-np.sin(lon), np.cos(lon), np.zeros_like(lon)], 1)
    north = np.cross(up, east)
    light = (-east + north) / np.sqrt(2.0) + up  # 45° up from the north-west
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm[:, None]
    n *= np.sign(np.einsum("fk,fk->f", n, up))[:, None]  # whichever way the triangle winds
    flat = np.einsum("fk,fk->f", up, light)
    out: NDArray[np.float64] = np.clip(np.einsum("fk,fk->f", n, light) / flat, 0.3, 1.4)
    return np.where(norm > 0, out, 1.0)


class GlobePass:
    """The globe's GL objects in one context (its image, the terrain's region); draws a
    ``GlobeMesh`` and the imagery over it first in a frame's target, in the logarithmic depth
    the terrain and the city of that frame share (``render._depth``). Imagery tiles are the
    target renderer's textures, loaded by the frame's one loader."""

    def __init__(self, ctx: moderngl.Context, image: NDArray[np.uint8]) -> None:
        self.ctx = ctx
        make_current(ctx)
        self.wireframe = False
        self.prog = ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        img = np.ascontiguousarray(image[::-1])  # row 0 at the bottom: v = 0 at latitude -90
        self.tex = ctx.texture((img.shape[1], img.shape[0]), 3, img.tobytes(), alignment=1)
        self.tex.build_mipmaps()
        self.tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.tex.repeat_x = True
        self.tex.repeat_y = False
        self.region: moderngl.Texture | None = None
        self.prog["u_tex"] = 0
        self.prog["u_region"] = 1
        self.prog["u_has_region"] = False
        #: The terrain's own tiles draw the region's data: the globe only fills their holes.
        self.behind_region = False
        #: The imagery patches' own depth and framebuffer over the target's colour.
        self._patch: tuple[Any, moderngl.Renderbuffer, moderngl.Framebuffer] | None = None
        self._imagery_prog = ctx.program(
            vertex_shader=_IMAGERY_VERTEX, fragment_shader=_IMAGERY_FRAGMENT
        )
        self._imagery_prog["u_tile"] = 0
        self._imagery_prog["u_dist"] = 1

    def set_region(self, image: NDArray[np.uint8], box: tuple[float, float, float, float]) -> None:
        """Drape ``image`` ((H, W, 4) RGBA, row 0 north, alpha 0 where there is no data) over
        ``box`` (west, south, east, north, degrees), over the global image."""
        if self.region is not None:
            self.region.release()
        img = np.ascontiguousarray(image[::-1])
        self.region = self.ctx.texture((img.shape[1], img.shape[0]), 4, img.tobytes(), alignment=1)
        self.region.build_mipmaps()
        self.region.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.region.repeat_x = self.region.repeat_y = False
        w, s, e, n = box
        self.prog["u_box"] = (
            (w + 180.0) / 360.0,
            (s + 90.0) / 180.0,
            (e + 180.0) / 360.0,
            (n + 90.0) / 180.0,
        )
        self.prog["u_has_region"] = True

    def draw_facets(self, camera: Camera, mesh: GlobeMesh, fbo: moderngl.Framebuffer) -> None:
        """Draw the globe's facets from ``camera`` into ``fbo`` (its colour, its distance),
        before anything else of the frame."""
        make_current(self.ctx)
        if not len(mesh.positions):  # nothing of the Earth in view: the background alone
            return
        fbo.use()
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        rel = (mesh.positions - camera.position).reshape(-1, 3).astype(np.float32)
        ll = pole_longitudes(mesh.latlon)
        lat, lon = ll[..., 0], ll[..., 1]
        uv = np.stack([(lon + 180.0) / 360.0, (lat + 90.0) / 180.0], axis=-1).reshape(-1, 2)
        shade = np.repeat(relief_shade(mesh.positions, ll), 3).astype(np.float32)[:, None]
        data = np.hstack([rel, uv.astype(np.float32), shade])
        vbo = self.ctx.buffer(np.ascontiguousarray(data, np.float32).tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "3f 2f 1f", "in_pos", "in_uv", "in_shade")])
        mvp = camera.view_projection(camera.position)
        self.prog["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))  # type: ignore[union-attr]
        self.prog["u_rot"].write(np.ascontiguousarray(camera.rotation.T, np.float32))  # type: ignore[union-attr]
        self.prog["u_behind_region"] = self.behind_region
        self.tex.use(0)
        if self.region is not None:
            self.region.use(1)
        self.ctx.wireframe = self.wireframe
        vao.render(moderngl.TRIANGLES)
        self.ctx.wireframe = False
        vao.release()
        vbo.release()

    def draw_imagery(
        self,
        camera: Camera,
        imagery: Sequence[ImageryDraw],
        colour: moderngl.Renderbuffer,
        dist: moderngl.Texture,
        texture: Callable[[int], moderngl.Texture | None],
    ) -> None:
        """The imagery layers' tiles (bottom to top) over the globe drawn in the target whose
        colour attachment is ``colour``, each patch where the globe's surface is (``dist``, as
        the facets left it), with its image ``texture(key)``."""
        make_current(self.ctx)
        patch = self._patch_fbo(colour)
        for layer in imagery:
            self._draw_imagery(camera, layer, patch, dist, texture)
        self.ctx.depth_func = "<"
        self.ctx.enable_only(moderngl.DEPTH_TEST)

    def _patch_fbo(self, colour: moderngl.Renderbuffer) -> moderngl.Framebuffer:
        """The imagery patches' framebuffer: the target's colour and a depth of their own."""
        if self._patch is not None and self._patch[0] is colour:
            return self._patch[2]
        self._release_patch()
        depth = self.ctx.depth_renderbuffer(colour.size)
        self._patch = (colour, depth, self.ctx.framebuffer([colour], depth))
        return self._patch[2]

    def _release_patch(self) -> None:
        if self._patch is not None:
            # moderngl rebinds its idea of the bound framebuffer: not a deleted one
            self.ctx.detect_framebuffer(0).use()
            self._patch[2].release()
            self._patch[1].release()
            self._patch = None

    def _draw_imagery(
        self,
        camera: Camera,
        layer: ImageryDraw,
        fbo: moderngl.Framebuffer,
        dist: moderngl.Texture,
        texture: Callable[[int], moderngl.Texture | None],
    ) -> None:
        if not layer.keys:
            return
        n = layer.n
        t = len(layer.keys)
        # two triangles a cell, as plain triangles: tile i is vertices [i·6n², (i+1)·6n²)
        grid = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
        a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()
        c, d = grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
        tri = np.stack([a, c, b, b, c, d], axis=1).ravel()
        per = tri.size
        pos = layer.positions.reshape(t, -1, 3)[:, tri].astype(np.float32)
        tt = np.broadcast_to(layer.t.reshape(-1, 2)[tri].astype(np.float32), (t, per, 2))
        sub = np.broadcast_to(layer.subs.astype(np.float32)[:, None, :], (t, per, 4))
        data = np.concatenate([pos, tt, sub], axis=2)
        vbo = self.ctx.buffer(np.ascontiguousarray(data, np.float32).tobytes())
        vao = self.ctx.vertex_array(
            self._imagery_prog, [(vbo, "3f 2f 4f", "in_pos", "in_t", "in_sub")]
        )
        fbo.use()
        fbo.color_mask = (False, False, False, False)
        fbo.clear(depth=1.0)  # the patches' own depths: the colour stays
        fbo.color_mask = (True, True, True, True)
        fbo.use()
        self.ctx.enable_only(moderngl.DEPTH_TEST | moderngl.BLEND)
        self.ctx.depth_func = "<="
        # the colour blended, the alpha (the globe's mark) kept
        self.ctx.blend_func = (  # type: ignore[assignment]
            moderngl.SRC_ALPHA,
            moderngl.ONE_MINUS_SRC_ALPHA,
            moderngl.ZERO,
            moderngl.ONE,
        )
        mvp = camera.view_projection(camera.position)
        self._imagery_prog["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))  # type: ignore[union-attr]
        self._imagery_prog["u_rot"].write(np.ascontiguousarray(camera.rotation.T, np.float32))  # type: ignore[union-attr]
        dist.use(1)
        for i, key in enumerate(layer.keys):
            tex = texture(key)
            if tex is None:  # evicted since the frame chose it: the globe shows there
                continue
            tex.use(0)
            vao.render(moderngl.TRIANGLES, vertices=per, first=i * per)
        vao.release()
        vbo.release()

    def close(self) -> None:
        make_current(self.ctx)
        if self.region is not None:
            self.region.release()
            self.region = None
        self._release_patch()
        for obj in (self.tex, self._imagery_prog, self.prog):
            obj.release()
