"""Refit the magnitudes of a curve to new points, mesh and signs fixed, differentiable in the
points by implicit differentiation.

The objective of item ``b`` in the log-magnitudes ``s`` (``F = σ ⊙ exp(s)``, ``σ`` the
curve's signs, so no value can change sign or reach 0) is

    ``E_b(s) = Δ1_b(F) / h_b² + reg · mean_{v ∈ b} (s_v − s0_v)²``

with ``Δ1_b = Σ_t (n_t/n_b) F_tᵀ M_t F_t / |∇f_t|²`` (eq. 3.1, the mean squared first-order
distance of the item's points to the curve, ``M_t`` from
:func:`torch_isc.pipeline.signs.triangle_moments`), ``h_b = rel_scale ·`` the item's mesh
bounding-box diagonal (so ``Δ1 / h²`` is O(1) for points a percent of the size off the
curve), and ``s0`` the curve's own log-magnitudes. ``Δ1`` is invariant to scaling ``F`` and
ignores vertices of triangles without points: the tiny ``reg`` term fixes that flat
direction and those vertices, so the minimizer ``s*`` is unique and ``∂²E/∂s²`` invertible.

It is minimized tightly by a damped Newton method (Levenberg–Marquardt) on per-item dense
Hessians (assembled from per-triangle 3×3 Hessians, ``torch.func``), with per-item
damping and acceptance: an item's iterates never depend on the other items. The backward
pass does not unroll the iterations: ``∇_s E(s*, M) = 0`` gives
``ds*/dM = −H⁻¹ ∂²E/∂s∂M``, so the vector-Jacobian product solves ``H λ = ḡ`` (``H``
symmetric) and returns ``−(∂²E/∂s∂M)ᵀ λ`` by double backward. The mesh is held fixed
(no gradient to the vertex positions through the refit).
"""
from __future__ import annotations

import dataclasses
from typing import List, Optional, Sequence

import torch

from torch_isc.core.curve import ImplicitCurve
from torch_isc.core.locate import barycentric, locate_grid
from torch_isc.pipeline.evidence import triangle_moments

__all__ = ["refit", "attach_point_gradients", "RefitProblem"]


