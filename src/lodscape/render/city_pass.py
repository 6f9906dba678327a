"""The city pass (paper 001): the city's merged meshes and instanced street objects, drawn into the
terrain pass's framebuffer with the same camera, after the terrain.

Optimised path, per frame: leaves culled by the frustum (R-tree, from the root) and given a level
of detail; for each material one ``glMultiDrawElementsIndirect`` over the visible leaves' runs of
its merged mesh; for each street model part one instanced multi-draw (the leaves' runs of the
instance buffer); and coherent hierarchical occlusion culling (CHC++'s scheme on the tree's two
lowest levels): leaves seen last frame are drawn first; the others are tested with occlusion
queries against that depth (all issued, then all read: one batch; a parent hidden as a whole
last frame is asked with its box first, and its leaves only if it is seen) and drawn at once if
any sample passes; the leaves drawn first are queried after the frame to learn which became
hidden. A leaf is never dropped because of a query made in an earlier frame, so occlusion
culling cannot remove a pixel; a leaf whose box holds the eye is always drawn. Materials are the
layers of one texture array (``city.materials``).

Naive path (``CityOptions.naive()``): every object drawn with its own draw call per material, full
detail, no culling: the baseline of paper 001's benchmark.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.city.materials import layers, material
from lodscape.city.mesh import MODELS
from lodscape.city.model import CityModel, CityOptions
from lodscape.lod.camera import Camera
from lodscape.render._depth import with_log_depth
from lodscape.render._shaders import shader
from lodscape.render.labels import object_label

__all__ = ["CityPass", "CityStats"]

_G = TypeVar("_G")
F64 = NDArray[np.float64]

_VERTEX = shader("city_vertex.glsl")

_FRAGMENT = shader("city_fragment.glsl")

_BOX_VERTEX = shader("city_box_vertex.glsl")


def _variant(source: str, *defines: str) -> str:
    """``source`` with ``defines``; the buffers' variant on GLSL 4.30 with the draw parameters."""
    head = "#version 330"
    if "BLOCKS" in defines:
        head = "#version 430\n#extension GL_ARB_shader_draw_parameters : require"
    return source.replace("#version 330", "\n".join([head, *(f"#define {d}" for d in defines)]))


_BOX_FRAGMENT = shader("city_box_fragment.glsl")
_ALL = (True, True, True, True)
_NONE = (False, False, False, False)
_CUBE = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float32)
_CUBE_TRIS = np.array(
    [
        0,
        1,
        3,
        0,
        3,
        2,
        4,
        6,
        7,
        4,
        7,
        5,
        0,
        4,
        5,
        0,
        5,
        1,
        2,
        3,
        7,
        2,
        7,
        6,
        0,
        2,
        6,
        0,
        6,
        4,
        1,
        5,
        7,
        1,
        7,
        3,
    ],
    np.uint32,
)


@dataclass(frozen=True)
class CityStats:
    draw_calls: int = 0
    triangles: int = 0
    objects_drawn: int = 0
    culled_frustum: int = 0
    culled_lod: int = 0
    culled_occlusion: int = 0
    queries: int = 0
    #: Of the queries, those asked of inner nodes (parents of leaves) rather than leaves.
    node_queries: int = 0
    boxes_tested: int = 0
    #: Microseconds the pass took, submission and GPU work (``CityOptions.timed``; else 0).
    pass_us: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f"city_{k}": int(v) for k, v in self.__dict__.items()}


