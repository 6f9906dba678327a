"""Block compression of textures (S3TC: BC1 for RGB, BC3 for RGBA), pure numpy, vectorised over
blocks, so a worker thread compresses a tile before the GPU sees it (paper 001's hardware
texture compression: a quarter to an eighth of the texture memory, read as such by the GPU).

Each 4×4 block's colours are fitted along their principal axis (a few power iterations on the
block's covariance), the two extremes' projections become the 5:6:5 end points, and every
texel takes the nearest of the four colours on that line; BC3's alpha takes its block's
extremes and the nearest of eight levels between them (0 and 255 exactly where the alpha is a
mask). The mip chain is made on the CPU (2×2 means, as glGenerateMipmap would) and each level
compressed, since a GL cannot build mipmaps of a compressed texture.

``decode`` turns blocks back into texels (the tests compare it with the GL's own decoding).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["BC1", "BC3", "Compressed", "compress", "decode", "mip_chain"]

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]

#: GL_COMPRESSED_RGB_S3TC_DXT1_EXT and GL_COMPRESSED_RGBA_S3TC_DXT5_EXT.
BC1 = 0x83F0
BC3 = 0x83F3


@dataclass(frozen=True)
class Compressed:
    """A texture's compressed mip chain: ``levels[i]`` is (width, height, blocks) of level i."""

    format: int
    levels: tuple[tuple[int, int, bytes], ...]

    @property
    def nbytes(self) -> int:
        return sum(len(b) for _, _, b in self.levels)