class RefitProblem:
    """The fixed parts of the refit objective of a curve batch and its point partition."""

    def __init__(self, curve: ImplicitCurve, count: torch.Tensor, reg: float, rel_scale: float):
        mesh = curve.mesh.detach()
        self.mesh = mesh
        B, dt, dev = mesh.num_items, mesh.dtype, mesh.device
        with torch.no_grad():
            v = curve.values.detach()
            self.sig = torch.sign(v)
            self.s0 = torch.log(v.abs())
            self.act = (count > 0).nonzero().squeeze(1)              # triangles with points
            fi = mesh.face_item
            nb = torch.zeros(B, dtype=dt, device=dev).index_add_(0, fi, count)
            bbox = mesh.item_bbox()
            h = rel_scale * (bbox[:, 2:] - bbox[:, :2]).norm(dim=1)
            self.w = (count / nb[fi].clamp_min(1) / (h * h)[fi])[self.act]
            self.faces = mesh.faces[self.act]
            self.G = mesh.bary_gradients()[self.act]
            self.tri_item = fi[self.act]
            nv = mesh.verts_per_item.to(dt)
            self.reg_w = (reg / nv.clamp_min(1))[mesh.vert_item]
            mean_mag = torch.zeros(B, dtype=dt, device=dev).index_add_(0, mesh.vert_item, v.abs()) / nv.clamp_min(1)
            self.guard = ((1e-10 * mean_mag) ** 2)[self.tri_item]
            self.vmax = int(mesh.verts_per_item.max()) if B else 0
            self.loc = torch.arange(v.shape[0], device=dev) - mesh.verts_first_idx[mesh.vert_item]
        self.B, self.dt, self.dev = B, dt, dev

    # ----------------------------------------------------------- objective
    @staticmethod
    def _tri(s3, M3, G3, sg3, guard):
        F = sg3 * torch.exp(s3)
        g = (G3 * F[:, None]).sum(0)
        return (F @ M3 @ F) / ((g * g).sum() + guard)

    def energy(self, s: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
        """``(B,)`` the objective of every item; ``M (T, 3, 3)`` the full moment tensor."""
        Ma = M[self.act]
        F = self.sig[self.faces] * torch.exp(s[self.faces])
        g = (self.G * F[..., None]).sum(1)
        q = torch.einsum("ti,tij,tj->t", F, Ma, F) / ((g * g).sum(1) + self.guard)
        E = torch.zeros(self.B, dtype=self.dt, device=self.dev).index_add(0, self.tri_item, self.w * q)
        r = s - self.s0
        return E.index_add(0, self.mesh.vert_item, self.reg_w * r * r)

    def grad(self, s: torch.Tensor, M: torch.Tensor):
        with torch.enable_grad():
            s_ = s.detach().requires_grad_(True)
            E = self.energy(s_, M.detach())
            (g,) = torch.autograd.grad(E.sum(), s_)
        return E.detach(), g

    def hessian(self, s: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
        """``(B, Vmax, Vmax)`` per-item dense Hessians (padding: identity)."""
        B, n = self.B, self.vmax
        H = torch.zeros(B, n, n, dtype=self.dt, device=self.dev)
        if self.act.numel():
            Ht = torch.func.vmap(torch.func.hessian(self._tri))(
                s.detach()[self.faces], M.detach()[self.act], self.G, self.sig[self.faces], self.guard)
            Ht = Ht * self.w[:, None, None]
            li = self.loc[self.faces]                                   # (A,3)
            it = self.tri_item[:, None, None].expand(-1, 3, 3)
            H.index_put_((it.reshape(-1), li[:, :, None].expand(-1, 3, 3).reshape(-1),
                          li[:, None, :].expand(-1, 3, 3).reshape(-1)), Ht.reshape(-1), accumulate=True)
        vi = self.mesh.vert_item
        H.index_put_((vi, self.loc, self.loc), 2.0 * self.reg_w, accumulate=True)
        pad = torch.ones(B, n, dtype=torch.bool, device=self.dev)
        pad[vi, self.loc] = False
        return H + torch.diag_embed(pad.to(self.dt))

    def pad(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(self.B, self.vmax, dtype=x.dtype, device=x.device)
        return out.index_put((self.mesh.vert_item, self.loc), x)

    def unpad(self, X: torch.Tensor) -> torch.Tensor:
        return X[self.mesh.vert_item, self.loc]

    # ----------------------------------------------------------- solver
    def solve(self, M: torch.Tensor, max_iter: int = 100, step_tol: float = 1e-13) -> torch.Tensor:
        s = self.s0.clone()
        B, vi = self.B, self.mesh.vert_item
        mu = torch.full((B,), 1e-6, dtype=self.dt, device=self.dev)
        E, g = self.grad(s, M)
        for _ in range(max_iter):
            H = self.hessian(s, M)
            diag = torch.diagonal(H, dim1=1, dim2=2)
            lam = mu * diag.abs().mean(1).clamp_min(torch.finfo(self.dt).tiny)
            d = self.unpad(torch.linalg.solve(H + lam[:, None, None] * torch.eye(self.vmax, dtype=self.dt, device=self.dev),
                                              -self.pad(g)[..., None])[..., 0])
            E2, g2 = self.grad(s + d, M)
            gn = torch.zeros(B, dtype=self.dt, device=self.dev).scatter_reduce(0, vi, g.abs(), "amax")
            gn2 = torch.zeros(B, dtype=self.dt, device=self.dev).scatter_reduce(0, vi, g2.abs(), "amax")
            # near the optimum E changes at rounding level: accept steps that shrink the gradient
            ok = (E2 < E) | ((E2 <= E + 1e-12 * E.abs()) & (gn2 < gn))
            okv = ok[vi]
            s = torch.where(okv, s + d, s)
            g = torch.where(okv, g2, g)
            E = torch.where(ok, E2, E)
            mu = torch.where(ok, (mu * 0.25).clamp_min(1e-12), mu * 8.0)
            step = torch.zeros(B, dtype=self.dt, device=self.dev).scatter_reduce(0, vi, d.abs(), "amax")
            if bool(((step < step_tol) | (mu > 1e12)).all()):
                break
        return s


class _ImplicitRefit(torch.autograd.Function):
    @staticmethod
    def forward(ctx, M, problem, max_iter):
        s = problem.solve(M.detach(), max_iter)
        ctx.problem = problem
        ctx.save_for_backward(M, s)
        return s

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gs):
        M, s = ctx.saved_tensors
        pb = ctx.problem
        H = pb.hessian(s, M)
        lam = pb.unpad(torch.linalg.solve(H, pb.pad(gs)[..., None])[..., 0])
        with torch.enable_grad():
            M_ = M.detach().requires_grad_(True)
            s_ = s.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(pb.energy(s_, M_).sum(), s_, create_graph=True)
            (gM,) = torch.autograd.grad(g, M_, grad_outputs=lam)
        return -gM, None, None


def refit(curve: ImplicitCurve, points: torch.Tensor, point_item: Optional[torch.Tensor] = None,
          reg: float = 1e-4, rel_scale: float = 1e-2, max_iter: int = 500) -> ImplicitCurve:
    """Re-fit the magnitudes of ``curve`` to ``points (N, 2)`` (``point_item (N,)``, default 0),
    mesh and signs held fixed; differentiable in the points (implicit differentiation).

    Points off their item's mesh are ignored; an item without points keeps its values.
    Returns a curve on the same mesh with values ``σ ⊙ exp(s*)`` (see the module docstring).

    Example:
        >>> import math
        >>> from torch_isc import ImplicitCurve, hexagon_mesh
        >>> from torch_isc.core.measures import area
        >>> m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
        >>> c = ImplicitCurve(m, m.verts.norm(dim=1) - 0.5)
        >>> t = torch.arange(40, dtype=torch.float64) * (2 * math.pi / 40)
        >>> pts = (0.55 * torch.stack([t.cos(), t.sin()], 1)).requires_grad_()
        >>> r = refit(c, pts)
        >>> bool(torch.equal(r.signs, c.signs)), round(float(area(r).detach()), 2)   # pi * 0.55**2 = 0.950
        (True, 0.95)
        >>> area(r).sum().backward(); pts.grad.shape
        torch.Size([40, 2])
    """
    mesh = curve.mesh.detach()
    pts = points.to(mesh.dtype)
    if point_item is None:
        if mesh.num_items != 1:
            raise ValueError("point_item is required for a batch of more than one curve")
        point_item = torch.zeros(pts.shape[0], dtype=torch.long, device=pts.device)
    with torch.no_grad():
        face, _ = locate_grid(mesh, pts, point_item)
    ok = face >= 0
    f = face[ok]
    p = pts[ok]
    bary = barycentric(mesh.verts, mesh.faces, f, p)                   # differentiable in the points
    mom = triangle_moments(mesh, p, f, bary)
    problem = RefitProblem(curve, mom.count, reg, rel_scale)
    s = _ImplicitRefit.apply(mom.M, problem, max_iter)
    return ImplicitCurve(curve.mesh, problem.sig * torch.exp(s), validate=False)


def attach_point_gradients(results_or_curves: Sequence, point_sets: Sequence[torch.Tensor],
                           keep_values: bool = True, **refit_kw) -> List:
    """Give reconstructed curves a gradient with respect to their input points.

    One batched :func:`refit` of all items (each item's curve is re-fitted to its own
    points only). With ``keep_values=True`` (default) the returned values are exactly the
    given ones (``F + (F* − F*.detach())``): the outputs do not change when gradients are
    requested, and the gradient is that of the refit ``F*(points)`` (the optimum of the
    refit objective started from them). With ``keep_values=False`` the values are ``F*``.

    Args:
        results_or_curves: a list of :class:`ReconstructionResult` (anything with a
            ``curve``) or of :class:`ImplicitCurve`; each curve a batch of one or more items.
        point_sets: one ``(N_b, 2)`` tensor per entry, in the curve's coordinates.

    Returns the same kind of list (results get ``dataclasses.replace(r, curve=...)``). When
    no point set requires grad (or grad mode is off) the input list is returned as it is.

    Example (the call ``reconstruct_batch`` makes at its end)::

        if torch.is_grad_enabled() and any(p.requires_grad for p in point_sets):
            results = attach_point_gradients(results, point_sets)
    """
    items = list(results_or_curves)
    sets = list(point_sets)
    if len(items) != len(sets):
        raise ValueError(f"attach_point_gradients: {len(items)} curves but {len(sets)} point sets")
    if not items or not torch.is_grad_enabled() or not any(torch.is_tensor(p) and p.requires_grad for p in sets):
        return items
    curves = [x.curve if hasattr(x, "curve") else x for x in items]
    if any(c.num_items != 1 for c in curves):
        raise ValueError("attach_point_gradients: one item per curve")
    batch = ImplicitCurve.cat([ImplicitCurve(c.mesh.detach(), c.values.detach(), validate=False) for c in curves])
    dt, dev = batch.mesh.dtype, batch.mesh.device
    pts = torch.cat([torch.as_tensor(p).to(device=dev, dtype=dt).reshape(-1, 2) for p in sets])
    counts = torch.tensor([int(torch.as_tensor(p).reshape(-1, 2).shape[0]) for p in sets], device=dev)
    point_item = torch.repeat_interleave(torch.arange(len(sets), device=dev), counts)
    new = refit(batch, pts, point_item, **refit_kw).values
    vals = batch.values + (new - new.detach()) if keep_values else new
    out = []
    v0 = 0
    for x, c in zip(items, curves):
        n = c.values.shape[0]
        nc = ImplicitCurve(c.mesh, vals[v0:v0 + n].to(c.values.dtype), validate=False)
        v0 += n
        out.append(dataclasses.replace(x, curve=nc) if hasattr(x, "curve") else nc)
    return out
