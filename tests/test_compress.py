"""Block-compressed textures (paper 001): the numpy BC1/BC3 encoder against the GL's own decoding,
and a scene drawn with compressed imagery against the same scene uncompressed."""

from __future__ import annotations

import numpy as np
import pytest

import lodscape
from lodscape.data import sample_dem_path
from lodscape.imagery.compress import BC1, BC3, compress, decode, mip_chain
from lodscape.render._context import create_context


def _picture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A photo-like picture: smooth colour fields, fine noise, and hard edges."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([np.sin(6 * x + 1), np.cos(5 * y), np.sin(4 * (x + y))], -1) * 0.5 + 0.5
    base[(x - 0.5) ** 2 + (y - 0.4) ** 2 < 0.04] = (0.9, 0.2, 0.1)  # a disc with a hard rim
    img = base * 200 + 30 + rng.normal(0, 4, (h, w, 3))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(float) - b.astype(float)) ** 2).mean())
    return 10 * np.log10(255.0**2 / max(mse, 1e-9))


@pytest.mark.parametrize("shape", [(256, 256), (257, 255), (5, 3), (1, 1)])
def test_every_level_compresses_to_the_gl_sizes_and_decodes_close(shape: tuple[int, int]) -> None:
    h, w = shape
    img = _picture(h, w)
    c = compress(img)
    assert c.format == BC1
    levels = mip_chain(img)
    assert [(lw, lh) for lw, lh, _ in c.levels] == [(lv.shape[1], lv.shape[0]) for lv in levels]
    # the GL's level sizes, down to 1×1
    assert [lw for lw, _, _ in c.levels] == [max(1, w >> i) for i in range(len(c.levels))]
    assert c.levels[-1][:2] == (1, 1)
    for (lw, lh, blocks), level in zip(c.levels, levels, strict=True):
        assert len(blocks) == 8 * -(-lw // 4) * -(-lh // 4)
        assert decode(BC1, lw, lh, blocks).shape == level.shape
    if h >= 64:
        assert _psnr(decode(BC1, w, h, c.levels[0][2]), img) > 33.0
        # a sixth of RGB's bytes, all levels together
        assert c.nbytes < img.nbytes * 4 / 3 / 5.9


def test_alpha_masks_stay_exact_in_bc3() -> None:
    img = _picture(64, 64)
    alpha = np.where(np.add.outer(np.arange(64), np.arange(64)) < 70, 0, 255).astype(np.uint8)
    rgba = np.concatenate([img, alpha[..., None]], axis=2)
    c = compress(rgba)
    assert c.format == BC3
    out = decode(BC3, 64, 64, c.levels[0][2])
    assert np.array_equal(out[..., 3], alpha)
    assert _psnr(out[..., :3], img) > 33.0
    # a smooth alpha ramp comes back within an eighth of its block's range
    ramp = np.broadcast_to(np.arange(64, dtype=np.uint8)[None, :] * 4, (64, 64))
    c2 = compress(np.concatenate([img, ramp[..., None]], axis=2))
    got = decode(BC3, 64, 64, c2.levels[0][2])[..., 3].astype(int)
    assert np.abs(got - ramp).max() <= 2


def _level(w: int, h: int, comp: int, level: int) -> np.ndarray:
    """Mip ``level`` of the texture bound to unit 0, as the GL decodes it (glGetTexImage)."""
    import ctypes

    gl = ctypes.CDLL("libOpenGL.so.0")
    gl.glPixelStorei(0x0D05, 1)  # GL_PACK_ALIGNMENT
    out = np.zeros((h, w, comp), np.uint8)
    fmt = 0x1907 if comp == 3 else 0x1908  # GL_RGB, GL_RGBA
    gl.glGetTexImage(0x0DE1, level, fmt, 0x1401, out.ctypes.data_as(ctypes.c_void_p))
    return out


def test_the_gl_decodes_our_blocks_as_we_do() -> None:
    from lodscape.render import _compressed

    ctx = create_context()
    try:
        if not _compressed.has_s3tc(ctx):
            pytest.skip("this GL has no S3TC")
        for comp in (3, 4):
            img = _picture(32, 48, seed=comp)
            if comp == 4:
                img = np.concatenate([img, (img[..., :1] > 128).astype(np.uint8) * 255], axis=2)
            c = compress(img)
            tex = _compressed.texture(ctx, c)
            tex.use(0)
            for level, (lw, lh, blocks) in enumerate(c.levels):
                gl = _level(lw, lh, comp, level)
                ours = decode(c.format, lw, lh, blocks)
                assert np.abs(gl.astype(int) - ours).max() <= 1, (comp, level)
            tex.release()
    finally:
        ctx.release()


def test_a_scene_with_compressed_textures_looks_the_same_in_less_memory() -> None:
    got = {}
    for on in (False, True):
        opts = lodscape.SceneOptions(compress_textures=on)
        with lodscape.open(sample_dem_path(), opts) as scene:
            cam = scene.overview_camera(160, 120)
            rgb, depth = scene.render(cam)
            assert scene._renderer is not None
            assert scene._renderer.compress is on
            got[on] = (rgb, depth, scene.frame_stats()["resident_mb"])
    (a, da, mb_a), (b, db, mb_b) = got[False], got[True]
    assert np.array_equal(da, db)  # the same geometry
    assert _psnr(a, b) > 30.0
    assert mb_b < 0.6 * mb_a  # textures are most of the GPU bytes here


def test_compressed_texture_errors_name_the_problem() -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        compress(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        compress(np.zeros((0, 4, 3), np.uint8))
