"""A global inside/outside prior for the signs: the generalized winding number of the points
with oriented normals,

    w(q) = Σ_i a_i o_i·(p_i − q) / (2π (|p_i − q|² + ε²)),

about 1 inside a closed curve, 0 outside, 1/2 on it. It averages over all the points, so noise
and gaps move it little, unlike the local line evidence of the Ising energy.

- normals: PCA of each point's nearest neighbours (taken along two shifted Morton orders), the
  covariance then smoothed over the neighbour graph so the support grows past the noise width;
- orientation: Z2 synchronisation of the normals on the neighbour graph (a start by label
  propagation with parity, then power iterations of the signed coupling ``κ_ij n_i·n_j``), the
  coupling anisotropic (neighbours along the tangent, not across a gap to a parallel curve);
- per connected piece (chains cut at corners and tips) one sign, chosen so that the winding of
  all pieces on a grid over the item is nearest {0, 1} (a descent from a few starts): nesting
  parity, and open arcs between corners, come out of that one rule;
- a self-check: where the chosen winding still overshoots [0, 1] on more than a few percent of
  the grid, the orientation is inconsistent and the item's prior is trusted less (0 at 5%);
- pieces of fewer than ``MIN_PIECE`` points (outliers, specks) and points whose orientation the
  synchronisation leaves unsure weigh nothing.

Everything is batched over the packed points (item by item) with tensor ops; the pair sums go in
chunks, so memory stays bounded.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import torch

from torch_isc.pipeline.noise import approximate_knn

from torch_isc.core.segments import (edge_components, expand_in_chunks, first_index, hash_uniform, segment_count,
                                     segment_median, sym2_eigvals, sym2_eigvec)
from torch_isc.pipeline import budget

__all__ = ["WindingPrior", "knn", "point_normals", "orient_normals", "winding_prior", "winding_at", "winding_on_grid",
           "winding_field"]

#: a connected piece of fewer points is no curve (an outlier, a speck): it weighs nothing
MIN_PIECE = 5
#: candidates on each side along each Morton order
_WINDOW = 16
#: pairs per chunk of a pair sum
_BUDGET = 1 << 22


@dataclass
class WindingPrior:
    """``points (P, 2)``, ``item (P,)``, ``b (P, 2)`` the oriented normals times the length
    each point stands for (0 for points that weigh nothing), ``eps (B,)`` the smoothing length,
    ``trust (B,)`` in [0, 1], how consistent the orientation came out (see :data:`OVERSHOOT`)."""
    points: torch.Tensor
    item: torch.Tensor
    b: torch.Tensor
    eps: torch.Tensor
    trust: torch.Tensor
    #: ``(B, G, G)`` the winding on the piece-sign grid (first axis x), its corner ``lo (B, 2)``
    #: and extent ``ext (B, 2)``: what the field interpolates
    grid: Optional[torch.Tensor] = None
    lo: Optional[torch.Tensor] = None
    ext: Optional[torch.Tensor] = None


def knn(points: torch.Tensor, item: torch.Tensor, k: int, window: int = _WINDOW) -> Tuple[torch.Tensor, torch.Tensor]:
    """:func:`~torch_isc.pipeline.noise.approximate_knn` with this module's window."""
    return approximate_knn(points, item, k, window)


def point_normals(points: torch.Tensor, nbr: torch.Tensor, d2: torch.Tensor, smooth_rounds: int = 2,
                  return_spread: bool = False, scale: Optional[torch.Tensor] = None):
    """``(P, 2)`` unit normals (unoriented): the minor axis of the covariance of each point and
    its neighbours, the covariance then averaged over the neighbours ``smooth_rounds`` times
    (each round widens the support by about one neighbourhood). With ``return_spread``, also
    ``(P, 2)`` the eigenvalues (minor, major) of the unsmoothed covariance. ``scale (P,)``: the
    neighbours weigh ``exp(-d²/2 scale²)`` (a parallel curve a few spacings away stays out)."""
    dt = points.dtype
    valid = torch.isfinite(d2)
    wn = valid.to(dt)
    if scale is not None:
        wn = torch.where(valid, torch.exp(-0.5 * d2 / scale[:, None] ** 2), torch.zeros_like(wn))
    w = torch.cat([torch.ones_like(wn[:, :1]), wn], 1)                           # (P, k+1), self first
    pts = torch.cat([points[:, None, :], points[nbr]], 1)
    m = w.sum(1)
    mean = (pts * w[..., None]).sum(1) / m[:, None]
    qd = (pts - mean[:, None, :]) * w[..., None]
    C = torch.einsum("pki,pkj->pij", qd, qd) / m[:, None, None]
    cov = torch.stack([C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]], 1)
    spread = torch.stack(sym2_eigvals(*cov.unbind(1)), 1)
    idx = torch.cat([torch.arange(points.shape[0], device=points.device)[:, None], nbr], 1)
    for _ in range(int(smooth_rounds)):
        cov = (cov[idx] * w[..., None]).sum(1) / m[:, None]
    a, b, d = cov.unbind(1)
    lmin, _ = sym2_eigvals(a, b, d)
    n = sym2_eigvec(a, b, d, lmin)
    nn = n.norm(dim=1, keepdim=True)
    ok = torch.isfinite(nn) & (nn > 0)
    n = torch.where(ok, n / nn.clamp_min(torch.finfo(dt).tiny), torch.tensor([1.0, 0.0], dtype=dt, device=n.device))
    return (n, spread) if return_spread else n


