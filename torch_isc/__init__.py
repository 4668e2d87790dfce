"""torch_isc: implicit simplicial curves in PyTorch (Taubin & Ronfard, PAMI 1996).

Reconstruct 2D curves of unknown topology from unorganized points, batched, on CPU or GPU.
"""
from torch_isc.pipeline.config import ConfigError, ReconstructConfig, load_config
from torch_isc.core.curve import ImplicitCurve, InvalidValuesError
from torch_isc.core.extract import Polylines, extract_zero_set
from torch_isc.core.locate import barycentric, locate_children, locate_grid, locate_walk
from torch_isc.core.mesh import InvalidMeshError, MeshBatch, hexagon_mesh, square_mesh
from torch_isc.pipeline.result import ReconstructionResult
from torch_isc.core.points import PointSetError
from torch_isc.pipeline.loop import reconstruct, reconstruct_batch
from torch_isc.pipeline.refit import attach_point_gradients, refit
from torch_isc import measures, render  # noqa: E402  (torch_isc.measures, torch_isc.render)

__version__ = "0.1.0"

__all__ = [
    "reconstruct", "reconstruct_batch", "ReconstructionResult", "ReconstructConfig", "load_config",
    "ImplicitCurve", "MeshBatch", "Polylines", "hexagon_mesh", "square_mesh", "extract_zero_set",
    "barycentric", "locate_grid", "locate_children", "locate_walk",
    "ConfigError", "InvalidMeshError", "InvalidValuesError", "PointSetError",
    "refit", "attach_point_gradients", "measures", "render",
]
