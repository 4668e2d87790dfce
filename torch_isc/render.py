"""Soft occupancy and soft rasterization of implicit simplicial curves (public API; see
:mod:`torch_isc.core.render`): ``soft_inside``, ``rasterize``, ``pixel_centers``.

Example:
    >>> import torch, torch_isc
    >>> m = torch_isc.square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
    >>> c = torch_isc.ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)
    >>> torch_isc.render.rasterize(c, 8, 8, tau=0.05).shape
    torch.Size([1, 8, 8])
"""
from torch_isc.core.render import pixel_centers, rasterize, soft_inside  # noqa: F401

__all__ = ["soft_inside", "rasterize", "pixel_centers"]
