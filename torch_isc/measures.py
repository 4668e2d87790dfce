"""Differentiable measures of implicit simplicial curves (public API; see
:mod:`torch_isc.core.measures`): ``area``, ``length``, ``centroid``, ``curvature``,
``point_curve_distance``.

Example:
    >>> import torch, torch_isc
    >>> m = torch_isc.square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
    >>> c = torch_isc.ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)
    >>> torch_isc.measures.area(c), torch_isc.measures.length(c)
    (tensor([1.4400], dtype=torch.float64), tensor([4.8000], dtype=torch.float64))
"""
from torch_isc.core.measures import (TriangleSegments, area, centroid, curvature, length,  # noqa: F401
                                     point_curve_distance, triangle_segments)

__all__ = ["area", "length", "centroid", "curvature", "point_curve_distance", "TriangleSegments",
           "triangle_segments"]
