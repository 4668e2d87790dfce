"""A batched L-BFGS: one optimizer per item of a packed batch, run together.

``torch.optim.LBFGS`` over a packed batch shares one line search across items, so an item's
result would depend on its batch. Here every dot product, step size, curvature pair and
stopping test is per segment (item), so each item follows exactly the trajectory it would
follow alone. Dimension-free: it knows nothing about meshes.

The direction comes from the compact representation of the inverse Hessian (Byrd, Nocedal &
Schnabel 1994), so one iteration costs a fixed handful of tensor ops whatever the history
length, instead of the two-loop recursion's four ops per stored pair.

Once the history has filled (after ``history`` rounds run in lockstep, as a plain batched
L-BFGS would), every round has fixed shapes and no host read (GPU-ready): each segment keeps
its last ``history`` pairs in a fixed buffer, the backtracking line search tries ``trials``
step lengths in one stacked call of the objective over the whole working set and takes the
first accepted per segment, and a segment that accepted none carries on halving in the next
round from where it stopped (its state is unchanged, so its direction is too). The accepted
step is therefore the first of ``1, 1/2, ..., 1/2^(max_backtracks-1)`` satisfying the Armijo
condition, as in a sequential search, and the arithmetic is that of the sequential search:
trajectories are bit-identical whatever ``trials``. How many segments still run is read on the
host every ``check_every`` rounds; the working set is then compacted when it has halved.
"""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch

from torch_isc.core.segments import segment_sum

__all__ = ["batched_lbfgs"]


