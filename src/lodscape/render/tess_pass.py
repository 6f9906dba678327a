"""The GPU terrain mode (paper 001): each tile a few quad patches, tessellated in hardware and
displaced by the tile's height texture, so the CPU sends a handful of uniforms and one draw per
tile whatever the detail.

Control shader: each patch edge gets a level, a power of two up to the patch's cells, that is
the larger of two rules. The pixel rule of paper 000: the edge's length on screen
(length · d / distance, d the camera's pixels per unit of tangent) over ``px_per_segment``. The
error rule: the tile's error table says how far each level strays from the full grid (metres);
projected from the nearest the edge can be, it must stay under the tile's share of the frame's
screen-space error (``max_sse`` less the error the tile's own level already has). An edge's
level depends on its two ends and its own table row only, so the two patches on an edge (and,
up to rounding, the two tiles on a border) split it alike; the tiles' skirts, as in the CPU
mode, close what a border between levels leaves.

Evaluation shader: a vertex is the bilinear blend of the grid's base positions and normals on
the ellipsoid (``terrain.heightmap.tile_frame``) displaced by the bilinear height, in the tile's
east-north-up frame, which the draw's matrix turns into the camera's in float64 on the CPU.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.errors import LodscapeError
from lodscape.lod.camera import Camera
from lodscape.render._shaders import shader
from lodscape.terrain.heightmap import LEVELS, HeightTile, patch_layout, tile_frame

__all__ = ["TessTerrain", "TessellationUnavailable", "patch_grid"]

F64 = NDArray[np.float64]

_VERTEX = shader("tess_vertex.glsl")

_CONTROL = shader("tess_control.glsl")

_EVALUATION = shader("tess_evaluation.glsl")


#: Texture units of the imagery layers (the terrain's own texture is 0, the GPU mode's tables
#: 1..3, the land-cover materials 4).
LAYER_UNIT = 5
#: Imagery layers the terrain shaders blend over the terrain's own texture.
MAX_OVERLAYS = 4
#: Per imagery layer, the texture a tile wears and its window (offset u, v, scale).
Layers = Sequence[tuple[moderngl.Texture, tuple[float, float, float]]]


def bind_layers(uniforms: Mapping[str, Any], layers: Layers) -> None:
    """Bind a tile's imagery layers to their units and write their windows."""
    u = uniforms.get("u_layer_uv")
    if u is None or not layers:
        return
    uv = np.zeros((MAX_OVERLAYS, 3), np.float32)
    uv[:, 2] = 1.0
    for i, (tex, window) in enumerate(layers):
        tex.use(LAYER_UNIT + i)
        uv[i] = window
    # the compiler keeps the slots of the layers a program holds (``Renderer.layers``)
    u.write(uv[: u.array_length].tobytes())


class TessellationUnavailable(LodscapeError):
    """The OpenGL driver has no tessellation shaders (OpenGL 4.0)."""


def patch_grid(segments: int) -> NDArray[np.float32]:
    """Control points (4 per patch: u, v, skirt) of a tile of ``segments`` cells: P×P surface
    patches row by row from the north-west, then the skirt patches of the north, east, south
    and west edges (each: two points on the edge, then the same two hanging)."""
    p, _ = patch_layout(segments)
    g = np.arange(p + 1, dtype=np.float64) / p
    out = []
    for j in range(p):
        for i in range(p):
            u0, u1, v0, v1 = g[i], g[i + 1], g[j], g[j + 1]
            out += [[u0, v0, 0], [u1, v0, 0], [u1, v1, 0], [u0, v1, 0]]
    for k in range(p):
        a, b = g[k], g[k + 1]
        for e0, e1 in (
            ((a, 0.0), (b, 0.0)),  # north
            ((1.0, a), (1.0, b)),  # east
            ((a, 1.0), (b, 1.0)),  # south
            ((0.0, a), (0.0, b)),  # west
        ):
            out += [[*e0, 0], [*e1, 0], [*e1, 1], [*e0, 1]]
    return np.asarray(out, np.float32)


@dataclass(eq=False)
class _Tile:
    height: moderngl.Texture
    errors: moderngl.Texture
    segments: int
    z: int
    y: int
    origin: F64
    basis: F64
    up: bytes
    nbytes: int


