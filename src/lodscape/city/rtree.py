"""Packed R-trees over object boxes (paper 001's scene tree), and hierarchical frustum culling.

Two bulk packings of the leaves, both vectorised: STR (sort-tile-recursive: slabs by x, runs by
y) and Hilbert (objects in the order of their centres' Hilbert index); the levels above group
consecutive nodes of that order. Paper 001 found a Priority R-tree best;
``bench/bench_city.py`` compares these two on the benchmark's paths (frame time, triangles and
boxes tested per frame) and the scene keeps the better (``DEFAULT_PACKING``): Hilbert, though
its leaves' boxes cover more ground than STR's.

A tree is stored level by level, leaves first: ``levels[0]`` holds the leaves' boxes (each leaf a
run of ``order`` objects), ``levels[k]`` the boxes of groups of ``fanout`` nodes of level k-1.
Culling walks from the root down, one numpy call per level, and does not test the children of a
node that lies wholly inside the frustum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["DEFAULT_PACKING", "RTree", "box_planes", "pack"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
DEFAULT_PACKING = "hilbert"


@dataclass(frozen=True, eq=False)
class RTree:
    """A packed R-tree: objects reordered (``order``), each leaf a run of consecutive objects."""

    #: Objects in leaf order (indices into the caller's arrays).
    order: I64
    #: (L + 1,) start of each leaf's run in ``order``.
    leaf_start: I64
    #: Boxes (n, 6: min xyz, max xyz) per level, leaves first; the last level has one node.
    levels: tuple[F64, ...]
    fanout: int
    packing: str

    @property
    def leaves(self) -> int:
        return len(self.levels[0])

    def cull(self, planes: F64) -> tuple[NDArray[np.bool_], int]:
        """Leaves that may be in view of ``planes`` (inward (6, 4), in the boxes' frame), and
        how many boxes were tested."""
        top = len(self.levels) - 1
        nodes = np.arange(len(self.levels[top]))
        inside = np.zeros(len(nodes), dtype=bool)
        tested = 0
        for k in range(top, -1, -1):
            # nodes under one wholly inside are not tested again
            todo = np.nonzero(~inside)[0]
            tested += len(todo)
            state = np.ones(len(nodes), dtype=np.int8)
            state[todo] = box_planes(self.levels[k][nodes[todo]], planes)
            keep = state >= 0
            nodes, inside = nodes[keep], state[keep] > 0
            if k == 0:
                break
            n_below = len(self.levels[k - 1])
            child = nodes[:, None] * self.fanout + np.arange(self.fanout)
            ok = child < n_below
            inside = np.broadcast_to(inside[:, None], child.shape)[ok]
            nodes = child[ok]
        out = np.zeros(self.leaves, dtype=bool)
        out[nodes] = True
        return out, tested


def box_planes(boxes: F64, planes: F64) -> NDArray[np.int8]:
    """For each box: -1 outside a plane, 1 inside all, 0 crossing."""
    lo, hi = boxes[:, :3], boxes[:, 3:]
    n, w = planes[:, :3], planes[:, 3]
    # the corner farthest along each normal (p-vertex) and the nearest (n-vertex)
    pos = n[None, :, :] > 0.0
    pv = np.where(pos, hi[:, None, :], lo[:, None, :])
    nv = np.where(pos, lo[:, None, :], hi[:, None, :])
    far = np.einsum("bpi,pi->bp", pv, n) + w
    near = np.einsum("bpi,pi->bp", nv, n) + w
    out = np.zeros(len(boxes), dtype=np.int8)
    out[(near >= 0.0).all(axis=1)] = 1
    out[(far < 0.0).any(axis=1)] = -1
    return out


def _hilbert(x: NDArray[np.uint64], y: NDArray[np.uint64], bits: int = 16) -> NDArray[np.uint64]:
    """Hilbert index of integer points (vectorised, the classic xy2d)."""
    d = np.zeros(x.shape, dtype=np.uint64)
    x, y = x.copy(), y.copy()
    n = np.uint64(1 << bits)
    s = n // np.uint64(2)
    while s > 0:
        rx = ((x & s) > 0).astype(np.uint64)
        ry = ((y & s) > 0).astype(np.uint64)
        d += s * s * ((np.uint64(3) * rx) ^ ry)
        # rotate
        flip = ry == 0
        swap_x = flip & (rx == 1)
        x = np.where(swap_x, n - np.uint64(1) - x, x)
        y = np.where(swap_x, n - np.uint64(1) - y, y)
        x, y = np.where(flip, y, x), np.where(flip, x, y)
        s //= np.uint64(2)
    return d


def _order(boxes: F64, leaf: int, packing: str) -> I64:
    c = (boxes[:, :3] + boxes[:, 3:]) / 2.0
    n = len(boxes)
    if packing == "hilbert":
        lo, hi = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
        q = ((c[:, :2] - lo) / np.maximum(hi - lo, 1e-9) * 65535.0).astype(np.uint64)
        order: I64 = np.argsort(_hilbert(q[:, 0], q[:, 1]), kind="stable")
        return order
    if packing != "str":
        raise ValueError(f"unknown R-tree packing {packing!r} (str or hilbert)")
    leaves = math.ceil(n / leaf)
    slabs = max(1, math.ceil(math.sqrt(leaves)))
    # a slab holds whole leaves: a leaf cut by a slab's end would span the whole y range
    per_slab = math.ceil(leaves / slabs) * leaf
    by_x = np.argsort(c[:, 0], kind="stable")
    slab = np.empty(n, dtype=np.int64)
    slab[by_x] = np.arange(n) // per_slab
    result: I64 = np.lexsort((c[:, 1], slab))
    return result


def _union(boxes: F64, start: I64) -> F64:
    lo = np.minimum.reduceat(boxes[:, :3], start[:-1], axis=0)
    hi = np.maximum.reduceat(boxes[:, 3:], start[:-1], axis=0)
    return np.concatenate([lo, hi], axis=1)


def pack(boxes: F64, *, leaf: int = 16, fanout: int = 8, packing: str = DEFAULT_PACKING) -> RTree:
    """A packed R-tree over (N, 6) boxes: leaves of up to ``leaf`` objects, ``fanout`` children
    per node above them."""
    boxes = np.asarray(boxes, dtype=np.float64)
    n = len(boxes)
    if n == 0:
        raise ValueError("an R-tree needs at least one object")
    order = _order(boxes, leaf, packing)
    start = np.append(np.arange(0, n, leaf), n).astype(np.int64)
    levels = [_union(boxes[order], start)]
    while len(levels[-1]) > 1:
        # upper levels group consecutive nodes: the leaves' order is already spatial
        cur = levels[-1]
        s = np.append(np.arange(0, len(cur), fanout), len(cur)).astype(np.int64)
        levels.append(_union(cur, s))
    return RTree(order, start, tuple(levels), fanout, packing)
