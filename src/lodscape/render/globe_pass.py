"""The globe pass (paper 002): a QTM mesh in Earth-centred coordinates, drawn relative to the
camera in float32 (the subtraction made in float64 on the CPU, so orbit and street level are
equally steady), textured from an equirectangular image by each facet's own longitudes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.lod.camera import Camera
from lodscape.lod.globe import GlobeMesh, pole_longitudes
from lodscape.render._context import create_context, make_current

__all__ = ["GlobeRenderer", "ImageryDraw"]


@dataclass(frozen=True)
class ImageryDraw:
    """One imagery layer's tiles for a frame: per tile, its patch (positions relative to the
    camera, (T, V, 3), V = (n+1)² points of an n × n grid, rows north to south), where those
    points are in the tile ((V, 2), 0..1 with the patch's margin beyond), the texture key it is
    drawn with (its own or an ancestor's) and where in that image it lies ((T, 4): u0, v0,
    du, dv)."""

    positions: NDArray[np.float64]
    t: NDArray[np.float64]
    keys: list[int]
    subs: NDArray[np.float64]
    n: int


_VERTEX = """
#version 330
uniform mat4 u_mvp;     // projection · view for positions relative to the camera
uniform mat3 u_rot;
in vec3 in_pos;
in vec2 in_uv;
in float in_shade;
out vec2 v_uv;
out float v_dist;
out float v_shade;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_uv = in_uv;
    v_dist = -(u_rot * in_pos).z;
    v_shade = in_shade;
}
"""
_FRAGMENT = """
#version 330
uniform sampler2D u_tex;
uniform sampler2D u_region;  // the terrain's own imagery over its box (alpha 0: no data)
uniform vec4 u_box;          // the box in u_tex's coordinates: u0, v0, u1, v1
uniform bool u_has_region;
uniform bool u_mark_region;  // the view distance negated where the region has data
in vec2 v_uv;
in float v_dist;
in float v_shade;
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_dist;
void main() {
    vec3 rgb = min(texture(u_tex, v_uv).rgb * v_shade, vec3(1.0));
    float covered = 0.0;
    if (u_has_region) {
        // a facet's own longitudes may run past ±180: try the box a turn either way too
        for (int k = -1; k <= 1; k++) {
            vec2 uv = (v_uv + vec2(float(k), 0.0) - u_box.xy) / (u_box.zw - u_box.xy);
            if (all(greaterThanEqual(uv, vec2(0.0))) && all(lessThanEqual(uv, vec2(1.0)))) {
                vec4 r = texture(u_region, uv);
                rgb = mix(rgb, r.rgb, r.a);  // its tint carries its own hillshade
                covered = max(covered, r.a);
            }
        }
    }
    f_color = vec4(rgb, 1.0);
    f_dist = (u_mark_region && covered > 0.5) ? -v_dist : v_dist;
}
"""

#: Imagery tiles over the globe (``lodscape.lod.mercator``), each a patch of the surface lifted
#: a little above it (by its cells' sag) and widened a little past its edges, so that together
#: they cover every pixel of the globe's own surface: a patch's fragment is kept where it is
#: the visible surface (no farther than the globe's at that pixel, which hides the far side of
#: the Earth and what hills hide), and where it lies inside its own tile; among patches the
#: nearest wins.
_IMAGERY_VERTEX = """
#version 330
uniform mat4 u_mvp;
uniform mat3 u_rot;
in vec3 in_pos;
in vec2 in_t;     // where the point is in its tile: 0..1 west to east, north to south
in vec4 in_sub;   // where the tile lies in the image drawn: u0, v0, du, dv
out vec2 v_t;
out float v_dist;
flat out vec4 v_sub;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_t = in_t;
    v_dist = -(u_rot * in_pos).z;
    v_sub = in_sub;
}
"""
_IMAGERY_FRAGMENT = """
#version 330
uniform sampler2D u_tile;
uniform sampler2D u_dist;   // the globe pass's view distance per pixel (negated: its data)
in vec2 v_t;
in float v_dist;
flat in vec4 v_sub;
out vec4 f_color;
void main() {
    float g = abs(texelFetch(u_dist, ivec2(gl_FragCoord.xy), 0).r);
    if (isinf(g) || v_dist > g * 1.002 + 30.0) discard;  // no globe here, or hidden
    // inside its tile a patch is drawn at its depth; in its margin only where no tile's own
    // patch is (the farthest depth: a crack between two patches' meshes), with its edge texels
    bool inside = all(greaterThanEqual(v_t, vec2(0.0))) && all(lessThanEqual(v_t, vec2(1.0)));
    gl_FragDepth = inside ? gl_FragCoord.z : 1.0;
    f_color = texture(u_tile, v_sub.xy + v_sub.zw * clamp(v_t, 0.0, 1.0));
}
"""


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


class GlobeRenderer:
    """Headless: draws a ``GlobeMesh`` and reads back RGB and view distance."""

    def __init__(
        self,
        image: NDArray[np.uint8],
        background: tuple[float, float, float],
        ctx: moderngl.Context | None = None,
    ) -> None:
        self._owns_ctx = ctx is None
        self.ctx = create_context() if ctx is None else ctx
        make_current(self.ctx)
        #: False: ``draw`` leaves the picture in ``colour_framebuffer`` (a window copies it).
        self.read_back = True
        self.wireframe = False
        self.lod_colours = False
        self._colour_fbo: moderngl.Framebuffer | None = None
        self.background = background
        self.prog = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        img = np.ascontiguousarray(image[::-1])  # row 0 at the bottom: v = 0 at latitude -90
        self.tex = self.ctx.texture((img.shape[1], img.shape[0]), 3, img.tobytes(), alignment=1)
        self.tex.build_mipmaps()
        self.tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.tex.repeat_x = True
        self.tex.repeat_y = False
        self._fbo: moderngl.Framebuffer | None = None
        self._size = (0, 0)
        self.region: moderngl.Texture | None = None
        self.prog["u_tex"] = 0
        self.prog["u_region"] = 1
        self.prog["u_has_region"] = False
        #: Negate the view distance where the draped region has data (the terrain's own tiles
        #: are drawn there, see ``lodscape.globe``).
        self.mark_region = False
        self._targets: list[Any] = []
        self._dist: moderngl.Texture | None = None
        self._colour: moderngl.Texture | None = None
        self._patch_fbo: moderngl.Framebuffer | None = None
        #: Imagery tiles on the GPU: key -> (texture, bytes).
        self._tiles: dict[int, tuple[moderngl.Texture, int]] = {}
        self._imagery_prog = self.ctx.program(
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

    def draw(
        self, camera: Camera, mesh: GlobeMesh, imagery: Sequence[ImageryDraw] = ()
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """Draw the globe from ``camera``, then the imagery layers' tiles over it (bottom to
        top); RGB and view distance read back (unless ``read_back`` is off)."""
        make_current(self.ctx)
        w, h = camera.width, camera.height
        if self._size != (w, h):
            self._release_targets()
            color = self.ctx.texture((w, h), 4)
            dist = self.ctx.texture((w, h), 1, dtype="f4")
            dist.filter = (moderngl.NEAREST, moderngl.NEAREST)
            depth = self.ctx.depth_renderbuffer((w, h))
            patches = self.ctx.depth_renderbuffer((w, h))
            self._targets = [color, dist, depth, patches]
            self._fbo = self.ctx.framebuffer([color, dist], depth)
            self._colour_fbo = self.ctx.framebuffer([color])
            self._patch_fbo = self.ctx.framebuffer([color], patches)
            self._dist = dist
            self._colour = color
            self._size = (w, h)
        fbo = self._fbo
        assert fbo is not None
        fbo.use()
        fbo.color_mask = ((True,) * 4, (False,) * 4)  # type: ignore[assignment]
        fbo.clear(*self.background, 1.0, depth=1.0)
        fbo.color_mask = ((False,) * 4, (True,) * 4)  # type: ignore[assignment]
        fbo.clear(float("inf"), 0.0, 0.0, 0.0)
        fbo.color_mask = ((True,) * 4, (True,) * 4)  # type: ignore[assignment]
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        if len(mesh.positions):  # nothing of the Earth in view: the background alone
            rel = (mesh.positions - camera.position).reshape(-1, 3).astype(np.float32)
            ll = pole_longitudes(mesh.latlon)
            lat, lon = ll[..., 0], ll[..., 1]
            uv = np.stack([(lon + 180.0) / 360.0, (lat + 90.0) / 180.0], axis=-1).reshape(-1, 2)
            shade = np.repeat(relief_shade(mesh.positions, ll), 3).astype(np.float32)[:, None]
            data = np.hstack([rel, uv.astype(np.float32), shade])
            vbo = self.ctx.buffer(np.ascontiguousarray(data, np.float32).tobytes())
            vao = self.ctx.vertex_array(
                self.prog, [(vbo, "3f 2f 1f", "in_pos", "in_uv", "in_shade")]
            )
            mvp = camera.view_projection(camera.position)
            self.prog["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))  # type: ignore[union-attr]
            self.prog["u_rot"].write(np.ascontiguousarray(camera.rotation.T, np.float32))  # type: ignore[union-attr]
            self.prog["u_mark_region"] = self.mark_region
            self.tex.use(0)
            if self.region is not None:
                self.region.use(1)
            self.ctx.wireframe = self.wireframe
            vao.render(moderngl.TRIANGLES)
            self.ctx.wireframe = False
            vao.release()
            vbo.release()
            for layer in imagery:
                self._draw_imagery(camera, layer)
        if not self.read_back:
            return np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), np.float32)
        rgb = np.frombuffer(fbo.read(components=3, attachment=0, alignment=1), np.uint8)
        d = np.frombuffer(fbo.read(components=1, attachment=1, alignment=1, dtype="f4"), np.float32)
        return (
            np.ascontiguousarray(rgb.reshape(h, w, 3)[::-1]),
            np.ascontiguousarray(d.reshape(h, w)[::-1]),
        )

    # --- imagery tiles (``stream.gpu.GpuResources``) --------------------------------------

    def prepare(self, key: int, made: Any) -> Any:
        """On a worker: nothing to make beside the image."""
        return made

    def upload_resource(self, key: int, made: Any) -> int:
        """Upload imagery tile ``key`` ((H, W, 4) RGBA, row 0 north) with mipmaps; its bytes."""
        make_current(self.ctx)
        if key in self._tiles:
            return self._tiles[key][1]
        image = np.ascontiguousarray(made, dtype=np.uint8)
        if image.ndim != 3 or image.shape[2] not in (3, 4):
            raise ValueError(
                f"imagery tile {key}: expected an (H, W, 3|4) image, got {image.shape}"
            )
        tex = self.ctx.texture((image.shape[1], image.shape[0]), image.shape[2], image, alignment=1)
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = False
        nbytes = image.nbytes * 4 // 3
        self._tiles[key] = (tex, nbytes)
        return nbytes

    def release(self, key: int) -> None:
        tile = self._tiles.pop(key, None)
        if tile is not None:
            make_current(self.ctx)
            tile[0].release()

    def _draw_imagery(self, camera: Camera, layer: ImageryDraw) -> None:
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
        fbo = self._patch_fbo
        assert fbo is not None
        assert self._dist is not None
        fbo.use()
        fbo.color_mask = (False, False, False, False)
        fbo.clear(depth=1.0)  # the patches' own depths: the colour stays
        fbo.color_mask = (True, True, True, True)
        fbo.use()
        self.ctx.enable_only(moderngl.DEPTH_TEST | moderngl.BLEND)
        self.ctx.depth_func = "<="
        self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        mvp = camera.view_projection(camera.position)
        self._imagery_prog["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))  # type: ignore[union-attr]
        self._imagery_prog["u_rot"].write(np.ascontiguousarray(camera.rotation.T, np.float32))  # type: ignore[union-attr]
        self._dist.use(1)
        for i, key in enumerate(layer.keys):
            self._tiles[key][0].use(0)
            vao.render(moderngl.TRIANGLES, vertices=per, first=i * per)
        vao.release()
        vbo.release()
        self.ctx.depth_func = "<"
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        assert self._fbo is not None
        self._fbo.use()

    def _release_targets(self) -> None:
        for obj in (self._fbo, self._colour_fbo, self._patch_fbo, *self._targets):
            if obj is not None:
                obj.release()
        self._targets = []
        self._fbo = self._colour_fbo = self._patch_fbo = None
        self._dist = self._colour = None

    def show(self, rgb: NDArray[np.uint8]) -> None:
        """Put ``rgb`` ((H, W, 3), row 0 at the top, the last frame's size) in the colour
        framebuffer (what a window copies): a picture composed on the CPU."""
        assert self._colour is not None
        make_current(self.ctx)
        rgba = np.concatenate([rgb[::-1], np.full((*rgb.shape[:2], 1), 255, np.uint8)], axis=2)
        self._colour.write(np.ascontiguousarray(rgba).tobytes())

    @property
    def colour_framebuffer(self) -> moderngl.Framebuffer | None:
        """The last frame's colour alone (what a window's framebuffer is copied from)."""
        return self._colour_fbo

    def close(self) -> None:
        if self.region is not None:
            self.region.release()
            self.region = None
        for key in list(self._tiles):
            self.release(key)
        self._release_targets()
        if self._owns_ctx:
            self.ctx.release()
