"""Denoise the points at the item's own noise scale before the loop.

A triangle of five noisy points says little: its line fit (the sign evidence) and the
magnitude fit follow the noise. Each point is moved onto a weighted local parabola fitted to
its neighbours, the weights being

* spatial: a bump ``(1 - (r/R)²)²`` over a radius ``R = denoise_radius`` noise widths (never
  fewer than the point's few nearest neighbours), so the fit averages over the noise's scale;
* along the local normal: ``exp(-s² / 2(denoise_band σ)²)`` of the neighbour's offset ``s``
  across the point's current tangent (bilateral), so a second curve a few noise widths away,
  or the other side of a sharp corner, barely counts.

The parabola (not a line) keeps the curvature: a line through the neighbours of a point of a
circle would pull it inward by about ``R²/6ρ``. A move is at most ``denoise_max_move`` noise
widths, so an outlier (whose neighbours are all far along its normal) stays where it is, and
noise-free data (noise estimate 0) are not moved at all. The fit is repeated
``denoise_iterations`` times (Jacobi: every point from the previous positions), the neighbours
found once (approximate kNN along Morton orders, :func:`noise.approximate_knn`). Everything is a
few tensor ops over the packed batch, in blocks of points (bounded memory); dtype and device
follow the points; points are expected normalized per item (so the result is invariant to the
item's translation and scale).
"""
from __future__ import annotations

from typing import Optional

import torch

from torch_isc.core.segments import segment_median, sym2_eigvals, sym2_eigvec
from torch_isc.pipeline.noise import NoiseConfig, approximate_knn, knn_budget, nearest_candidates, take
from torch_isc.pipeline import budget

__all__ = ["denoise_points"]

#: the fewest neighbours (self excluded) the radius always covers
MIN_NEIGHBOURS = 8
#: a fit whose weights sum below this (the point itself counts 1) moves nothing
MIN_WEIGHT = 3.0
#: rounds of the reweighted fit per pass
ROUNDS = 3
#: a neighbourhood whose spread across its fit is this many times the item's median spread
#: holds two strands (one wall: the noise's variance; two strands g apart: that plus about g²/4)
SPLIT_SPREAD = 2.0
#: the median spread counts at least this fraction of the noise's variance (the fit's own
#: residual spread over one wall is about half of it; data with no spread flag nothing)
SPREAD_FLOOR = 0.1
#: offsets beyond this many bands from the fit are another curve, not this one's spread
SPREAD_CLIP = 3.0


