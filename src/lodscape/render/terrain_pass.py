"""The terrain pass: textured tile meshes into an offscreen colour + view-distance framebuffer.

Precision: vertices stay float32 relative to their tile centre, and the Earth-sized translation
(centre − camera) is folded into each draw's matrix in float64 on the CPU before the cast, so the
GPU never adds two large numbers and a tile 6,000 km from the origin does not jitter.

Depth: the view distance (camera-space −z, metres) is written to an R32F colour attachment rather
than read back from the depth buffer, whose non-linear 24-bit values lose centimetres far away.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from types import TracebackType
from typing import Any, TypeVar

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import WGS84_A, WGS84_B, enu_basis
from lodscape.geo.keys import is_texture, tile_id_of_array, tile_of
from lodscape.geo.tiles import bounds_array, tile_from_id_array
from lodscape.imagery.compress import Compressed
from lodscape.imagery.compress import compress as compress_image
from lodscape.imagery.tint import NODATA_GREY
from lodscape.lod.camera import Camera
from lodscape.lod.view import DrawItem
from lodscape.render import labels
from lodscape.render._context import create_context, is_software, make_current
from lodscape.render._depth import with_log_depth
from lodscape.render._shaders import shader
from lodscape.render.target import FrameTarget, GLObject, as_rgb, clip_y
from lodscape.render.tess_pass import LAYER_UNIT, MAX_OVERLAYS, TessTerrain, bind_layers
from lodscape.terrain.heightmap import height_tile
from lodscape.terrain.mesh import TileMesh, grid_indices

__all__ = ["DrawItem", "DrawStats", "Renderer"]

Rgb = tuple[float, float, float]


_T = TypeVar("_T", bound=GLObject)

#: The terrain's underside, shared by both ground shaders: seen from below (the surface's
#: normal, turned to the outside, faces away from the eye; past the data's edge or a hole's rim)
#: it is a dark curtain, not the ground's colours seen from beneath. A skirt, which hangs plumb,
#: is part of it where it hangs above the eye (seen from above, skirts fill cracks in the
#: ground's colours). The CPU meshes are wound counter-clockwise seen from above (``upload``
#: makes them so), so their back faces are the surface seen from below: the rasteriser's
#: facing, where the tessellated mode (HEIGHT_NORMALS) works the normal out per fragment.
_UNDERSIDE = shader("terrain_underside.glsl")

_VERTEX_SHADER = shader("terrain_vertex.glsl")

_FRAGMENT_SHADER = shader("terrain_fragment.glsl")

_LANDCOVER_FRAGMENT_SHADER = shader("terrain_landcover_fragment.glsl")

_ELLIPSOID_VERTEX = shader("terrain_ellipsoid_vertex.glsl")

_ELLIPSOID_FRAGMENT = shader("terrain_ellipsoid_fragment.glsl")
_ELLIPSOID_FRAGMENT = _ELLIPSOID_FRAGMENT.replace("NO_DATA_LABEL", f"{float(labels.NO_DATA):.1f}")

#: Colour of the ellipsoid where there is no terrain: the no-data grey, lit as the tint is.
ELLIPSOID_GREY = (NODATA_GREY / 255.0,) * 3

#: A dataset's second pass (``Renderer.draw_labels``): compiled with LABELS, a fragment writes
#: its view-space normal (towards the camera) and its semantic class (``render.labels``) into
#: an RGBA32F target instead of its colour; ``u_class_label`` maps a ground class to its label.
#: A variant, not a branch: the colour programs carry none of it.
_LABELS = shader("terrain_labels.glsl")
_FRAGMENT_SHADER = _FRAGMENT_SHADER.replace("UNDERSIDE_GLSL", _UNDERSIDE + _LABELS)
_LANDCOVER_FRAGMENT_SHADER = _LANDCOVER_FRAGMENT_SHADER.replace(
    "UNDERSIDE_GLSL", _UNDERSIDE + _LABELS
)

#: Ground texture coordinates wrap every this many metres (a whole number of every repeat).
GROUND_WRAP = 4096.0

_VERTEX_FORMAT = ("3f 2f 1f", "in_pos", "in_uv", "in_skirt")
_MAX_ANISOTROPY = 16.0
_ALL = (True, True, True, True)
_NONE = (False, False, False, False)


@dataclass(frozen=True)
class DrawStats:
    """What the last ``Renderer.draw`` issued."""

    draw_calls: int = 0
    triangles: int = 0
    #: Milliseconds the CPU spent issuing the terrain's draws (uniforms and calls, no waiting
    #: for the GPU): the CPU side of a frame's terrain.
    submit_ms: float = 0.0


@dataclass(eq=False)
class _Tile:
    vbo: moderngl.Buffer
    vao: moderngl.VertexArray
    #: An irregular mesh's own index buffer (None: the shared one of its grid size).
    ibo: moderngl.Buffer | None
    segments: int
    triangles: int
    nbytes: int
    center: NDArray[np.float64]
    up: bytes
    cone: NDArray[np.float64] | None = None
    #: The geomorph offsets' buffer (None: the mesh is not morphed).
    morph: moderngl.Buffer | None = None


@dataclass(eq=False)
class _GpuTile:
    """What the renderer keeps on the CPU of a tile drawn by the GPU terrain mode."""

    center: NDArray[np.float64]
    cone: NDArray[np.float64] | None
    nbytes: int
    #: Triangles of the tile's CPU mesh (the full tessellation draws about as many).
    triangles: int


class Renderer:
    """Owns the GL objects of the tiles uploaded to it and draws any subset of them per frame.

    Every method must be called from the thread that created the renderer (the GL thread).
    ``anisotropy`` caps the anisotropic filtering of tile textures (1 disables it; software
    rasterisers always get 1).
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        ctx: moderngl.Context | None = None,
        background: Rgb = (0.53, 0.70, 0.90),
        anisotropy: float = _MAX_ANISOTROPY,
        terrain_mode: str = "cpu",
        tess_px: float = 4.0,
        ground: str = "imagery",
        ellipsoid: bool = True,
        compress: bool = False,
        layers: int = MAX_OVERLAYS,
        log_depth: bool = False,
    ) -> None:
        if terrain_mode not in ("cpu", "gpu"):
            raise ValueError(f"terrain mode is cpu or gpu, got {terrain_mode!r}")
        if ground not in ("imagery", "landcover"):
            raise ValueError(f"ground is imagery or landcover, got {ground!r}")
        #: "landcover": textures are class masks, coloured from the ground materials.
        self.ground = ground
        self._owns_ctx = ctx is None
        self.ctx: moderngl.Context = create_context() if ctx is None else ctx
        self._thread = threading.get_ident()
        self._closed = False
        self.last_stats = DrawStats()
        self._live = 0
        self._tiles: dict[int, _Tile] = {}
        self._textures: dict[int, tuple[moderngl.Texture, int]] = {}
        # one index buffer per segment count, shared by its tiles and freed with the last of them
        self._indices: dict[int, tuple[moderngl.Buffer, int]] = {}
        make_current(self.ctx)
        if not 0 <= layers <= MAX_OVERLAYS:
            raise ValueError(f"at most {MAX_OVERLAYS} imagery layers, got {layers}")
        #: Imagery layers a tile may carry: the programs hold the code of this many.
        self.layers = layers
        fragment = _FRAGMENT_SHADER if ground == "imagery" else _LANDCOVER_FRAGMENT_SHADER
        fragment = _with_define(fragment, f"LAYERS {layers}")
        #: Depth is the log of the distance (``render._depth``): one depth test for passes
        #: from the street to orbit (the globe's), at the cost of the early depth test.
        self.log_depth = log_depth
        if log_depth:
            fragment = with_log_depth(fragment)
        self._fragment = fragment
        self._program = self._track(
            self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=fragment)
        )
        #: The label pass's variants (``draw_labels``), made when first asked for, and the
        #: vertex arrays it makes for its tiles (released when it ends).
        self._labels_prog: moderngl.Program | None = None
        self._label_vaos: dict[int, moderngl.VertexArray] = {}
        #: Texture keys with no texel to cut (alpha everywhere), the program variant that
        #: draws their tiles without a discard, and its vertex arrays per tile.
        self._whole: set[int] = set()
        #: Draw the tiles whose texture has nothing to cut by the variant without a discard
        #: (False: every tile by the cutting program, as before; for the benchmark).
        self.no_discard = True
        self._whole_prog: moderngl.Program | None = None
        self._whole_vaos: dict[int, moderngl.VertexArray] = {}
        self._ellipsoid_labels: tuple[moderngl.Program, moderngl.VertexArray] | None = None
        self._bind(self._program)
        self._set_units(self._program)
        # what an imagery layer shows where it has no tile (yet): nothing
        self._clear = self._track(self.ctx.texture((1, 1), 4, bytes(4)))
        #: Draw the ellipsoid (height 0) behind the terrain: the world outside the data.
        self.ellipsoid = ellipsoid
        self._ellipsoid: tuple[moderngl.Program, moderngl.VertexArray] | None = None
        #: The Earth's image on the ellipsoid (``set_earth``; None: the no-data grey).
        self._earth: moderngl.Texture | None = None
        self._data_box = np.zeros(4, np.float32)
        #: The ground materials a land-cover mask is coloured from.
        self._materials = self._ground_materials() if ground == "landcover" else None
        # 1 turns it off. On a software rasteriser (llvmpipe) anisotropic filtering triples the
        # cost of a frame and takes minutes at a grazing view over a magnified texture: off there
        cap = 1.0 if is_software(self.ctx) else float(self.ctx.max_anisotropy)
        self._anisotropy = max(1.0, min(cap, float(anisotropy)))
        #: Where frames are drawn and how they come back (``render.target``).
        self.target = FrameTarget(
            self.ctx,
            self._track,
            self._free,
            self._use,
            background=as_rgb(background),
            log_depth=log_depth,
        )
        self.target._target_for(width, height)
        #: The land-cover classes the ground textures hold (the label pass maps them).
        self._classes: tuple[str, ...] | None = None
        if ground == "landcover":
            from lodscape.imagery.landcover import CLASSES

            self._classes = CLASSES
        #: "gpu": tiles are height textures tessellated in hardware (``render.tess_pass``).
        self.terrain_mode = terrain_mode
        #: Draw the terrain's triangles as lines (the viewer's wireframe key).
        self.wireframe = False
        #: Tint each tile by its level (the viewer's LOD colouring key).
        self.lod_colours = False
        #: Imagery textures go to the GPU block-compressed (BC1 RGB, BC3 RGBA; compressed on
        #: the workers in ``prepare``) where the context takes S3TC; asked for where it does
        #: not, textures stay uncompressed and ``compress_note`` says why.
        self.compress, self.compress_note = self._compression(compress and ground == "imagery")
        self._tess: TessTerrain | None = None
        self._gpu_tiles: dict[int, _GpuTile] = {}
        if terrain_mode == "gpu":
            self._tess = TessTerrain(self.ctx, fragment)
            self._tess.px_per_segment = float(tess_px)

    def _ground_materials(self) -> moderngl.TextureArray:
        """The land-cover classes' materials, one mipmapped layer each, on unit 4."""
        from lodscape.imagery.landcover import ground_layers

        stack = ground_layers()
        mats = self._track(
            self.ctx.texture_array(
                (stack.shape[2], stack.shape[1], stack.shape[0]), 4, stack.tobytes()
            )
        )
        mats.build_mipmaps()
        mats.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        mats.repeat_x = mats.repeat_y = True
        self._uniform("u_ground_materials").value = 4
        return mats

    def _compression(self, asked: bool) -> tuple[bool, str | None]:
        """Whether textures go block-compressed, and why not where asked for and refused."""
        if not asked:
            return False, None
        from lodscape.render._compressed import has_s3tc

        if has_s3tc(self.ctx):
            return True, None
        return False, (
            "texture compression: this OpenGL has no S3TC (BC1/BC3) textures; textures stay "
            "uncompressed"
        )

    @property
    def read_back(self) -> bool:
        """False: frames stay in the target (a window shows it); nothing comes back."""
        return self.target.read_back

    @read_back.setter
    def read_back(self, on: bool) -> None:
        self.target.read_back = on

    @property
    def colour_framebuffer(self) -> moderngl.Framebuffer | None:
        """The last frame's colour alone, as a framebuffer a window's can be copied from."""
        return self.target.colour_framebuffer

    @property
    def anisotropy(self) -> float:
        """The anisotropic filtering cap textures get in this context."""
        return self._anisotropy

    # --- resources --------------------------------------------------------------------------

    def prepare(self, key: int, made: TileMesh | NDArray[np.uint8]) -> Any:
        """On a worker (``stream.gpu.GpuResources``): in the GPU terrain mode, a mesh's height
        texture made beside it, so the GL thread only uploads; with ``compress``, a texture's
        compressed mip chain. Touches no GL state."""
        if self.compress and is_texture(key) and not isinstance(made, TileMesh | Compressed):
            return compress_image(np.asarray(made, np.uint8))
        if self._tess is None or not isinstance(made, TileMesh) or made.height_tile is not None:
            return made
        t = tile_of(key)
        return replace(made, height_tile=height_tile(made, t.z, t.x, t.y))

    def upload_resource(self, key: int, made: TileMesh | Compressed | NDArray[np.uint8]) -> int:
        """On the GL thread (``stream.gpu.GpuResources``): upload a mesh or a texture by its
        key; returns the GPU bytes it holds."""
        if is_texture(key):
            self.upload_texture(key, made if isinstance(made, Compressed) else np.asarray(made))
        elif isinstance(made, TileMesh):
            self.upload(made)
        else:
            raise TypeError(f"mesh key {key} came with {type(made).__name__}, not a TileMesh")
        return self._nbytes(key)

    def _nbytes(self, key: int) -> int:
        if key in self._textures:
            return self._textures[key][1]
        tile: _Tile | _GpuTile | None = self._tiles.get(key) or self._gpu_tiles.get(key)
        return 0 if tile is None else tile.nbytes

    def upload(self, mesh: TileMesh) -> None:
        """Make ``mesh`` drawable under its key; uploading a key again is a no-op."""
        self._use()
        if mesh.key in self._tiles or mesh.key in self._gpu_tiles:
            return
        if self._tess is not None:
            t = tile_of(mesh.key)
            ht = (
                mesh.height_tile
                if mesh.height_tile is not None
                else height_tile(mesh, t.z, t.x, t.y)
            )
            nbytes = self._tess.upload(ht)
            self._gpu_tiles[mesh.key] = _GpuTile(
                np.asarray(mesh.center, np.float64).copy(),
                None if mesh.cone is None else np.asarray(mesh.cone, np.float64),
                nbytes,
                mesh.triangles,
            )
            self._live += 2
            return
        s = mesh.segments
        vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        if mesh.indices is not None:
            indices = np.ascontiguousarray(mesh.indices, dtype=np.uint32)
            if vertices.ndim != 2 or vertices.shape[1] != 6 or indices.ndim != 2:
                raise ValueError(f"mesh {mesh.key}: expected (N, 6) vertices and (M, 3) indices")
            if indices.size and int(indices.max()) >= vertices.shape[0]:
                raise ValueError(f"mesh {mesh.key}: index beyond its {len(vertices)} vertices")
            indices = wound_up(vertices, indices, np.asarray(mesh.up, np.float64))
            ibo = self._track(self.ctx.buffer(indices))
            s = 0
        elif vertices.shape != ((s + 1) ** 2 + 4 * s, 6) or s < 1:
            raise ValueError(
                f"mesh {mesh.key}: expected {(s + 1) ** 2 + 4 * s}x6 vertices for {s} segments, "
                f"got {vertices.shape}"
            )
        else:
            ibo = self._index_buffer(s)
        vbo = self._track(self.ctx.buffer(vertices))
        content: list[tuple[Any, ...]] = [(vbo, *_VERTEX_FORMAT)]
        mbo = None
        if mesh.morph is not None and mesh.morph.shape == (len(vertices), 3):
            mbo = self._track(self.ctx.buffer(np.ascontiguousarray(mesh.morph, np.float32)))
            content.append((mbo, "3f", "in_morph"))
        vao = self._track(
            self.ctx.vertex_array(  # type: ignore[no-untyped-call]  # untyped in moderngl's stubs
                self._program,
                content,
                index_buffer=ibo,
                index_element_size=4,
            )
        )
        self._tiles[mesh.key] = _Tile(
            vbo,
            vao,
            ibo if s == 0 else None,
            s,
            mesh.triangles,
            mesh.nbytes,
            np.asarray(mesh.center, dtype=np.float64).copy(),
            np.asarray(mesh.up, dtype=np.float32).tobytes(),
            None if mesh.cone is None else np.asarray(mesh.cone, dtype=np.float64),
            mbo,
        )

    def upload_texture(self, key: int, image: NDArray[np.uint8] | Compressed) -> None:
        """Make ``image`` ((H, W, 3) RGB or (H, W, 4) RGBA, row 0 north; alpha 0 where there is
        no terrain; or its ``Compressed`` mip chain) usable under ``key``, with mipmaps;
        uploading a key again is a no-op. With ``compress`` an image is compressed here."""
        self._use()
        if key in self._textures:
            return
        if self.compress and not isinstance(image, Compressed):
            image = compress_image(np.asarray(image, np.uint8))
        if isinstance(image, Compressed):
            from lodscape.render import _compressed

            if not self.compress:
                raise ValueError(f"texture {key}: compressed, but this renderer does not compress")
            tex = self._track(_compressed.texture(self.ctx, image))
            tex.repeat_x = tex.repeat_y = False
            if self._anisotropy > 1.0:
                tex.anisotropy = self._anisotropy
            self._textures[key] = (tex, image.nbytes)
            return
        image = np.ascontiguousarray(image, dtype=np.uint8)
        if self.ground == "landcover":
            if image.ndim != 3 or image.shape[2] != 1:
                raise ValueError(f"texture {key}: expected an (H, W, 1) mask, got {image.shape}")
            # classes are not blended by the sampler (the shader blends their materials): no
            # mipmaps, nearest texels, one byte each
            tex = self._track(
                self.ctx.texture((image.shape[1], image.shape[0]), 1, image, alignment=1)
            )
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
            self._textures[key] = (tex, image.nbytes)
            return
        if image.ndim != 3 or image.shape[2] not in (3, 4):
            raise ValueError(
                f"texture {key}: expected an (H, W, 3) or (H, W, 4) image, got {image.shape}"
            )
        # rows go up as written, so image row 0 (north) is at t = 0, where v = 0 samples
        tex = self._track(
            self.ctx.texture((image.shape[1], image.shape[0]), image.shape[2], image, alignment=1)
        )
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = False
        if self._anisotropy > 1.0:
            tex.anisotropy = self._anisotropy
        # a full mip chain adds a third to the base level
        self._textures[key] = (tex, image.nbytes * 4 // 3)
        if image.shape[2] == 3 or bool((image[..., 3] >= 128).all()):
            self._whole.add(key)  # nothing to cut: its tiles draw without a discard

    def release(self, key: int) -> None:
        """Free the GL objects of mesh or texture ``key`` (one not resident is ignored)."""
        self._use()
        texture = self._textures.pop(key, None)
        if texture is not None:
            self._free(texture[0])
        self._whole.discard(key)
        whole_vao = self._whole_vaos.pop(key, None)
        if whole_vao is not None:
            self._free(whole_vao)
        if self._gpu_tiles.pop(key, None) is not None:
            assert self._tess is not None
            self._tess.release(key)
            self._live -= 2
            return
        tile = self._tiles.pop(key, None)
        if tile is None:
            return
        for obj in (tile.vao, tile.vbo):
            self._free(obj)
        if tile.morph is not None:
            self._free(tile.morph)
        if tile.ibo is not None:
            self._free(tile.ibo)
            return
        ibo, users = self._indices[tile.segments]
        if users > 1:
            self._indices[tile.segments] = (ibo, users - 1)
        else:
            del self._indices[tile.segments]
            self._free(ibo)

    def resident(self) -> dict[int, int]:
        """GPU bytes of every uploaded mesh (its vertices) and texture (with its mips)."""
        out = {key: tile.nbytes for key, tile in self._tiles.items()}
        out.update((key, tile.nbytes) for key, tile in self._gpu_tiles.items())
        out.update((key, nbytes) for key, (_, nbytes) in self._textures.items())
        return out

    def texture(self, key: int) -> moderngl.Texture | None:
        """The texture uploaded as ``key`` (None: not on the GPU)."""
        entry = self._textures.get(key)
        return None if entry is None else entry[0]

    def live_objects(self) -> int:
        """GL objects this renderer holds now (programs, buffers, VAOs, textures, FBO parts)."""
        return self._live

    # --- drawing ----------------------------------------------------------------------------

    def draw(
        self,
        camera: Camera,
        items: Sequence[DrawItem],
        *,
        background: Rgb | None = None,
        after: Sequence[Callable[[Camera, moderngl.Framebuffer], None]] = (),
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """Render ``items`` from ``camera``: RGB (H, W, 3) uint8, row 0 at the top, and view
        distance (H, W) float32 in metres along the view axis, +inf where nothing was drawn.
        ``after`` passes (the city) draw into the same framebuffer once the terrain is in
        (``lodscape.frame.FrameLoop`` draws a frame's passes through ``target`` instead)."""
        return self._draw(camera, items, background, after, labelled=False)

    def draw_labels(
        self,
        camera: Camera,
        items: Sequence[DrawItem],
        *,
        after: Sequence[Callable[[Camera, moderngl.Framebuffer], None]] = (),
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """The same frame as ``draw`` (same items, same passes) drawn for a dataset: (H, W, 4)
        float32 of the view-space normal facing the camera (x right, y up, z backwards) and
        the semantic label (``render.labels``; 0 where nothing was drawn), and the distance.
        The draw statistics stay the colour frame's."""
        if self.target.ring:
            raise RuntimeError("draw_labels reads back at once: no read ring")
        return self._draw(camera, items, None, after, labelled=True)  # type: ignore[return-value]

    def _label_program(self) -> moderngl.Program:
        """The label pass's variant of the terrain program (made when first asked for)."""
        if self._labels_prog is None:
            prog = self._variant("LABELS")
            u = prog.get("u_class_label", None)
            if isinstance(u, moderngl.Uniform):
                # the compiler keeps only the slots a shader reads (one, for imagery)
                table = labels.ground_labels(self._classes)
                u.write(table[: u.array_length].tobytes())
            self._labels_prog = prog
        return self._labels_prog

    def _set_units(self, prog: moderngl.Program) -> None:
        """A terrain program's samplers on their texture units."""
        for unit, name in (
            (0, "u_tex"),
            (4, "u_ground_materials"),
            *((LAYER_UNIT + i, f"u_layer{i}") for i in range(MAX_OVERLAYS)),
        ):
            u = prog.get(name, None)
            if isinstance(u, moderngl.Uniform):
                u.value = unit

    def _bind(self, prog: moderngl.Program) -> None:
        """Draw the CPU terrain with ``prog`` (the colour program or its label variant)."""
        self._program = prog
        self._u_mvp = self._uniform("u_mvp")
        self._u_rot = self._uniform("u_rot")
        self._u_offset = self._uniform("u_offset")
        self._u_up = self._uniform("u_up")
        self._u_skirt = self._uniform("u_skirt")
        self._u_uv = self._uniform("u_uv")
        self._u_morph = self._uniform("u_morph")

    def _vao_of(self, key: int, tile: _Tile) -> moderngl.VertexArray:
        """A tile's vertex array for the bound program: its own, or (the label pass) one made
        for the pass over the same buffers."""
        if self._program is tile.vao.program:
            return tile.vao
        made = self._whole_vaos if self._program is self._whole_prog else self._label_vaos
        vao = made.get(key)
        if vao is None:
            content: list[tuple[Any, ...]] = [(tile.vbo, *_VERTEX_FORMAT)]
            if tile.morph is not None:
                content.append((tile.morph, "3f", "in_morph"))
            ibo = tile.ibo if tile.ibo is not None else self._indices[tile.segments][0]
            vao = self._track(
                self.ctx.vertex_array(  # type: ignore[no-untyped-call]
                    self._program, content, index_buffer=ibo, index_element_size=4
                )
            )
            made[key] = vao
        return vao

    def _whole_program(self) -> moderngl.Program:
        """The colour program without the cut (made when first asked for)."""
        if self._whole_prog is None:
            self._whole_prog = self._variant("WHOLE")
        return self._whole_prog

    def _variant(self, define: str) -> moderngl.Program:
        """The terrain program compiled with ``define``, its samplers on their units."""
        prog = self._track(
            self.ctx.program(
                vertex_shader=_VERTEX_SHADER, fragment_shader=_with_define(self._fragment, define)
            )
        )
        self._set_units(prog)
        return prog

    def _draw(
        self,
        camera: Camera,
        items: Sequence[DrawItem],
        background: Rgb | None,
        after: Sequence[Callable[[Camera, moderngl.Framebuffer], None]],
        *,
        labelled: bool,
    ) -> tuple[NDArray[Any], NDArray[np.float32]]:
        self._use()
        # resolve every key before touching GL state, so a bad frame changes nothing
        resolved = self._resolve(items)
        fbo = self.target.begin(camera, background=background, labelled=labelled)
        camera = self.target.camera(camera)  # as the frame draws it (upside down when read)
        with self._labelling() if labelled else contextlib.nullcontext():
            self._draw_tiles(camera, items, resolved, fbo, labelled)
        if self.ellipsoid:
            self.draw_ellipsoid(camera, labelled)
        for extra in after:
            extra(camera, fbo)
            fbo.use()
        return self.target.end(camera, labelled)

    def _resolve(
        self, items: Sequence[DrawItem]
    ) -> tuple[list[_Tile | _GpuTile], list[moderngl.Texture]]:
        """The GL objects of ``items``' meshes and textures; a KeyError names one not uploaded."""
        tiles: list[_Tile | _GpuTile] = []
        textures = []
        for item in items:
            tile: _Tile | _GpuTile | None = self._tiles.get(item.key) or self._gpu_tiles.get(
                item.key
            )
            texture = self._textures.get(item.texture)
            if tile is None or texture is None:
                what = f"mesh {item.key}" if tile is None else f"texture {item.texture}"
                raise KeyError(f"{what} is not uploaded to this renderer (upload it first)")
            tiles.append(tile)
            textures.append(texture[0])
        return tiles, textures

    def draw_tiles(self, camera: Camera, items: Sequence[DrawItem], labelled: bool = False) -> None:
        """The terrain pass: ``items`` into the frame ``begin`` started."""
        self._use()
        fbo = self.target.fbo(labelled)
        with self._labelling() if labelled else contextlib.nullcontext():
            self._draw_tiles(camera, items, self._resolve(items), fbo, labelled)

    @contextlib.contextmanager
    def _labelling(self) -> Iterator[None]:
        """The label pass's programs bound; the colour ones again after, the statistics
        staying the colour frame's."""
        stats = self.last_stats
        main = self._program
        self._bind(self._label_program())
        if self._tess is not None:
            self._tess.use_labels(True, labels.ground_labels(self._classes))
        try:
            yield
        finally:
            self._bind(main)
            if self._tess is not None:
                self._tess.use_labels(False, labels.ground_labels(self._classes))
            for vao in self._label_vaos.values():
                self._free(vao)
            self._label_vaos.clear()
            self.last_stats = stats

    def _draw_tiles(
        self,
        camera: Camera,
        items: Sequence[DrawItem],
        resolved: tuple[list[_Tile | _GpuTile], list[moderngl.Texture]],
        fbo: moderngl.Framebuffer,
        labelled: bool,
    ) -> None:
        tiles, textures = resolved
        layers = [self._layers(item) for item in items]
        rot = camera.rotation
        ctx = self.ctx
        fbo.use()
        # no culling: skirts and steep faces are seen from both sides
        ctx.enable_only(moderngl.DEPTH_TEST)
        ctx.wireframe = self.wireframe
        ctx.depth_func = "<"

        t_submit = time.perf_counter()
        ground = _ground_windows([it.key for it in items], camera)
        tints = _tints([it.key for it in items], self.lod_colours)
        if self._materials is not None:
            self._materials.use(4)
            sun = self._program.get("u_sun", None)  # the label variant lights nothing
            if isinstance(sun, moderngl.Uniform):
                sun.write(_sun_view(camera))
        if self._tess is not None:
            if self._materials is not None:
                self._tess.set_sun(_sun_view(camera))
            calls, triangles, submit_s = self._tess.draw(
                camera,
                [
                    (it.key, tex, it.skirt, it.uv, it.sse_budget, g, tint, lay, it.morph)
                    for it, tex, g, tint, lay in zip(
                        items, textures, ground, tints, layers, strict=True
                    )
                ],
            )
            self.last_stats = DrawStats(calls, triangles, submit_s * 1e3)
            ctx.wireframe = False
            return
        triangles = calls = 0
        cpu_tiles = [t for t in tiles if isinstance(t, _Tile)]
        centres = np.array([t.center for t in cpu_tiles]).reshape(-1, 3)
        # every tile's matrix and view-space centre at once, in float64 until the cast; GLSL
        # matrices are column-major: the transposes of the row-major NumPy ones
        mvps = np.ascontiguousarray(
            camera.view_projections(centres).transpose(0, 2, 1), dtype=np.float32
        )
        offsets = ((centres - camera.position) @ rot.T).astype(np.float32)
        main = self._program
        whole = [
            self.no_discard
            and self.ground == "imagery"
            and not labelled
            and item.texture in self._whole
            for item in items
        ]
        # the variant without a discard first, then the cutting one; each near tiles first, so
        # the depth test spares the shading of what they hide
        near = np.linalg.norm(centres - camera.position, axis=1)
        order = sorted(range(len(items)), key=lambda i: (not whole[i], near[i]))
        uniforms: dict[str, Any] = {}
        for n, i in enumerate(order):
            if n == 0 or whole[i] != whole[order[n - 1]]:
                self._bind(self._whole_program() if whole[i] else main)
                self._u_rot.write(np.ascontiguousarray(rot.T, dtype=np.float32))
                uniforms = {
                    name: self._program.get(name, None)
                    for name in ("u_ground", "u_tint", "u_layers", "u_layer_uv")
                }
                if isinstance(uniforms["u_layers"], moderngl.Uniform):
                    uniforms["u_layers"].value = len(layers[0]) if layers else 0
            item, ct, tex = items[i], cpu_tiles[i], textures[i]
            bind_layers(uniforms, layers[i])
            if isinstance(uniforms["u_ground"], moderngl.Uniform):
                uniforms["u_ground"].value = ground[i]
            if isinstance(uniforms["u_tint"], moderngl.Uniform):
                uniforms["u_tint"].value = tints[i]
            self._u_mvp.write(mvps[i])
            self._u_offset.write(offsets[i])
            self._u_up.write(ct.up)
            self._u_skirt.value = float(item.skirt)
            self._u_uv.value = item.uv
            self._u_morph.value = float(item.morph) if ct.morph is not None else 0.0
            tex.use(0)
            vao = self._vao_of(item.key, ct)
            if item.runs is None:
                vao.render(moderngl.TRIANGLES)
                triangles += ct.triangles
                calls += 1
                continue
            for first, count in item.runs:
                vao.render(moderngl.TRIANGLES, vertices=3 * count, first=3 * first)
                triangles += count
                calls += 1
        if self._program is not main:
            self._bind(main)
        self.last_stats = DrawStats(calls, triangles, (time.perf_counter() - t_submit) * 1e3)
        ctx.wireframe = False

    def draw_ellipsoid(self, camera: Camera, labelled: bool = False) -> None:
        """The ellipsoid behind everything, drawn after the terrain at the far plane where the
        depth buffer is still clear (the depth test runs before its shader, so the pixels the
        terrain covers cost nothing), no depth written (the city's passes then draw as over
        the sky); its distance in the distance attachment."""
        fbo = self.target.fbo(labelled)
        fbo.use()
        ctx = self.ctx
        ctx.wireframe = False
        ctx.enable_only(moderngl.DEPTH_TEST)
        ctx.depth_func = "<="
        fbo.depth_mask = False
        # only where its rays can meet it: the sky's pixels are not ray-cast (the rasteriser
        # drops them before the shader)
        fbo.scissor = _ellipsoid_scissor(camera)  # type: ignore[assignment]  # None: no box
        p, vao = self._ellipsoid_program(labelled)
        axes = np.array([WGS84_A, WGS84_A, WGS84_B])
        eye = camera.position / axes  # float64 until the upload
        ty = math.tan(math.radians(camera.fov_y) / 2.0)
        values: dict[str, Any] = {
            "u_to_world": np.ascontiguousarray(camera.rotation, np.float32),  # (R^T) col-major
            # a frame read back is drawn upside down: its window rows run from the top
            "u_tan": np.array([ty * camera.aspect, ty * clip_y(camera)], np.float32),
            "u_size": np.array([camera.width, camera.height], np.float32),
            "u_eye": eye.astype(np.float32),
            "u_c": np.array([float(eye @ eye) - 1.0], np.float32),
            "u_inv_axes": (1.0 / axes).astype(np.float32),
            "u_sun": _sun_world(camera).astype(np.float32),
            "u_colour": np.array(ELLIPSOID_GREY, np.float32),
        }
        for name, value in values.items():
            u = p.get(name, None)
            if isinstance(u, moderngl.Uniform):
                u.write(np.ascontiguousarray(value).tobytes())
        earth = p.get("u_earth", None)
        if isinstance(earth, moderngl.Uniform) and self._earth is not None:
            unit = 15  # a unit no tile texture takes
            self._earth.use(location=unit)
            earth.value = unit
            box = p.get("u_data", None)
            if isinstance(box, moderngl.Uniform):
                box.write(self._data_box.tobytes())
        vao.render(moderngl.TRIANGLES, vertices=3)
        fbo.scissor = None  # type: ignore[assignment]  # moderngl: the test off
        fbo.depth_mask = True
        ctx.depth_func = "<"

    def set_earth(
        self,
        image: NDArray[np.uint8] | None,
        data: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    ) -> None:
        """Draw ``image`` (equirectangular RGB, row 0 at latitude 90, column 0 at longitude
        -180: the Blue Marble) on the ellipsoid outside the ``data`` box (west, south, east,
        north, degrees), the no-data grey inside it (its holes); None: the grey everywhere."""
        self._data_box = np.radians(np.asarray(data, np.float64)).astype(np.float32)
        if self._earth is not None:
            self._free(self._earth)
            self._earth = None
        if image is not None:
            rgb = np.ascontiguousarray(image[..., :3], np.uint8)
            tex = self._track(self.ctx.texture((rgb.shape[1], rgb.shape[0]), 3, rgb.tobytes()))
            tex.build_mipmaps()
            tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            tex.repeat_x, tex.repeat_y = True, False
            self._earth = tex
        if self._ellipsoid is not None:  # the program's variant follows
            self._free(self._ellipsoid[1])
            self._free(self._ellipsoid[0])
            self._ellipsoid = None

    def _ellipsoid_program(
        self, labelled: bool = False
    ) -> tuple[moderngl.Program, moderngl.VertexArray]:
        """The ellipsoid's program (or its label variant) and its empty vertex array."""
        got = self._ellipsoid_labels if labelled else self._ellipsoid
        if got is None:
            fragment = (
                _with_define(_ELLIPSOID_FRAGMENT, "LABELS") if labelled else _ELLIPSOID_FRAGMENT
            )
            if not labelled and self._earth is not None:
                fragment = _with_define(fragment, "EARTH")
            program = self._track(
                self.ctx.program(vertex_shader=_ELLIPSOID_VERTEX, fragment_shader=fragment)
            )
            got = (program, self._track(self.ctx.vertex_array(program, [])))
            if labelled:
                self._ellipsoid_labels = got
            else:
                self._ellipsoid = got
        return got

    def _layers(self, item: DrawItem) -> list[tuple[moderngl.Texture, tuple[float, float, float]]]:
        """A tile's imagery layers as textures: a layer tile not uploaded (failed, or not in
        yet) is transparent, so the layer below shows."""
        if len(item.layers) > self.layers:
            raise ValueError(
                f"this renderer draws at most {self.layers} imagery layers, got {len(item.layers)}"
            )
        out = []
        for key, window in item.layers:
            entry = self._textures.get(key) if key >= 0 else None
            out.append((self._clear if entry is None else entry[0], window))
        return out

    def close(self) -> None:
        """Release every GL object, and the context when this renderer created it."""
        if self._closed:
            return
        self._use()
        for key in [*self._tiles, *self._textures, *self._gpu_tiles]:
            self.release(key)
        self.target.close()
        if self._tess is not None:
            self._tess.close()
            self._tess = None
        self._free(self._clear)
        for pair in (self._ellipsoid, self._ellipsoid_labels):
            if pair is not None:
                self._free(pair[1])
                self._free(pair[0])
        self._ellipsoid = self._ellipsoid_labels = None
        if self._earth is not None:
            self._free(self._earth)
            self._earth = None
        for vao in self._whole_vaos.values():
            self._free(vao)
        self._whole_vaos.clear()
        for prog in (self._labels_prog, self._whole_prog):
            if prog is not None:
                self._free(prog)
        self._labels_prog = self._whole_prog = None
        self._free(self._program)
        self._closed = True
        if self._owns_ctx:
            self.ctx.release()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # --- internals --------------------------------------------------------------------------

    def _use(self) -> None:
        if self._closed:
            raise RuntimeError("this Renderer is closed")
        if threading.get_ident() != self._thread:
            raise RuntimeError("a Renderer must be used from the thread that created it")
        make_current(self.ctx)

    def _track(self, obj: _T) -> _T:
        self._live += 1
        return obj

    def _free(self, obj: GLObject) -> None:
        obj.release()
        self._live -= 1

    def _uniform(self, name: str) -> moderngl.Uniform:
        uniform = self._program[name]
        if not isinstance(uniform, moderngl.Uniform):
            raise TypeError(f"terrain shader member {name!r} is not a uniform")
        return uniform

    def _index_buffer(self, segments: int) -> moderngl.Buffer:
        entry = self._indices.get(segments)
        if entry is None:
            entry = (self._track(self.ctx.buffer(grid_indices(segments))), 0)
        self._indices[segments] = (entry[0], entry[1] + 1)
        return entry[0]


def wound_up(
    vertices: NDArray[np.float32], indices: NDArray[np.uint32], up: NDArray[np.float64]
) -> NDArray[np.uint32]:
    """``indices`` with every triangle counter-clockwise seen from ``up`` (the surface shader
    tells its underside by the rasteriser's facing); plumb ones (skirts) are left as they are.
    Meshers and tilesets wind either way (RTIN clockwise, quantized-mesh counter-clockwise)."""
    if not indices.size:
        return indices
    p = vertices[:, :3].astype(np.float64)
    a, b, c = p[indices[:, 0]], p[indices[:, 1]], p[indices[:, 2]]
    flip = np.cross(b - a, c - a) @ up < 0.0
    if not flip.any():
        return indices
    out = indices.copy()
    out[flip, 1], out[flip, 2] = indices[flip, 2], indices[flip, 1]
    return out


def _with_define(source: str, name: str) -> str:
    """A shader's source with ``#define name`` after its version line."""
    head, _, rest = source.lstrip("\n").partition("\n")
    return f"{head}\n#define {name}\n{rest}"


def _ground_windows(keys: Sequence[int], camera: Camera) -> list[tuple[float, float, float]]:
    """Per tile: its west and north edges in ground metres (Web Mercator scaled to the ground at
    the camera's latitude), modulo ``GROUND_WRAP``, and its size: what ground textures repeat
    over, continuous from tile to tile."""
    if not keys:
        return []
    z, x, y = tile_from_id_array(tile_id_of_array(np.array(keys, dtype=np.uint64)))
    left, _, right, top = bounds_array(z, x, y)
    size = right - left
    k = math.cos(math.radians(camera.lat))
    out = np.column_stack([np.mod(left * k, GROUND_WRAP), np.mod(top * k, GROUND_WRAP), size * k])
    return [(float(a), float(b), float(c)) for a, b, c in out]


#: LOD colouring: a colour per level, repeating (the viewer's key L).
_LEVEL_COLOURS = (
    (0.90, 0.20, 0.20),
    (0.95, 0.60, 0.10),
    (0.90, 0.90, 0.20),
    (0.30, 0.80, 0.30),
    (0.20, 0.70, 0.90),
    (0.30, 0.35, 0.90),
    (0.70, 0.30, 0.85),
)


def _tints(keys: Sequence[int], on: bool) -> list[tuple[float, float, float, float]]:
    """Per tile the tint of its level (half strength), or none."""
    if not on:
        return [(0.0, 0.0, 0.0, 0.0)] * len(keys)
    out = []
    for k in keys:
        r, g, b = _LEVEL_COLOURS[tile_of(k).z % len(_LEVEL_COLOURS)]
        out.append((r, g, b, 0.5))
    return out


def _ellipsoid_scissor(camera: Camera) -> tuple[int, int, int, int] | None:
    """The window rectangle (x, y, width, height; row 0 at the bottom of the target) holding
    every pixel whose ray meets the ellipsoid (``Camera.ellipsoid_box``), None for the whole
    view. A frame read back is drawn upside down: its box's rows turn with it."""
    box = camera.ellipsoid_box()
    if box is None:
        return None
    x0, y0, x1, y1 = box
    if clip_y(camera) < 0.0:
        y0, y1 = -y1, -y0
    w, h = camera.width, camera.height
    left, right = math.floor((x0 + 1.0) / 2.0 * w), math.ceil((x1 + 1.0) / 2.0 * w)
    bottom, top = math.floor((y0 + 1.0) / 2.0 * h), math.ceil((y1 + 1.0) / 2.0 * h)
    if (left, bottom, right, top) == (0, 0, w, h):
        return None
    return left, bottom, right - left, top - bottom


def _sun_world(camera: Camera) -> NDArray[np.float64]:
    """Towards the sun (azimuth 315°, 45° up at the camera, as the tint's hillshade), ECEF."""
    az, alt = math.radians(315.0), math.radians(45.0)
    enu = np.array([math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
    world: NDArray[np.float64] = enu_basis(camera.lon, camera.lat).T @ enu
    return world


def _sun_view(camera: Camera) -> NDArray[np.float32]:
    """``_sun_world`` in view space."""
    return np.asarray(camera.rotation @ _sun_world(camera), np.float32)
