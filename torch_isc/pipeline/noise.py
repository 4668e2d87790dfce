"""The noise level of every item and the local frame of every point (the tolerance's floor
and the coverage test's tangents), from local parabola fits at each point's neighbours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import torch

from torch_isc.core.segments import (first_index, hash_uniform, local_index, segment_count, segment_median,
                                     segment_sum, sym2_eigvals, sym2_eigvec)
from torch_isc.pipeline.knobs import check_section, knob

__all__ = ["NoiseConfig", "NoiseEstimate", "estimate_noise", "noise_and_frames"]


@dataclass
class NoiseConfig:
    """The noise estimate (flat keys of configs/default.yaml)."""
    #: neighbours of each point in its local fit
    noise_neighbours: int = knob(8, ge=3)
    #: candidates taken on each side along each of two Morton orders
    noise_window: int = knob(12, gt=0)
    #: an item whose median neighbourhood aspect is below this is a blob (data denser than the noise)
    noise_blob_aspect: float = knob(2.0, gt=0)
    #: the aspect at which a subset is believed line-like
    noise_line_aspect: float = knob(2.5, gt=0)
    #: the fewest points a hashed subset may keep
    noise_min_subset: int = knob(64, gt=0)
    #: passes of the point denoising before the loop (pipeline/denoise.py); 0 disables
    denoise_iterations: int = knob(3, ge=0)
    #: neighbours of each point (approximate kNN) among which its local parabola is fitted
    denoise_neighbours: int = knob(24, ge=3)
    #: radius of the fit, in noise widths (at least the point's few nearest neighbours)
    denoise_radius: float = knob(8.0, gt=0)
    #: scale of the weight across the point's tangent, in noise widths (bilateral: a close
    #: second curve or the other side of a corner barely counts)
    denoise_band: float = knob(1.5, gt=0)
    #: the largest move of a point, in noise widths (outliers stay)
    denoise_max_move: float = knob(3.0, ge=0)
    #: the band across, in noise widths, for points whose neighbourhood holds two strands (its
    #: spread across the first fit at least twice the item's median): two close curves or a
    #: thin gap are not averaged into one; 0 disables (denoise_band everywhere)
    denoise_split_band: float = knob(0.0, ge=0)
    #: what sees the denoised points: all (the whole loop), evidence (only the sign evidence),
    #: geometry (the fit, the test and the band; the signs read the raw points)
    denoise_use: str = knob("all", choices=("all", "evidence", "geometry"))
    #: the noise level the loop assumes after denoising, as a fraction of the raw estimate
    denoise_noise_scale: float = knob(1.0, gt=0, le=1)
    #: one round of neighbour descent on the denoising's approximate neighbours: the neighbours
    #: of this many nearest neighbours join the candidates (Morton candidates stop at quadtree
    #: cell walls, and the fits then cut a noisy band into dashes and strands); 0 disables
    denoise_refine_hops: int = knob(4, ge=0)
    #: Morton candidates on each side of a point for the denoising's neighbours (at least
    #: noise_window and half of denoise_neighbours)
    denoise_window: int = knob(24, ge=1)

    def __post_init__(self):
        check_section(self)


@dataclass
class NoiseEstimate:
    """``level (B,)`` the noise of each item (a standard deviation); ``frames (P, 3)`` each
    point's unit tangent and the reach of its neighbourhood."""
    level: torch.Tensor
    frames: torch.Tensor


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
                         ks: Tuple[int, ...]) -> List[Tuple[torch.Tensor, ...]]:
    """For the points ``idx`` and each ``k`` of ``ks``: the residual variance of a line fitted to
    each point and its ``k`` nearest candidates (its neighbours along the Morton ``orders``), the
    fit's point count, the larger eigenvalue of the neighbourhood's covariance, the residual
    variance of a parabola fitted to the same points, and the point's frame ``(n, 3)``: the unit
    major axis of the neighbourhood (the local tangent) and the distance to its farthest
    neighbour. The candidates are searched once: the ``k`` nearest are the first ``k`` of the
    largest ``k``'s, nearest first."""
    c, repeat = window_candidates(orders, idx, offs, point_item)
    # (the windows hold no other item's point; a missing neighbour, the point itself, weighs 0)
    nbr, nd = nearest_candidates(points, idx, c, (c == idx[:, None]) | repeat, min(max(ks), c.shape[1]))
    return [_line_fits(points, idx, nbr[:, :k], nd[:, :k]) for k in ks]