def _segdot(a: torch.Tensor, b: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    return segment_sum(a * b, seg, n)


def _segmat(A: torch.Tensor, b: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, k)``: per segment, the dot products of the rows of ``A (k, N)`` with ``b (N,)``."""
    return torch.zeros(n, A.shape[0], dtype=A.dtype, device=A.device).index_add_(0, seg, (A * b).T)


def _direction(g: torch.Tensor, S: torch.Tensor, Y: torch.Tensor, SY: torch.Tensor, YY: torch.Tensor,
               gamma: torch.Tensor, seg: torch.Tensor, B: int) -> torch.Tensor:
    """``H g`` with ``H = γI + [S γY] [[R⁻ᵀ(D + γYᵀY)R⁻¹, −R⁻ᵀ], [−R⁻¹, 0]] [Sᵀ; γYᵀ]``, where
    ``R`` is the upper triangle of ``SᵀY`` and ``D`` its diagonal (per segment). The small
    ``k×k`` algebra runs in float64. A pair stored as zeros (skipped for its segment) carries a
    unit ``s·y`` diagonal: a unit pivot, so it contributes nothing."""
    k = S.shape[0]
    if k == 0:
        return gamma[seg] * g
    W = torch.cat([S, Y])                                        # one product for both
    ab = _segmat(W, g, seg, B).double()[..., None]              # (B, 2k, 1)
    a, b = ab[:, :k], ab[:, k:]
    gm = gamma.double()[:, None, None]
    R = torch.triu(SY)
    DY = gm * YY
    DY.diagonal(dim1=1, dim2=2).add_(torch.diagonal(SY, dim1=1, dim2=2))     # D + γYᵀY
    p = torch.linalg.solve_triangular(R, a, upper=True)                      # R⁻¹ Sᵀg
    q = torch.linalg.solve_triangular(R.transpose(1, 2), DY @ p - gm * b, upper=False)
    c = torch.cat([q, -gm * p], 1)[..., 0].to(g.dtype)[seg]                 # (N, 2k)
    return gamma[seg] * g + (c.T * W).sum(0)


def _pair(S, Y, s_new, y_new, seg, B, dt):
    """The products of a new pair ``(s, y)`` with the pairs ``S, Y`` that stay, in two segmented
    products (S·y, Y·y, s·y, y·y and Y·s, s·s), and the curvature test: a pair is kept only with
    enough positive curvature, a skipped one is stored as zeros (with a unit ``s·y``). Returns the stored ``s, y``,
    ``keep``, the next ``gamma`` and the new column ``s_i·y`` / rows ``y_j·y``, ``s·y_j``."""
    k = S.shape[0]
    P1 = _segmat(torch.cat([S, Y, s_new[None], y_new[None]]), y_new, seg, B)
    P2 = _segmat(torch.cat([Y, s_new[None]]), s_new, seg, B)
    sy, yy, ss = P1[:, -2], P1[:, -1], P2[:, -1]
    keep = (sy > 1e-12 * yy.sqrt() * ss.sqrt()) & (sy > 0)
    ks = keep[seg]
    s_new = torch.where(ks, s_new, 0.0)
    y_new = torch.where(ks, y_new, 0.0)
    gamma = torch.where(keep & (yy > 0), sy / yy.clamp_min(torch.finfo(dt).tiny), 1.0)
    kd = keep.double()[:, None]
    col = P1[:, :k].double() * kd                                       # s_i · y_new
    yrow = torch.cat([P1[:, k:2 * k], yy[:, None]], 1).double() * kd    # y_j · y_new
    row = torch.cat([P2[:, :k].double() * kd, torch.where(keep, sy, 1.0).double()[:, None]], 1)   # s_new · y_j
    return s_new, y_new, gamma, col, yrow, row


def _grown(SY, YY, col, yrow, row):
    """``SY, YY`` with the new pair's column and row appended."""
    k = col.shape[1]
    SY = torch.cat([torch.cat([SY, col[:, :, None]], 2), row[:, None, :]], 1)
    YY = torch.cat([torch.cat([YY, yrow[:, :k, None]], 2), yrow[:, None, :]], 1)
    return SY, YY


def batched_lbfgs(fun: Callable[..., torch.Tensor], x0: torch.Tensor, seg: torch.Tensor, num_segments: int,
                  iterations: int = 50, history: int = 8, rel_tol: float = 1e-7, max_backtracks: int = 12,
                  c1: float = 1e-4, with_grad: bool = False, stacked: bool = False, trials: int = 2,
                  check_every: int = 4, restrict: Optional[Callable] = None, shrink: float = 0.5
                  ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Minimize ``fun`` segment by segment.

    Every segment follows the trajectory of a plain sequential L-BFGS with a halving Armijo
    backtracking search (steps ``1, 1/2, ..., 1/2^(max_backtracks-1)``, the first accepted taken),
    whatever the batch, and whatever ``trials`` and ``check_every``: those change only how the
    work is laid out.

    While the history fills (the first ``history`` rounds) the rounds run in lockstep: the
    search tries ``trials`` steps per stacked call and reads on the host whether another block
    is needed. After that every round has fixed shapes and no host read: ``trials`` steps in
    one stacked call over the whole working set, the first accepted taken per segment; a segment
    that accepted none keeps its state (hence its direction) and carries on halving in the next
    round; every segment keeps its own last ``history`` pairs in a fixed buffer. Whether any
    segment is still running is read every ``check_every`` rounds.

    Args:
        fun: maps ``x (n,)`` to per-segment objectives ``(num_segments,)``; segment ``b``'s
            objective may depend only on ``x[seg == b]``. With ``stacked=True`` it maps
            ``X (K, n)`` to ``(K, num_segments)`` (every row evaluated alike), so a block of
            trials is one call. With ``with_grad=True`` it returns ``(objectives, gradient)``
            itself (no autograd), the gradient shaped like its input.
        x0: ``(n,)`` start. seg: ``(n,)`` long segment of each entry.
        trials: step lengths per stacked call; check_every: rounds between host reads of
            how many segments are still running (after the history has filled).
        restrict: ``restrict(items) -> (fun, restrict)``, the objective of the segments
            ``items (num_segments,)`` bool alone (segments renumbered in order, entries kept in
            order). Given, the working set is compacted at a read that finds at most
            ``shrink`` of its segments running (at most log(B) times), so the finished ones
            stop costing arithmetic.
    Returns:
        ``x``, the per-segment objective at ``x``, and the number of iterations each segment ran.
    """
    B = num_segments
    dt = x0.dtype
    dev = x0.device
    n = x0.shape[0]
    mb = int(max_backtracks)
    m, K = int(history), max(1, min(int(trials), mb))
    iterations = int(iterations)

    def evaluate1(x):
        if with_grad:
            with torch.no_grad():
                return fun(x)
        x = x.detach().requires_grad_(True)
        with torch.enable_grad():
            f = fun(x)
            g, = torch.autograd.grad(f.sum(), x)
        return f.detach(), g.detach()

    def evaluate(X):                                         # (k, n) -> (k, B), (k, n)
        if stacked:
            return evaluate1(X)
        fs, gs = zip(*(evaluate1(x) for x in X))
        return torch.stack(fs), torch.stack(gs)

    cols = torch.arange(n, device=dev)
    rows = torch.arange(B, device=dev)
    jj = torch.arange(K, device=dev)[:, None]
    halves = torch.pow(0.5, jj.to(dt))                       # (K, 1), exact powers of two

    def search(x, f, d, gd, step0, left):
        """One stacked block of trials ``step0 / 2^j`` for the segments with ``j < left``:
        whether each accepted one, and the first accepted point with its objective and gradient."""
        step = step0 * halves                                # (K, B)
        X = x + step[:, seg] * d                             # (K, n) every trial, whole set
        FT, GT = evaluate(X)
        ok = (jj < left) & torch.isfinite(FT) & (FT <= f + c1 * step * gd)
        acc = ok.any(0)
        first = ok.to(torch.uint8).argmax(0)                 # the first accepted trial
        fseg = first[seg]
        return acc, X[fseg, cols], FT[first, rows], GT[fseg, cols]

    def descent(g, S, Y, SY, YY, gamma):
        d = -_direction(g, S, Y, SY, YY, gamma, seg, B)
        gd = _segdot(g, d, seg, B)
        # not a descent direction: fall back to steepest descent (no host read: where, always)
        bad = ~(gd < 0)
        d = torch.where(bad[seg], -g * gamma[seg], d)
        gd = torch.where(bad, _segdot(g, d, seg, B), gd)
        return d, gd

    x = x0.detach().clone()
    f, g = evaluate(x[None])
    f, g = f[0], g[0]
    S = torch.zeros(0, n, dtype=dt, device=dev)              # stored pairs, oldest first
    Y = torch.zeros_like(S)
    SY = torch.zeros(B, 0, 0, dtype=torch.float64, device=dev)  # per segment s_i·y_j
    YY = torch.zeros_like(SY)                                    # per segment y_i·y_j
    active = torch.isfinite(f)
    iters = torch.zeros(B, dtype=torch.long, device=dev)
    gamma = 1.0 / torch.sqrt(_segdot(g, g, seg, B)).clamp_min(1.0)
    tiny = torch.finfo(dt).tiny
    one = torch.ones(B, dtype=dt, device=dev)

    def converged(f, f_new, moved):
        return moved & ((f - f_new).abs() <= rel_tol * f.abs().clamp_min(tiny))

    # the history fills: lockstep rounds, a host read per block of trials
    r = 0
    while r < min(m, iterations):
        if not bool(active.any()):
            return x, f, iters
        d, gd = descent(g, S, Y, SY, YY, gamma)
        x_new, f_new, g_new = x, f, g
        moved = torch.zeros_like(active)
        step0 = one
        for tried in range(0, mb, K):
            left = torch.where(active & ~moved, mb - tried, 0)
            acc, xt, ft, gt = search(x, f, d, gd, step0, left)
            x_new = torch.where(acc[seg], xt, x_new)
            g_new = torch.where(acc[seg], gt, g_new)
            f_new = torch.where(acc, ft, f_new)
            moved = moved | acc
            if tried + K >= mb or not bool((active & ~moved).any()):
                break
            step0 = step0 * 0.5 ** K
        s_new, y_new, gam, col, yrow, row = _pair(S, Y, x_new - x, g_new - g, seg, B, dt)
        gamma = gam
        S, Y = torch.cat([S, s_new[None]]), torch.cat([Y, y_new[None]])
        SY, YY = _grown(SY, YY, col, yrow, row)
        if S.shape[0] > m:
            S, Y, SY, YY = S[1:], Y[1:], SY[:, 1:, 1:], YY[:, 1:, 1:]
        small = converged(f, f_new, moved)
        iters = iters + moved.long()
        x, f, g = x_new, f_new, g_new
        active = active & moved & ~small
        r += 1
    if iterations <= m:
        return x, f, iters

    # fixed shapes from here on, no host read but every check_every rounds. left: trials left in
    # the segment's current iteration, 0 once it has stopped
    left = torch.where(active & (iters < iterations), mb, 0)
    step0 = one
    x_out, f_out, it_out = x, f, iters                      # the whole batch, once compacted
    ent = item = None                                        # the working set's entries and segments
    Bw = B
    for r in range((iterations - m) * -(-mb // K)):
        if r % check_every == 0:
            alive = left > 0
            if restrict is None:
                if not bool(alive.any()):
                    break
            else:
                na = int(alive.sum())
                if na == 0:
                    break
                if na <= shrink * Bw:
                    x_out, f_out, it_out = _put(x_out, f_out, it_out, ent, item, x, f, iters)
                    e = alive[seg].nonzero().squeeze(1)
                    b = alive.nonzero().squeeze(1)
                    ent = e if ent is None else ent[e]
                    item = b if item is None else item[b]
                    renum = torch.cumsum(alive, 0) - 1
                    seg, Bw = renum[seg[e]], na
                    B = Bw
                    x, g, S, Y = x[e], g[e], S[:, e], Y[:, e]
                    f, iters, gamma, left, step0 = f[b], iters[b], gamma[b], left[b], step0[b]
                    SY, YY = SY[b], YY[b]
                    one = one[b]
                    cols = torch.arange(x.shape[0], device=dev)
                    rows = torch.arange(Bw, device=dev)
                    fun, restrict = restrict(alive)
        d, gd = descent(g, S, Y, SY, YY, gamma)
        moved, xt, ft, gt = search(x, f, d, gd, step0, left)
        ms = moved[seg]
        x_new = torch.where(ms, xt, x)
        g_new = torch.where(ms, gt, g)
        f_new = torch.where(moved, ft, f)
        # the oldest pair drops out for a segment that moved; the others keep theirs
        s_new, y_new, gam, col, yrow, row = _pair(S[1:], Y[1:], x_new - x, g_new - g, seg, B, dt)
        gamma = torch.where(moved, gam, gamma)
        S = torch.where(ms, torch.cat([S[1:], s_new[None]]), S)
        Y = torch.where(ms, torch.cat([Y[1:], y_new[None]]), Y)
        SYn, YYn = _grown(SY[:, 1:, 1:], YY[:, 1:, 1:], col, yrow, row)
        mv = moved[:, None, None]
        SY, YY = torch.where(mv, SYn, SY), torch.where(mv, YYn, YY)
        iters = iters + moved.long()
        stop = converged(f, f_new, moved) | (iters >= iterations)
        left = torch.where(moved, mb, left - K).clamp_min(0).masked_fill(stop, 0)
        step0 = torch.where(moved, one, step0 * 0.5 ** K)
        x, f, g = x_new, f_new, g_new
    return _put(x_out, f_out, it_out, ent, item, x, f, iters)


def _put(x_out, f_out, it_out, ent, item, x, f, iters):
    """The working set's ``x, f, iters`` written into the whole batch's."""
    if ent is None:
        return x, f, iters
    return x_out.index_copy(0, ent, x), f_out.index_copy(0, item, f), it_out.index_copy(0, item, iters)