def mip_chain(image: U8) -> list[U8]:
    """Level 0 and each 2×2 mean below it, down to 1×1 (an odd row or column is dropped, as
    the GL's level sizes ``max(1, n >> i)`` do)."""
    out = [image]
    cur = image.astype(np.float32)
    while cur.shape[0] > 1 or cur.shape[1] > 1:
        h, w = cur.shape[:2]
        if h > 1:
            cur = 0.5 * (cur[0 : 2 * (h // 2) : 2] + cur[1 : 2 * (h // 2) : 2])
        if w > 1:
            cur = 0.5 * (cur[:, 0 : 2 * (w // 2) : 2] + cur[:, 1 : 2 * (w // 2) : 2])
        out.append(np.clip(np.rint(cur), 0, 255).astype(np.uint8))
    return out


def compress(image: U8) -> Compressed:
    """An (H, W, 3) or (H, W, 4) uint8 image's mip chain, each level BC1 (RGB) or BC3 (RGBA)."""
    image = np.asarray(image, np.uint8)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or 0 in image.shape[:2]:
        raise ValueError(f"expected an (H, W, 3) or (H, W, 4) image, got {image.shape}")
    rgba = image.shape[2] == 4
    levels = []
    for level in mip_chain(image):
        h, w = level.shape[:2]
        blocks = _blocks(level)
        colour = _bc1(blocks[..., :3])
        data = np.concatenate([_alpha(blocks[..., 3]), colour], axis=1) if rgba else colour
        levels.append((w, h, data.tobytes()))
    return Compressed(BC3 if rgba else BC1, tuple(levels))


def _blocks(image: U8) -> U8:
    """(H, W, C) → (blocks, 16, C) in block row order, texels row by row inside a block; the
    edges repeated out to whole blocks."""
    h, w, c = image.shape
    ph, pw = -h % 4, -w % 4
    if ph or pw:
        image = np.pad(image, ((0, ph), (0, pw), (0, 0)), mode="edge")
    bh, bw = image.shape[0] // 4, image.shape[1] // 4
    b = image.reshape(bh, 4, bw, 4, c).transpose(0, 2, 1, 3, 4)
    return np.ascontiguousarray(b.reshape(bh * bw, 16, c))


def _to565(rgb: F32) -> NDArray[np.uint16]:
    q = np.clip(np.rint(rgb * np.array([31.0, 63.0, 31.0]) / 255.0), 0, [31, 63, 31])
    q = q.astype(np.uint16)
    out: NDArray[np.uint16] = (q[..., 0] << 11) | (q[..., 1] << 5) | q[..., 2]
    return out


def _from565(c: NDArray[np.uint16]) -> F32:
    c = c.astype(np.uint32)
    r, g, b = (c >> 11) & 31, (c >> 5) & 63, c & 31
    out: F32 = np.stack([(r << 3) | (r >> 2), (g << 2) | (g >> 4), (b << 3) | (b >> 2)], -1)
    return out.astype(np.float32)


def _palette(c0: NDArray[np.uint16], c1: NDArray[np.uint16]) -> F32:
    """(n, 4, 3) the four-colour mode's colours (c0 > c1)."""
    a, b = _from565(c0), _from565(c1)
    out: F32 = np.stack([a, b, (2 * a + b) / 3.0, (a + 2 * b) / 3.0], axis=1)
    return out


def _bc1(px: U8) -> U8:
    """(n, 16, 3) texels → (n, 8) BC1 blocks (always the four-colour mode)."""
    x = px.astype(np.float32)
    mean = x.mean(axis=1, keepdims=True)
    d = x - mean
    cov = np.einsum("nki,nkj->nij", d, d)
    axis = np.ones((len(x), 3), np.float32)
    for _ in range(6):
        axis = np.einsum("nij,nj->ni", cov, axis)
        axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    t = np.einsum("nki,ni->nk", d, axis)
    lo = mean[:, 0] + t.min(axis=1, keepdims=True) * axis
    hi = mean[:, 0] + t.max(axis=1, keepdims=True) * axis
    c0, c1 = _to565(hi), _to565(lo)
    # four-colour mode wants c0 > c1; equal end points: one colour, every index 0
    swap = c0 < c1
    c0, c1 = np.where(swap, c1, c0), np.where(swap, c0, c1)
    pal = _palette(c0, c1)
    dist = ((x[:, :, None, :] - pal[:, None, :, :]) ** 2).sum(axis=3)
    idx = dist.argmin(axis=2).astype(np.uint32)
    idx[c0 == c1] = 0
    bits = (idx << (2 * np.arange(16, dtype=np.uint32))).sum(axis=1, dtype=np.uint32)
    out = np.empty((len(x), 8), np.uint8)
    out[:, 0:2] = c0.astype("<u2").view(np.uint8).reshape(-1, 2)
    out[:, 2:4] = c1.astype("<u2").view(np.uint8).reshape(-1, 2)
    out[:, 4:8] = bits.astype("<u4").view(np.uint8).reshape(-1, 4)
    return out


def _alpha_levels(a0: NDArray[np.uint8], a1: NDArray[np.uint8]) -> F32:
    """(n, 8) BC3's alpha levels for a0 > a1 (eight-level mode)."""
    a, b = a0.astype(np.float32)[:, None], a1.astype(np.float32)[:, None]
    k = np.arange(1, 7, dtype=np.float32)[None, :]
    inner = np.floor(((7.0 - k) * a + k * b) / 7.0)
    out: F32 = np.concatenate([a, b, inner], axis=1)
    return out


def _alpha(alpha: U8) -> U8:
    """(n, 16) alpha → (n, 8) BC3 alpha blocks."""
    a0, a1 = alpha.max(axis=1), alpha.min(axis=1)
    flat = a0 == a1
    # a one-level block still uses the eight-level mode (a0 > a1): index 0 everywhere
    a1 = np.where(flat & (a0 > 0), a0 - 1, a1).astype(np.uint8)
    a0 = np.where(flat & (a0 == 0), 1, a0).astype(np.uint8)
    lv = _alpha_levels(a0, a1)
    idx = np.abs(alpha.astype(np.float32)[:, :, None] - lv[:, None, :]).argmin(axis=2)
    bits = (idx.astype(np.uint64) << (3 * np.arange(16, dtype=np.uint64))).sum(
        axis=1, dtype=np.uint64
    )
    out = np.empty((len(alpha), 8), np.uint8)
    out[:, 0], out[:, 1] = a0, a1
    out[:, 2:8] = bits.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :6]
    return out


def decode(fmt: int, width: int, height: int, data: bytes) -> U8:
    """Blocks back into (height, width, 3 or 4) texels (four-colour and eight-level modes,
    which are all ``compress`` writes)."""
    bw, bh = -(-width // 4), -(-height // 4)
    step = 8 if fmt == BC1 else 16
    raw = np.frombuffer(data, np.uint8).reshape(bh * bw, step)
    colour = raw[:, -8:]
    c0 = colour[:, 0:2].copy().view("<u2")[:, 0]
    c1 = colour[:, 2:4].copy().view("<u2")[:, 0]
    bits = colour[:, 4:8].copy().view("<u4")[:, 0]
    idx = (bits[:, None] >> (2 * np.arange(16, dtype=np.uint32))) & 3
    rgb = np.take_along_axis(_palette(c0, c1), idx[:, :, None].astype(np.int64), axis=1)
    px = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    if fmt == BC3:
        a = raw[:, :8]
        abits = np.zeros(len(a), np.uint64)
        for i in range(6):
            abits |= a[:, 2 + i].astype(np.uint64) << np.uint64(8 * i)
        aidx = (abits[:, None] >> (3 * np.arange(16, dtype=np.uint64))) & np.uint64(7)
        lv = _alpha_levels(a[:, 0], a[:, 1])
        alpha = np.take_along_axis(lv, aidx.astype(np.int64), axis=1).astype(np.uint8)
        px = np.concatenate([px, alpha[:, :, None]], axis=2)
    c = px.shape[2]
    img = px.reshape(bh, bw, 4, 4, c).transpose(0, 2, 1, 3, 4).reshape(bh * 4, bw * 4, c)
    return np.ascontiguousarray(img[:height, :width])
