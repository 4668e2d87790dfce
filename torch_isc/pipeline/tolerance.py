"""Testing (Section 3.3), guarded by the noise estimate (:mod:`torch_isc.pipeline.noise`).

The paper's test marks a triangle when the largest squared distance of its points to the
curve exceeds ``δ``. On noisy data that test cannot pass once triangles are small, and
refinement then runs until sparse triangles make spurious loops. So the tolerance of an
item is never below ``noise_factor ×`` its estimated noise, a triangle needs
``min_points_split`` points before its error alone can split it, and a triangle whose
line-fit error is far above the noise (two strokes of a thin feature in one triangle) is
split even with few points. A cluster of points far from every curve (a small component the
mesh has not resolved) splits its triangles whatever their counts (:func:`far_clusters`),
while a lone outlier does not. A piece of curve that leaves the data *across* them (a bridge
between two curves a few sample spacings apart) is split below the data's reach and below
``min_split_size`` (``coverage_transverse``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Tuple

import torch

from torch_isc.core.segments import segment_max, segment_sum

from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline.knobs import check_section, knob

if TYPE_CHECKING:
    from torch_isc.pipeline.evidence import Evidence
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["TestConfig", "Verdict", "test_fit", "effective_tolerance", "triangle_errors", "mark_triangles", "far_clusters",
           "curve_coverage_excess", "point_curve_distance2", "triangle_segments"]


@dataclass
class TestConfig:
    """The test of Section 3.3 and its guards (flat keys of configs/default.yaml)."""
    __test__ = False                     # not a pytest class
    #: delta, a distance: relative to the item's bbox diagonal, or absolute (tolerance_mode)
    tolerance: float = knob(0.004, gt=0)
    tolerance_mode: str = knob("relative", choices=("relative", "absolute"))
    #: max (the paper's delta_t) or rms
    test_statistic: str = knob("max", choices=("max", "rms"))
    #: the tolerance used is at least this many times the estimated noise; 0 disables
    noise_factor: float = knob(2.5, ge=0)
    #: fewer points than this cannot split a triangle for fitting error alone
    min_points_split: int = knob(6, ge=0)
    #: ...but a line-fit error this many times above the noise splits it (thin features; the fit
    #: sees the denoised points, whose spread about one strand is a fraction of the noise)
    thin_feature_factor: float = knob(1.0, ge=0)
    #: never split a triangle whose longest edge is below this many effective tolerances
    min_split_size: float = knob(3.0, ge=0)
    #: also test curve-to-data (walls across rings, bridges between close curves)
    coverage_test: bool = knob(True)
    #: a coverage failure whose piece of curve runs across the data (largest |cos| to the tangents
    #: of the points that see it below this) splits below the data's reach too; 0 disables
    coverage_transverse: float = knob(0.95, ge=0, le=1)
    #: ...down to this many effective tolerances (instead of min_split_size)
    transverse_split_size: float = knob(1.0, ge=0)
    #: ...in items whose estimated noise exceeds this fraction of their tolerance (0: every item)
    transverse_noisy: float = knob(0.5, ge=0)
    #: points a far cluster needs (a point and its nearest far neighbours) to split its triangles
    #: whatever their counts (small components); 0 disables the rule
    far_cluster_points: int = knob(6, ge=0)
    #: a point is far when its distance to the curve exceeds this many effective tolerances
    far_cluster_factor: float = knob(1.5, ge=0)
    #: ...and it is in a cluster when its cluster's radius is below this fraction of that distance
    far_cluster_ratio: float = knob(0.75, gt=0)
    #: ...and splits its triangles down to this many effective tolerances, below min_split_size
    #: (a cluster of points off the curve is structure, not noise); min_split_size or more: no lower
    cluster_split_size: float = knob(1.5, ge=0)

    def __post_init__(self):
        check_section(self)


def triangle_errors(mesh: MeshBatch, residual: torch.Tensor, face: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per triangle, the max and the mean of the points' squared distances ``residual (P,)``."""
    T = mesh.faces.shape[0]
    ok = face >= 0
    # points with no triangle add 0 to triangle 0 (no boolean indexing: no host read)
    f, r = face.clamp_min(0), torch.where(ok, residual, torch.zeros_like(residual))
    mx = segment_max(r, f, T, fill=0)
    sm = segment_sum(r, f, T)
    cnt = segment_sum(ok.to(residual.dtype), f, T)
    return mx, sm / cnt.clamp_min(1)


