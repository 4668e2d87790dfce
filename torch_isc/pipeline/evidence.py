"""The data's local evidence per triangle (Section 3.2): point moments, least-squares lines,
and where a line may testify to a crossing. Shared by the sign estimate, the geometry fit
(the moments ``M_t`` of eq. 3.2) and the test (line-fit errors).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from torch_isc.core.segments import segment_sum

from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline.knobs import check_section, knob

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["EvidenceConfig", "TriangleMoments", "LineFits", "LocalFits", "triangle_moments", "pooled_moments", "line_fits",
           "crossing_reach", "own_fits", "local_fits", "Evidence", "gather_evidence"]


@dataclass
class EvidenceConfig:
    """How much data a triangle's line fit needs to count (flat keys of configs/default.yaml)."""
    #: points a triangle needs for its line fit to count as evidence (1-2 points fit a line exactly)
    min_points_fit: int = knob(3, gt=0)
    #: a fitted line testifies to a crossing up to this many residual spreads past its points
    crossing_reach_slack: float = knob(1.0, ge=0)

    def __post_init__(self):
        check_section(self)


@dataclass
class TriangleMoments:
    """Per-triangle sums over the points inside it (eq. 3.2 and the line fit).

    Attributes:
        count: ``(T,)`` number of points. M: ``(T, 3, 3)`` mean of ``X_t(p) X_t(p)ᵀ``.
        centroid: ``(T, 2)`` mean point (triangle centroid where empty).
        scatter: ``(T, 2, 2)`` covariance of the points.
    """
    count: torch.Tensor
    M: torch.Tensor
    centroid: torch.Tensor
    scatter: torch.Tensor


def triangle_moments(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor, bary: torch.Tensor) -> TriangleMoments:
    """Scatter-add the moments of ``points (P, 2)`` located in ``face (P,)`` with ``bary (P, 3)``.

    Cost O(P); afterwards Δ1 costs O(T) per evaluation. Points with ``face < 0`` are ignored.
    """
    T = mesh.faces.shape[0]
    dt = mesh.dtype
    ok = face >= 0
    # a point with no triangle adds zeros to triangle 0 (no boolean indexing: no host read)
    f, X = face.clamp_min(0), torch.where(ok[:, None], bary.to(dt), torch.zeros((), dtype=dt, device=mesh.device))
    p = points.to(dt)
    count = segment_sum(ok.to(dt), f, T)
    M = torch.zeros(T, 9, dtype=dt, device=mesh.device).index_add_(0, f, (X[:, :, None] * X[:, None, :]).reshape(-1, 9))
    # moments about the triangle centroid keep float32 accurate on small triangles
    tc = mesh.verts.detach()[mesh.faces].mean(1)
    q = torch.where(ok[:, None], p - tc[f], torch.zeros((), dtype=dt, device=mesh.device))
    s1 = torch.zeros(T, 2, dtype=dt, device=mesh.device).index_add_(0, f, q)
    s2 = torch.zeros(T, 4, dtype=dt, device=mesh.device).index_add_(0, f, (q[:, :, None] * q[:, None, :]).reshape(-1, 4))
    n = count.clamp_min(1)
    mean = s1 / n[:, None]
    cov = s2.view(T, 2, 2) / n[:, None, None] - mean[:, :, None] * mean[:, None, :]
    return TriangleMoments(count, M.view(T, 3, 3) / n[:, None, None], tc + mean, cov)


def pooled_moments(mesh: MeshBatch, mom: TriangleMoments) -> TriangleMoments:
    """Moments of the points of each triangle and its (up to) three edge-neighbours.

    Combined exactly (parallel-axis rule on the per-triangle means and covariances), so
    small triangles keep their precision. ``M`` is not pooled (it is per-triangle)."""
    nb = mesh.face_neighbors
    T = nb.shape[0]
    idx = torch.cat([torch.arange(T, device=nb.device)[:, None], nb], 1)      # (T,4)
    ok = idx >= 0
    j = idx.clamp_min(0)
    n = torch.where(ok, mom.count[j], torch.zeros_like(mom.count[j]))      # (T,4)
    N = n.sum(1)
    m = mom.centroid[j]                                                     # (T,4,2)
    # offsets from the own centroid keep the sums small
    d = m - mom.centroid[:, None, :]
    mean_d = (n[..., None] * d).sum(1) / N.clamp_min(1)[:, None]
    dd = d - mean_d[:, None, :]
    C = (n[..., None, None] * (mom.scatter[j] + dd[..., :, None] * dd[..., None, :])).sum(1) / N.clamp_min(1)[:, None, None]
    return TriangleMoments(N, mom.M, mom.centroid + mean_d, C)


