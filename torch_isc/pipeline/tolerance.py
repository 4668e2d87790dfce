"""Testing (Section 3.3) and the noise estimate that guards it.

The paper's test marks a triangle when the largest squared distance of its points to the
curve exceeds ``δ``. On noisy data that test cannot pass once triangles are small, and
refinement then runs until sparse triangles make spurious loops. So the tolerance of an
item is never below ``noise_factor ×`` its estimated noise, a triangle needs
``min_points_split`` points before its error alone can split it, and a triangle whose
line-fit error is far above the noise (two strokes of a thin feature in one triangle) is
split even with few points.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import hash_uniform, segment_median, sym2_eigvals, sym2_eigvec

__all__ = ["effective_tolerance", "estimate_noise", "triangle_errors", "mark_triangles",
           "curve_coverage_excess", "point_curve_distance2", "triangle_segments"]


def _morton(q: torch.Tensor) -> torch.Tensor:
    """Interleave the bits of two 16-bit integer coordinates ``(P, 2)`` -> ``(P,)``."""
    def spread(x):
        x = x & 0xFFFF
        x = (x | (x << 8)) & 0x00FF00FF
        x = (x | (x << 4)) & 0x0F0F0F0F
        x = (x | (x << 2)) & 0x33333333
        x = (x | (x << 1)) & 0x55555555
        return x
    return spread(q[:, 0]) | (spread(q[:, 1]) << 1)


def _local_line_residual(points: torch.Tensor, point_item: torch.Tensor, idx: torch.Tensor, orders, offs,
                         k: int) -> Tuple[torch.Tensor, ...]:
    """For the points ``idx``: the residual variance of a line fitted to each point and its ``k``
    nearest candidates (its neighbours along the Morton ``orders``), the fit's point count, the
    larger eigenvalue of the neighbourhood's covariance, the residual variance of a parabola
    fitted to the same points, and the point's frame ``(n, 3)``: the unit major axis of the
    neighbourhood (the local tangent) and the distance to its farthest neighbour."""
    P = points.shape[0]
    dev, dt = points.device, points.dtype
    c = torch.cat([order[(pos[idx][:, None] + offs[None, :]).clamp(0, P - 1)] for order, pos in orders], 1)
    c, _ = torch.sort(c, 1)
    dup = torch.zeros_like(c, dtype=torch.bool)
    dup[:, 1:] = c[:, 1:] == c[:, :-1]
    self_or_other = (c == idx[:, None]) | (point_item[c] != point_item[idx][:, None]) | dup
    d2 = ((points[c] - points[idx][:, None, :]) ** 2).sum(-1)
    d2 = torch.where(self_or_other, torch.full_like(d2, float("inf")), d2)
    nd, ni = torch.topk(d2, min(k, c.shape[1]), dim=1, largest=False)
    nbr = c.gather(1, ni)
    valid = torch.isfinite(nd)
    pts = torch.cat([points[idx][:, None, :], points[nbr]], 1)          # (n, k+1, 2)
    w = torch.cat([torch.ones(idx.shape[0], 1, dtype=torch.bool, device=dev), valid], 1).to(dt)
    m = w.sum(1)
    mean = (pts * w[..., None]).sum(1) / m[:, None]
    qd = (pts - mean[:, None, :]) * w[..., None]
    C = torch.einsum("pki,pkj->pij", qd, qd) / m[:, None, None]
    a, b, d = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    lam, lmax = sym2_eigvals(a, b, d)
    lam = lam.clamp_min(0)
    t = sym2_eigvec(a, b, d, lmax)                                        # the major axis
    t = t / t.norm(dim=1, keepdim=True).clamp_min(torch.finfo(dt).tiny)
    t = torch.where(torch.isfinite(t) & (t.norm(dim=1, keepdim=True) > 0.5), t,
                    torch.tensor([1.0, 0.0], dtype=dt, device=dev))
    reach = torch.where(valid, nd, torch.zeros_like(nd)).amax(1).sqrt()
    return (lam * m / (m - 2).clamp_min(1), m, lmax, _quadratic_residual(qd, w, t, lmax, m),
            torch.cat([t, reach[:, None]], 1))


def _quadratic_residual(qd: torch.Tensor, w: torch.Tensor, t: torch.Tensor, lmax, m) -> torch.Tensor:
    """``(n,)`` the residual variance of ``y = c0 + c1 x + c2 x²`` fitted to each neighbourhood
    ``qd (n, k, 2)`` (centred, weights ``w``) in its principal frame (x along the major axis),
    corrected for the three parameters. A line fit to a sparsely sampled curved arc measures
    the curvature as well as the noise (an arc of half-length h and radius R leaves
    ``h⁴ / 45R²``); the parabola takes the curvature out."""
    dt = qd.dtype
    q = qd.double()
    t = t.double()
    x = (q * t[:, None, :]).sum(-1) / lmax.double().sqrt().clamp_min(1e-300)[:, None]
    y = q[..., 0] * t[:, None, 1] - q[..., 1] * t[:, None, 0]
    ww = w.double()
    basis = torch.stack([ww, ww * x, ww * x * x], -1)                       # (n, k, 3)
    A = basis.transpose(1, 2) @ basis                                         # w² = w: 0/1 weights
    r = (basis * y[..., None]).sum(1)                                         # (n, 3)
    A = A + 1e-12 * torch.eye(3, dtype=A.dtype, device=A.device) * A.diagonal(dim1=1, dim2=2).sum(1)[:, None, None]
    coef = torch.linalg.solve(A, r[..., None])[..., 0]
    res = ((ww * (y - (coef[:, None, 0] + coef[:, None, 1] * x + coef[:, None, 2] * x * x))) ** 2).sum(1)
    out = (res / (m.double() - 3).clamp_min(1)).to(dt)
    return torch.where(m > 3, out, torch.zeros_like(out))


def _noise_at_scale(points: torch.Tensor, point_item: torch.Tensor, num_items: int, k: int,
                    window: int) -> Tuple[torch.Tensor, ...]:
    """Per item: the median residual variance of the local parabola fits, the median aspect
    ``sqrt(λmax / λmin)`` of the neighbourhoods (line fits), and the number of points used;
    per point: its frame (see :func:`_local_line_residual`)."""
    P = points.shape[0]
    dev, dt = points.device, points.dtype
    offs = torch.cat([torch.arange(-window, 0, device=dev), torch.arange(1, window + 1, device=dev)])
    orders = []
    for shift in (0.0, 0.3719):
        q = ((points + 0.75 + shift * 0.5) / 2.0 * 65535).long().clamp(0, 65535)
        key = point_item * (1 << 32) + _morton(q)
        order = torch.argsort(key, stable=True)
        pos = torch.empty_like(order)
        pos[order] = torch.arange(P, device=dev)
        orders.append((order, pos))
    lam = torch.empty(P, dtype=dt, device=dev)
    lmax = torch.empty(P, dtype=dt, device=dev)
    m = torch.empty(P, dtype=dt, device=dev)
    quad = torch.empty(P, dtype=dt, device=dev)
    frame = torch.empty(P, 3, dtype=dt, device=dev)
    # the (points x candidates) arrays go in blocks: bounded memory for millions of points
    block = max(1, (1 << 21) // (4 * window))
    for b0 in range(0, P, block):
        idx = torch.arange(b0, min(P, b0 + block), device=dev)
        lam[idx], m[idx], lmax[idx], quad[idx], frame[idx] = _local_line_residual(points, point_item, idx, orders,
                                                                                  offs, k)
    ok = m >= 4
    var = segment_median(quad[ok], point_item[ok], num_items)
    aspect = torch.sqrt(lmax / lam.clamp_min(torch.finfo(dt).tiny))
    asp = segment_median(aspect[ok], point_item[ok], num_items)
    return var, asp, torch.bincount(point_item[ok], minlength=num_items), frame


def estimate_noise(points: torch.Tensor, point_item: torch.Tensor, num_items: int, k: int = 8,
                   window: int = 12, blob_aspect: float = 2.0, line_aspect: float = 2.5,
                   min_points: int = 64, return_frames: bool = False):
    """``(B,)`` noise level (a standard deviation, in the points' units) of each item.

    For every point, a parabola ``y = c0 + c1 x + c2 x²`` (x along the principal axis) is fitted
    to it and its ``k`` nearest neighbours (approximate: taken among its neighbours along two
    shifted Morton orders, so the cost is a sort, not a search); the noise variance is the
    median over the item of the residual variance, corrected for the three parameters of the
    fit. A straight line would read the sagitta of a sparsely sampled arc as noise (60 points
    on a circle: 1.8% of the radius). Points are expected normalized per item (bounding box
    centred, diagonal 1).

    When the points are much denser than the noise is wide, ``k`` neighbours form a round
    blob and their residual measures the spacing, not the noise. An item whose median
    neighbourhood aspect ``sqrt(λmax/λmin)`` is below ``blob_aspect`` (a well-sampled noisy
    line gives more) is refitted on subsets of 1/4, 1/16, ... of its points (chosen by a hash
    of the point's index within its item, so not by its batch) until the aspect reaches
    ``line_aspect``, as long as a subset keeps ``min_points`` points (data that never become
    line-like, such as uniform clutter, keep the full-density estimate). The parabola takes the
    curvature of the longer neighbourhood of a subset out, so subsets of 64 points are
    believed (600 points on a circle with noise 2.7x their spacing: 0.9 of the noise, against
    0.68 when only subsets of 256 points were); smaller ones would fit a large part of the
    curve (or a nearby second curve) rather than the noise, so a couple of hundred points with
    noise about their spacing keep a low estimate (about 0.85 of the noise).

    With ``return_frames=True`` it also returns ``(P, 3)`` each point's local frame: the unit
    major axis of its neighbourhood (the curve's tangent there) and the distance to the
    farthest of its ``k`` neighbours (0 for a point alone in its item).
    """
    with torch.no_grad():
        P = points.shape[0]
        dev, dt = points.device, points.dtype
        if P < 3:
            z = torch.zeros(num_items, dtype=dt, device=dev)
            fr = torch.tensor([1.0, 0.0, 0.0], dtype=dt, device=dev).expand(P, 3).clone()
            return (z, fr) if return_frames else z
        var, asp, _, frames = _noise_at_scale(points, point_item, num_items, k, window)
        chosen = asp >= blob_aspect
        if bool(chosen.all()):
            return (var.sqrt(), frames) if return_frames else var.sqrt()
        cnt = torch.bincount(point_item, minlength=num_items)
        first = torch.cumsum(cnt, 0) - cnt
        u = hash_uniform(torch.arange(P, device=dev) - first[point_item], dtype=torch.float64)
        rate = 1.0
        while not bool(chosen.all()):
            rate /= 4.0
            # an item still undecided, with enough points left at this rate, is refitted
            todo = ~chosen & (cnt.to(torch.float64) * rate >= min_points)
            if not bool(todo.any()):
                break
            keep = todo[point_item] & (u < rate)
            pi = point_item[keep]
            v2, a2, n2, _ = _noise_at_scale(points[keep], pi, num_items, k, window)
            use = todo & (n2 >= min_points)
            line = use & (a2 >= line_aspect)
            # only a line-like scale is believed: data that are a blob at every scale (no
            # curve, e.g. uniform clutter) keep the full-density estimate
            var = torch.where(line, v2, var)
            chosen = chosen | line | (todo & ~use)
        return (var.sqrt(), frames) if return_frames else var.sqrt()


def triangle_errors(mesh: MeshBatch, residual: torch.Tensor, face: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per triangle, the max and the mean of the points' squared distances ``residual (P,)``."""
    T = mesh.faces.shape[0]
    ok = face >= 0
    f, r = face[ok], residual[ok]
    mx = torch.zeros(T, dtype=residual.dtype, device=residual.device).scatter_reduce(0, f, r, "amax")
    sm = torch.zeros(T, dtype=residual.dtype, device=residual.device).index_add_(0, f, r)
    cnt = torch.bincount(f, minlength=T).to(residual.dtype)
    return mx, sm / cnt.clamp_min(1)


def effective_tolerance(tol: torch.Tensor, noise: torch.Tensor, noise_factor: float) -> torch.Tensor:
    """``(B,)`` the distance an item is tested at: its tolerance, never below
    ``noise_factor`` times its estimated noise."""
    return torch.maximum(tol, noise_factor * noise)


def mark_triangles(mesh: MeshBatch, residual: torch.Tensor, face: torch.Tensor, count: torch.Tensor,
                   line_eps: torch.Tensor, tol: torch.Tensor, noise: torch.Tensor, statistic: str,
                   noise_factor: float, min_points_split: int, min_points_fit: int,
                   thin_factor: float, min_split_size: float = 0.0,
                   coverage: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
                   ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mark the triangles that fail the test.

    Args:
        residual: ``(P,)`` squared point-to-curve distances. count: ``(T,)`` points per triangle.
        line_eps: ``(T,)`` line-fit errors. tol, noise: ``(B,)`` distances.
        coverage: optional :func:`curve_coverage_excess` ``(excess, reach)``: a triangle whose
            piece of curve is farther from the data than the effective tolerance is marked too,
            while it is larger than the reach of the points near it (the data's resolution).
    Returns:
        marked ``(T,)`` bool, the effective tolerance ``(B,)`` and the largest error ``(B,)``
        (a distance, the chosen statistic).
    """
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
    if coverage is not None:
        # the data-to-curve test cannot see curve where there are no data (a wall across a
        # ring, a bridge between two close curves): the curve-to-data side, down to the
        # resolution of the sampling (finer, the data cannot tell where the curve goes)
        excess, reach = coverage
        marked |= torch.isfinite(excess) & (excess > eff[fi]) & (longest > 2.0 * reach)
    # below the resolution the tolerance allows, splitting only fits the noise
    if min_split_size > 0:
        marked &= longest > min_split_size * eff[fi]
    worst = torch.zeros(mesh.num_items, dtype=stat.dtype, device=stat.device).scatter_reduce(0, fi, stat, "amax")
    return marked, eff, worst.sqrt()


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
                          frames: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(T,)`` how far the midpoint ``m_t`` of each triangle's zero-set segment lies off the
    data, sideways: the smallest ``|(m_t − p)·n_p|`` over the points ``p`` of the triangle and
    its three neighbours that see it, i.e. with ``|(m_t − p)·τ_p| ≤ r_p``, where ``τ_p, n_p``
    are the tangent and normal of the data at ``p`` and ``r_p`` the reach of its neighbourhood
    (``frames (P, 3)`` from :func:`estimate_noise`). A curve that leaves the data sideways (a
    wall across a ring, a bridge between two close curves) is caught; one that runs on along
    the data into a sampling gap is seen by no point and left alone (splitting cannot fill a
    gap). ``-inf`` where the triangle holds no segment, ``inf`` where no point sees it. Also
    ``(T,)`` the smallest reach of those points (inf: none): the size below which the data
    cannot place the curve."""
    seg, has = triangle_segments(mesh, values)
    mid = seg.mean(1)                                              # (T,2)
    T = mid.shape[0]
    ok = face >= 0
    f = face[ok]
    p = points[ok].to(mid.dtype)
    fr = frames[ok].to(mid.dtype)
    tau, reach = fr[:, :2], fr[:, 2]
    cand = torch.cat([f[:, None], mesh.face_neighbors[f]], 1)      # (P,4)
    valid = (cand >= 0) & has[cand.clamp_min(0)]
    c = cand.clamp_min(0)
    off = mid[c] - p[:, None, :]                                   # (P,4,2)
    along = (off * tau[:, None, :]).sum(-1)
    across = off[..., 0] * tau[:, None, 1] - off[..., 1] * tau[:, None, 0]
    # a point vouches only for what lies within its neighbourhood along the curve: beyond it
    # (a sampling gap) it says nothing, and splitting would not fill the gap
    seen = valid & (along.abs() <= reach[:, None])
    d = across.abs()
    out = torch.full((T,), float("inf"), dtype=mid.dtype, device=mid.device)
    out = out.scatter_reduce(0, c[seen], d[seen], "amin")
    rmin = torch.full((T,), float("inf"), dtype=mid.dtype, device=mid.device)
    rmin = rmin.scatter_reduce(0, c[seen], reach[:, None].expand_as(d)[seen], "amin")
    return torch.where(has, out, torch.full_like(out, -float("inf"))), rmin
