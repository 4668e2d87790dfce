"""A batched L-BFGS: one optimizer per item of a packed batch, run together.

``torch.optim.LBFGS`` over a packed batch shares one line search across items, so an item's
result would depend on its batch. Here every dot product, step size, curvature pair and
stopping test is per segment (item), so each item follows exactly the trajectory it would
follow alone. Dimension-free: it knows nothing about meshes.

The direction comes from the compact representation of the inverse Hessian (Byrd, Nocedal &
Schnabel 1994), so one iteration costs a fixed handful of tensor ops whatever the history
length, instead of the two-loop recursion's four ops per stored pair.
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
    ``k×k`` algebra runs in float64."""
    k = S.shape[0]
    if k == 0:
        return gamma[seg] * g
    W = torch.cat([S, Y])                                        # one product for both
    ab = _segmat(W, g, seg, B).double()[..., None]              # (B, 2k, 1)
    a, b = ab[:, :k], ab[:, k:]
    gm = gamma.double()[:, None, None]
    D = torch.diagonal(SY, dim1=1, dim2=2)
    # a pair stored as zeros (skipped for this segment) gets a unit pivot and contributes nothing
    R = torch.triu(SY) + torch.diag_embed((D == 0).double())
    p = torch.linalg.solve_triangular(R, a, upper=True)                      # R⁻¹ Sᵀg
    q = torch.linalg.solve_triangular(R.transpose(1, 2), (torch.diag_embed(D) + gm * YY) @ p - gm * b, upper=False)
    c = torch.cat([q, -gm * p], 1)[..., 0].to(g.dtype)[seg]                 # (N, 2k)
    return gamma[seg] * g + (c.T * W).sum(0)


def batched_lbfgs(fun: Callable[..., torch.Tensor], x0: torch.Tensor, seg: torch.Tensor, num_segments: int,
                  iterations: int = 50, history: int = 8, rel_tol: float = 1e-7, max_backtracks: int = 12,
                  c1: float = 1e-4, masked: bool = False, with_grad: bool = False
                  ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Minimize ``fun`` segment by segment.

    Args:
        fun: maps ``x (n,)`` to per-segment objectives ``(num_segments,)``; segment ``b``'s
            objective may depend only on ``x[seg == b]``. With ``masked=True`` it is called as
            ``fun(x, items)`` with ``items (num_segments,)`` bool (or None for all) and needs to
            be right only for the segments in ``items``: the line search then re-evaluates
            only the segments still searching. With ``with_grad=True`` it returns
            ``(objectives, gradient (n,))`` itself (no autograd).
        x0: ``(n,)`` start. seg: ``(n,)`` long segment of each entry.
    Returns:
        ``x``, the per-segment objective at ``x``, and the number of iterations each segment ran.
    """
    B = num_segments
    dt = x0.dtype
    dev = x0.device

    def evaluate(x, items: Optional[torch.Tensor] = None):
        if with_grad:
            with torch.no_grad():
                return fun(x, items) if masked else fun(x)
        x = x.detach().requires_grad_(True)
        with torch.enable_grad():
            f = fun(x, items) if masked else fun(x)
            g, = torch.autograd.grad(f.sum(), x)
        return f.detach(), g.detach()

    x = x0.detach().clone()
    f, g = evaluate(x)
    S = torch.zeros(0, x.shape[0], dtype=dt, device=dev)      # stored pairs, oldest first
    Y = torch.zeros_like(S)
    SY = torch.zeros(B, 0, 0, dtype=torch.float64, device=dev)  # per segment s_i·y_j
    YY = torch.zeros_like(SY)                                    # per segment y_i·y_j
    active = torch.isfinite(f)
    iters = torch.zeros(B, dtype=torch.long, device=dev)
    gamma = 1.0 / torch.sqrt(_segdot(g, g, seg, B)).clamp_min(1.0)
    for it in range(int(iterations)):
        if not bool(active.any()):
            break
        d = -_direction(g, S, Y, SY, YY, gamma, seg, B)
        gd = _segdot(g, d, seg, B)
        # not a descent direction: fall back to steepest descent (no host read: where, always)
        bad = ~(gd < 0)
        d = torch.where(bad[seg], -g * gamma[seg], d)
        gd = torch.where(bad, _segdot(g, d, seg, B), gd)
        step = torch.ones(B, dtype=dt, device=dev)
        done = ~active
        x_new, f_new, g_new = x, f, g             # replaced (never written) per accepted segment
        for _ in range(max_backtracks):
            xt = x + step[seg] * d
            searching = ~done
            ft, gt = evaluate(xt, None if bool(searching.all()) else searching)
            ok = searching & torch.isfinite(ft) & (ft <= f + c1 * step * gd)
            sel = ok[seg]
            x_new = torch.where(sel, xt, x_new)
            g_new = torch.where(sel, gt, g_new)
            f_new = torch.where(ok, ft, f_new)
            done = done | ok
            if bool(done.all()):
                break
            step = torch.where(done, step, step * 0.5)
        moved = done & active
        failed = active & ~done                      # no acceptable step: this segment has converged
        iters = iters + moved.long()
        s_new = torch.where(moved[seg], x_new - x, torch.zeros_like(x))
        y_new = torch.where(moved[seg], g_new - g, torch.zeros_like(g))
        # every new dot product in two segmented products: S·y, Y·y, s·y, y·y and Y·s, s·s
        k = S.shape[0] + 1
        P1 = _segmat(torch.cat([S, Y, s_new[None], y_new[None]]), y_new, seg, B)
        P2 = _segmat(torch.cat([Y, s_new[None]]), s_new, seg, B)
        sy, yy, ss = P1[:, -2], P1[:, -1], P2[:, -1]
        # keep a pair only with enough positive curvature; a skipped pair is stored as zeros
        keep = (sy > 1e-12 * yy.sqrt() * ss.sqrt()) & (sy > 0)
        s_new = torch.where(keep[seg], s_new, torch.zeros_like(s_new))
        y_new = torch.where(keep[seg], y_new, torch.zeros_like(y_new))
        gamma = torch.where(keep & (yy > 0), sy / yy.clamp_min(torch.finfo(dt).tiny), torch.ones_like(sy))
        kd = keep.double()[:, None]
        col = P1[:, :k - 1].double() * kd                       # s_i · y_new
        yrow = torch.cat([P1[:, k - 1:2 * k - 2], yy[:, None]], 1).double() * kd    # y_j · y_new
        row = torch.cat([P2[:, :k - 1], sy[:, None]], 1).double() * kd              # s_new · y_j
        S = torch.cat([S, s_new[None]])
        Y = torch.cat([Y, y_new[None]])
        SY = torch.cat([torch.cat([SY, col[:, :, None]], 2), row[:, None, :]], 1)
        YY = torch.cat([torch.cat([YY, yrow[:, :k - 1, None]], 2), yrow[:, None, :]], 1)
        if k > history:
            S, Y, SY, YY = S[1:], Y[1:], SY[:, 1:, 1:], YY[:, 1:, 1:]
        small = moved & ((f - f_new).abs() <= rel_tol * f.abs().clamp_min(torch.finfo(dt).tiny))
        x, f, g = x_new, f_new, g_new
        active = active & ~failed & ~small
    return x, f, iters