class CityPass:
    """GL objects of one city in one context; ``draw`` adds it to the bound framebuffer."""

    def __init__(
        self,
        ctx: moderngl.Context,
        model: CityModel,
        anisotropy: float = 1.0,
        compress: bool = False,
        buffers: bool = False,
        log_depth: bool = False,
    ) -> None:
        self.ctx = ctx
        #: Fragments write the logarithmic depth of the frame they join (``render._depth``).
        self.log_depth = log_depth
        self.model = model
        self.indirect_ok = ctx.version_code >= 430
        #: The camera in a uniform buffer (written once a frame for every program) and the
        #: street objects' instances in a shader storage buffer (read by the draw's base
        #: instance) where the GL has them (4.3 and the draw parameters); else plain uniforms
        #: per program and instanced vertex attributes.
        self.buffers = (
            buffers
            and self.indirect_ok
            and (ctx.version_code >= 460 or "GL_ARB_shader_draw_parameters" in ctx.extensions)
        )
        self._objs: list[Any] = []
        blocks = ("BLOCKS",) if self.buffers else ()
        prog = self._keep(
            ctx.program(
                vertex_shader=_variant(_VERTEX, *blocks),
                fragment_shader=self._fragment(_FRAGMENT, *blocks),
            )
        )
        iprog = self._keep(
            ctx.program(
                vertex_shader=_variant(_VERTEX, "INSTANCED", *blocks),
                fragment_shader=self._fragment(_FRAGMENT, *blocks),
            )
        )
        self._frame_ubo: moderngl.Buffer | None = None
        if self.buffers:
            self._frame_ubo = self._keep(ctx.buffer(reserve=160))
        # programs are indexed by uniform name: moderngl types members as a union
        self._prog: Any = prog
        self._iprog: Any = iprog
        self._meshes: dict[tuple[int, str], moderngl.VertexArray] = {}
        self._tris: dict[tuple[int, str], int] = {}
        #: Per mesh and per street-object model: its vertex, index and instance buffers (what
        #: the label pass's vertex arrays are made of).
        self._buffers: dict[Any, tuple[Any, Any, Any]] = {}
        self._blocks = blocks
        for key, geo in model.geometry.items():
            if not len(geo.triangles):
                continue
            vbo = self._keep(ctx.buffer(geo.vertices().tobytes()))
            ibo = self._keep(ctx.buffer(geo.triangles.tobytes()))
            vao = self._keep(
                ctx.vertex_array(prog, [(vbo, "3f 3f 2f", "in_pos", "in_normal", "in_uv")], ibo, 4)
            )
            self._meshes[key] = vao
            self._buffers[key] = (vbo, ibo, None)
        self._models: dict[tuple[str, str], tuple[moderngl.VertexArray, int]] = {}
        #: Per street-object kind, its instances' storage buffer (the buffers' path).
        self._instances: dict[str, moderngl.Buffer] = {}
        self._upload_instances(iprog)
        self._materials = self._material_atlas(compress, anisotropy)
        bprog = self._keep(
            ctx.program(
                vertex_shader=_variant(_BOX_VERTEX, *blocks),
                fragment_shader=self._fragment(_BOX_FRAGMENT, *blocks),
            )
        )
        self._bprog: Any = bprog
        if self.buffers:
            # the programs' Frame blocks read binding 0, and their materials unit 0, for good
            programs: tuple[Any, ...] = (prog, iprog, bprog)
            for p in programs:
                p["Frame"].binding = 0
                if "u_materials" in p:
                    p["u_materials"].value = 0
        cube = self._keep(ctx.buffer(_CUBE.tobytes()))
        cidx = self._keep(ctx.buffer(_CUBE_TRIS.tobytes()))
        self._box = self._keep(ctx.vertex_array(bprog, [(cube, "3f", "in_pos")], cidx, 4))
        self._indirect = self._keep(ctx.buffer(reserve=20 * max(model.tree.leaves, 1)))
        self._visible = np.zeros(model.tree.leaves, dtype=bool)
        self._parent_hidden = np.zeros(
            len(model.tree.levels[min(1, len(model.tree.levels) - 1)]), bool
        )
        self._queries: list[moderngl.Query] = []
        #: Queries read a frame later, and the leaves (and which hold the eye) they ask about.
        self._later: list[moderngl.Query] = []
        self._pending: tuple[NDArray[np.int64], NDArray[np.bool_]] | None = None
        self._frame = 0
        self.last = CityStats()
        self._node_queries = 0
        #: Draw labels and normals (``Renderer.draw_labels``) instead of colours: the label
        #: variants of the programs and their vertex arrays, swapped in by ``use_labels``.
        self.labels = False
        self._other: tuple[Any, Any, dict[Any, Any], dict[Any, Any]] | None = None

    def _upload_instances(self, iprog: Any) -> None:
        """The street objects: per kind its instances, per material its model's buffers."""
        ctx = self.ctx
        for kind, inst in self.model.instances.items():
            if not len(inst):
                continue
            ibuf = self._keep(ctx.buffer(np.ascontiguousarray(inst, np.float32).tobytes()))
            self._instances[kind] = ibuf
            for mat, geo in MODELS[kind].items():
                vbo = self._keep(ctx.buffer(geo.vertices().tobytes()))
                ibo = self._keep(ctx.buffer(geo.triangles.tobytes()))
                layout: list[Any] = [(vbo, "3f 3f 2f", "in_pos", "in_normal", "in_uv")]
                if not self.buffers:
                    layout.append((ibuf, "4f 1f/i", "in_inst", "in_heading"))
                vao = self._keep(ctx.vertex_array(iprog, layout, ibo, 4))
                self._models[(kind, mat)] = (vao, len(geo.triangles))
                self._buffers[(kind, mat)] = (vbo, ibo, ibuf)

    def _material_atlas(self, compress: bool, anisotropy: float) -> Any:
        """The materials the city's meshes and street objects use, as one texture array."""
        ctx = self.ctx
        # materials: one texture array, a layer each (deduplicated by name), mipmapped
        found = {m for _, m in self.model.geometry} | {m for _, m in self._models}
        names = sorted(found) or ["plaster"]
        self._layer = {name: i for i, name in enumerate(names)}
        texels = layers(names)
        size = texels.shape[1]
        if compress:  # the facade and roof atlas block-compressed (BC3), its mips made here
            from lodscape.imagery.compress import compress as compress_image
            from lodscape.render._compressed import texture_array

            tex = self._keep(texture_array(ctx, [compress_image(t) for t in texels]))
        else:
            tex = self._keep(ctx.texture_array((size, size, len(names)), 4, texels.tobytes()))
            tex.build_mipmaps()
            tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = True
        tex.anisotropy = anisotropy
        return tex

    def reset(self) -> None:
        """Forget last frame's visibility (occlusion culling starts from nothing seen)."""
        self._visible[:] = False
        self._parent_hidden[:] = False
        self._pending = None
        self._frame = 0

    def _keep(self, obj: _G) -> _G:
        self._objs.append(obj)
        return obj

    def release(self) -> None:
        for obj in reversed(self._objs):
            obj.release()
        # moderngl's queries have no release: they go with the context
        self._objs.clear()
        self._queries.clear()
        self._later.clear()
        self._pending = None

    # --- drawing ---------------------------------------------------------------------------

    def _uniforms(self, camera: Camera) -> None:
        m = self.model
        basis = m.frame.basis
        to_ecef = np.eye(4)
        to_ecef[:3, :3] = basis.T
        mvp = camera.view_projection(m.frame.origin) @ to_ecef
        rot = camera.rotation @ basis.T
        offset = camera.rotation @ (m.frame.origin - camera.position)
        sun = np.array([math.cos(0.8) * 0.5, math.sin(0.8) * 0.5, 0.75])
        sun /= np.linalg.norm(sun)
        if self._frame_ubo is not None:
            # one write a frame: the Frame block (std140: two mat4, two vec4) of every program
            block = np.zeros(40, np.float32)
            block[0:16] = np.ascontiguousarray(mvp.T, np.float32).ravel()
            rot4 = np.eye(4)
            rot4[:3, :3] = rot
            block[16:32] = np.ascontiguousarray(rot4.T, np.float32).ravel()
            block[32:35] = offset
            block[36:39] = sun
            self._frame_ubo.write(block.tobytes())
            self._frame_ubo.bind_to_uniform_block(0)
            self._materials.use(0)
            return
        for prog in (self._prog, self._iprog):
            prog["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))
            prog["u_rot"].write(np.ascontiguousarray(rot.T, np.float32))
            prog["u_offset"].write(np.asarray(offset, np.float32))
            if not self.labels:  # the label variants sample and light nothing
                prog["u_sun"].write(sun.astype(np.float32))
                prog["u_materials"].value = 0
        self._materials.use(0)
        self._bprog["u_mvp"].write(np.ascontiguousarray(mvp.T, np.float32))

    def _bind_instances(self, kind: str) -> None:
        """The buffers' path: ``kind``'s instances as the Instances storage buffer."""
        if self.buffers:
            self._instances[kind].bind_to_storage_buffer(1)

    def use_labels(self, on: bool) -> None:
        """Draw with the label variants (normals and labels, ``render.labels``) or the colour
        programs; the variants are made when first asked for."""
        if on == self.labels:
            return
        if self._other is None:
            self._other = self._label_variants()
        mine = (self._prog, self._iprog, self._meshes, self._models)
        self._prog, self._iprog, self._meshes, self._models = self._other
        self._other = mine
        self.labels = on

    def _fragment(self, source: str, *defines: str) -> str:
        """A fragment shader's variant, writing the log depth where the frame asks for it."""
        out = _variant(source, *defines)
        return with_log_depth(out) if self.log_depth else out

    def _label_variants(self) -> tuple[Any, Any, dict[Any, Any], dict[Any, Any]]:
        ctx, blocks = self.ctx, self._blocks
        frag = self._fragment(_FRAGMENT, *blocks, "LABELS")
        prog: Any = self._keep(
            ctx.program(vertex_shader=_variant(_VERTEX, *blocks), fragment_shader=frag)
        )
        iprog: Any = self._keep(
            ctx.program(vertex_shader=_variant(_VERTEX, "INSTANCED", *blocks), fragment_shader=frag)
        )
        if self.buffers:
            for p in (prog, iprog):
                p["Frame"].binding = 0
        # the label variants read no texture coordinates: the linker drops them, the layout skips
        attrs = ("3f 3f 8x", "in_pos", "in_normal")
        meshes: dict[Any, Any] = {}
        for mesh_key in self._meshes:
            vbo, ibo, _ = self._buffers[mesh_key]
            meshes[mesh_key] = self._keep(ctx.vertex_array(prog, [(vbo, *attrs)], ibo, 4))
        models: dict[Any, Any] = {}
        for model_key, (_, ntri) in self._models.items():
            vbo, ibo, ibuf = self._buffers[model_key]
            layout: list[Any] = [(vbo, *attrs)]
            if not self.buffers:
                layout.append((ibuf, "4f 1f/i", "in_inst", "in_heading"))
            models[model_key] = (self._keep(ctx.vertex_array(iprog, layout, ibo, 4)), ntri)
        return prog, iprog, meshes, models

    def _label(self, prog: Any, kind: str | None) -> None:
        """The label pass: ``prog`` draws ``kind``'s label (None: buildings)."""
        if self.labels:
            prog["u_label"].value = float(object_label(kind))

    def _use(self, prog: Any, mat: str) -> None:
        """Point ``prog`` at ``mat``'s layer of the material array."""
        if self.labels:
            return
        prog["u_layer"].value = float(self._layer[mat])
        prog["u_repeat"].value = material(mat).repeat

    def draw(self, camera: Camera, options: CityOptions, fbo: moderngl.Framebuffer) -> CityStats:
        """Draw the city into ``fbo`` (the terrain's colour + distance target, depth kept)."""
        if not options.timed:
            return self._draw(camera, options, fbo)
        self.ctx.finish()
        t = time.perf_counter()
        stats = self._draw(camera, options, fbo)
        self.ctx.finish()
        self.last = replace(stats, pass_us=int((time.perf_counter() - t) * 1e6))
        return self.last

    def _draw(self, camera: Camera, options: CityOptions, fbo: moderngl.Framebuffer) -> CityStats:
        self._fbo = fbo
        self._uniforms(camera)
        self._label(self._prog, None)
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        if options.is_naive:
            self.last = self._draw_naive(options)
            return self.last
        m = self.model
        fl = m.frame_lists(camera, options)
        shown = fl.lod < 2
        leaves, lod = fl.leaves[shown], fl.lod[shown]
        calls = tris = queries = 0
        occluded = np.zeros(0, dtype=np.int64)
        self._resolve_pending()
        if options.occlusion and len(leaves):
            eye = m.local_eye(camera)
            boxes = m.tree.levels[0][leaves]
            margin = (camera.near or 0.0) * 2.0 + 0.01
            holds_eye = np.all((boxes[:, :3] - margin <= eye) & (eye <= boxes[:, 3:] + margin), 1)
            # drawn without asking: seen last frame, holding the eye, or cheaper than a query
            cheap = m.leaf_triangles[lod, leaves] < options.query_min_triangles
            before = self._visible[leaves] | holds_eye | cheap
            c, t = self._draw_leaves(leaves[before], lod[before], options)
            calls, tris = calls + c, tris + t
            # the others: queries against the depth drawn so far, hierarchical (CHC++): where
            # every shown leaf of a node was hidden last frame, the node's box is asked first
            rest = np.nonzero(~before)[0]
            self._node_queries = 0
            seen, asked = self._query_hierarchy(leaves, rest, options)
            queries += asked
            now = rest[seen]
            c, t = self._draw_leaves(leaves[now], lod[now], options)
            calls, tris = calls + c, tris + t
            occluded = leaves[rest[~seen]]
            # which of the leaves drawn first are hidden now: asked after the frame, read at the
            # start of the next (by then the GPU has answered: no wait)
            # (CHC++: each only every ``revisit`` frames, staggered; the others stay visible)
            self._frame += 1
            due = (leaves + self._frame) % max(options.revisit, 1) == 0
            first = np.nonzero(before & ~cheap & due)[0]
            kept = np.nonzero(before & ~cheap & ~due)[0]
            self._issue(leaves[first], self._later, m.tree.levels[0][leaves[first]])
            queries += len(first)
            self._visible = np.zeros_like(self._visible)
            self._visible[leaves[now]] = True
            self._visible[leaves[kept]] = True
            self._pending = (leaves[first], holds_eye[first])
        else:
            c, t = self._draw_leaves(leaves, lod, options)
            calls, tris = calls + c, tris + t
        drawn_objects = int(m.leaf_objects[leaves].sum()) - int(m.leaf_objects[occluded].sum())
        self.last = CityStats(
            calls,
            tris,
            drawn_objects,
            fl.culled_frustum,
            fl.culled_lod,
            int(m.leaf_objects[occluded].sum()),
            queries,
            self._node_queries if options.occlusion else 0,
            fl.boxes_tested,
        )
        return self.last

    def _draw_leaves(
        self, leaves: NDArray[np.int64], lod: NDArray[np.int64], options: CityOptions
    ) -> tuple[int, int]:
        if not len(leaves):
            return 0, 0
        m = self.model
        calls = tris = 0
        for (level, mat), vao in self._meshes.items():
            sel = leaves[lod == level]
            if not len(sel):
                continue
            first, count = m.runs[(level, mat)]
            f, c = first[sel], count[sel]
            ok = c > 0
            f, c = f[ok], c[ok]
            if not len(f):
                continue
            self._use(self._prog, mat)
            tris += int(c.sum()) // 3
            if options.indirect and self.indirect_ok:
                cmd = np.zeros((len(f), 5), np.uint32)
                cmd[:, 0], cmd[:, 1], cmd[:, 2] = c, 1, f
                self._indirect.orphan(max(cmd.nbytes, 20))
                self._indirect.write(cmd.tobytes())
                vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=len(f))
                calls += 1
            else:
                for fi, ci in zip(f.tolist(), c.tolist(), strict=True):
                    vao.render(moderngl.TRIANGLES, vertices=ci, first=fi)
                    calls += 1
        full = leaves[lod == 0]
        for (kind, mat), (vao, ntri) in self._models.items():
            start, count = m.instance_runs[kind]
            s, c = start[full], count[full]
            ok = c > 0
            s, c = s[ok], c[ok]
            if not len(s):
                continue
            self._use(self._iprog, mat)
            self._label(self._iprog, kind)
            self._bind_instances(kind)
            tris += int(c.sum()) * ntri
            if options.instancing and self.indirect_ok:
                cmd = np.zeros((len(s), 5), np.uint32)
                cmd[:, 0], cmd[:, 1], cmd[:, 4] = 3 * ntri, c, s
                self._indirect.orphan(max(cmd.nbytes, 20))
                self._indirect.write(cmd.tobytes())
                vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=len(s))
                calls += 1
            else:
                calls += self._one_by_one(vao, ntri, s, c)
        return calls, tris

    def _one_by_one(
        self,
        vao: moderngl.VertexArray,
        ntri: int,
        start: NDArray[np.int64],
        count: NDArray[np.int64],
    ) -> int:
        """One draw per street object (the naive path): single indirect commands."""
        if not self.indirect_ok:
            raise RuntimeError("street objects need OpenGL 4.3 (multi-draw-indirect)")
        idx = np.concatenate([np.arange(a, a + b) for a, b in zip(start, count, strict=True)])
        cmd = np.zeros((len(idx), 5), np.uint32)
        cmd[:, 0], cmd[:, 1], cmd[:, 4] = 3 * ntri, 1, idx
        self._indirect.orphan(max(cmd.nbytes, 20))
        self._indirect.write(cmd.tobytes())
        for i in range(len(idx)):
            vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=1, first=i)
        return len(idx)

    def _draw_naive(self, options: CityOptions) -> CityStats:
        m = self.model
        calls = tris = 0
        for (level, mat), vao in self._meshes.items():
            if level != 0:
                continue
            first, count = m.object_runs[mat]
            self._use(self._prog, mat)
            for fi, ci in zip(first.tolist(), count.tolist(), strict=True):
                if ci:
                    vao.render(moderngl.TRIANGLES, vertices=ci, first=fi)
                    calls += 1
                    tris += ci // 3
        everything = np.arange(m.tree.leaves)
        for (kind, mat), (vao, ntri) in self._models.items():
            start, count = m.instance_runs[kind]
            self._use(self._iprog, mat)
            self._label(self._iprog, kind)
            self._bind_instances(kind)
            calls += self._one_by_one(vao, ntri, start[everything], count[everything])
            tris += int(count.sum()) * ntri
        return CityStats(calls, tris, m.objects)

    def _query_hierarchy(
        self, shown: NDArray[np.int64], rest: NDArray[np.int64], options: CityOptions
    ) -> tuple[NDArray[np.bool_], int]:
        """Which of ``shown[rest]`` (leaves hidden last frame) pass the depth test now, and how
        many queries it took. A parent found hidden as a whole last frame (every shown leaf of
        it hidden) is asked first, with its box, where all its shown leaves are among them; its
        leaves are asked only if it is seen (a second batch). A parent's box holds its leaves',
        so a hidden parent hides them all. Asking only parents hidden last frame keeps the
        hierarchy from adding queries where little is hidden (CHC++'s coherence, one level up)."""
        tree = self.model.tree
        leaves = shown[rest]
        if not options.hierarchical or len(tree.levels) < 2 or not len(leaves):
            return self._query(leaves), len(leaves)
        n_parents = len(tree.levels[1])
        parent = tree.parent(leaves)
        shown_per = np.bincount(tree.parent(shown), minlength=n_parents)
        rest_per = np.bincount(parent, minlength=n_parents)
        whole = (rest_per == shown_per) & (rest_per >= 2)
        grouped = whole & self._parent_hidden
        ask_parent = grouped[parent]
        parents = np.nonzero(grouped)[0]
        direct = leaves[~ask_parent]
        # batch one: the parents hidden last frame, and the other leaves themselves
        first = self._query(
            np.concatenate([direct, parents]),
            np.concatenate([tree.levels[0][direct], tree.levels[1][parents]]),
        )
        seen = np.zeros(len(leaves), dtype=bool)
        seen[~ask_parent] = first[: len(direct)]
        parent_seen = np.zeros(n_parents, dtype=bool)
        parent_seen[parents] = first[len(direct) :]
        # batch two: the leaves of the parents that were seen
        again = np.nonzero(ask_parent & parent_seen[parent])[0]
        seen[again] = self._query(leaves[again])
        # next frame's hidden parents: every shown leaf was in question and none is seen
        any_seen = np.bincount(parent[seen], minlength=n_parents) > 0
        self._parent_hidden = whole & ~any_seen
        self._node_queries = len(parents)
        return seen, len(first) + len(again)

    def _resolve_pending(self) -> None:
        """Read last frame's after-the-frame queries into the visibility of its leaves."""
        if self._pending is None:
            return
        first, holds_eye = self._pending
        self._pending = None
        still = np.array([q.samples > 0 for q in self._later[: len(first)]], dtype=bool)
        self._visible[first[still | holds_eye]] = True

    def _query(self, leaves: NDArray[np.int64], boxes: F64 | None = None) -> NDArray[np.bool_]:
        """Whether any sample of each leaf's box (or of ``boxes``) passes the depth test (one
        batch, read at once)."""
        if not len(leaves):
            return np.zeros(0, dtype=bool)
        if boxes is None:
            boxes = self.model.tree.levels[0][leaves]
        self._issue(leaves, self._queries, boxes)
        return np.array([q.samples > 0 for q in self._queries[: len(leaves)]], dtype=bool)

    def _issue(self, leaves: NDArray[np.int64], pool: list[moderngl.Query], boxes: F64) -> None:
        """Draw each box (depth test on, no writes) inside its own query of ``pool``."""
        if not len(leaves):
            return
        while len(pool) < len(leaves):
            pool.append(self.ctx.query(samples=True))
        fbo = self._fbo
        fbo.color_mask = (_NONE, _NONE)  # type: ignore[assignment]
        fbo.depth_mask = False
        lo_u, hi_u = self._bprog["u_lo"], self._bprog["u_hi"]
        for q, b in zip(pool, boxes, strict=False):
            lo_u.value = tuple(b[:3] - 0.05)
            hi_u.value = tuple(b[3:] + 0.05)
            with q:
                self._box.render(moderngl.TRIANGLES)
        fbo.color_mask = (_ALL, _ALL)  # type: ignore[assignment]
        fbo.depth_mask = True
