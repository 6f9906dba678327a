"""The globe pass (paper 002): a QTM mesh in Earth-centred coordinates, drawn relative to the
camera in float32 (the subtraction made in float64 on the CPU, so orbit and street level are
equally steady), textured from an equirectangular image by each facet's own longitudes."""

from __future__ import annotations

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.lod.camera import Camera
from lodscape.lod.globe import GlobeMesh, pole_longitudes
from lodscape.render._context import create_context, make_current

__all__ = ["GlobeRenderer"]

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
        self, camera: Camera, mesh: GlobeMesh
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        make_current(self.ctx)
        w, h = camera.width, camera.height
        if self._size != (w, h):
            color = self.ctx.renderbuffer((w, h), 4)
            dist = self.ctx.renderbuffer((w, h), 1, dtype="f4")
            depth = self.ctx.depth_renderbuffer((w, h))
            self._fbo = self.ctx.framebuffer([color, dist], depth)
            self._colour_fbo = self.ctx.framebuffer([color])
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
        if not self.read_back:
            return np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), np.float32)
        rgb = np.frombuffer(fbo.read(components=3, attachment=0, alignment=1), np.uint8)
        d = np.frombuffer(fbo.read(components=1, attachment=1, alignment=1, dtype="f4"), np.float32)
        return (
            np.ascontiguousarray(rgb.reshape(h, w, 3)[::-1]),
            np.ascontiguousarray(d.reshape(h, w)[::-1]),
        )

    @property
    def colour_framebuffer(self) -> moderngl.Framebuffer | None:
        """The last frame's colour alone (what a window's framebuffer is copied from)."""
        return self._colour_fbo

    def close(self) -> None:
        if self.region is not None:
            self.region.release()
            self.region = None
        if self._owns_ctx:
            self.ctx.release()