def _line_fits(points: torch.Tensor, idx: torch.Tensor, nbr: torch.Tensor, nd: torch.Tensor) -> Tuple[torch.Tensor, ...]:
    """:func:`_local_line_residual`'s fits of the points ``idx`` and their neighbours ``nbr``
    (squared distances ``nd``, ``inf`` where missing)."""
    dev, dt = points.device, points.dtype
    valid = torch.isfinite(nd)
    pts = torch.cat([points[idx][:, None, :], take(points, nbr)], 1)          # (n, k+1, 2)
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
                    torch.stack([torch.ones_like(a), torch.zeros_like(a)], 1))      # (1, 0), on the device
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


def morton_orders(points: torch.Tensor, item: torch.Tensor) -> List[Tuple[torch.Tensor, torch.Tensor]]:
    """Two Morton (Z-order) sorts of ``points (P, 2)`` (normalized to about [-1, 1]) within
    their ``item (P,)``, the second on a grid shifted by a non-dyadic fraction so that points a
    cell boundary splits in one order are near in the other. Each is ``(order, pos)``: the
    sorted indices and each point's rank. Neighbour candidates are the points a few ranks away."""
    P = points.shape[0]
    out = []
    for shift in (0.0, 0.3719):
        q = ((points.detach() + 0.75 + shift * 0.5) / 2.0 * 65535).long().clamp(0, 65535)
        order = torch.argsort(item * (1 << 32) + _morton(q), stable=True)
        pos = torch.empty_like(order)
        pos[order] = torch.arange(P, device=points.device)
        out.append((order, pos))
    return out


def window_offsets(window: int, device) -> torch.Tensor:
    """``(2 window,)`` the rank offsets ``-window .. -1, 1 .. window`` of :func:`window_candidates`."""
    return torch.cat([torch.arange(-window, 0, device=device), torch.arange(1, window + 1, device=device)])