def _couplings(points, normals, nbr, d2, rt, rn):
    """Directed kNN edges ``(i, j)``: the anisotropic kernel ``κ_ij`` (in i's frame: ``rt`` along
    the tangent, ``rn`` along the normal, per point) and ``n_i·n_j``."""
    P, k = nbr.shape
    i = torch.arange(P, device=points.device)[:, None].expand(P, k)
    d = points[nbr] - points[:, None, :]
    dn = (d * normals[:, None, :]).sum(-1)
    dtn2 = (d ** 2).sum(-1) - dn ** 2
    kap = torch.exp(-0.5 * (dtn2.clamp_min(0) / rt[:, None] ** 2 + dn ** 2 / rn[:, None] ** 2))
    kap = torch.where(torch.isfinite(d2), kap, torch.zeros_like(kap))
    dot = (normals[nbr] * normals[:, None, :]).sum(-1)
    return i.reshape(-1), nbr.reshape(-1), kap.reshape(-1), dot.reshape(-1)


def _parity_labels(P: int, a, b, sgn, join) -> torch.Tensor:
    """``(P,)`` ±1: a parity per vertex relative to the smallest vertex of its component in the
    graph of the edges ``(a, b)`` where ``join`` holds, propagated along the edges' signs
    ``sgn`` (a spanning forest grown by label propagation with pointer jumping; where cycles
    disagree, the smaller key wins)."""
    dev = a.device
    lab = torch.arange(P, device=dev)
    par = torch.zeros(P, dtype=torch.long, device=dev)                            # 0: +1, 1: -1
    flip = (sgn < 0).long()
    big = torch.full_like(a, 2 * P + 2)
    while True:
        key = 2 * lab + par
        ka = torch.where(join, 2 * lab[a] + (par[a] ^ flip), big)
        kb = torch.where(join, 2 * lab[b] + (par[b] ^ flip), big)
        new = key.scatter_reduce(0, b, ka, "amin").scatter_reduce(0, a, kb, "amin")
        nl, np_ = new // 2, new % 2
        nl2, np2 = nl[nl], np_ ^ np_[nl]                                             # pointer jumping
        nk = 2 * nl2 + np2
        if torch.equal(nk, key):
            return 1.0 - 2.0 * par.to(torch.float64)
        lab, par = nl2, np2


