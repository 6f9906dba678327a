"""Packed R-trees over object boxes (paper 001's scene tree), and hierarchical frustum culling.

Three bulk packings: STR (sort-tile-recursive: slabs by x, runs by y) and Hilbert (objects in
the order of their centres' Hilbert index), whose levels above group consecutive nodes of that
order, and the Priority R-tree (Arge, de Berg, Haverkort and Yi, 2004), which paper 001 found
best: each level is the leaves of a pseudo-PR-tree over the level below (the plan boxes as 4-d
points; at each node the most extreme boxes in each of the four directions make four priority
leaves, and the rest is split at the median of the next coordinate in turn), so thin or long
boxes do not stretch the leaves of compact ones. ``bench/bench_city.py`` compares the three on
the benchmark's paths (frame time, triangles and boxes tested per frame) and the scene keeps
the better (``DEFAULT_PACKING``).

A tree is stored level by level, leaves first: ``levels[0]`` holds the leaves' boxes (each leaf a
run of ``order`` objects), ``levels[k]`` the boxes of nodes each holding a run of at most
``fanout`` consecutive nodes of level k-1 (``starts[k-1]``). Culling walks from the root down,
one numpy call per level, and does not test the children of a node that lies wholly inside the
frustum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["DEFAULT_PACKING", "PACKINGS", "RTree", "box_planes", "pack"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
DEFAULT_PACKING = "hilbert"
#: The packings ``pack`` knows.
PACKINGS = ("hilbert", "str", "priority")


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
    #: ``starts[k]`` (len(levels[k + 1]) + 1,): where each node of level k + 1 starts its run
    #: of children in level k.
    starts: tuple[I64, ...]

    @property
    def leaves(self) -> int:
        return len(self.levels[0])

    def parent(self, nodes: I64, level: int = 0) -> I64:
        """The parents (in level ``level + 1``) of ``nodes`` of level ``level``."""
        out: I64 = np.searchsorted(self.starts[level], nodes, side="right") - 1
        return out

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
            first, end = self.starts[k - 1][nodes], self.starts[k - 1][nodes + 1]
            inside = np.repeat(inside, end - first)
            nodes = _ranges(first, end)
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


def _ranges(first: I64, end: I64) -> I64:
    """The runs [first, end) one after another (vectorised)."""
    n = end - first
    total = int(n.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    at = np.repeat(first - np.cumsum(n) + n, n)
    out: I64 = at + np.arange(total)
    return out


def _pseudo_pr(points: F64, idx: I64, size: int, axis: int, out: list[I64]) -> None:
    """The leaves of a pseudo-PR-tree over ``points[idx]`` (4-d, smaller is more extreme in
    every coordinate), in depth-first order, each of at most ``size`` entries."""
    while len(idx) > size:
        for d in range(4):
            if len(idx) <= size:
                break
            # the priority leaf: the ``size`` most extreme in direction d
            part = np.argpartition(points[idx, d], size - 1)
            out.append(idx[part[:size]])
            idx = idx[part[size:]]
        if len(idx) <= size:
            break
        # the rest split at the median of the next coordinate, the lower half first
        half = len(idx) // 2
        part = np.argpartition(points[idx, axis], half)
        _pseudo_pr(points, idx[part[:half]], size, (axis + 1) % 4, out)
        idx, axis = idx[part[half:]], (axis + 1) % 4
    if len(idx):
        out.append(idx)


def _pr_groups(boxes: F64, size: int) -> list[I64]:
    """Groups of at most ``size`` boxes: the leaves of a pseudo-PR-tree over their plans."""
    points = np.stack([boxes[:, 0], boxes[:, 1], -boxes[:, 3], -boxes[:, 4]], axis=1)
    out: list[I64] = []
    _pseudo_pr(points, np.arange(len(boxes)), size, 0, out)
    return out


def _priority(boxes: F64, leaf: int, fanout: int) -> RTree:
    """A Priority R-tree: each level the pseudo-PR-tree leaves over the level below, the nodes
    below then put in the order of their new parents (runs of runs, down to the objects)."""
    groups = _pr_groups(boxes, leaf)
    order = np.concatenate(groups).astype(np.int64)
    leaf_start = np.concatenate([[0], np.cumsum([len(g) for g in groups])]).astype(np.int64)
    levels = [_union(boxes[order], leaf_start)]
    starts: list[I64] = []
    while len(levels[-1]) > 1:
        k = len(levels) - 1
        groups = _pr_groups(levels[k], fanout)
        perm = np.concatenate(groups).astype(np.int64)
        # reorder level k by perm, and every level below by the runs its nodes own
        levels[k] = levels[k][perm]
        for j in range(k - 1, -1, -1):
            below = starts[j]
            first, end = below[perm], below[perm + 1]
            starts[j] = np.concatenate([[0], np.cumsum(end - first)]).astype(np.int64)
            perm = _ranges(first, end)
            levels[j] = levels[j][perm]
        first, end = leaf_start[perm], leaf_start[perm + 1]
        order = order[_ranges(first, end)]
        leaf_start = np.concatenate([[0], np.cumsum(end - first)]).astype(np.int64)
        s = np.concatenate([[0], np.cumsum([len(g) for g in groups])]).astype(np.int64)
        starts.append(s)
        levels.append(_union(levels[k], s))
    return RTree(order, leaf_start, tuple(levels), fanout, "priority", tuple(starts))


def _order(boxes: F64, leaf: int, packing: str) -> I64:
    c = (boxes[:, :3] + boxes[:, 3:]) / 2.0
    n = len(boxes)
    if packing == "hilbert":
        lo, hi = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
        q = ((c[:, :2] - lo) / np.maximum(hi - lo, 1e-9) * 65535.0).astype(np.uint64)
        order: I64 = np.argsort(_hilbert(q[:, 0], q[:, 1]), kind="stable")
        return order
    if packing != "str":
        raise ValueError(f"unknown R-tree packing {packing!r} ({', '.join(PACKINGS)})")
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
    if packing == "priority":
        return _priority(boxes, leaf, fanout)
    order = _order(boxes, leaf, packing)
    start = np.append(np.arange(0, n, leaf), n).astype(np.int64)
    levels = [_union(boxes[order], start)]
    starts = []
    while len(levels[-1]) > 1:
        # upper levels group consecutive nodes: the leaves' order is already spatial
        cur = levels[-1]
        s = np.append(np.arange(0, len(cur), fanout), len(cur)).astype(np.int64)
        starts.append(s)
        levels.append(_union(cur, s))
    return RTree(order, start, tuple(levels), fanout, packing, tuple(starts))