def refine_knn(points: torch.Tensor, nbr: torch.Tensor, d2: torch.Tensor, hops: int = 6,
               pairs_per_block: Optional[int] = None):
    """One round of neighbour descent on an approximate kNN (``nbr (P, k)``, ``d2 (P, k)``
    ascending, ``inf`` where missing): each point's candidates are its neighbours and the
    neighbours of its ``hops`` nearest, of which the ``k`` nearest are kept. The Morton
    candidates of :func:`approximate_knn` come from the quadtree cells a point sits in, so its
    neighbourhood is cut off at cell walls; a fit over such a one-sided neighbourhood moves the
    points of a cell together, and a noisy band denoises into axis-aligned dashes and parallel
    strands (a stroke's wall becomes two or three curves). Neighbours of neighbours reach across
    the walls. Items never mix (a neighbour is in the point's item)."""
    P, k = nbr.shape
    h = min(int(hops), k)
    if P == 0 or h <= 0:
        return nbr, d2
    dev = points.device
    C = k + h * k
    block = max(1, (knn_budget(dev) if pairs_per_block is None else pairs_per_block) // C)
    out_n = torch.empty_like(nbr)
    out_d = torch.empty_like(d2)
    for b0 in range(0, P, block):
        idx = torch.arange(b0, min(P, b0 + block), device=dev)
        own = take(nbr, idx)
        c = torch.cat([own, take(nbr, own[:, :h]).reshape(idx.shape[0], -1)], 1)
        # a missing neighbour is the point itself (approximate_knn's convention): masked below;
        # sorted so that repeats sit side by side
        c, _ = torch.sort(c, 1)
        bad = c == idx[:, None]
        bad[:, 1:] |= c[:, 1:] == c[:, :-1]
        out_n[idx], out_d[idx] = nearest_candidates(points, idx, c, bad, k)
    return out_n, out_d


def _tangents(x: torch.Tensor, nbr: torch.Tensor, valid: torch.Tensor, R: torch.Tensor, fallback: torch.Tensor,
              block: int) -> torch.Tensor:
    """``(P, 2)`` each point's unit tangent: the major axis of its neighbourhood's covariance,
    weighted by the bump over the fit's radius ``R`` (the noise estimate's frames come from 8
    neighbours: where the points are denser than the noise is wide, a round blob with a random
    axis). ``fallback`` where the neighbourhood has no axis."""
    P = x.shape[0]
    t = torch.empty_like(fallback)
    for b0 in range(0, P, block):
        idx = torch.arange(b0, min(P, b0 + block), device=x.device)
        q = take(x, take(nbr, idx)) - take(x, idx)[:, None, :]
        q2 = q * q
        w = (1.0 - (q2[..., 0] + q2[..., 1]) / R[idx, None] ** 2).clamp_min(0) ** 2   # (q * q).sum(-1), bit for bit
        w = torch.where(valid[idx], w, torch.zeros_like(w))
        W = (1.0 + w.sum(1)).clamp_min(torch.finfo(x.dtype).tiny)          # the point itself (q = 0) counts
        mean = (w[..., None] * q).sum(1) / W[:, None]
        qd = q - mean[:, None, :]
        C = torch.einsum("pk,pki,pkj->pij", w, qd, qd) + mean[:, :, None] * mean[:, None, :]
        a, b, d = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
        _, lmax = sym2_eigvals(a, b, d)
        v = sym2_eigvec(a, b, d, lmax)
        v = v / v.norm(dim=1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)
        good = torch.isfinite(v).all(1, keepdim=True) & (v.norm(dim=1, keepdim=True) > 0.5) & (lmax[:, None] > 0)
        t[idx] = torch.where(good, v, fallback[idx])
    return t


def _fit_rows(x, t, nbr, valid, R, bands, cap, idx, ridge, sel, spread: bool):
    """One pass of the weighted parabola fit for the points ``idx``: their new positions
    ``(n, 2)``, tangents ``(n, 2)`` and, with ``spread``, the spatially weighted mean squared
    offset of their neighbours from the fitted parabola (within :data:`SPREAD_CLIP` bands;
    else None)."""
    dt = x.dtype
    xi, ti = take(x, idx), take(t, idx)
    ni = torch.stack([-ti[:, 1], ti[:, 0]], 1)
    nb = take(nbr, idx)
    # the offsets by coordinate, the point itself first (zero): (q * t).sum(-1) of (n, kk+1, 2)
    # as q0 t0 + q1 t1 + 0, bit for bit (a sum starts at +0), without the slow size-2 reductions
    q = []
    for j in range(2):
        qj = torch.zeros(nb.shape[0], nb.shape[1] + 1, dtype=dt, device=x.device)
        torch.sub(take(x[:, j], nb), xi[:, j, None], out=qj[:, 1:])
        q.append(qj)
    ok = torch.cat([torch.ones_like(valid[idx, :1]), valid[idx]], 1)
    Ri = R[idx, None]
    sb = bands[idx, None]
    u = (q[0] * ti[:, None, 0]).add_(q[1] * ti[:, None, 1]).add_(0.0).div_(Ri)   # along the tangent, in radii
    s = (q[0] * ni[:, None, 0]).add_(q[1] * ni[:, None, 1]).add_(0.0)           # across it
    r2 = u * u + (s / Ri) ** 2
    wsp = (1.0 - r2).clamp_min(0) ** 2
    wsp = torch.where(ok, wsp, torch.zeros_like(wsp))
    # the normal equations of the parabola need the moments of u up to the fourth
    upow = torch.stack([torch.ones_like(u), u, u * u, u * u * u, (u * u) ** 2], -1)    # (n, kk+1, 5)
    W = wsp.sum(1)
    reg = torch.diag_embed(ridge.expand(idx.shape[0], 3) * W[:, None])
    fit = torch.zeros_like(s)                                  # round 0: about the point itself
    for _ in range(ROUNDS):
        # the weight across is centred on the last fit: a mean shift across the curve
        # within the parabola model, which settles on the nearest ridge of the data
        w = wsp * torch.exp(-0.5 * ((s - fit) / sb) ** 2)
        mom = torch.einsum("pk,pkj->pj", w, upow)                  # (n, 5)
        A = mom[:, sel] + reg
        rhs = torch.einsum("pk,pkj->pj", w * s, upow[..., :3])
        coef = torch.linalg.solve_ex(A, rhs[..., None])[0][..., 0]      # singular: not finite, no move
        fit = coef[:, None, 0] + u * (coef[:, None, 1] + u * coef[:, None, 2])
    W = w.sum(1)
    move = coef[:, 0].clamp(-cap[idx], cap[idx])
    good = (W >= MIN_WEIGHT) & torch.isfinite(coef).all(1)
    move = torch.where(good, move, torch.zeros_like(move))
    xn = xi + move[:, None] * ni
    # the parabola's slope at the point turns the tangent (slope per radius)
    slope = torch.where(good, coef[:, 1] / Ri[:, 0], torch.zeros_like(move))
    tt = ti + slope[:, None] * ni
    tn = tt / tt.norm(dim=1, keepdim=True).clamp_min(torch.finfo(dt).tiny)
    var = None
    if spread:
        r = s - fit
        near = (r.abs() <= SPREAD_CLIP * sb) & torch.isfinite(r)
        wv = torch.where(near, wsp, torch.zeros_like(wsp))
        var = (wv * torch.where(near, r * r, torch.zeros_like(r))).sum(1) / wv.sum(1).clamp_min(torch.finfo(dt).tiny)
        var = torch.where(good, var, torch.zeros_like(var))
    return xn, tn, var


def denoise_knn(points: torch.Tensor, point_item: torch.Tensor, cfg: NoiseConfig):
    """The denoising's neighbours: ``(nbr (P, k), d2 (P, k))`` of :func:`approximate_knn`
    refined by :func:`refine_knn` (``k = cfg.denoise_neighbours``), or None where the denoising
    is off. The small clusters' search (:func:`~torch_isc.pipeline.blobs.find_blobs`) takes
    them too: one search instead of two."""
    if cfg.denoise_iterations <= 0 or points.shape[0] < 3:
        return None
    with torch.no_grad():
        k = cfg.denoise_neighbours
        nbr, d2 = approximate_knn(points, point_item, k, max(cfg.noise_window, (k + 1) // 2, cfg.denoise_window))
        if cfg.denoise_refine_hops > 0:
            nbr, d2 = refine_knn(points, nbr, d2, cfg.denoise_refine_hops)
    return nbr, d2


def denoise_points(points: torch.Tensor, point_item: torch.Tensor, noise: torch.Tensor, frames: torch.Tensor,
                   cfg: NoiseConfig, return_tangents: bool = False, knn=None):
    """``(P, 2)`` the points moved onto their local weighted parabolas (see the module).

    ``points (P, 2)`` normalized per item, ``point_item (P,)``, ``noise (B,)`` each item's noise
    level (a standard deviation, normalized units), ``frames (P, 3)`` each point's unit tangent
    (first two columns; :func:`noise.noise_and_frames`). ``cfg.denoise_iterations == 0``
    returns ``points`` itself. With ``return_tangents``, ``(points, tangents (P, 2))``: each
    point's unit tangent of its last fit (the frames' own where nothing was fitted). ``knn``:
    :func:`denoise_knn`'s neighbours, where the caller has them."""
    iters = cfg.denoise_iterations
    P = points.shape[0]
    if iters <= 0 or P < 3:
        return (points, frames[:, :2].to(points.dtype)) if return_tangents else points
    with torch.no_grad():
        dev, dt = points.device, points.dtype
        nbr, d2 = denoise_knn(points, point_item, cfg) if knn is None else knn
        valid = torch.isfinite(d2)
        kk = nbr.shape[1]
        sigma = noise.to(dt)[point_item]                                  # (P,)
        # the radius: denoise_radius noise widths, but at least the MIN_NEIGHBOURS-th neighbour
        # (sparse data: the fit needs points); only the k neighbours found can count
        dk = torch.where(valid, d2, torch.zeros_like(d2)).sqrt()
        near = dk[:, min(MIN_NEIGHBOURS, kk) - 1]
        R = torch.maximum(cfg.denoise_radius * sigma, near) * (1.0 + 1e-3)
        R = R.clamp_min(torch.finfo(dt).tiny)
        sband = (cfg.denoise_band * sigma).clamp_min(torch.finfo(dt).tiny)
        cap = cfg.denoise_max_move * sigma
        x = points.detach()
        block = max(1, knn_budget(dev) // (8 * (kk + 1)))
        t = _tangents(x, nbr, valid, R, frames[:, :2].to(dt), block)
        ridge = torch.tensor([0.0, 1e-3, 1e-3], dtype=dt, device=dev)
        sel = torch.tensor([[0, 1, 2], [1, 2, 3], [2, 3, 4]], device=dev)   # the Hankel matrix of the moments
        split = cfg.denoise_split_band > 0
        bands = sband
        for it in budget.rounds(iters):
            xn = torch.empty_like(x)
            tn = torch.empty_like(t)
            var = torch.empty_like(sigma) if split and it == 0 else None
            for b0 in range(0, P, block):
                idx = torch.arange(b0, min(P, b0 + block), device=dev)
                xn[idx], tn[idx], v = _fit_rows(x, t, nbr, valid, R, bands, cap, idx, ridge, sel, var is not None)
                if var is not None:
                    var[idx] = v
            if var is not None:
                # two strands: the spread across the fit, relative to the item's median spread
                # (one wall), says the neighbourhood holds a second strand a couple of noise
                # widths away (two close curves, a thin gap, the arms of a corner). There the
                # weight across narrows to denoise_split_band so each point keeps to its own
                # strand; elsewhere the wide band averages the noise
                med = segment_median(var, point_item, noise.shape[0])[point_item]
                two = var > SPLIT_SPREAD * torch.maximum(med, SPREAD_FLOOR * sigma * sigma)
                bands = torch.where(two, cfg.denoise_split_band * sigma, sband).clamp_min(torch.finfo(dt).tiny)
                rows = two.nonzero().squeeze(1)                                 # one host read per solve
                for b0 in range(0, rows.shape[0], block):
                    idx = rows[b0:b0 + block]
                    xn[idx], tn[idx], _ = _fit_rows(x, t, nbr, valid, R, bands, cap, idx, ridge, sel, False)
            x, t = xn, tn
        # the total move is bounded too (a point is never carried off by its neighbours' drift)
        d = x - points.detach()
        dn = d.norm(dim=1)
        x = points.detach() + d * (cap / dn.clamp_min(torch.finfo(dt).tiny)).clamp(max=1.0)[:, None]
        return (x.to(points.dtype), t.to(points.dtype)) if return_tangents else x.to(points.dtype)