def orient_normals(points: torch.Tensor, item: torch.Tensor, num_items: int, noise: torch.Tensor,
                   k: int = 12, sync_iterations: int = 30, smooth_rounds: int = 2, join_kernel: float = 0.3,
                   join_dot: float = 0.9, max_pieces: int = 32, return_grid: bool = False,
                   smooth_widths: float = 2.0):
    """Normals, their orientation and each point's weight.

    Returns ``o (P, 2)`` oriented unit normals (outward of the inside region, nesting
    included), ``a (P,)`` the length each point stands for (0 for points of pieces smaller than
    ``MIN_PIECE`` or left unsure by the synchronisation), ``piece (P,)`` the component label,
    ``h (B,)`` the median neighbour spacing of each item, ``over (B,)`` the fraction of the
    piece-sign grid where the winding overshoots [0, 1] (an inconsistent orientation)."""
    dev, dt = points.device, points.dtype
    P = points.shape[0]
    nbr, d2 = knn(points, item, k)
    d1 = d2[:, 0].sqrt()
    h = segment_median(torch.where(torch.isfinite(d1), d1, torch.zeros_like(d1)), item, num_items)
    sig = noise.to(dt)
    n, spread = point_normals(points, nbr, d2, smooth_rounds, return_spread=True,
                              scale=torch.maximum(NORMAL_SPACINGS * h, NORMAL_NOISE * sig)[item].clamp_min(torch.finfo(dt).tiny))
    rt = torch.maximum(3.0 * h, 3.0 * sig)[item].clamp_min(torch.finfo(dt).tiny)
    rn = torch.maximum(h, 2.0 * sig)[item].clamp_min(torch.finfo(dt).tiny)
    a_, b_, kap, dot = _couplings(points, n, nbr, d2, rt, rn)
    # pieces: chains of neighbours along the curve with nearly parallel normal lines (not across
    # a thin stroke or a tip, where the oriented normals are opposite while the lines agree)
    # a corner or a tip: a neighbourhood far from a line (beyond the noise) has no normal line,
    # and the orientation must not run through it (a tip turns the oriented normal around
    # while the fitted lines of its two sides agree)
    corner = (spread[:, 0] > CORNER_RATIO * spread[:, 1]) & (spread[:, 0] > (CORNER_NOISE * sig[item]) ** 2)
    strong = (kap > join_kernel) & (dot.abs() > join_dot) & ~corner[a_] & ~corner[b_]
    piece = edge_components(P, torch.stack([a_, b_], 1), strong)
    # Z2 synchronisation within each piece: a spanning-forest start, then power iterations of
    # x <- x + D^-1 W x with the signed coupling W_ij = κ_ij n_i·n_j
    x = _parity_labels(P, a_, b_, dot, strong).to(dt)
    same = piece[a_] == piece[b_]
    c = torch.where(same, kap * dot, torch.zeros_like(kap))
    deg = torch.zeros(P, dtype=dt, device=dev).index_add_(0, a_, c.abs()).index_add_(0, b_, c.abs()).clamp_min(1e-30)
    for _ in budget.rounds(sync_iterations):
        y = torch.zeros_like(x).index_add_(0, a_, c * x[b_]).index_add_(0, b_, c * x[a_])
        x = x + y / deg
        x = x / segment_max_abs(x, piece, P)[piece]
    sure = x.abs() > 0.25                               # a point its neighbours disagree about
    s = torch.where(x < 0, -1.0, 1.0).to(dt)
    o = n * s[:, None]
    # the length each point stands for: 1 / (points per unit length along the tangent), a
    # tangential kernel density within the reach of the neighbours (not across to another curve)
    reach = torch.where(torch.isfinite(d2), d2, torch.zeros_like(d2)).amax(1).sqrt()
    rk = (reach / 3.0).clamp_min(torch.finfo(dt).tiny)
    dd = points[nbr] - points[:, None, :]
    dn = (dd * n[:, None, :]).sum(-1)
    dtn2 = ((dd ** 2).sum(-1) - dn ** 2).clamp_min(0)
    kd = torch.exp(-0.5 * dtn2 / rk[:, None] ** 2) * (dn.abs() <= 3 * rn[:, None]) * torch.isfinite(d2)
    dens = (kd.sum(1) + 1.0) / (math.sqrt(2 * math.pi) * rk)
    # a neighbour the Morton candidates missed halves a density: the median over the neighbours
    ln = 1.0 / dens
    ln = torch.where(torch.isfinite(d2), ln[nbr], ln[:, None])
    ln = torch.cat([(1.0 / dens)[:, None], ln], 1).median(1).values
    size = segment_count(piece, P)
    a = torch.where((size[piece] >= MIN_PIECE) & sure, ln, torch.zeros_like(dens))
    # one sign per piece: the choice whose winding number is nearest {0, 1} (nesting parity,
    # open arcs between corners and tips alike)
    eps = float(smooth_widths) * torch.maximum(sig, h)
    sg, over, grid = _piece_signs(points, item, num_items, o * a[:, None], piece, a, eps, max_pieces)
    return (o * sg[:, None], a, piece, h, over, grid) if return_grid else (o * sg[:, None], a, piece, h, over)