def effective_tolerance(tol: torch.Tensor, noise: torch.Tensor, noise_factor: float) -> torch.Tensor:
    """``(B,)`` the distance an item is tested at: its tolerance, never below
    ``noise_factor`` times its estimated noise."""
    return torch.maximum(tol, noise_factor * noise)


def mark_triangles(mesh: MeshBatch, residual: torch.Tensor, face: torch.Tensor, count: torch.Tensor,
                   line_eps: torch.Tensor, tol: torch.Tensor, noise: torch.Tensor, cfg: TestConfig,
                   min_points_fit: int, coverage: Optional[Tuple[torch.Tensor, torch.Tensor]] = None,
                   clusters: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
                   ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mark the triangles that fail the test.

    Args:
        residual: ``(P,)`` squared point-to-curve distances. count: ``(T,)`` points per triangle.
        line_eps: ``(T,)`` line-fit errors. tol, noise: ``(B,)`` distances (``cfg.tolerance``
            is not read: ``tol`` is it per item, in the working units).
        min_points_fit: the points a line fit needs to count (``EvidenceConfig``).
        coverage: optional :func:`curve_coverage_excess` ``(excess, reach[, alignment])``: a
            triangle whose piece of curve is farther from the data than the effective tolerance
            is marked too, while it is larger than the reach of the points near it (the data's
            resolution), or, when its alignment is below ``cfg.coverage_transverse`` and its
            item's noise above ``cfg.transverse_noisy`` tolerances, down to
            ``cfg.transverse_split_size`` effective tolerances (past ``min_split_size``).
        clusters: optional :func:`far_clusters` ``(member, radius)`` per point: a triangle
            holding a member is marked whatever its count, while its longest edge exceeds the
            member's cluster radius (finer, its triangles hold a point or two each) and
            ``cfg.cluster_split_size`` effective tolerances (past ``min_split_size``).
    Returns:
        marked ``(T,)`` bool, the effective tolerance ``(B,)`` and the largest error ``(B,)``
        (a distance, the chosen statistic).
    """
    statistic, noise_factor, min_points_split = cfg.test_statistic, cfg.noise_factor, cfg.min_points_split
    thin_factor, min_split_size = cfg.thin_feature_factor, cfg.min_split_size
    fi = mesh.face_item
    mx, mean = triangle_errors(mesh, residual, face)
    stat = mx if statistic == "max" else mean
    eff = effective_tolerance(tol, noise, noise_factor)
    allow = eff[fi]
    if statistic == "max":
        # the largest of n Gaussian deviations grows like sqrt(2 ln n): a triangle holding many
        # noisy points must not fail for that alone (dense scans would be refined to the floor)
        spread = torch.sqrt(2.0 * torch.log(count.clamp_min(1).to(noise.dtype)))
        allow = torch.maximum(allow, spread * noise[fi])
    fails = stat > allow ** 2
    marked = fails & (count >= min_points_split)
    # with few points the mean, which one outlier cannot move far, must still pass
    marked |= (count >= min_points_fit) & (mean > eff[fi] ** 2)
    thin = torch.maximum(tol, thin_factor * noise)
    marked |= (count >= min_points_fit) & (line_eps > thin[fi] ** 2)
    longest = mesh.kernel.longest_edge(mesh.verts.detach()[mesh.faces])
    across = None
    if coverage is not None:
        # the data-to-curve test cannot see curve where there are no data (a wall across a
        # ring, a bridge between two close curves): the curve-to-data side, down to the
        # resolution of the sampling (finer, the data cannot tell where the curve goes)
        excess, reach = coverage[0], coverage[1]
        off = torch.isfinite(excess) & (excess > eff[fi])
        marked |= off & (longest > 2.0 * reach)
        if len(coverage) > 2 and cfg.coverage_transverse > 0:
            # a piece across the data (a bridge between two close curves a few spacings apart)
            # is topology, not a detail the sampling cannot place: split below the reach and
            # below the size guard, down to its own floor
            across = off & (coverage[2] < cfg.coverage_transverse) & (longest > cfg.transverse_split_size * eff[fi])
            if cfg.transverse_noisy > 0:
                # on noise-free data the reach already resolves the sampling, and splitting below
                # it there only cuts notches at the ends of sampling gaps: noisy items only
                across &= (noise > cfg.transverse_noisy * tol)[fi]
    by_cluster = None
    if clusters is not None:
        member, radius = clusters
        f = face.clamp_min(0)
        split = member & (face >= 0) & (longest[f] > radius)
        by_cluster = segment_sum(split.to(residual.dtype), f, mesh.faces.shape[0]) > 0
    # below the resolution the tolerance allows, splitting only fits the noise
    if min_split_size > 0:
        marked &= longest > min_split_size * eff[fi]
    if by_cluster is not None:
        # a far cluster is evidence of unresolved structure (a tip, a neck, a small component):
        # it splits below the size guard, down to its own floor
        floor = min(cfg.cluster_split_size, min_split_size) if min_split_size > 0 else 0.0
        marked |= by_cluster & (longest > floor * eff[fi])
    if across is not None:
        marked |= across
    worst = segment_max(stat, fi, mesh.num_items, fill=0)
    return marked, eff, worst.sqrt()


#: candidates on each side of a far point along each Morton order (its neighbours are found among them)
CLUSTER_WINDOW = 8


def _morton_knn(points: torch.Tensor, item: torch.Tensor, k: int, window: int = CLUSTER_WINDOW) -> torch.Tensor:
    """``(n,)`` the distance of each of ``points (n, 2)`` (normalized, within about 1 of the origin)
    to its ``k``-th nearest other point of the same ``item``, by
    :func:`~torch_isc.pipeline.noise.approximate_knn` (inf where fewer than ``k`` candidates)."""
    from torch_isc.pipeline.noise import approximate_knn
    if k > 4 * window:
        return torch.full((points.shape[0],), float("inf"), dtype=points.dtype, device=points.device)
    return approximate_knn(points, item, k, window)[1][:, k - 1].sqrt()


def far_clusters(points: torch.Tensor, point_item: torch.Tensor, residual: torch.Tensor, reach: torch.Tensor,
                 eff: torch.Tensor, cluster_points: int, far_factor: float, ratio: float
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Which points belong to a cluster far from every curve: structure the mesh has not
    resolved (a small component), as opposed to isolated outliers.

    A point is *far* when its distance ``d`` to the curve (``residual (P,)``, squared; inf when
    no curve is near, then ``reach (P,)``, a lower bound of that distance, stands in) exceeds
    ``far_factor × eff`` (``eff (B,)``, the item's effective tolerance). It is in a cluster when
    its ``cluster_points − 1`` nearest *far* neighbours lie within ``ratio × d`` of it: enough
    points for a curve, in a radius small against their distance to the curve. One outlier, or
    a few, never have that many far neighbours so close; a sampled curve far from the fit has.

    Returns ``(P,)`` bool and ``(P,)`` the cluster radius (the distance to the
    ``(cluster_points − 1)``-th far neighbour; inf off clusters)."""
    P = points.shape[0]
    dev, dt = points.device, residual.dtype
    inf = torch.full((P,), float("inf"), dtype=dt, device=dev)
    if cluster_points < 2 or P == 0:
        return torch.zeros(P, dtype=torch.bool, device=dev), inf
    d = torch.where(torch.isfinite(residual), residual.clamp_min(0).sqrt(), reach.to(dt))
    far = d > far_factor * eff[point_item]
    idx = far.nonzero().squeeze(1)                  # one host read: how many far points
    if idx.numel() == 0:
        return torch.zeros(P, dtype=torch.bool, device=dev), inf
    rk = _morton_knn(points[idx].to(dt), point_item[idx], cluster_points - 1)
    radius = inf.index_copy(0, idx, rk)
    return far & (radius <= ratio * d), torch.where(far, radius, inf)


def triangle_segments(mesh: MeshBatch, values: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """The zero-set piece of every triangle: ``(T, 2, 2)`` end points and ``(T,)`` bool
    (whether the triangle holds one)."""
    return mesh.kernel.zero_set_pieces(mesh.verts.detach()[mesh.faces], values.detach()[mesh.faces])


def point_curve_distance2(mesh: MeshBatch, values: torch.Tensor, points: torch.Tensor,
                          face: torch.Tensor) -> torch.Tensor:
    """``(P,)`` squared distance of each point to the zero-set segments of its triangle and
    of that triangle's three neighbours, or, for a point none of them holds a segment for, of
    the neighbours' neighbours (inf when none of those does either).

    Unlike ``f²/|∇f|²`` (the distance to the *extended* zero line of the point's triangle),
    this sees a point whose triangle has no curve at all. The second ring keeps a point next
    to the curve from reading "no curve near" only because the triangles around it are small
    (refinement near a dense noisy band)."""
    seg, has = triangle_segments(mesh, values)
    ok = face >= 0
    f = face.clamp_min(0)
    nb = mesh.face_neighbors
    ring1 = torch.cat([f[:, None], nb[f]], 1)                         # (P,4)
    d2 = mesh.kernel.piece_distance2(seg, has, points, ring1)
    far = (ok & torch.isinf(d2)).nonzero().squeeze(1)
    if far.numel():
        r1 = nb[f[far]]                                              # (F,3)
        ring2 = nb[r1.clamp_min(0)].masked_fill((r1 < 0)[..., None], -1)   # (F,3,3)
        d2[far] = mesh.kernel.piece_distance2(seg, has, points[far], ring2.reshape(far.shape[0], 9))
    return torch.where(ok, d2, torch.full_like(d2, float("inf")))


def curve_coverage_excess(mesh: MeshBatch, values: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                          frames: torch.Tensor, alignment: bool = False) -> Tuple[torch.Tensor, ...]:
    """``(T,)`` how far the midpoint ``m_t`` of each triangle's zero-set segment lies off the
    data, sideways: the smallest ``|(m_t − p)·n_p|`` over the points ``p`` of the triangle and
    its three neighbours that see it, i.e. with ``|(m_t − p)·τ_p| ≤ r_p``, where ``τ_p, n_p``
    are the tangent and normal of the data at ``p`` and ``r_p`` the reach of its neighbourhood
    (``frames (P, 3)`` from :func:`estimate_noise`). A curve that leaves the data sideways (a
    wall across a ring, a bridge between two close curves) is caught; one that runs on along
    the data into a sampling gap is seen by no point and left alone (splitting cannot fill a
    gap). ``-inf`` where the triangle holds no segment, ``inf`` where no point sees it. Also
    ``(T,)`` the smallest reach of those points (inf: none): the size below which the data
    cannot place the curve. With ``alignment``, also ``(T,)`` the largest ``|cos|`` between the
    segment and the tangents ``τ_p`` of those points (0 where none sees it): a small one is a
    piece running *across* the data (a bridge between two close curves), not along it."""
    seg, has = triangle_segments(mesh, values)
    mid = seg.mean(1)                                              # (T,2)
    T = mid.shape[0]
    ok = face >= 0
    f = face.clamp_min(0)
    p = points.to(mid.dtype)
    fr = frames.to(mid.dtype)
    tau, reach = fr[:, :2], fr[:, 2]
    cand = torch.cat([f[:, None], mesh.face_neighbors[f]], 1)      # (P,4)
    valid = ok[:, None] & (cand >= 0) & has[cand.clamp_min(0)]
    c = cand.clamp_min(0)
    off = mid[c] - p[:, None, :]                                   # (P,4,2)
    along = (off * tau[:, None, :]).sum(-1)
    across = off[..., 0] * tau[:, None, 1] - off[..., 1] * tau[:, None, 0]
    # a point vouches only for what lies within its neighbourhood along the curve: beyond it
    # (a sampling gap) it says nothing, and splitting would not fill the gap
    seen = valid & (along.abs() <= reach[:, None])
    # what a point does not see enters the minima as inf (no boolean indexing: no host read)
    inf = torch.full_like(across, float("inf"))
    d = torch.where(seen, across.abs(), inf)
    out = torch.full((T,), float("inf"), dtype=mid.dtype, device=mid.device)
    out = out.scatter_reduce(0, c.reshape(-1), d.reshape(-1), "amin")
    rmin = torch.full((T,), float("inf"), dtype=mid.dtype, device=mid.device)
    r_seen = torch.where(seen, reach[:, None].expand_as(d), inf)
    rmin = rmin.scatter_reduce(0, c.reshape(-1), r_seen.reshape(-1), "amin")
    excess = torch.where(has, out, torch.full_like(out, -float("inf")))
    if not alignment:
        return excess, rmin
    u = seg[:, 1] - seg[:, 0]
    u = u / u.norm(dim=1, keepdim=True).clamp_min(torch.finfo(u.dtype).tiny)
    cos = torch.where(seen, (u[c] * tau[:, None, :]).sum(-1).abs(), torch.zeros_like(d))
    align = torch.zeros((T,), dtype=mid.dtype, device=mid.device)
    align = align.scatter_reduce(0, c.reshape(-1), cos.reshape(-1), "amax")
    return excess, rmin, align


@dataclass
class Verdict:
    """The test's outcome for a working set: ``marked (T,)`` the failing triangles,
    ``tolerance (B,)`` the effective tolerance, ``worst (B,)`` the largest error (a distance),
    ``residual (P,)`` each point's squared distance to the curve, ``unresolved (B,)`` how many
    points lie in clusters far from every curve (:func:`far_clusters`; 0 without that test):
    structure the mesh has not resolved, which the size floor may keep from being split; or, in
    an item where more than half of the points lie beyond the tolerance, how many do."""
    marked: torch.Tensor
    tolerance: torch.Tensor
    worst: torch.Tensor
    residual: torch.Tensor
    unresolved: Optional[torch.Tensor] = None


def test_fit(ws: "WorkingSet", values: torch.Tensor, ev: "Evidence", cfg: TestConfig, min_points_fit: int) -> Verdict:
    """The test stage: data-to-curve distances (and, with ``cfg.coverage_test``, curve-to-data)
    of the fitted ``values`` against each item's effective tolerance; with ``cfg.far_cluster_points``,
    far clusters (:func:`far_clusters`) split their triangles."""
    with torch.no_grad():
        mesh = ws.mesh
        residual = point_curve_distance2(mesh, values, ws.points, ws.face)
        coverage = (curve_coverage_excess(mesh, values, ws.points, ws.face, ws.frames,
                                          alignment=cfg.coverage_transverse > 0) if cfg.coverage_test else None)
        clusters = None
        if cfg.far_cluster_points > 0:
            eff = effective_tolerance(ws.tol, ws.noise, cfg.noise_factor)
            # no curve in a point's two rings: it is at least about its triangle's size away
            size = mesh.kernel.longest_edge(mesh.verts.detach()[mesh.faces])[ws.face.clamp_min(0)]
            clusters = far_clusters(ws.points, ws.point_item, residual, size, eff, cfg.far_cluster_points,
                                    cfg.far_cluster_factor, cfg.far_cluster_ratio)
        marked, eff, worst = mark_triangles(mesh, residual, ws.face, ev.moments.count, ev.fits.eps, ws.tol, ws.noise,
                                            cfg, min_points_fit, coverage=coverage, clusters=clusters)
        B = mesh.num_items
        unresolved = (segment_sum(clusters[0].long(), ws.point_item, B) if clusters is not None
                      else torch.zeros(B, dtype=torch.long, device=residual.device))
        # a curve that explains fewer than half of the points is no answer, whatever the test
        # excused (triangles too sparse to split: 7 points of a circle around a small loop)
        ok = ws.face >= 0
        beyond = segment_sum((ok & (residual > eff[ws.point_item] ** 2)).long(), ws.point_item, B)
        located = segment_sum(ok.long(), ws.point_item, B)
        unresolved = torch.where(2 * beyond > located, torch.maximum(unresolved, beyond), unresolved)
        return Verdict(marked, eff, worst, residual, unresolved)


test_fit.__test__ = False                 # not a pytest test
