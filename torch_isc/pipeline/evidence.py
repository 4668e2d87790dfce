"""The data's local evidence per triangle (Section 3.2): point moments, least-squares lines,
and where a line may testify to a crossing. Shared by the sign estimate, the geometry fit
(the moments ``M_t`` of eq. 3.2) and the test (line-fit errors).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch

from torch_isc.core.segments import segment_sum

from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline.knobs import check_section, knob

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["EvidenceConfig", "TriangleMoments", "LineFits", "LocalFits", "triangle_moments", "pooled_moments", "line_fits",
           "crossing_reach", "own_fits", "local_fits", "ring_moments", "scaled_moments", "TwoLines", "two_lines",
           "two_line_evidence", "Evidence",
           "gather_evidence"]


@dataclass
class EvidenceConfig:
    """How much data a triangle's line fit needs to count (flat keys of configs/default.yaml)."""
    #: points a triangle needs for its line fit to count as evidence (1-2 points fit a line exactly)
    min_points_fit: int = knob(3, gt=0)
    #: a fitted line testifies to a crossing up to this many residual spreads past its points
    crossing_reach_slack: float = knob(1.0, ge=0)
    #: a sign fit must span this many noise widths along its line: a triangle whose points span
    #: less borrows the points of the triangles around it (:func:`scaled_moments`); 0 disables
    evidence_noise_widths: float = knob(0.0, ge=0)
    #: ...over at most this many rings of triangles around it
    evidence_rings: int = knob(3, ge=0)
    #: ...as long as the wider fit stays a line: residual spread within this many noise widths
    evidence_line_widths: float = knob(2.0, gt=0)
    #: two parallel lines instead of one where a triangle's points split along its line's normal
    #: into two sides this many noise widths apart (a stroke or a gap one triangle wide); 0 disables
    two_line_separation: float = knob(0.0, ge=0)
    #: ...each side within this many noise widths of its own line (residual spread)
    two_line_spread: float = knob(1.5, gt=0)

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


def _combine(n: torch.Tensor, m: torch.Tensor, C: torch.Tensor, ref: torch.Tensor):
    """Pool groups ``(..., k)`` of (count ``n``, mean ``m (..., k, 2)``, covariance ``C``) about
    ``ref (..., 2)`` (parallel-axis rule, offsets from ``ref`` keep float32 accurate): the
    pooled count, mean and covariance."""
    N = n.sum(-1)
    d = m - ref[..., None, :]
    Nc = N.clamp_min(torch.finfo(n.dtype).tiny)
    mean_d = (n[..., None] * d).sum(-2) / Nc[..., None]
    dd = d - mean_d[..., None, :]
    cov = (n[..., None, None] * (C + dd[..., :, None] * dd[..., None, :])).sum(-3) / Nc[..., None, None]
    return N, ref + mean_d, cov


def ring_moments(mesh: MeshBatch, mom: TriangleMoments) -> TriangleMoments:
    """One ring wider: every triangle's moments pooled over the triangles that share a corner
    with it, through the corners' stars (a triangle is counted once per corner it shares: the
    own triangle 3 times, an edge neighbour twice, a corner neighbour once, a tent-shaped
    kernel). Counts are weighted counts. ``M`` is not pooled."""
    f = mesh.faces
    V = mesh.verts.shape[0]
    dt = mom.scatter.dtype
    v = mesh.verts.detach().to(dt)
    # triangle -> vertex star, about the vertex (offsets small where the triangles are)
    fv = f.reshape(-1)
    n3 = mom.count[:, None].expand(-1, 3).reshape(-1)
    d = mom.centroid[:, None, :] - v[f]                                   # (T,3,2)
    d = d.reshape(-1, 2)
    cnt = torch.zeros(V, dtype=dt, device=v.device).index_add_(0, fv, n3)
    s1 = torch.zeros(V, 2, dtype=dt, device=v.device).index_add_(0, fv, n3[:, None] * d)
    C3 = mom.scatter[:, None].expand(-1, 3, -1, -1).reshape(-1, 2, 2)
    s2 = torch.zeros(V, 2, 2, dtype=dt, device=v.device).index_add_(
        0, fv, n3[:, None, None] * (C3 + d[:, :, None] * d[:, None, :]))
    nc = cnt.clamp_min(torch.finfo(dt).tiny)
    vm = s1 / nc[:, None]
    vcov = s2 / nc[:, None, None] - vm[:, :, None] * vm[:, None, :]
    # vertex stars -> triangle, about the triangle's own centroid
    N, mean, cov = _combine(cnt[f], v[f] + vm[f], vcov[f], mom.centroid)
    return TriangleMoments(N, mom.M, mean, cov)


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
class TwoLines:
    """The points of each triangle split by the side of its line they lie on (offsets ``y``
    along the line's normal from the centroid): ``n (T, 2)`` counts, ``mean (T, 2)`` the mean
    offset of each side, ``var (T,)`` the pooled variance about the two side means."""
    n: torch.Tensor
    mean: torch.Tensor
    var: torch.Tensor


