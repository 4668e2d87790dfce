"""A batched L-BFGS: one optimizer per item of a packed batch, run together.

``torch.optim.LBFGS`` over a packed batch shares one line search across items, so an item's
result would depend on its batch. Here every dot product, step size, curvature pair and
stopping test is per segment (item), so each item follows exactly the trajectory it would
follow alone. Dimension-free: it knows nothing about meshes.

The direction comes from the compact representation of the inverse Hessian (Byrd, Nocedal &
Schnabel 1994), so one iteration costs a fixed handful of tensor ops whatever the history
length, instead of the two-loop recursion's four ops per stored pair.

Once the history has filled (after ``history`` rounds run in lockstep, as a plain batched
L-BFGS would, on a CPU; elsewhere from the first round, the history starting as skipped pairs),
every round has fixed shapes and no host read (GPU-ready; on CUDA recorded once as a graph and
replayed, :mod:`torch_isc.pipeline.graphs`): each segment keeps
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
from torch_isc.pipeline import budget, graphs

__all__ = ["batched_lbfgs", "true_indices"]


#: device types whose L-BFGS fills its history in lockstep rounds (host reads per block of
#: trials, fewer evaluations); elsewhere the fixed-shape rounds start from a zero history: the
#: same trajectories in exact arithmetic, the bits to rounding. On a CPU the lockstep blocks
#: are cheaper (one trial a round there: carrying a long backtrack over rounds costs a whole
#: evaluation of the working set a halving)
_LOCKSTEP_FILL = {"cpu": True}


#: device types on which the fit's short reductions run as explicit adds, its gathers and
#: scatters of rows of 2 one column at a time and the segment sums from contiguous copies: 1.5x
#: faster on a CPU, where reductions over a dim of 2-3 and broadcasts over it are slow; on a GPU
#: the fused forms are fewer launches. Both forms give the same bits on a CPU.
UNFUSED_DEVICES = {"cpu"}


def unfused(x: torch.Tensor) -> bool:
    """Whether ``x``'s device takes the unfused forms (:data:`UNFUSED_DEVICES`)."""
    return x.device.type in UNFUSED_DEVICES


def true_indices(mask: torch.Tensor, count: int) -> torch.Tensor:
    """``(count,)`` the indices where the 1-D ``mask`` is True, ``count`` being their number
    (read on the host already): no second host read, where the device has ``nonzero_static``."""
    try:
        return torch.nonzero_static(mask, size=count).squeeze(1)
    except (NotImplementedError, RuntimeError):
        return mask.nonzero().squeeze(1)


