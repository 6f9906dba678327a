"""Does one multi-draw-indirect call pay against one draw per tile? (issue 24, item 1)

The terrain pass draws one call per tile: its own vertex buffer, texture and uniforms. The
alternative is the city's: every tile in one shared vertex buffer, the textures as layers of one
array texture, per-tile data in a storage buffer read by ``gl_DrawID``, one
``glMultiDrawElementsIndirect``. This measures both on the same triangles, in one context:
N tiles of a 64×64-cell grid (8,192 triangles each) tiling the viewport, each with its own
256² RGBA mipmapped texture, 1280×720, cleared and read back per frame; medians of 9 frames,
alternating. Both pictures are compared byte for byte.

    python bench/bench_draws.py [--tiles 16 64 256]
"""

from __future__ import annotations

import argparse
import statistics
import time

import moderngl
import numpy as np

from lodscape.render._context import create_context
from lodscape.terrain.mesh import grid_indices

SEGMENTS = 64

_PER_TILE = (
    """
#version 330
uniform vec2 u_offset;
in vec3 in_pos;
in vec2 in_uv;
out vec2 v_uv;
void main() {
    gl_Position = vec4(in_pos.xy + u_offset, in_pos.z, 1.0);
    v_uv = in_uv;
}
""",
    """
#version 330
uniform sampler2D u_tex;
in vec2 v_uv;
out vec4 f_color;
void main() { f_color = texture(u_tex, v_uv); }
""",
)

_ONE_DRAW = (
    """
#version 430
#extension GL_ARB_shader_draw_parameters : require
layout(std430, binding = 0) readonly buffer Tiles { vec4 tile[]; };  // offset xy, layer
in vec3 in_pos;
in vec2 in_uv;
out vec2 v_uv;
flat out int v_layer;
void main() {
    vec4 t = tile[gl_DrawIDARB];
    gl_Position = vec4(in_pos.xy + t.xy, in_pos.z, 1.0);
    v_uv = in_uv;
    v_layer = int(t.z);
}
""",
    """
#version 430
uniform sampler2DArray u_tex;
in vec2 v_uv;
flat in int v_layer;
out vec4 f_color;
void main() { f_color = texture(u_tex, vec3(v_uv, float(v_layer))); }
""",
)


def run(ctx: moderngl.Context, n: int) -> tuple[float, float, bool]:
    s = SEGMENTS
    side = int(np.ceil(np.sqrt(n)))
    g = np.linspace(0.0, 1.0, s + 1, dtype=np.float32)
    u, v = np.meshgrid(g, g)
    idx = grid_indices(s)[: 2 * s * s].ravel()  # the surface's triangles, not the skirts
    rng = np.random.default_rng(0)
    verts, images = [], []
    for i in range(n):
        x = (i % side) / side * 2 - 1 + u / side * 2
        y = (i // side) / side * 2 - 1 + v / side * 2
        z = 0.5 + 0.01 * np.sin(x * 30.0)
        verts.append(np.stack([x, y, z, u, v], -1).reshape(-1, 5).astype(np.float32))
        images.append(rng.integers(0, 255, (256, 256, 4), dtype=np.uint8))
    objects: list[object] = []

    def keep(obj):  # type: ignore[no-untyped-def]
        objects.append(obj)
        return obj

    ibo = keep(ctx.buffer(idx))
    per = keep(ctx.program(vertex_shader=_PER_TILE[0], fragment_shader=_PER_TILE[1]))
    tiles = []
    for vert, img in zip(verts, images, strict=True):
        vao = keep(
            ctx.vertex_array(  # type: ignore[no-untyped-call]
                per,
                [(keep(ctx.buffer(vert)), "3f 2f", "in_pos", "in_uv")],
                index_buffer=ibo,
                index_element_size=4,
            )
        )
        tex = keep(ctx.texture((256, 256), 4, img.tobytes()))
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tiles.append((vao, tex))
    one = keep(ctx.program(vertex_shader=_ONE_DRAW[0], fragment_shader=_ONE_DRAW[1]))
    pool = keep(ctx.buffer(np.concatenate(verts)))
    vao1 = keep(
        ctx.vertex_array(  # type: ignore[no-untyped-call]
            one, [(pool, "3f 2f", "in_pos", "in_uv")], index_buffer=ibo, index_element_size=4
        )
    )
    array = keep(ctx.texture_array((256, 256, n), 4, np.concatenate(images).tobytes()))
    array.build_mipmaps()
    array.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
    ssbo = keep(ctx.buffer(np.array([[0, 0, i, 0] for i in range(n)], np.float32)))
    cmds = np.array([[len(idx), 1, 0, i * (s + 1) ** 2, 0] for i in range(n)], np.uint32)
    indirect = keep(ctx.buffer(cmds))
    fbo = keep(ctx.simple_framebuffer((1280, 720)))
    fbo.use()
    ctx.enable_only(moderngl.DEPTH_TEST)
    offset = per["u_offset"]

    def per_tile() -> bytes:
        fbo.clear(depth=1.0)
        for vao, tex in tiles:
            tex.use(0)
            offset.value = (0.0, 0.0)  # type: ignore[union-attr]
            vao.render(moderngl.TRIANGLES)
        return fbo.read(components=3)

    def one_draw() -> bytes:
        fbo.clear(depth=1.0)
        array.use(0)
        ssbo.bind_to_storage_buffer(0)
        vao1.render_indirect(indirect, moderngl.TRIANGLES, count=n)
        return fbo.read(components=3)

    same = per_tile() == one_draw()
    a, b = [], []
    for _ in range(9):
        t = time.perf_counter()
        per_tile()
        a.append(time.perf_counter() - t)
        t = time.perf_counter()
        one_draw()
        b.append(time.perf_counter() - t)
    for obj in reversed(objects):
        obj.release()  # type: ignore[attr-defined]
    return statistics.median(a) * 1e3, statistics.median(b) * 1e3, same


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tiles", type=int, nargs="+", default=[16, 64, 256])
    args = ap.parse_args()
    ctx = create_context()
    print(ctx.info["GL_RENDERER"], ctx.version_code)
    if ctx.version_code < 430 or (
        ctx.version_code < 460 and "GL_ARB_shader_draw_parameters" not in ctx.extensions
    ):
        raise SystemExit("needs OpenGL 4.3 with ARB_shader_draw_parameters")
    for n in args.tiles:
        a, b, same = run(ctx, n)
        print(
            f"{n:4d} tiles ({n * 2 * SEGMENTS**2:,d} triangles): one draw per tile {a:.1f} ms, "
            f"one multi-draw-indirect {b:.1f} ms (×{a / b:.2f}); same picture: {same}"
        )


if __name__ == "__main__":
    main()