def segment_max_abs(x: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    return torch.zeros(n, dtype=x.dtype, device=x.device).scatter_reduce(0, seg, x.abs(), "amax").clamp_min(1e-30)


#: a neighbourhood whose minor spread exceeds this fraction of its major one is a corner...
CORNER_RATIO = 0.1
#: ...when its minor spread is also beyond this many noise widths
CORNER_NOISE = 1.5
#: the normal fit's weights fall off at this many spacings or noise widths, the larger
NORMAL_SPACINGS = 2.5
NORMAL_NOISE = 8.0
#: a winding number this far below 0 or above 1 betrays a wrong orientation
OVERSHOOT = 0.15
#: an item whose grid has this fraction of such values gets no prior (linearly from 0)
OVERSHOOT_LIMIT = 0.05
#: grid of the piece-sign choice, per side of each item's bounding box
_GRID = 32
#: starts of the piece-sign descent
_RESTARTS = 4


def _piece_signs(points, item, B, b, piece, a, eps, max_pieces) -> torch.Tensor:
    """``(P,)`` ±1: a sign per piece such that the winding number of all pieces, on a grid over
    each item's bounding box (and a margin), is nearest to {0, 1}: the energy
    ``Σ_q min(w_q², (w_q − 1)²)``. The ``max_pieces`` longest pieces of an item are decided in
    order of length (each against the longer ones), then once more each against all the others;
    the other pieces keep their sign."""
    dev, dt = points.device, points.dtype
    P = points.shape[0]
    out = torch.ones(P, dtype=dt, device=dev)
    C = int(max_pieces)
    if P == 0 or C == 0:
        return out
    # the pieces of each item ranked by length
    length = torch.zeros(P, dtype=dt, device=dev).index_add_(0, piece, a)
    is_lab = (torch.arange(P, device=dev) == piece) & (length > 0)
    labs = torch.nonzero(is_lab).squeeze(1)
    li = item[labs]
    order = torch.argsort(li.to(dt) * 4.0 - length[labs] / length[labs].max().clamp_min(1e-30), stable=True)
    labs, li = labs[order], li[order]
    cnt = segment_count(li, B)
    rank_l = torch.arange(labs.shape[0], device=dev) - first_index(cnt)[li]
    rank = torch.full((P,), C, dtype=torch.long, device=dev)
    rank[labs] = rank_l.clamp_max(C)
    prank = rank[piece]                                            # C: not decided here
    # a G x G grid over each item's bounding box grown by 10%
    big = torch.finfo(dt).max
    idx2 = item[:, None].expand(-1, 2)
    lo = torch.full((B, 2), big, dtype=dt, device=dev).scatter_reduce(0, idx2, points, "amin")
    hi = torch.full((B, 2), -big, dtype=dt, device=dev).scatter_reduce(0, idx2, points, "amax")
    lo, hi = torch.where(lo <= hi, lo, torch.zeros_like(lo)), torch.where(lo <= hi, hi, torch.zeros_like(hi))
    ext = hi - lo
    lo, ext = lo - 0.1 * ext, 1.2 * ext
    G = _GRID
    t = (torch.arange(G, device=dev, dtype=dt) + 0.5) / G
    uv = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)          # (Q, 2)
    Q = uv.shape[0]
    grid = lo[:, None, :] + uv[None] * ext[:, None, :]                               # (B, Q, 2)
    eps2 = eps ** 2
    M = torch.zeros(B * Q * (C + 1), dtype=dt, device=dev)
    pcnt = segment_count(item, B)
    pfirst = first_index(pcnt)
    qi = torch.arange(B, device=dev).repeat_interleave(Q)
    qq = grid.reshape(-1, 2)
    for _, _, row, slot in expand_in_chunks(pcnt[qi], _BUDGET):
        p = pfirst[qi[row]] + slot
        d = points[p] - qq[row]
        val = (b[p] * d).sum(1) / (2 * math.pi * ((d ** 2).sum(1) + eps2[qi[row]]))
        M.index_add_(0, row * (C + 1) + prank[p], val)
    M = M.view(B, Q, C + 1)
    rest = M[:, :, C]                                              # pieces kept as they are
    Mc = M[:, :, :C]
    # coordinate descent from several starts (the first: longest first, each piece against the
    # longer ones; the others: hashed random signs), the lowest energy kept per item
    R = _RESTARTS
    Mr = Mc[:, None]                                                           # (B, 1, Q, C)
    key = torch.arange(R * C, device=dev).view(1, R, C)
    S = torch.where(hash_uniform(key, dtype=torch.float64) < 0.5, -1.0, 1.0).to(dt).expand(B, R, C).clone()
    S[:, 0] = 0.0
    w = rest[:, None, :] + (S[:, :, None, :] * Mr).sum(-1)                     # (B, R, Q)

    def energy(w):
        return torch.minimum(w ** 2, (w - 1) ** 2).sum(-1)

    for r in range(2):
        for j in range(C):
            base = w - S[:, :, j:j + 1] * Mr[..., j]
            ep, en = energy(base + Mr[..., j]), energy(base - Mr[..., j])
            sj = torch.where(en < ep, -1.0, 1.0).to(dt)
            S[:, :, j] = sj
            w = base + sj[..., None] * Mr[..., j]
    best = torch.argmin(energy(w), 1)                                          # first minimum
    S = S.gather(1, best[:, None, None].expand(B, 1, C))[:, 0]
    w = w.gather(1, best[:, None, None].expand(B, 1, Q))[:, 0]
    sp = torch.cat([S, torch.ones(B, 1, dtype=dt, device=dev)], 1)
    # a consistent orientation has no winding below 0 or above 1 (beyond the smoothing's ripple)
    over = ((w < -OVERSHOOT) | (w > 1 + OVERSHOOT)).to(dt).mean(1)
    return sp[item, prank], over, (w.view(B, G, G), lo, ext)


