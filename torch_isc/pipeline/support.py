"""Curve-to-data evidence for the sign estimate: an edge that lies provably far from every
data point should not change sign.

The line evidence of eq. 3.6 says where the data put a crossing; nothing in it says that a
crossing *away* from the data is wrong, except the empty triangles' ``L = (1, 1, 1)``. A
triangle that holds a few points of one wall of a thin neck, or the points of a sharp inner
corner, is not empty, and the Ising minimum then cuts necks (a channel of outside signs across
a stroke) or leaves small loops inside strokes, whose zero set runs where no data are. The
zero set of a fit must pass within the tolerance of the data (that is what the test asks), so
a sign change on an edge whose every point is farther than that from the data contradicts the
data as much as a missing crossing does. This module turns that into a ferromagnetic
coupling added to the edge weights ``H_e``.

The distance of an edge to the data is bounded below by the triangle inequality: every point
``x`` of edge ``(i, j)`` (length ``ℓ``) has ``d(x) ≥ max(d_i − |x − v_i|, d_j − |x − v_j|)``,
whose minimum along the edge is ``(d_i + d_j − ℓ) / 2`` (``d_i``: vertex ``i``'s distance to the
nearest data point). The same bound gives the geometry fit's crossing term.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Tuple

import torch

from torch_isc.core.mesh import MeshBatch

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["edge_data_gap", "unsupported_coupling", "support_coupling"]


def edge_data_gap(mesh: MeshBatch, data_dist: torch.Tensor) -> torch.Tensor:
    """``(E,)`` a lower bound of each edge's distance to the data, ``max(0, (d_i + d_j − ℓ)/2)``
    from the vertex distances ``data_dist (V,)`` (``inf`` where a vertex has no known data
    point near it, so the edge's bound is ``inf`` too)."""
    with torch.no_grad():
        e = mesh.edges
        v = mesh.verts.detach()
        ell = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
        d = data_dist.to(v.dtype)
        return (0.5 * (d[e[:, 0]] + d[e[:, 1]] - ell)).clamp_min(0)


def unsupported_coupling(gap: torch.Tensor, reach: torch.Tensor, weight: float) -> torch.Tensor:
    """``(E,)`` the coupling (``≤ 0``, i.e. favouring equal signs) added to ``H_e``:
    ``−weight · clamp(gap / reach − 1, 0, 1)``: nothing for an edge that may come within
    ``reach`` (per edge) of the data, the full ``weight`` from twice that on."""
    with torch.no_grad():
        u = (gap / reach.clamp_min(torch.finfo(gap.dtype).tiny) - 1.0).clamp(0.0, 1.0)
        return -float(weight) * u


def support_coupling(ws: "WorkingSet", weight: float, noise_widths: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(E,)`` :func:`unsupported_coupling` for the working set's mesh, and ``(V,)`` bool, the
    vertices farther than ``reach`` from the data. ``reach`` is the item's tolerance, never
    below ``noise_widths`` times its noise (the distance the test allows a curve to be from
    the data). Vertex distances are those to the points located in or next to each vertex's
    star (:func:`~torch_isc.pipeline.values.vertex_data_distance_near`); an edge with an end of
    unknown distance gets no coupling."""
    from torch_isc.pipeline.values import vertex_data_distance_near
    with torch.no_grad():
        mesh = ws.mesh
        d = vertex_data_distance_near(mesh, ws.points, ws.face)
        reach = torch.maximum(ws.tol, noise_widths * ws.noise).to(mesh.dtype)
        far = d > reach[mesh.vert_item]
        if weight <= 0:
            return torch.zeros(mesh.edges.shape[0], dtype=mesh.dtype, device=mesh.device), far
        # an edge with no data point near one of its ends gets nothing: the empty triangles speak
        # there already, and a gap in the sampling must stay closable
        gap = edge_data_gap(mesh, d)
        gap = torch.where(torch.isfinite(gap), gap, torch.zeros_like(gap))
        return unsupported_coupling(gap, reach[mesh.edge_item], weight), far
