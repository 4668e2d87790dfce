"""torch_isc: implicit simplicial curves in PyTorch (Taubin & Ronfard, PAMI 1996).

Reconstruct 2D curves of unknown topology from unorganized points, batched, on CPU or GPU.

The names below load their modules on first use (PEP 562), so ``import torch_isc`` and the
command line's start do not import torch before they need it.
"""
from __future__ import annotations

import importlib
from typing import Any, List

__version__ = "0.1.0"

_EXPORTS = {
    "ConfigError": "torch_isc.pipeline.config", "ReconstructConfig": "torch_isc.pipeline.config",
    "load_config": "torch_isc.pipeline.config",
    "ImplicitCurve": "torch_isc.core.curve", "InvalidValuesError": "torch_isc.core.curve",
    "Polylines": "torch_isc.core.extract", "extract_zero_set": "torch_isc.core.extract",
    "barycentric": "torch_isc.core.locate", "locate_children": "torch_isc.core.locate",
    "locate_grid": "torch_isc.core.locate", "locate_walk": "torch_isc.core.locate",
    "InvalidMeshError": "torch_isc.core.mesh", "MeshBatch": "torch_isc.core.mesh",
    "hexagon_mesh": "torch_isc.core.mesh", "square_mesh": "torch_isc.core.mesh",
    "ReconstructionResult": "torch_isc.pipeline.result", "PointSetError": "torch_isc.core.points",
    "reconstruct": "torch_isc.pipeline.loop", "reconstruct_batch": "torch_isc.pipeline.loop",
    "refit": "torch_isc.pipeline.refit", "attach_point_gradients": "torch_isc.pipeline.refit",
}
_SUBMODULES = ("measures", "render", "images", "io", "metrics", "runner", "cli", "core", "pipeline")

__all__ = sorted(_EXPORTS) + ["measures", "render"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"torch_isc.{name}")
    else:
        raise AttributeError(f"module 'torch_isc' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> List[str]:
    return sorted(set(globals()) | set(_EXPORTS) | set(_SUBMODULES))
