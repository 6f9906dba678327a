"""The GPU stage: what is uploaded, its bytes, and the rule that frees it (a byte budget, least
recently drawn first, never a resource the last frame drew).

The stage talks to the GPU through ``GpuResources`` (cesium-native's ``prepareInLoadThread`` /
``prepareInMainThread`` / ``free``): the renderer implements it, and so does a test's fake, so
streaming is tested frame by frame without OpenGL.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape._lru import ByteLRU
from lodscape.geo.keys import is_texture
from lodscape.lod.view import MeshInfo
from lodscape.terrain.mesh import TileMesh

__all__ = ["GpuResources", "GpuStage", "Made"]

#: A decoded resource: a tile mesh, or a texture's pixels.
Made = TileMesh | NDArray[np.uint8]


class GpuResources(Protocol):
    """Where decoded resources go. ``prepare`` runs on a worker thread (CPU work that needs no
    GL: the GPU terrain mode's height texture); ``upload`` and ``release`` on the GL thread."""

    def prepare(self, key: int, made: Made) -> Made: ...

    def upload_resource(self, key: int, made: Made) -> int:
        """Make ``made`` drawable under ``key``; returns the GPU bytes it holds."""
        ...

    def release(self, key: int) -> None: ...


class GpuStage:
    """The resources uploaded through one ``GpuResources``, with their bytes and, for meshes,
    what the view needs of them (``MeshInfo``)."""

    def __init__(self, gpu: GpuResources, budget_bytes: float) -> None:
        self.gpu = gpu
        self.budget_bytes = budget_bytes
        #: Resident keys and their GPU bytes, least recently drawn first.
        self._lru: ByteLRU[int, None] = ByteLRU()
        self._meshes: dict[int, MeshInfo] = {}
        self._keys: NDArray[np.uint64] | None = None
        #: Uploaded since the last eviction: not drawn yet, wanted by the next frame.
        self._fresh: set[int] = set()

    def __contains__(self, key: object) -> bool:
        return key in self._lru

    @property
    def nbytes(self) -> int:
        return self._lru.nbytes

    def keys(self) -> NDArray[np.uint64]:
        """The resident keys, sorted (made once per change, not per call)."""
        if self._keys is None:
            self._keys = np.array(sorted(self._lru), dtype=np.uint64)
        return self._keys

    @property
    def meshes(self) -> Mapping[int, MeshInfo]:
        return self._meshes

    def upload(self, key: int, made: Made) -> None:
        if key in self._lru:
            return
        nbytes = self.gpu.upload_resource(key, made)
        if not is_texture(key) and isinstance(made, TileMesh):
            self._meshes[key] = MeshInfo(
                np.asarray(made.center, np.float64),
                None if made.cone is None else np.asarray(made.cone, np.float64),
                int(made.triangles),
            )
        self._lru.put(key, None, nbytes)
        self._keys = None
        self._fresh.add(key)

    def upload_within(self, items: Iterable[tuple[int, Made]], budget_ms: float) -> int:
        """Upload (key, resource) pairs in order until ``budget_ms`` of this thread's time is
        spent; returns how many went up (the rest were not consumed)."""
        spent = 0.0
        count = 0
        for key, made in items:
            t = time.perf_counter()
            self.upload(key, made)
            spent += (time.perf_counter() - t) * 1e3
            count += 1
            if spent >= budget_ms:
                break
        return count

    def drawn(self, keys: Iterable[int]) -> None:
        """Mark ``keys`` as drawn this frame (most recently used)."""
        for k in keys:
            self._lru.touch(k)

    def evict(self, keep: frozenset[int]) -> int:
        """Release the least recently drawn resources, never one of ``keep`` (what the last
        frame drew) nor one uploaded since the last eviction (what the next frame asked for),
        until the stage fits its budget; returns how many went."""
        gone = self._lru.shrink(self.budget_bytes, keep | self._fresh)
        self._fresh = set()
        for key, _ in gone:
            self._meshes.pop(key, None)
            self.gpu.release(key)
        if gone:
            self._keys = None
        return len(gone)

    def clear(self) -> None:
        """Forget everything (the GPU objects went with their renderer)."""
        self._lru.clear()
        self._meshes.clear()
        self._fresh = set()
        self._keys = None