def winding_prior(points: torch.Tensor, item: torch.Tensor, num_items: int, noise: torch.Tensor,
                  k: int = 12, sync_iterations: int = 30, smooth_widths: float = 2.0) -> WindingPrior:
    """The oriented, weighted points of every item and the smoothing length
    ``ε = smooth_widths · max(noise, spacing)``."""
    with torch.no_grad():
        o, a, _, h, over, (grid, lo, ext) = orient_normals(points.detach(), item, num_items, noise, k,
                                                             sync_iterations, return_grid=True,
                                                             smooth_widths=smooth_widths)
        eps = float(smooth_widths) * torch.maximum(noise.to(points.dtype), h)
        trust = (1.0 - over / OVERSHOOT_LIMIT).clamp(0, 1)
        return WindingPrior(points.detach(), item, o * a[:, None], eps, trust, grid, lo, ext)


def winding_on_grid(prior: WindingPrior, q: torch.Tensor, q_item: torch.Tensor) -> torch.Tensor:
    """``(M,)`` the winding at ``q`` interpolated (bilinear) from the prior's grid, held at the
    grid's border value beyond it: O(1) per point, where :func:`winding_at` sums over all
    points. The grid's cells are about 1/27 of the item's size: near the curve, where the
    field is weak anyway, the values blur."""
    G = prior.grid.shape[1]
    u = (q.detach().to(prior.grid.dtype) - prior.lo[q_item]) / prior.ext[q_item] * G - 0.5
    u = u.clamp(0, G - 1)
    i0 = u.floor().long().clamp_max(G - 2)
    f = u - i0
    flat = prior.grid.reshape(-1)
    base = q_item * (G * G) + i0[:, 0] * G + i0[:, 1]

    def at(di, dj):
        return flat[base + di * G + dj]
    fx, fy = f[:, 0], f[:, 1]
    return ((1 - fx) * (1 - fy) * at(0, 0) + fx * (1 - fy) * at(1, 0) + (1 - fx) * fy * at(0, 1) + fx * fy * at(1, 1))


def winding_at(prior: WindingPrior, q: torch.Tensor, q_item: torch.Tensor) -> torch.Tensor:
    """``(M,)`` the winding number of each item's prior at the points ``q (M, 2)`` of items
    ``q_item (M,)`` (every point of the item, in chunks of bounded memory)."""
    with torch.no_grad():
        dev, dt = q.device, prior.points.dtype
        B = prior.eps.shape[0]
        cnt = segment_count(prior.item, B)
        first = first_index(cnt)
        out = torch.zeros(q.shape[0], dtype=dt, device=dev)
        qd = q.detach().to(dt)
        eps2 = prior.eps ** 2
        for _, _, row, slot in expand_in_chunks(cnt[q_item], _BUDGET):
            p = first[q_item[row]] + slot
            d = prior.points[p] - qd[row]
            val = (prior.b[p] * d).sum(1) / ((d ** 2).sum(1) + eps2[q_item[row]])
            out.index_add_(0, row, val)
        return out / (2 * math.pi)


def winding_field(prior: WindingPrior, verts: torch.Tensor, vert_item: torch.Tensor, weight: float) -> torch.Tensor:
    """``(V,)`` the field term of the Ising energy, ``Σ_v g_v F_v`` with ``g_v = weight (2w−1)``
    for ``w`` clamped to [0, 1]: positive inside (favours F = −1), negative outside, about 0
    near the curve, on open curves' ends and wherever the prior is unsure."""
    w = winding_on_grid(prior, verts, vert_item) if prior.grid is not None else winding_at(prior, verts, vert_item)
    ok = (w > -OVERSHOOT) & (w < 1 + OVERSHOOT)
    g = (2.0 * w.clamp(0, 1) - 1.0) * prior.trust[vert_item]
    return float(weight) * torch.where(ok, g, torch.zeros_like(g))