def _segdot(a: torch.Tensor, b: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    return segment_sum(a * b, seg, n)


def _segmat(A: torch.Tensor, b: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, k)``: per segment, the dot products of the rows of ``A (k, N)`` with ``b (N,)``."""
    return _segrows(A * b, seg, n)


def _segrows(P: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, k)``: per segment, the sums of the rows of ``P (k, N)`` (each column summed in
    entry order, so a column's bits do not depend on the other rows)."""
    # on a CPU a contiguous source: the same sums, about 1.5x faster than the transposed view
    return torch.zeros(n, P.shape[0], dtype=P.dtype, device=P.device).index_add_(
        0, seg, P.T.contiguous() if unfused(P) else P.T)


def _neg_direction(g: torch.Tensor, dg: torch.Tensor, H: torch.Tensor, Q: torch.Tensor, gamma: torch.Tensor,
                   seg: torch.Tensor, B: int) -> torch.Tensor:
    """``−H g`` with ``H = γI + [S γY] [[R⁻ᵀ(D + γYᵀY)R⁻¹, −R⁻ᵀ], [−R⁻¹, 0]] [Sᵀ; γYᵀ]``, where
    ``R`` is the upper triangle of ``SᵀY`` and ``D`` its diagonal (per segment); ``dg = −γ g``
    per entry. ``H (2, k, N)`` holds the pairs ``S, Y``, ``Q (B, 2, k, k)`` per segment ``SᵀY``
    and ``YᵀY``. The small ``k×k`` algebra runs in float64. A pair stored as zeros (skipped for
    its segment) carries a unit ``s·y`` diagonal: a unit pivot, so it contributes nothing."""
    k = H.shape[1]
    if k == 0:
        return dg
    W = H.reshape(2 * k, -1)                                     # S then Y: one product for both
    ab = _segmat(W, g, seg, B).double()[..., None]              # (B, 2k, 1)
    a, b = ab[:, :k], ab[:, k:]
    gm = gamma.double()[:, None, None]
    SY, YY = Q[:, 0], Q[:, 1]
    DY = gm * YY
    DY.diagonal(dim1=1, dim2=2).add_(torch.diagonal(SY, dim1=1, dim2=2))     # D + γYᵀY
    R = torch.triu(SY)
    p = torch.linalg.solve_triangular(R, a, upper=True)                     # R⁻¹ Sᵀg
    # −q = R⁻ᵀ (γ Yᵀg − (D + γYᵀY) p): a triangular solve is odd in its right-hand side, so
    # solving for −q directly gives −q's bits without a negation
    nq = torch.linalg.solve_triangular(R.transpose(1, 2), gm * b - DY @ p, upper=False)
    c = torch.cat([nq, gm * p], 1)[..., 0].to(g.dtype).index_select(0, seg)   # (N, 2k), negated
    return dg + (c.T * W).sum(0)


def _pair(Hold: torch.Tensor, Qold: torch.Tensor, hn: torch.Tensor, seg: torch.Tensor, B: int, tiny: float,
          zero: torch.Tensor, one: torch.Tensor, one64: torch.Tensor):
    """The history with a new pair ``hn = (s, y) (2, N)`` appended to the pairs that stay,
    ``Hold (2, k, N)`` with their products ``Qold (B, 2, k, k)``: the products of the new pair
    (S·y, Y·y, s·y, y·y, Y·s, s·s) in one segmented sum, and the curvature test: a pair is kept
    only with enough positive curvature, a skipped one is stored as zeros (with a unit ``s·y``).
    Returns ``H (2, k+1, N)``, ``Q (B, 2, k+1, k+1)`` and the next ``gamma``."""
    k, n = Hold.shape[1], hn.shape[1]
    s, y = hn[0], hn[1]
    Hn = torch.cat([Hold, hn[:, None]], 1)
    Pr = hn.new_empty(3, k + 1, n)
    torch.mul(Hn, y, out=Pr[:2])                             # s_i·y, s·y | y_i·y, y·y
    torch.mul(Hold[1], s, out=Pr[2, :k])                     # y_i·s
    torch.mul(s, s, out=Pr[2, k])                            # s·s
    P = _segrows(Pr.view(3 * (k + 1), n), seg, B).view(B, 3, k + 1)
    sy, yy = P[:, 0, k], P[:, 1, k]
    r = P[:, 1:, k].sqrt()                                   # √(y·y), √(s·s)
    # enough curvature: s·y > 1e-12 |y| |s| (the bound is >= 0 or NaN, so this also says s·y > 0)
    keep = sy > 1e-12 * r[:, 0] * r[:, 1]
    torch.where(keep.index_select(0, seg), hn, zero, out=Hn[:, k])           # a skipped pair is stored as zeros
    gamma = torch.where(keep & (yy > 0), sy / yy.clamp_min(tiny), one)
    Pd = (P * keep[:, None, None]).double()                  # times 1 or 0, exact in either dtype
    # the new last rows: s·y_j then s·y (a unit pivot when skipped) in place of s·s, no longer
    # needed; y_j·y, y·y
    torch.where(keep, Pd[:, 0, k], one64, out=Pd[:, 2, k])
    rows = Pd[:, 1:].flip(1)[:, :, None]                     # (B, 2, 1, k+1)
    if not k:
        return Hn, rows, gamma
    # below Qold's columns s_i·y and y_i·y, those rows
    Qn = torch.cat([torch.cat([Qold, Pd[:, :2, :k, None]], 3), rows], 2)
    return Hn, Qn, gamma


def batched_lbfgs(fun: Callable[..., torch.Tensor], x0: torch.Tensor, seg: torch.Tensor, num_segments: int,
                  iterations: int = 50, history: int = 8, rel_tol: float = 1e-7, max_backtracks: int = 12,
                  c1: float = 1e-4, with_grad: bool = False, stacked: bool = False, trials: int = 2,
                  check_every: int = 4, restrict: Optional[Callable] = None, shrink: float = 0.5,
                  tail_trials: int = 4, tail_entries: int = 2048
                  ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Minimize ``fun`` segment by segment.

    Every segment follows the trajectory of a plain sequential L-BFGS with a halving Armijo
    backtracking search (steps ``1, 1/2, ..., 1/2^(max_backtracks-1)``, the first accepted taken),
    whatever the batch, and whatever ``trials`` and ``check_every``: those change only how the
    work is laid out.

    On a CPU (``_LOCKSTEP_FILL``), while the history fills (the first ``history`` rounds) the
    rounds run in lockstep: the
    search tries ``trials`` steps in its first stacked call, twice as many in each further one,
    and reads on the host whether another block is needed. After that every round has fixed shapes and no host read: ``trials`` steps in
    one stacked call over the whole working set, the first accepted taken per segment; a segment
    that accepted none keeps its state (hence its direction) and carries on halving in the next
    round; every segment keeps its own last ``history`` pairs in a fixed buffer (on other devices
    from the first round, the buffer starting with skipped pairs). Whether any
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
        tail_trials, tail_entries: once compaction has left at most ``tail_entries`` entries
            (the last segments of a batch) every stacked call tries at least ``tail_trials``
            step lengths: the rounds a backtracking straggler adds are paid by the whole batch
            in launches and host reads (the slowest segment of a large batch sets the number
            of rounds), while its arithmetic is small. A set that starts small (one item) keeps
            ``trials``: on a CPU 4 trials made a lone 1,000-point curve's fits 1.2x slower.
        restrict: ``restrict(items) -> (fun, restrict)``, the objective of the segments
            ``items (num_segments,)`` bool alone (segments renumbered in order, entries kept in
            order). Given, the working set is compacted at a read that finds at most
            ``shrink`` of its segments running (at most log(B) times), so the finished ones
            stop costing arithmetic.
    Returns:
        ``x``, the per-segment objective at ``x``, and the number of iterations each segment ran.
    """
    if int(max_backtracks) < 1 or int(check_every) < 1:
        raise ValueError(f"batched_lbfgs: max_backtracks and check_every must be at least 1, not "
                         f"{max_backtracks} and {check_every}")
    B = num_segments
    dt = x0.dtype
    dev = x0.device
    n = x0.shape[0]
    mb = int(max_backtracks)
    m, K = int(history), max(1, min(int(trials), mb))
    Kt = max(K, min(int(tail_trials), mb))                   # trials once the working set is small

    def trials_for(n_entries: int) -> int:
        return Kt if n_entries <= tail_entries else K

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

    # constants of every round, made once (a Python scalar in torch.where is one more kernel)
    zero = torch.zeros((), dtype=dt, device=dev)
    one0 = torch.ones((), dtype=dt, device=dev)
    one64 = torch.ones((), dtype=torch.float64, device=dev)
    mb_t = torch.full((), mb, dtype=torch.long, device=dev)
    zero_l = torch.zeros((), dtype=torch.long, device=dev)
    neg_inf = float("-inf")
    cols = torch.arange(n, device=dev)
    blocks = {}                                              # trials per block -> (j, 2^-j) as (k, 1)

    def halves(K):
        if K not in blocks:
            j = torch.arange(K, device=dev)[:, None]
            blocks[K] = j, torch.pow(0.5, j.to(dt))          # exact powers of two
        return blocks[K]

    def search(XG, f, d, gd, step0, left, K=K):
        """One stacked block of trials ``step0 / 2^j`` (``j < K``) for the segments with
        ``j < left``: whether each accepted one, and the first accepted point with its gradient
        (stacked, ``(2, n)``) and objective."""
        jj, hv = halves(K)
        step = step0[None] if K == 1 else step0 * hv         # (K, B); times 1 is exact
        X = XG[0] + step[:, seg] * d                         # (K, n) every trial, whole set
        FT, GT = evaluate(X)
        # FT <= f + ... (f finite, the rest <= 0) is False for NaN and +inf: only -inf is left out
        ok = (jj < left) & (FT <= f + c1 * step * gd) & (FT > neg_inf)
        if K == 1:
            return ok[0], torch.stack([X[0], GT[0]]), FT[0]
        acc = ok.any(0)
        first = ok.to(torch.uint8).argmax(0)                 # the first accepted trial
        return acc, torch.stack([X, GT])[:, first.index_select(0, seg), cols], FT.gather(0, first[None])[0]

    def descent(g, H, Q, gamma, seg, B):
        dg = -g * gamma.index_select(0, seg)                                 # steepest descent, the fallback
        d = _neg_direction(g, dg, H, Q, gamma, seg, B)
        gds = _segmat(torch.stack([d, dg]), g, seg, B)       # g·d and g·dg in one sum
        # not a descent direction: fall back to steepest descent (no host read: where, always)
        good = gds[:, 0] < 0
        return torch.where(good.index_select(0, seg), d, dg), torch.where(good, gds[:, 0], gds[:, 1])

    x = x0.detach().clone()
    f, g = evaluate(x[None])
    f = f[0]
    XG = torch.stack([x, g[0]])                              # the point and its gradient
    H = torch.zeros(2, 0, n, dtype=dt, device=dev)           # stored pairs S, Y, oldest first
    Q = torch.zeros(B, 2, 0, 0, dtype=torch.float64, device=dev)   # per segment s_i·y_j, y_i·y_j
    active = torch.isfinite(f)
    iters = torch.zeros(B, dtype=torch.long, device=dev)
    gamma = 1.0 / torch.sqrt(_segdot(XG[1], XG[1], seg, B)).clamp_min(1.0)
    tiny = torch.finfo(dt).tiny
    one = torch.ones(B, dtype=dt, device=dev)

    def small_change(f, f_new):
        return (f - f_new).abs() <= rel_tol * f.abs().clamp_min(tiny)

    def converged(f, f_new, moved):
        return moved & small_change(f, f_new)

    # the history fills: lockstep rounds, a host read per block of trials; each block after the
    # first tries twice as many steps (a few segments backtrack far: fewer blocks, fewer reads).
    # Elsewhere than on a CPU the fixed-shape rounds start at once, from a history of skipped
    # (zero) pairs, which contribute nothing to the direction: no host read in the first rounds,
    # and on CUDA every round replays
    fill = min(m, iterations) if _LOCKSTEP_FILL.get(dev.type, False) else 0
    if not fill:
        H = torch.zeros(2, m, n, dtype=dt, device=dev)
        Q = torch.zeros(B, 2, m, m, dtype=torch.float64, device=dev)
        Q[:, 0].diagonal(dim1=1, dim2=2).fill_(1.0)          # a skipped pair's unit s·y pivot
    r = 0
    while r < fill and not budget.stop(r):
        d, gd = descent(XG[1], H, Q, gamma, seg, B)
        XGn, f_new = XG, f
        moved = torch.zeros_like(active)
        step0 = one
        tried, kb = 0, K
        while True:
            kb = min(kb, mb - tried)
            left = (active & ~moved) * (mb - tried)
            acc, xgt, ft = search(XG, f, d, gd, step0, left, kb)
            XGn = torch.where(acc.index_select(0, seg), xgt, XGn)
            f_new = torch.where(acc, ft, f_new)
            moved = moved | acc
            if tried == 0:
                # whether any segment was still running is read with the first block's outcome
                # (one read less per round; a round found idle costs its first block, once)
                searching, running = torch.stack([(active & ~moved).any(), active.any()]).tolist()
                if not running:
                    return XG[0], f, iters
            tried += kb
            if tried >= mb or not (searching if tried == kb else bool((active & ~moved).any())):
                break
            step0 = step0 * 0.5 ** kb
            kb *= 2
        H, Q, gamma = _pair(H, Q, XGn - XG, seg, B, tiny, zero, one0, one64)
        small = converged(f, f_new, moved)
        iters = iters + moved
        XG, f = XGn, f_new
        active = active & moved & ~small
        r += 1
    if fill and iterations <= m:
        return XG[0], f, iters

    # fixed shapes from here on, no host read but every check_every rounds. left: trials left in
    # the segment's current iteration, 0 once it has stopped
    left = (active & (iters < iterations)) * mb
    step0 = one
    Kc = K                                                   # K only grows: the bound on rounds holds
    x_out, f_out, it_out = XG[0], f, iters                  # the whole batch, once compacted
    ent = item = None                                        # the working set's entries and segments
    Bw = B

    def one_round(XG, H, Q, gamma, f, iters, left, step0):
        """One fixed-shape round of the whole working set: the state after it."""
        d, gd = descent(XG[1], H, Q, gamma, seg, Bw)
        moved, xgt, ft = search(XG, f, d, gd, step0, left, Kc)
        ms = moved.index_select(0, seg)
        XGn = torch.where(ms, xgt, XG)
        f_new = torch.where(moved, ft, f)
        # the oldest pair drops out for a segment that moved; the others keep theirs
        Hn, Qn, gam = _pair(H[:, 1:], Q[:, :, 1:, 1:], XGn - XG, seg, Bw, tiny, zero, one0, one64)
        gamma = torch.where(moved, gam, gamma)
        H = torch.where(ms, Hn, H)
        Q = torch.where(moved[:, None, None, None], Qn, Q)
        iters = iters + moved
        # a segment that moved gets a new iteration unless it has converged or run out; one that
        # did not has Kc trials fewer (left > 0 implies iters < iterations, so it cannot have run out)
        stop = small_change(f, f_new) | (iters >= iterations)
        left = torch.where(moved, torch.where(stop, zero_l, mb_t), (left - Kc).clamp_min(0))
        step0 = torch.where(moved, one, step0 * 0.5 ** Kc)
        return XGn, H, Q, gamma, f_new, iters, left, step0

    state = (XG, H, Q, gamma, f, iters, left, step0)
    # on a GPU one round is recorded once per working set and replayed check_every times a
    # block (pipeline/graphs.py): the same kernels, one launch a round. One round, not a whole
    # block: recording costs what launching its kernels would, and a working set lasts only tens
    # of rounds between compactions
    replay = graphs.active(dev, "fit")
    graph = None
    total = (iterations - fill) * -(-mb // Kc)
    r = 0
    while r < total and not budget.stop(r):
        if r % check_every == 0:
            XG, H, Q, gamma, f, iters, left, step0 = state
            alive = left > 0
            if restrict is None:
                if not bool(alive.any()):
                    break
            else:
                na = int(alive.sum())
                if na == 0:
                    break
                if na <= shrink * Bw:
                    x_out, f_out, it_out = _put(x_out, f_out, it_out, ent, item, XG[0], f, iters)
                    ae = alive.index_select(0, seg)
                    e, b = true_indices(ae, int(ae.sum())), true_indices(alive, na)
                    ent = e if ent is None else ent[e]
                    item = b if item is None else item[b]
                    renum = torch.cumsum(alive, 0) - 1
                    seg, Bw = renum[seg[e]], na
                    XG, H = XG[:, e], H[:, :, e]
                    f, iters, gamma, left, step0 = f[b], iters[b], gamma[b], left[b], step0[b]
                    Q = Q[b]
                    one = one[b]
                    cols = torch.arange(XG.shape[1], device=dev)
                    fun, restrict = restrict(alive)
                    Kc = trials_for(XG.shape[1])
                    state = (XG, H, Q, gamma, f, iters, left, step0)
                    graph = None
            if replay and r + check_every <= total:
                if graph is None:
                    halves(Kc)                               # made outside the graph's pool
                    graph, state = _record_round(one_round, state, dev)
                    replay = graph is not None
                if graph is not None:
                    for _ in range(check_every):
                        graph.replay()
                    r += check_every
                    continue
        state = one_round(*state)
        graph = None                                         # the state is no longer the graph's
        r += 1
    XG, H, Q, gamma, f, iters, left, step0 = state
    return _put(x_out, f_out, it_out, ent, item, XG[0], f, iters)


def _record_round(one_round: Callable, state, dev: torch.device):
    """A graph of one application of ``one_round`` that writes the state after it into the
    state's tensors, and those tensors: copies, owned by the graph (a state tensor can alias
    another or a tensor the caller keeps, e.g. the unit step). ``(None, state)`` where
    recording failed."""
    static = tuple(t.clone() for t in state)

    def step():
        for t, v in zip(static, one_round(*static)):
            t.copy_(v)
    graph = graphs.capture(step, dev, "fit")
    return (None, state) if graph is None else (graph, static)


def _put(x_out, f_out, it_out, ent, item, x, f, iters):
    """The working set's ``x, f, iters`` written into the whole batch's."""
    if ent is None:
        return x, f, iters
    return x_out.index_copy(0, ent, x), f_out.index_copy(0, item, f), it_out.index_copy(0, item, iters)
