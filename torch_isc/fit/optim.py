"""A batched L-BFGS: one optimizer per item of a packed batch, run together.

``torch.optim.LBFGS`` over a packed batch shares one line search across items, so an item's
result would depend on its batch. Here every dot product, step size, curvature pair and
stopping test is per segment (item), so each item follows exactly the trajectory it would
follow alone. Dimension-free: it knows nothing about meshes.
"""
from __future__ import annotations

from typing import Callable, Tuple

import torch

__all__ = ["batched_lbfgs"]


def _segdot(a: torch.Tensor, b: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    return torch.zeros(n, dtype=a.dtype, device=a.device).index_add_(0, seg, a * b)


def batched_lbfgs(fun: Callable[[torch.Tensor], torch.Tensor], x0: torch.Tensor, seg: torch.Tensor, num_segments: int,
                  iterations: int = 50, history: int = 8, rel_tol: float = 1e-7, max_backtracks: int = 12,
                  c1: float = 1e-4) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Minimize ``fun`` segment by segment.

    Args:
        fun: maps ``x (n,)`` to per-segment objectives ``(num_segments,)``; segment ``b``'s
            objective may depend only on ``x[seg == b]``.
        x0: ``(n,)`` start. seg: ``(n,)`` long segment of each entry.
    Returns:
        ``x``, the per-segment objective at ``x``, and the number of iterations each segment ran.
    """
    B = num_segments
    dt = x0.dtype

    def evaluate(x):
        x = x.detach().requires_grad_(True)
        with torch.enable_grad():
            f = fun(x)
            g, = torch.autograd.grad(f.sum(), x)
        return f.detach(), g.detach()

    x = x0.detach().clone()
    f, g = evaluate(x)
    S, Y, RHO = [], [], []
    active = torch.isfinite(f)
    iters = torch.zeros(B, dtype=torch.long, device=x.device)
    for it in range(int(iterations)):
        if not bool(active.any()):
            break
        # two-loop recursion, all dot products per segment
        q = g.clone()
        alphas = []
        for s_, y_, r_ in zip(reversed(S), reversed(Y), reversed(RHO)):
            a = r_ * _segdot(s_, q, seg, B)
            alphas.append(a)
            q = q - a[seg] * y_
        if S:
            sy = _segdot(S[-1], Y[-1], seg, B)
            yy = _segdot(Y[-1], Y[-1], seg, B)
            gamma = torch.where((sy > 0) & (yy > 0), sy / yy.clamp_min(torch.finfo(dt).tiny), torch.ones_like(sy))
        else:
            gn = torch.sqrt(_segdot(g, g, seg, B))
            gamma = 1.0 / gn.clamp_min(1.0)
        r = gamma[seg] * q
        for s_, y_, r_, a in zip(S, Y, RHO, reversed(alphas)):
            b = r_ * _segdot(y_, r, seg, B)
            r = r + (a - b)[seg] * s_
        d = -r
        gd = _segdot(g, d, seg, B)
        bad = ~(gd < 0)
        if bool(bad.any()):                     # not a descent direction: fall back to steepest descent
            d = torch.where(bad[seg], -g * gamma[seg], d)
            gd = _segdot(g, d, seg, B)
        step = torch.ones(B, dtype=dt, device=x.device)
        done = ~active
        x_new, f_new, g_new = x.clone(), f.clone(), g.clone()
        for _ in range(max_backtracks):
            xt = x + step[seg] * d
            ft, gt = evaluate(xt)
            ok = ~done & torch.isfinite(ft) & (ft <= f + c1 * step * gd)
            if bool(ok.any()):
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
        sy = _segdot(s_new, y_new, seg, B)
        rho = torch.where(sy > 1e-12 * _segdot(y_new, y_new, seg, B).sqrt() * _segdot(s_new, s_new, seg, B).sqrt(),
                          1.0 / sy.clamp_min(torch.finfo(dt).tiny), torch.zeros_like(sy))
        rho = torch.where(sy > 0, rho, torch.zeros_like(rho))
        S.append(s_new)
        Y.append(y_new)
        RHO.append(rho)
        if len(S) > history:
            S.pop(0), Y.pop(0), RHO.pop(0)
        small = moved & ((f - f_new).abs() <= rel_tol * f.abs().clamp_min(torch.finfo(dt).tiny))
        x, f, g = x_new, f_new, g_new
        active = active & ~failed & ~small
    return x, f, iters