def window_candidates(orders, idx: torch.Tensor, offs: torch.Tensor, item: torch.Tensor
                      ) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(c, repeat)``, both ``(R, 2 len(offs))``: the points ``offs`` ranks away from each of
    the points ``idx`` along each of the two :func:`morton_orders` (the first order's window,
    then the second's; ``offs`` from :func:`window_offsets`), and which entries repeat a point
    that the row holds unmarked in another place (each point but the row's own is left unmarked
    exactly once). Ranks are clamped to the point's own item (its points are
    consecutive in every order): a clamped rank repeats the item's first or last point, which
    the window already holds unclamped (or which is the row's own point), and a point of the
    second window within ``window`` ranks of the row's point along the first order is in the
    first window. A row thus holds the same points in the same places, up to the item's index
    offset, wherever the item sits in the batch: the nearest among exactly equal distances (a
    lattice) are then the same picks (clamped to the batch, an item's rows held the other items'
    points, masked, in other places, and ``topk`` broke the ties by place). Repeats are marked,
    not sorted out: a row sort cost more than the rest of the search."""
    counts = torch.bincount(item, minlength=1)
    lo = (counts.cumsum(0) - counts)[item[idx]][:, None]
    hi = lo + counts[item[idx]][:, None] - 1
    (o1, p1), (o2, p2) = orders
    own1 = take(p1, idx)[:, None]
    r1 = own1 + offs[None, :]
    r2 = take(p2, idx)[:, None] + offs[None, :]
    k1 = torch.minimum(torch.maximum(r1, lo), hi)
    k2 = torch.minimum(torch.maximum(r2, lo), hi)
    c2 = take(o2, k2)
    window = offs.shape[0] // 2
    in_first = (take(p1, c2) - own1).abs() <= window
    repeat = torch.cat([k1 != r1, (k2 != r2) | in_first], 1)
    return torch.cat([take(o1, k1), c2], 1), repeat


#: pairs per block of an approximate neighbour search on the CPU (bounded memory for millions of
#: points; larger blocks ran slower a pair there, out of cache)
KNN_BUDGET = 1 << 22
#: per device type: the pairs per block (:func:`knn_budget`); a CUDA device not listed gets a
#: share of its memory, any other device _KNN_BUDGET_OTHER
_KNN_BUDGETS = {"cpu": KNN_BUDGET}
_KNN_BUDGET_OTHER = 1 << 26
#: a CUDA device's budget: its memory over this many bytes a pair (a block's arrays peak at
#: about 36 bytes a pair: candidates, their sorted copy, distances, gathered points)
_KNN_BYTES_PER_PAIR = 256


def knn_budget(device: torch.device) -> int:
    """Pairs per block of the neighbour searches and the denoising on ``device``. On an
    accelerator the blocks are as large as memory allows (1/256 of a CUDA device's memory, a
    peak of about 1/7 of it), so the number of blocks, each a fixed run of launches, does not
    grow with the batch there (a block per 25-45 thousand points on the CPU; 1.3 million points
    a block on an 80 GB device). Blocks cut the rows, not the sums: the results are the same."""
    b = _KNN_BUDGETS.get(device.type)
    if b is not None:
        return b
    if device.type == "cuda":
        mem = torch.cuda.get_device_properties(device).total_memory
        return max(KNN_BUDGET, mem // _KNN_BYTES_PER_PAIR)
    return _KNN_BUDGET_OTHER


def take(t: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``t[index]`` for a non-negative long ``index`` of any shape, as one ``index_select``
    (advanced indexing with a 2-D index ran 2-4x slower on the CPU; the same values)."""
    return t.index_select(0, index.reshape(-1)).view(index.shape + t.shape[1:])


def squared_distances(points: torch.Tensor, idx: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """``(R, C)``: ``((points[c] - points[idx][:, None, :]) ** 2).sum(-1)`` bit for bit (a sum of
    two squares rounds once either way), by coordinate columns: no ``(R, C, 2)`` gather."""
    out = None
    for j in range(points.shape[1]):
        col = points[:, j]
        d = take(col, c).sub_(take(col, idx)[:, None])
        d = d.mul_(d)
        out = d if out is None else out.add_(d)
    return out


def nearest_candidates(points: torch.Tensor, idx: torch.Tensor, c: torch.Tensor, bad: torch.Tensor,
                       k: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest of each row's candidates. ``c: (R, C)`` point indices, ``bad: (R, C)``
    candidates to leave out (the row's own point, and all but one copy of a point the row holds
    twice), ``idx: (R,)`` the rows' own points. Returns ``(R, k)`` indices (a missing neighbour
    is the row's own point) and their squared distances (``inf`` where missing), nearest first."""
    dd = squared_distances(points, idx, c).masked_fill_(bad, float("inf"))
    nd, ni = torch.topk(dd, k, dim=1, largest=False)
    return torch.where(torch.isfinite(nd), c.gather(1, ni), idx[:, None]), nd


def approximate_knn(points: torch.Tensor, item: torch.Tensor, k: int, window: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Approximate ``k`` nearest neighbours of every point within its item, among its
    ``window`` neighbours on each side along the two :func:`morton_orders` (points normalized
    to about [-1, 1]; a sort, not a search). Returns ``nbr (P, kk)`` long and ``d2 (P, kk)``
    squared distances, ``kk = min(k, 4 window)``, nearest first (``inf`` where a point has fewer
    candidates; ``nbr`` is then the point itself)."""
    P = points.shape[0]
    dev = points.device
    offs = window_offsets(window, dev)
    orders = morton_orders(points, item)
    kk = min(k, 4 * window)
    nbr = torch.empty(P, kk, dtype=torch.long, device=dev)
    d2 = torch.empty(P, kk, dtype=points.dtype, device=dev)
    block = max(1, knn_budget(dev) // (4 * window))
    for b0 in range(0, P, block):                       # bounded memory for many points
        idx = torch.arange(b0, min(P, b0 + block), device=dev)
        c, repeat = window_candidates(orders, idx, offs, item)
        bad = (c == idx[:, None]) | repeat             # the windows hold no other item's point
        nbr[idx], d2[idx] = nearest_candidates(points, idx, c, bad, kk)
    return nbr, d2


def _noise_at_scale(points: torch.Tensor, point_item: torch.Tensor, num_items: int, k: int,
                    window: int) -> Tuple[torch.Tensor, ...]:
    """Per item: the median residual variance of the local parabola fits, the median aspect
    ``sqrt(λmax / λmin)`` of the neighbourhoods (line fits), and the number of points used;
    per point: its frame (see :func:`_local_line_residual`)."""
    return _noise_at_scales(points, point_item, num_items, (k,), window)[0]


def _noise_at_scales(points: torch.Tensor, point_item: torch.Tensor, num_items: int, ks: Tuple[int, ...],
                     window: int) -> List[Tuple[torch.Tensor, ...]]:
    """:func:`_noise_at_scale` for each neighbour count of ``ks``, from one candidate search."""
    P = points.shape[0]
    dev, dt = points.device, points.dtype
    offs = window_offsets(window, dev)
    orders = morton_orders(points, point_item)
    outs = [(torch.empty(P, dtype=dt, device=dev), torch.empty(P, dtype=dt, device=dev),
             torch.empty(P, dtype=dt, device=dev), torch.empty(P, dtype=dt, device=dev),
             torch.empty(P, 3, dtype=dt, device=dev)) for _ in ks]
    # the (points x candidates) arrays go in blocks: bounded memory for millions of points
    block = max(1, knn_budget(dev) // 2 // (4 * window))
    for b0 in range(0, P, block):
        idx = torch.arange(b0, min(P, b0 + block), device=dev)
        for out, got in zip(outs, _local_line_residual(points, point_item, idx, orders, offs, ks)):
            for o, g in zip(out, got):
                o[idx] = g
    res = []
    for lam, m, lmax, quad, frame in outs:
        ok = m >= 4
        var = segment_median(quad[ok], point_item[ok], num_items)
        aspect = torch.sqrt(lmax / lam.clamp_min(torch.finfo(dt).tiny))
        asp = segment_median(aspect[ok], point_item[ok], num_items)
        res.append((var, asp, segment_sum(ok.long(), point_item, num_items), frame))
    return res


def estimate_noise(points: torch.Tensor, point_item: torch.Tensor, num_items: int,
                   cfg: Optional[NoiseConfig] = None) -> torch.Tensor:
    """``(B,)`` noise level (a standard deviation, in the points' units) of each item: the
    ``level`` of :func:`noise_and_frames`."""
    return noise_and_frames(points, point_item, num_items, cfg).level


#: Each aspect threshold acts as a ramp from ``threshold / (1 + ASPECT_BAND)`` (weight 0) to
#: ``threshold * (1 + ASPECT_BAND)`` (weight 1), linear in the log of the aspect. The band is
#: wider than the median aspect moves when one point of a 64-point subset moves or merges.
ASPECT_BAND = 0.25


def _aspect_ramp(aspect: torch.Tensor, threshold: float) -> torch.Tensor:
    """``(B,)`` in [0, 1]: how far ``aspect`` is past ``threshold``, over the band."""
    r = torch.log(aspect.double().clamp_min(1e-300) / threshold) / math.log1p(ASPECT_BAND)
    return (0.5 * (r + 1.0)).clamp(0.0, 1.0).to(aspect.dtype)


def noise_and_frames(points: torch.Tensor, point_item: torch.Tensor, num_items: int,
                     cfg: Optional[NoiseConfig] = None, source: Optional[torch.Tensor] = None) -> NoiseEstimate:
    """The noise level of each item and the local frame of each point, from one pass.

    For every point, a parabola ``y = c0 + c1 x + c2 x²`` (x along the principal axis) is fitted
    to it and its ``k`` nearest neighbours (approximate: taken among its neighbours along two
    shifted Morton orders, so the cost is a sort, not a search); the noise variance is the
    median over the item of the residual variance, corrected for the three parameters of the
    fit. A straight line would read the sagitta of a sparsely sampled arc as noise (60 points
    on a circle: 1.8% of the radius). The same fit over ``k // 2`` neighbours is made too; where
    it reads far less (:data:`MISFIT_RATIOS`), the full neighbourhood holds more than one
    parabola explains (a bend of a curve of few points, two close strands) and the smaller
    fit's variance is the estimate (a clean circle of 16 points: 0.7% of its radius, against
    12%). Points are expected normalized per item (bounding box centred, diagonal 1).

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

    The frames ``(P, 3)`` are each point's unit major axis of its neighbourhood (the curve's
    tangent there) and the distance to the farthest of its ``k`` neighbours (0 for a point
    alone in its item). ``k, window, blob_aspect, line_aspect, min_points`` are the
    ``noise_*`` knobs of ``cfg``. Each aspect test is a ramp over a band (``ASPECT_BAND``),
    not a switch: an aspect near a threshold blends the two scales' variances, so the estimate
    moves continuously with the points. ``source (P,)``: each point's index in the caller's
    set (:attr:`PointBatch.source`), the key of the subset hash (default: its index in the
    item), so that merging a repeat does not redraw the subsets.
    """
    cfg = NoiseConfig() if cfg is None else cfg
    k, window, min_points = cfg.noise_neighbours, cfg.noise_window, cfg.noise_min_subset
    blob_aspect, line_aspect = cfg.noise_blob_aspect, cfg.noise_line_aspect
    with torch.no_grad():
        P = points.shape[0]
        dev, dt = points.device, points.dtype
        if P < 3:
            z = torch.zeros(num_items, dtype=dt, device=dev)
            fr = torch.tensor([1.0, 0.0, 0.0], dtype=dt, device=dev).expand(P, 3).clone()
            return NoiseEstimate(z, fr)
        # two clean strands closer than the neighbourhood (nested rings a few spacings apart)
        # read as a noisy band at k neighbours; the nearest few see one strand each
        k_s = max(3, k // 2)
        (var0, asp, _, frames), (var_s, _, _, frames_s) = _noise_at_scales(points, point_item, num_items,
                                                                          (k, k_s), window)
        w_s = _ratio_ramp(var_s, var0, STRAND_RATIOS)
        frames = torch.where((w_s >= 0.5)[point_item][:, None], frames_s, frames)
        level = _blob_refit(points, point_item, num_items, var0, asp, source, k, window, min_points,
                            blob_aspect, line_aspect)
        # the fewer neighbours' variance where the full one is mostly misfit (two strands in one
        # neighbourhood, or a sparse curve's bend); this ramp lies above the strand test's, so
        # the level needs only this one
        w = _ratio_ramp(var_s, var0, MISFIT_RATIOS)
        return NoiseEstimate((w * var_s + (1 - w) * level).sqrt(), frames)


#: The strand test's ramp over the ratio of the noise read at half the neighbours to the noise
#: read at all of them: 1 (take the half's frames) below the first, 0 above the second. Two clean
#: strands a few spacings apart give 1e-3 or less (the larger neighbourhood spans both).
STRAND_RATIOS = (0.003, 0.01)

#: The same ratio's ramp for the noise level: below the first, the fewer neighbours' variance is
#: the estimate; above the second, the full one's. Noise dominates both fits on a well-sampled
#: noisy curve, which gives 0.55-0.95 (the fewer neighbours fit the noise a little more closely;
#: a dense noisy band, whose neighbourhoods are round, 0.55-0.7); where the full neighbourhood's
#: misfit dominates, the ratio falls toward the clean curve's 0.02-0.2: two strands in one
#: neighbourhood, or a sparsely sampled bend (eight neighbours span half of a 16-point circle,
#: and even a parabola reads 12% of its radius as noise).
MISFIT_RATIOS = (0.35, 0.5)


def _ratio_ramp(var_s: torch.Tensor, var0: torch.Tensor, ratios: Tuple[float, float]) -> torch.Tensor:
    """``(B,)`` in [0, 1]: the weight of the fewer neighbours' variance ``var_s`` against the
    full one ``var0``, a ramp in the log of their noise ratio over ``ratios`` (1 below the
    first, 0 above the second)."""
    lo, hi = ratios
    r = (var_s.double().clamp_min(0) / var0.double().clamp_min(1e-300)).sqrt().clamp_min(1e-300)
    w = (math.log(hi) - torch.log(r)) / (math.log(hi) - math.log(lo))
    return torch.where(var0 > 0, w.clamp(0.0, 1.0), torch.zeros_like(w)).to(var0.dtype)


def _blob_refit(points: torch.Tensor, point_item: torch.Tensor, num_items: int, var0: torch.Tensor,
                asp: torch.Tensor, source: Optional[torch.Tensor], k: int, window: int, min_points: int,
                blob_aspect: float, line_aspect: float) -> torch.Tensor:
    """``(B,)`` the noise variance of each item from its full-density variance ``var0`` and
    median aspect ``asp``, refitted on hashed subsets where the item is a blob (see
    :func:`noise_and_frames`)."""
    with torch.no_grad():
        # every threshold is a ramp over a band of aspects (blend weights, not a switch): a
        # perturbation far below the noise moves the estimate by about as much, never by a scale
        w = _aspect_ramp(asp, blob_aspect)
        if bool((w >= 1).all()):
            return var0
        est = w * var0
        left = 1.0 - w                                   # the weight still to place, per item
        cnt = segment_count(point_item, num_items)
        key = local_index(point_item, first_index(cnt)) if source is None else source
        u = hash_uniform(key, dtype=torch.float64)
        rate = 1.0
        while bool((left > 0).any()):
            rate /= 4.0
            # an item still undecided, with enough points left at this rate, is refitted; one
            # without keeps the full-density estimate for the rest of its weight
            todo = (left > 0) & (cnt.to(torch.float64) * rate >= min_points)
            if not bool(todo.any()):
                break
            keep = todo[point_item] & (u < rate)
            pi = point_item[keep]
            v2, a2, n2, _ = _noise_at_scale(points[keep], pi, num_items, k, window)
            use = todo & (n2 >= min_points)
            est = torch.where(todo & ~use, est + left * var0, est)
            left = torch.where(todo & ~use, torch.zeros_like(left), left)
            # only a line-like scale is believed: data that are a blob at every scale (no
            # curve, e.g. uniform clutter) keep the full-density estimate
            w2 = torch.where(use, _aspect_ramp(a2, line_aspect), torch.zeros_like(left))
            est = est + left * w2 * torch.where(use, v2, torch.zeros_like(v2))
            left = left * (1.0 - w2)
        return est + left * var0


