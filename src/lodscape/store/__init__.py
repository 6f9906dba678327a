"""Tileset formats: quantized-mesh terrain tiles, the embedded SQLite tileset, Cesium export."""

from lodscape.store import quantized_mesh

__all__ = ["quantized_mesh"]