class TessTerrain:
    """GL objects of the GPU terrain mode in one context: per tile a height texture and an
    error table, per tile row a frame texture, per grid size the patches."""

    #: Frame textures kept (one per tile row and grid size in use).
    FRAMES = 256

    def __init__(self, ctx: moderngl.Context, fragment_shader: str) -> None:
        if ctx.version_code < 400:
            raise TessellationUnavailable(
                f"the GPU terrain mode needs OpenGL 4.0 tessellation; this driver "
                f"({ctx.info.get('GL_RENDERER', '?')}) offers {ctx.version_code / 100:.1f}"
            )
        self.ctx = ctx
        self._fragment = fragment_shader
        self.program, self._p = self._make_program(())
        #: The label pass's program, its uniforms and its patches (made when first asked for),
        #: swapped in by ``use_labels``.
        self._other: tuple[Any, dict[str, moderngl.Uniform], dict[int, Any]] | None = None
        self.labelling = False
        self._tiles: dict[int, _Tile] = {}
        self._frames: OrderedDict[tuple[int, int, int], moderngl.Texture] = OrderedDict()
        self._patches: dict[int, tuple[moderngl.Buffer, moderngl.VertexArray, int]] = {}
        self._query = ctx.query(primitives=True)
        self.px_per_segment = 4.0

    def _make_program(
        self, defines: tuple[str, ...]
    ) -> tuple[moderngl.Program, dict[str, moderngl.Uniform]]:
        head = "\n".join(
            ["#version 410", "#define HEIGHT_NORMALS", *(f"#define {d}" for d in defines)]
        )
        program = self.ctx.program(
            vertex_shader=_VERTEX,
            tess_control_shader=_CONTROL,
            tess_evaluation_shader=_EVALUATION,
            fragment_shader=self._fragment.replace("#version 330", head),
        )
        p: dict[str, moderngl.Uniform] = {}
        for name in program:
            member = program[name]
            if isinstance(member, moderngl.Uniform):
                p[name] = member
        for unit, name in (
            (0, "u_tex"),
            (1, "u_frame"),
            (2, "u_height"),
            (3, "u_errors"),
            (4, "u_ground_materials"),
            *((LAYER_UNIT + i, f"u_layer{i}") for i in range(MAX_OVERLAYS)),
        ):
            if name in p:
                p[name].value = unit
        return program, p

    def use_labels(self, on: bool, class_labels: NDArray[np.float32]) -> None:
        """Draw with the label pass's program (normals and labels, ``render.labels``) or the
        colour one; ``class_labels`` maps a ground class to its label."""
        if on == self.labelling:
            return
        if self._other is None:
            program, p = self._make_program(("LABELS",))
            self._other = (program, p, {})
        mine = (self.program, self._p, self._patches)
        self.program, self._p, self._patches = self._other
        self._other = mine
        self.labelling = on
        u = self._p.get("u_class_label")
        if on and u is not None:
            u.write(class_labels[: u.array_length].tobytes())

    # --- resources --------------------------------------------------------------------------

    def upload(self, ht: HeightTile) -> int:
        """Make ``ht`` drawable under its key; returns the GPU bytes it holds."""
        s = ht.segments
        n = s + 1
        height = self.ctx.texture((n, n), 1, np.ascontiguousarray(ht.heights), dtype="f4")
        height.build_mipmaps()
        height.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        height.repeat_x = height.repeat_y = False
        errors = self.ctx.texture(
            (LEVELS + 2, ht.errors.shape[0]), 1, np.ascontiguousarray(ht.errors), dtype="f4"
        )
        errors.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._tiles[ht.key] = _Tile(
            height,
            errors,
            s,
            ht.z,
            ht.y,
            ht.origin,
            ht.basis,
            np.asarray(ht.up, np.float32).tobytes(),
            ht.nbytes,
        )
        return ht.nbytes

    def release(self, key: int) -> bool:
        tile = self._tiles.pop(key, None)
        if tile is None:
            return False
        tile.height.release()
        tile.errors.release()
        return True

    def has(self, key: int) -> bool:
        return key in self._tiles

    def close(self) -> None:
        for key in list(self._tiles):
            self.release(key)
        for tex in self._frames.values():
            tex.release()
        self._frames.clear()
        spare = [] if self._other is None else [self._other]
        for program, _, patches in [(self.program, self._p, self._patches), *spare]:
            for buf, vao, _ in patches.values():
                vao.release()
                buf.release()
            patches.clear()
            program.release()
        self._other = None

    def _frame(self, z: int, y: int, s: int) -> moderngl.Texture:
        key = (z, y, s)
        tex = self._frames.get(key)
        if tex is not None:
            self._frames.move_to_end(key)
            return tex
        grid, _, _ = tile_frame(z, y, s)
        n = s + 1
        # base positions in the first n rows, normals in the next n
        data = np.concatenate([grid[..., :4], grid[..., 4:]], axis=0)
        tex = self.ctx.texture((n, 2 * n), 4, np.ascontiguousarray(data), dtype="f4")
        tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = False
        self._frames[key] = tex
        while len(self._frames) > self.FRAMES:
            _, old = self._frames.popitem(last=False)
            old.release()
        return tex

    def _patch_vao(self, s: int) -> tuple[moderngl.VertexArray, int]:
        entry = self._patches.get(s)
        if entry is None:
            pts = patch_grid(s)
            buf = self.ctx.buffer(pts.tobytes())
            vao = self.ctx.vertex_array(self.program, [(buf, "3f", "in_patch")])
            entry = (buf, vao, len(pts))
            self._patches[s] = entry
        return entry[1], entry[2]

    # --- drawing ----------------------------------------------------------------------------

    def draw(
        self,
        camera: Camera,
        items: list[
            tuple[
                int,
                moderngl.Texture,
                float,
                tuple[float, float, float],
                float,
                tuple[float, float, float],
                tuple[float, float, float, float],
                Layers,
                float,
            ]
        ],
    ) -> tuple[int, int, float]:
        """Draw (key, texture, skirt, uv window, error budget px, ground window, tint, imagery
        layers, morph) items into the bound framebuffer; returns (draw calls, triangles the
        tessellator made, seconds spent issuing them). An item's morph: how far it still shows
        its grid of half the cells (the surface it replaced)."""
        t0 = time.perf_counter()
        ctx = self.ctx
        p = self._p
        ctx.patch_vertices = 4
        rot = camera.rotation
        p["u_scale"].value = float(camera.scale)
        p["u_px"].value = float(self.px_per_segment)
        p["u_near"].value = float(camera.near or 0.1)
        calls = 0
        with self._query:
            u_ground = p.get("u_ground")
            u_tint = p.get("u_tint")
            if "u_layers" in p:
                p["u_layers"].value = len(items[0][7]) if items else 0
            for key, tex, skirt, uv, budget, ground, tint, layers, morph in items:
                bind_layers(p, layers)
                if u_ground is not None:
                    u_ground.value = ground
                if u_tint is not None:
                    u_tint.value = tint
                tile = self._tiles[key]
                s = tile.segments
                pp, c = patch_layout(s)
                to_world = np.eye(4)
                to_world[:3, :3] = tile.basis.T
                mvp = camera.view_projection(tile.origin) @ to_world
                p["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))
                p["u_rot"].write(np.ascontiguousarray((rot @ tile.basis.T).T, np.float32))
                p["u_offset"].write(np.asarray(rot @ (tile.origin - camera.position), np.float32))
                p["u_eye"].write(
                    np.asarray(tile.basis @ (camera.position - tile.origin), np.float32)
                )
                # skirts hang along the frame's up, which is the centre's ellipsoid normal
                p["u_up"].value = (0.0, 0.0, 1.0)
                p["u_skirt"].value = float(skirt)
                p["u_uv"].value = uv
                p["u_budget"].value = float(max(budget, 1e-3))
                p["u_cells"].value = float(s)
                p["u_patches"].value = float(pp)
                p["u_max"].value = float(c)
                p["u_morph"].value = float(morph)
                tex.use(0)
                self._frame(tile.z, tile.y, s).use(1)
                tile.height.use(2)
                tile.errors.use(3)
                vao, vertices = self._patch_vao(s)
                vao.render(moderngl.PATCHES, vertices=vertices)
                calls += 1
        submit = time.perf_counter() - t0
        return calls, int(self._query.primitives), submit

    def set_sun(self, sun: NDArray[np.float32]) -> None:
        """Towards the sun, view space (the land-cover ground's lighting)."""
        if "u_sun" in self._p:
            self._p["u_sun"].write(np.asarray(sun, np.float32))

    def triangles_hint(self, key: int) -> int:
        """Triangles of a tile at full tessellation (two per cell, skirts included)."""
        tile = self._tiles.get(key)
        if tile is None:
            return 0
        s = tile.segments
        return 2 * s * s + 8 * s

    def resident(self) -> dict[int, int]:
        return {key: t.nbytes for key, t in self._tiles.items()}

    def frame_count(self) -> int:
        return len(self._frames)