def line_fits(mesh: MeshBatch, mom: TriangleMoments):
    """Closed-form least-squares line in every triangle.

    Returns:
        L ``(T, 3)``: signed distances of the triangle's vertices to its line (the
        minimizer of ``Lᵀ M L / Lᵀ N L`` up to scale); eps ``(T,)``: mean squared distance
        of the points to the line (the local error of fit ``ε_t``); normal ``(T, 2)``.
    """
    lam, normal = mesh.kernel.hyperplane_fit(mom.scatter)
    tri = mesh.verts.detach()[mesh.faces]                    # (T,3,2)
    L = ((tri - mom.centroid[:, None, :]) * normal[:, None, :]).sum(-1)
    return L, lam, normal


def crossing_reach(mesh: MeshBatch, mom: TriangleMoments, L: torch.Tensor, normal: torch.Tensor,
                   slack: float = 1.0) -> torch.Tensor:
    """``(T, 3)`` bool: where the fitted line crosses edge ``k`` (corners k+1, k+2), is the
    crossing within the extent of the triangle's points along the line?

    Points spread along a segment of half-length ``h`` have variance ``h²/3`` along it, so
    the extent is ``h = √(3 λ_max)`` (plus ``slack ×`` the residual spread ``√ε``)."""
    lam_max, lam_min = mesh.kernel.principal_spread(mom.scatter)
    h = torch.sqrt(3.0 * lam_max)
    # the curve runs on about half a sample spacing (h / (n-1)) past the last point
    half = h * (1.0 + 1.0 / (mom.count - 1).clamp_min(1)) + slack * torch.sqrt(lam_min)
    tang = torch.stack([-normal[:, 1], normal[:, 0]], 1)
    x, _ = mesh.kernel.edge_crossings(mesh.verts.detach()[mesh.faces], L)     # (T,3,2)
    u = ((x - mom.centroid[:, None, :]) * tang[:, None, :]).sum(-1)
    return u.abs() <= half[:, None]




@dataclass
class LineFits:
    """The line fit of every triangle's own points: ``L (T, 3)`` signed distances of its
    corners to the line, ``eps (T,)`` the mean squared residual, ``normal (T, 2)``."""
    L: torch.Tensor
    eps: torch.Tensor
    normal: torch.Tensor


@dataclass
class LocalFits:
    """The line evidence behind the edge weights: a triangle with fewer than
    ``min_points_fit`` points borrows its neighbours' points (pooled fit). ``L, eps`` the
    fits used, ``support (T,)`` the points behind them, ``reach (T, 3)`` whether each edge's
    crossing lies within the extent of those points."""
    L: torch.Tensor
    eps: torch.Tensor
    support: torch.Tensor
    reach: torch.Tensor


def own_fits(mesh: MeshBatch, mom: TriangleMoments) -> LineFits:
    """:func:`line_fits` as a record."""
    return LineFits(*line_fits(mesh, mom))


def local_fits(mesh: MeshBatch, mom: TriangleMoments, own: LineFits, cfg: EvidenceConfig) -> LocalFits:
    """The fits each triangle's sign evidence rests on: its own where it holds
    ``cfg.min_points_fit`` points, else the pooled fit of it and its edge neighbours."""
    pooled = pooled_moments(mesh, mom)
    Lp, epsp, nrmp = line_fits(mesh, pooled)
    few = mom.count < cfg.min_points_fit
    reach = torch.where(few[:, None], crossing_reach(mesh, pooled, Lp, nrmp, cfg.crossing_reach_slack),
                        crossing_reach(mesh, mom, own.L, own.normal, cfg.crossing_reach_slack))
    return LocalFits(torch.where(few[:, None], Lp, own.L), torch.where(few, epsp, own.eps),
                     torch.where(few, pooled.count, mom.count), reach)


@dataclass
class Evidence:
    """What the data say in each triangle of a working set this level: the moments and the
    own line fits (shared by the signs, the geometry fit and the test)."""
    moments: TriangleMoments
    fits: LineFits


def gather_evidence(ws: "WorkingSet") -> Evidence:
    """The stage that reads the data into the triangles of ``ws``."""
    with torch.no_grad():
        mom = triangle_moments(ws.mesh, ws.points, ws.face, ws.bary)
        return Evidence(mom, own_fits(ws.mesh, mom))