@dataclass
class LineFits:
    """The line fit of every triangle's own points: ``L (T, 3)`` signed distances of its
    corners to the line, ``eps (T,)`` the mean squared residual, ``normal (T, 2)``; ``two``
    the split of its points into two parallel lines (:func:`two_lines`), when gathered."""
    L: torch.Tensor
    eps: torch.Tensor
    normal: torch.Tensor
    two: Optional[TwoLines] = None


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


def two_lines(mesh: MeshBatch, mom: TriangleMoments, normal: torch.Tensor, points: torch.Tensor,
              face: torch.Tensor) -> TwoLines:
    """Split every triangle's points by the side of its least-squares line (through the
    centroid, ``normal (T, 2)``): per side the count and the mean offset along the normal, and
    the variance of the offsets about their side's mean (one scatter-add over the points)."""
    T = mom.count.shape[0]
    dt = mom.scatter.dtype
    ok = face >= 0
    f = face.clamp_min(0)
    y = ((points.to(dt) - mom.centroid[f]) * normal[f]).sum(1)
    y = torch.where(ok, y, torch.zeros_like(y))
    slot = f * 2 + (y >= 0).long()
    w = ok.to(dt)
    n = torch.zeros(2 * T, dtype=dt, device=y.device).index_add_(0, slot, w).view(T, 2)
    s1 = torch.zeros(2 * T, dtype=dt, device=y.device).index_add_(0, slot, w * y).view(T, 2)
    s2 = torch.zeros(2 * T, dtype=dt, device=y.device).index_add_(0, slot, w * y * y).view(T, 2)
    mean = s1 / n.clamp_min(1)
    var = (s2 - n * mean * mean).sum(1).clamp_min(0) / n.sum(1).clamp_min(1)
    return TwoLines(n, mean, var)


def two_line_evidence(mesh: MeshBatch, own: LineFits, noise: torch.Tensor, cfg: EvidenceConfig):
    """Where the points of a triangle are two parallel lines rather than one: each side of its
    line holds ``min_points_fit`` points, the side means lie ``two_line_separation`` noise
    widths apart and the points lie within ``two_line_spread`` noise widths of their side's
    line. One line through such a triangle runs between a stroke's (or a gap's) two walls and
    says nothing true about its corners; two lines say the corners between them have the other
    sign than those outside.

    Returns ``two (T,)`` bool, ``Q (T, 3)`` the product ``(y − a₁)(y − a₂)`` at the corners
    (its sign is the corner's side of the strip; ``y`` the corner's offset along the normal,
    ``a`` the side means) and ``var (T,)`` the two-line residual. ``noise (T,)``: each
    triangle's item noise."""
    tw = own.two
    widths, spread = float(cfg.two_line_separation), float(cfg.two_line_spread)
    m = float(cfg.min_points_fit)
    sep = tw.mean[:, 1] - tw.mean[:, 0]
    two = ((tw.n >= m).all(1) & (sep >= widths * noise) & (tw.var <= (spread * noise) ** 2)
           & (noise > 0))
    # own.L is the corners' offset along the normal from the centroid (the same y as the points')
    Q = (own.L - tw.mean[:, None, 0]) * (own.L - tw.mean[:, None, 1])
    return two, Q, tw.var


def own_fits(mesh: MeshBatch, mom: TriangleMoments) -> LineFits:
    """:func:`line_fits` as a record."""
    return LineFits(*line_fits(mesh, mom))


