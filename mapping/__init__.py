"""Gaussian-process occupancy mapping (O'Callaghan & Ramos, IJRR 2012), the occupancy-grid baseline and map
metrics (SPEC section 1: knows nothing of bags or GTSAM).

The main names are importable from the package (``from mapping import GPOccupancyMap, MapBuilder,
MapLayers``); each is imported on first use, so ``import mapping`` stays cheap (no SciPy, no numba).
"""

from __future__ import annotations

import importlib

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (type checkers read this name)
if TYPE_CHECKING:
    from mapping.build import MapBuilder
    from mapping.exports import MapLayers
    from mapping.gpmap import GPOccupancyMap, Prediction

#: Public name -> the module that defines it.
_LAZY = {
    "GPOccupancyMap": "mapping.gpmap",
    "Prediction": "mapping.gpmap",
    "MapBuilder": "mapping.build",
    "MapLayers": "mapping.exports",
}

__all__ = ["GPOccupancyMap", "MapBuilder", "MapLayers", "Prediction"]


def __getattr__(name: str) -> object:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mapping' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