def scaled_moments(mesh: MeshBatch, base: TriangleMoments, noise: torch.Tensor, cfg: EvidenceConfig
                   ) -> TriangleMoments:
    """Each triangle's moments widened, ring by ring (:func:`ring_moments`), until its points
    span ``cfg.evidence_noise_widths`` noise widths along their line (half-length ``√(3λ_max)``),
    for at most ``cfg.evidence_rings`` rings. A wider pool is taken only while it is still a
    line (residual spread ``√ε`` within ``cfg.evidence_line_widths`` noise widths, or within the
    narrower pool's): a pool across two strokes or around a corner keeps the narrower one.

    Why: the line of a triangle's own points passes through their centroid, which lies inside
    the triangle, so every triangle of a noisy band claims a crossing, in a direction a few
    noisy points set. A line fitted to a stretch several noise widths long lies near the curve,
    and testifies to a crossing only in the triangles the curve does cross.

    ``noise (T,)``: the noise level of each triangle's item."""
    widths = float(cfg.evidence_noise_widths)
    if widths <= 0 or int(cfg.evidence_rings) <= 0:
        return base
    out = base
    cur = base
    settled = torch.zeros_like(base.count, dtype=torch.bool)
    line_var = (float(cfg.evidence_line_widths) * noise) ** 2
    for _ in range(int(cfg.evidence_rings)):
        lmax, lmin = mesh.kernel.principal_spread(out.scatter)
        settled = settled | (3.0 * lmax >= (widths * noise) ** 2)
        cur = ring_moments(mesh, cur)
        _, wmin = mesh.kernel.principal_spread(cur.scatter)
        take = ~settled & (cur.count > 0) & (wmin <= torch.maximum(line_var, lmin))
        # a pool that stops being a line stops the widening for good
        settled = settled | (~take & (cur.count > 0))
        out = TriangleMoments(torch.where(take, cur.count, out.count), base.M,
                              torch.where(take[:, None], cur.centroid, out.centroid),
                              torch.where(take[:, None, None], cur.scatter, out.scatter))
    return out


def local_fits(mesh: MeshBatch, mom: TriangleMoments, own: LineFits, cfg: EvidenceConfig,
               noise: Optional[torch.Tensor] = None) -> LocalFits:
    """The fits each triangle's sign evidence rests on: its own where it holds
    ``cfg.min_points_fit`` points, else the pooled fit of it and its edge neighbours; with
    ``noise (B,)`` and ``cfg.evidence_noise_widths > 0``, either one widened to span that many
    noise widths (:func:`scaled_moments`)."""
    pooled = pooled_moments(mesh, mom)
    few = mom.count < cfg.min_points_fit
    if noise is not None and cfg.evidence_noise_widths > 0:
        base = TriangleMoments(torch.where(few, pooled.count, mom.count), mom.M,
                               torch.where(few[:, None], pooled.centroid, mom.centroid),
                               torch.where(few[:, None, None], pooled.scatter, mom.scatter))
        wide = scaled_moments(mesh, base, noise.to(mom.scatter.dtype)[mesh.face_item], cfg)
        # the support keeps the narrow count: whether a triangle has a fit or counts as empty
        # is the narrow neighbourhood's call
        L, eps, nrm = line_fits(mesh, wide)
        reach = crossing_reach(mesh, wide, L, nrm, cfg.crossing_reach_slack)
        out = LocalFits(L, eps, base.count, reach)
    else:
        Lp, epsp, nrmp = line_fits(mesh, pooled)
        reach = torch.where(few[:, None], crossing_reach(mesh, pooled, Lp, nrmp, cfg.crossing_reach_slack),
                            crossing_reach(mesh, mom, own.L, own.normal, cfg.crossing_reach_slack))
        out = LocalFits(torch.where(few[:, None], Lp, own.L), torch.where(few, epsp, own.eps),
                        torch.where(few, pooled.count, mom.count), reach)
    if noise is None or cfg.two_line_separation <= 0 or own.two is None:
        return out
    two, Q, var = two_line_evidence(mesh, own, noise.to(mom.scatter.dtype)[mesh.face_item], cfg)
    inside = (Q < 0).any(1)
    # a strip with no corner in it is below this mesh's resolution: no evidence (not "no
    # crossing"), the test's thin-feature rule splits such triangles
    return LocalFits(torch.where(two[:, None], Q, out.L), torch.where(two, var, out.eps),
                     torch.where(two & ~inside, torch.zeros_like(out.support), out.support),
                     torch.where(two[:, None], torch.ones_like(out.reach), out.reach))


@dataclass
class Evidence:
    """What the data say in each triangle of a working set this level: the moments and the
    own line fits (shared by the signs, the geometry fit and the test)."""
    moments: TriangleMoments
    fits: LineFits


def gather_evidence(ws: "WorkingSet", cfg: Optional[EvidenceConfig] = None) -> Evidence:
    """The stage that reads the data into the triangles of ``ws`` (with ``cfg``'s two-line
    model on, also the split of each triangle's points by the side of its line)."""
    with torch.no_grad():
        mom = triangle_moments(ws.mesh, ws.points, ws.face, ws.bary)
        own = own_fits(ws.mesh, mom)
        if cfg is not None and cfg.two_line_separation > 0:
            own.two = two_lines(ws.mesh, mom, own.normal, ws.points, ws.face)
        return Evidence(mom, own)
