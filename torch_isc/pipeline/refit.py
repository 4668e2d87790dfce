"""Refit the magnitudes of a curve to new points, mesh and signs fixed, differentiable in the
points by implicit differentiation.

The objective of item ``b`` in the log-magnitudes ``s`` (``F = σ ⊙ (exp(s) + floor)``, ``σ`` the
curve's signs, so no value can change sign or reach 0) is

    ``E_b(s) = Δ1_b(F) / h_b² + smoothness · J_b(F) / S_b(F) + reg · mean_{v ∈ b} (s_v − s0_v)²``

with ``Δ1_b = Σ_t (n_t/n_b) F_tᵀ M_t F_t / |∇f_t|²`` (eq. 3.1, the mean squared first-order
distance of the item's points to the curve, ``M_t`` from
:func:`torch_isc.pipeline.evidence.triangle_moments`), ``h_b = rel_scale ·`` the item's mesh
bounding-box diagonal (so ``Δ1 / h²`` is O(1) for points a percent of the size off the
curve), and ``s0`` the curve's own log-magnitudes. ``J / S`` is the smoothness term of the
loop's geometry fit (:class:`~torch_isc.pipeline.values.GeometryObjective`): the
length-weighted squared jump of ``∇f`` across the interior edges of the band (edges next to a
triangle with points or a sign change) over the length-weighted mean of ``|∇f|²`` there. It
makes the fit well posed where a triangle holds one or two points (which a whole family of
lines fits exactly, so ``Δ1`` alone lets a magnitude run off to 1e10). ``Δ1`` and ``J/S`` are
invariant to scaling ``F``, and vertices outside the band enter neither: the small ``reg``
term fixes that flat direction and those vertices (they stay at ``s0`` exactly), so the
minimizer ``s*`` is unique near ``s0`` and ``∂²E/∂s²`` invertible.

Solver: a damped Newton method (Levenberg–Marquardt) on per-item dense Hessians over the
*active* vertices (those of triangles holding points, of band edges and of crossings),
assembled with one ``index_add_`` (indices made once) from closed-form per-triangle 3×3
Hessians: with ``q = FᵀMF / d``, ``d = FᵀNF`` (``N = GGᵀ``),
``∇_F q = 2(MF − qNF)/d`` and ``∇²_F q = (2/d)(M − qN − NF ∇qᵀ − ∇q (NF)ᵀ)``, chained to ``s``
by ``∂F/∂s = diag(F)``; ``J/S`` is a ratio of quadratic forms too (the same formula, with a
rank-2 dense part per item, added with the scale term's rank 1 in one batched product). The
blocks are ragged: an item's block has its own active count rounded up to a size class
(``8 · 1.5^k``), a class is one batched ``(n, A, A)`` view of one flat buffer, so padding
stays below 2.25x of the entries and there is one Cholesky call per class. A damped block
that is not positive definite (``H`` of a ratio of quadratic forms can be indefinite) gives a
rejected step and more damping. Damping, acceptance and stopping are per item, so an item's
iterates never depend on the other items. An item stops when its gradient is at rounding level
relative to its objective (``‖∇E‖∞ ≤ 256 ε E``), or when an accepted undamped Newton step
is below ``step_tol`` with the damping at most 1e-10 of the mean curvature (quadratic convergence:
the error left is about its square).

:meth:`RefitProblem.geometry` builds the band stage's objective (the loop's
:class:`~torch_isc.pipeline.values.GeometryObjective`: its weights, floor, start, smoothness
band and dead-zoned crossing term, with exact Hessians of the crossing hinge) plus ``reg`` and
``scale_reg``. There ``s`` has a lower bound (a magnitude within 1e-3 of the floor: the
infimum of a collapsing magnitude lies at ``s = −∞``) handled by projected Newton (bound
vertices whose gradient points below leave the system), the damping follows the gain ratio
(/10 on a good model, x2, x4, ... on rejections), a float32 item also stops once the damped
Newton decrement is at rounding level of its objective, and finished items are dropped once
at most half remain (the problem is rebuilt for the others).

The backward pass does not unroll the iterations: ``∇_s E(s*, M) = 0`` gives
``ds*/dM = −H⁻¹ ∂²E/∂s∂M``, so the vector-Jacobian product solves ``H λ = ḡ`` (``H``
symmetric) and returns, per triangle, ``−w (2/d)(sym(μFᵀ) − (μᵀNF/d) FFᵀ)`` with
``μ = λ_t ⊙ F_t`` (closed form, no double backward; only ``Δ1`` depends on ``M``). The mesh is held fixed (no gradient
to the vertex positions through the refit).
"""
from __future__ import annotations

import dataclasses
import math
from typing import List, Optional, Sequence

import torch

from torch_isc.core.curve import ImplicitCurve
from torch_isc.core.locate import barycentric, locate_grid
from torch_isc.core.mesh import _segment_bbox
from torch_isc.core.points import PointSetError
from torch_isc.pipeline.evidence import triangle_moments
from torch_isc.pipeline import budget

__all__ = ["refit", "attach_point_gradients", "RefitProblem"]


class RefitProblem:
    """The fixed parts of the refit objective of a curve batch and its point partition.

    Args:
        curve: the curve (mesh, signs, starting magnitudes ``exp(s0)``).
        count: ``(T,)`` points per triangle. reg, rel_scale, smoothness: see the module docstring.
    """

    def __init__(self, curve: ImplicitCurve, count: torch.Tensor, reg: float, rel_scale: float,
                 smoothness: float = 0.0, floor: float = 0.0, scale_reg: float = 1.0):
        mesh = curve.mesh.detach()
        B, dt, dev = mesh.num_items, mesh.dtype, mesh.device
        with torch.no_grad():
            v = curve.values.detach().to(dt)
            fi, vi = mesh.face_item, mesh.vert_item
            nb = torch.zeros(B, dtype=dt, device=dev).index_add_(0, fi, count.to(dt))
            bbox = mesh.item_bbox()
            h = rel_scale * (bbox[:, 2:] - bbox[:, :2]).norm(dim=1)
            w = count.to(dt) / nb[fi].clamp_min(1) / (h * h)[fi]
            nv = mesh.verts_per_item.to(dt)
            mean_mag = torch.zeros(B, dtype=dt, device=dev).index_add_(0, vi, v.abs()) / nv.clamp_min(1)
            # each magnitude stays above ``floor`` times its start (the start is exactly the curve)
            self._build(mesh, torch.sign(v), count, w, floor * v.abs(), torch.log((1.0 - floor) * v.abs()),
                        (1e-10 * mean_mag) ** 2, reg, smoothness, scale_reg)

    @classmethod
    def geometry(cls, mesh, count: torch.Tensor, signs: torch.Tensor, init_mag: torch.Tensor, tol: torch.Tensor,
                 magnitude_floor: float, smoothness: float, crossing_weight: float = 0.0,
                 data_dist: Optional[torch.Tensor] = None, slack: Optional[torch.Tensor] = None,
                 reg: float = 1e-4, scale_reg: float = 1.0) -> "RefitProblem":
        """The objective of :class:`~torch_isc.pipeline.values.GeometryObjective` (same weights,
        floor, start, smoothness band and dead-zoned crossing term, built the same way) plus
        this class's ``reg`` and ``scale_reg`` terms, which make its minimizer unique: ``Δ1``,
        ``J/S`` and the crossing term are invariant to scaling ``F`` and only the floor breaks
        that, so without them the global scale is a nearly flat direction (and the vertices
        no term sees are flat ones)."""
        self = object.__new__(cls)
        mesh = mesh.detach()
        B, dt, dev = mesh.num_items, mesh.dtype, mesh.device
        with torch.no_grad():
            fi, vi = mesh.face_item, mesh.vert_item
            cnt = count.to(dt)
            nb = torch.zeros(B, dtype=dt, device=dev).index_add_(0, fi, cnt)
            w = cnt / nb[fi].clamp_min(1) / (tol * tol)[fi]
            nv = mesh.verts_per_item.to(dt)
            mean_mag = torch.zeros(B, dtype=dt, device=dev).index_add_(0, vi, init_mag) / nv.clamp_min(1)
            fl = (magnitude_floor * mean_mag)[vi]
            s0 = torch.log((init_mag - fl).clamp_min(1e-3 * mean_mag[vi]).clamp_min(torch.finfo(dt).tiny))
            cross = None
            if crossing_weight > 0 and data_dist is not None and slack is not None:
                v = mesh.verts
                ce = mesh.edges[signs[mesh.edges[:, 0]] != signs[mesh.edges[:, 1]]]
                c_item = vi[ce[:, 0]]
                c_len = (v[ce[:, 0]] - v[ce[:, 1]]).norm(dim=1)
                c_lim = (data_dist[ce] - slack[c_item][:, None]).clamp_min(0)
                c_lim = torch.where(torch.isfinite(c_lim), c_lim, torch.zeros_like(c_lim))
                n_cross = torch.zeros(B, dtype=dt, device=dev).index_add_(0, c_item, torch.ones_like(c_len))
                c_w = crossing_weight / n_cross.clamp_min(1)[c_item] / (tol * tol)[c_item]
                cross = (ce, c_item, c_len, c_lim, c_w)
            self._build(mesh, signs.to(dt), count, w, fl, s0, (1e-10 * mean_mag) ** 2, reg, smoothness, scale_reg,
                        cross)
            #: ``(V,)`` lower bound of ``s``: a magnitude within 1e-3 of its floor is at the floor (the
            #: objective's infimum there lies at ``s = -inf``, which no step count reaches)
            self.lower = torch.log(1e-3 * fl).clamp_min(torch.finfo(dt).min)
            # what a sub-batch's problem is rebuilt from (:meth:`solve` drops finished items)
            self._inputs = (count, signs, init_mag, tol, magnitude_floor, smoothness, crossing_weight, data_dist,
                            slack, reg, scale_reg)
            #: the starting damping: the start (distances to the data) is far from the optimum
            self.mu0 = 1e-2
        return self

    def _build(self, mesh, sig, count, w, floor, s0, guard, reg, smoothness, scale_reg, cross=None):
        """Set the fixed parts: ``w (T,)`` the weight of each triangle's ``FᵀMF/|∇f|²``,
        ``floor, s0 (V,)``, ``guard (B,)`` (added to ``|∇f|²``), ``cross``: the crossing term's
        ``(edges (C,2), item (C,), length (C,), limits (C,2), weight (C,))`` or None."""
        B, dt, dev = mesh.num_items, mesh.dtype, mesh.device
        self.mesh = mesh
        self.dt_, self.dev_ = dt, dev
        with torch.no_grad():
            V = sig.shape[0]
            self.act = (count > 0).nonzero().squeeze(1)              # triangles with points
            fi, vi = mesh.face_item, mesh.vert_item
            self.w = w[self.act]
            self.faces = mesh.faces[self.act]
            self.G = mesh.bary_gradients()[self.act]                   # (A,3,2)
            self.N = self.G @ self.G.transpose(1, 2)                   # (A,3,3)
            self.tri_item = fi[self.act]
            nv = mesh.verts_per_item.to(dt)
            self.reg_w = (reg / nv.clamp_min(1))[vi]
            self.sig = sig
            self.floor = floor
            self.s0 = s0
            self.guard = guard[self.tri_item]
            # smoothness: interior edges next to a triangle with points or a sign change (the band)
            self.smoothness = float(smoothness)
            fneg = self.sig[mesh.faces] < 0
            band_t = (count > 0) | (fneg.any(1) & ~fneg.all(1))
            ef = mesh.edge_faces
            efc = ef.clamp_min(0)
            band_e = ~mesh.is_boundary_edge & (band_t[efc[:, 0]] | band_t[efc[:, 1]])
            if self.smoothness <= 0:
                band_e = torch.zeros_like(band_e)
            ef = ef[band_e]
            e = mesh.edges[band_e]
            vv = mesh.verts
            el = (vv[e[:, 0]] - vv[e[:, 1]]).norm(dim=1)
            T = mesh.faces.shape[0]
            c = torch.zeros(T, dtype=dt, device=dev).index_add_(0, ef[:, 0], 0.5 * el).index_add_(0, ef[:, 1], 0.5 * el)
            self.sm = (c > 0).nonzero().squeeze(1)                    # the faces of the band edges
            sm_loc = torch.full((T,), -1, dtype=torch.long, device=dev)
            sm_loc[self.sm] = torch.arange(self.sm.shape[0], device=dev)
            self.sm_faces = mesh.faces[self.sm]
            self.sm_G = mesh.bary_gradients()[self.sm]
            self.sm_N = self.sm_G @ self.sm_G.transpose(1, 2)
            self.sm_c = c[self.sm]
            self.sm_item = fi[self.sm]
            self.e_faces = sm_loc[ef]                                  # (Eb,2) into the band faces
            self.e_len = el
            self.e_item = mesh.edge_item[band_e]
            self.cross = cross if cross is not None and cross[0].shape[0] > 0 else None
            # active vertices (of triangles with points, of band edges, of crossings), numbered per item
            av = torch.zeros(V, dtype=torch.bool, device=dev)
            av[self.faces.reshape(-1)] = True
            av[self.sm_faces.reshape(-1)] = True
            if self.cross is not None:
                av[self.cross[0].reshape(-1)] = True
            self.av = av.nonzero().squeeze(1)                          # (Va,) item-contiguous
            n_act = torch.zeros(B, dtype=torch.long, device=dev).index_add_(0, vi, av.long())
            start = torch.cumsum(n_act, 0) - n_act
            self.av_item = vi[self.av]
            self.av_loc = torch.arange(self.av.shape[0], device=dev) - start[self.av_item]
            loc = torch.full((V,), -1, dtype=torch.long, device=dev)
            loc[self.av] = self.av_loc
            self.face_loc = loc[self.faces]                            # (A,3)
            self.sm_loc = loc[self.sm_faces]
            self.c_loc = loc[self.cross[0]] if self.cross is not None else None
            #: ``(B,)`` active vertices per item (the dense Hessians are ``Amax x Amax``)
            self.active_counts = n_act
            self._layout(n_act)
            self.n_act = n_act.to(dt).clamp_min(1.0)
            self.scale_reg = float(scale_reg)
        self.B, self.dt, self.dev = B, dt, dev

    def _layout(self, n_act: torch.Tensor) -> None:
        """The Hessians' storage: one flat buffer of per-item dense blocks, an item's block
        ``A_b x A_b`` with ``A_b`` its active count rounded up to a size class (``8 · 1.5^k``),
        items of a class stored together so that each class is one batched ``(n, A, A)`` view:
        little padding and one factorization call per class. One host read (the counts)."""
        B, dt, dev = n_act.shape[0], self.dt_, self.dev_
        na = n_act.tolist()
        ladder, k = [0], 8.0
        while ladder[-1] < (max(na) if na else 0):
            ladder.append(int(math.ceil(k)))
            k *= 1.5
        size = [next(a for a in ladder if a >= n) for n in na]
        classes = sorted(set(a for a in size if a > 0))
        blk, hoff, voff = [0] * B, [0] * B, [0] * B
        self.groups = []                      # (A, items (n,), H offset, vector offset)
        ho = vo = 0
        for a in classes:
            its = [b for b in range(B) if size[b] == a]
            self.groups.append((a, torch.tensor(its, dtype=torch.long, device=dev), ho, vo))
            for b in its:
                blk[b], hoff[b], voff[b] = a, ho, vo
                ho += a * a
                vo += a
        self.hsize, self.vsize = ho, vo
        self.amax = max(size) if B else 0
        self.blk = torch.tensor(blk, dtype=torch.long, device=dev)
        self.hoff = torch.tensor(hoff, dtype=torch.long, device=dev)
        self.voff = torch.tensor(voff, dtype=torch.long, device=dev)
        self.av_slot = self.voff[self.av_item] + self.av_loc            # (Va,) into the flat vectors
        pad = torch.ones(self.vsize, dtype=dt, device=dev)
        pad[self.av_slot] = 0.0
        self.pad_flat = pad                                                # 1 at padding slots
        slot_item = torch.zeros(self.vsize, dtype=torch.long, device=dev)
        diag = torch.zeros(self.vsize, dtype=torch.long, device=dev)
        for a, its, ho_, vo_ in self.groups:
            n = its.shape[0]
            slot_item[vo_:vo_ + n * a] = its.repeat_interleave(a, output_size=n * a)
            diag[vo_:vo_ + n * a] = (ho_ + torch.arange(n, device=dev)[:, None] * (a * a)
                                     + torch.arange(a, device=dev)[None, :] * (a + 1)).reshape(-1)
        self.slot_item, self.hdiag = slot_item, diag
        h_item = torch.zeros(self.hsize, dtype=torch.long, device=dev)
        for a, its, ho_, vo_ in self.groups:
            n = its.shape[0]
            h_item[ho_:ho_ + n * a * a] = its.repeat_interleave(a * a, output_size=n * a * a)
        self.h_item = h_item                                               # (hsize,) each entry's item
        # the scatter indices of every Hessian term and the constant 6x6 Gram blocks of the
        # gradient jumps, made once (the sparsity does not change between iterations)
        li = self.face_loc
        self.ix_tri = self._hidx(self.tri_item[:, None, None], li[:, :, None], li[:, None, :]).reshape(-1)
        self.ix_reg = self._hidx(self.av_item, self.av_loc, self.av_loc)
        if self.cross is not None:
            cl = self.c_loc
            self.ix_c = self._hidx(self.cross[1][:, None, None], cl[:, :, None], cl[:, None, :]).reshape(-1)
        ea, eb = self.e_faces[:, 0], self.e_faces[:, 1]
        Dg = torch.cat([self.sm_G[ea], -self.sm_G[eb]], 1)              # (Eb,6,2)
        self.jump_gram = Dg @ Dg.transpose(1, 2)
        l6 = torch.cat([self.sm_loc[ea], self.sm_loc[eb]], 1)
        self.ix_jump = self._hidx(self.e_item[:, None, None], l6[:, :, None], l6[:, None, :]).reshape(-1)
        ls = self.sm_loc
        self.ix_sm = self._hidx(self.sm_item[:, None, None], ls[:, :, None], ls[:, None, :]).reshape(-1)
        self.ix_smv = (self.voff[self.sm_item][:, None] + ls).reshape(-1)

    def _hidx(self, item: torch.Tensor, li: torch.Tensor, lj: torch.Tensor) -> torch.Tensor:
        return self.hoff[item] + li * self.blk[item] + lj

    def _views(self, H: torch.Tensor):
        """Per size class: ``(items (n,), its H blocks as an (n, A, A) view, its slice of the flat vectors)``."""
        for a, its, ho, vo in self.groups:
            n = its.shape[0]
            yield its, H[ho:ho + n * a * a].view(n, a, a), slice(vo, vo + n * a)

    def _block_solve(self, H: torch.Tensor, rhs: torch.Tensor, lam: Optional[torch.Tensor] = None,
                     keep: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Flat ``x`` with ``(H_b + lam_b I) x_b = rhs_b`` per item. With ``lam`` (LM damping):
        Cholesky, NaN where the damped block is not positive definite (the caller rejects the
        step and damps more); ``keep`` (flat, 0/1): rows and columns left out (projected Newton).
        Without: LU (the implicit gradient's solve at the optimum)."""
        out = []
        for its, Hg, vs in self._views(H):
            n, a = Hg.shape[0], Hg.shape[1]
            r = rhs[vs].view(n, a)
            if lam is None:
                x = torch.linalg.solve_ex(Hg, r[..., None])[0][..., 0]
            else:
                Hg = Hg.clone()
                dg = lam[its][:, None].expand(n, a)
                if keep is not None:
                    # a left-out vertex: a diagonal 1e8 times the largest keeps its step at ~0
                    big = 1e8 * Hg.diagonal(dim1=1, dim2=2).abs().amax(1, keepdim=True)
                    dg = dg + (1.0 - keep[vs].view(n, a)) * big
                Hg.diagonal(dim1=1, dim2=2).add_(dg)
                L, info = torch.linalg.cholesky_ex(Hg)
                x = torch.cholesky_solve(r[..., None], L)[..., 0]
                x = torch.where((info == 0)[:, None], x, torch.full_like(x, float("nan")))
            out.append(x.reshape(-1))
        return torch.cat(out) if out else rhs.new_zeros(0)

    def _block_matvec(self, H: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        out = [(Hg @ x[vs].view(Hg.shape[0], -1, 1)).reshape(-1) for _, Hg, vs in self._views(H)]
        return torch.cat(out) if out else x.new_zeros(0)

    # ----------------------------------------------------------- objective
    def terms(self, s: torch.Tensor, M: torch.Tensor, hessian: bool = False):
        """The objective ``(B,)``, its gradient ``(V,)`` in ``s`` and, with ``hessian``, the
        per-item dense Hessians ``(B, Amax, Amax)`` over the active vertices (padding:
        identity). ``M``: the ``(A, 3, 3)`` moments of the active triangles. Closed form."""
        B, dt, dev = self.B, self.dt, self.dev
        D = self.sig[self.faces] * torch.exp(s[self.faces])            # (A,3) dF/ds
        F = D + self.sig[self.faces] * self.floor[self.faces]
        gf = (self.G * F[..., None]).sum(1)                            # (A,2) ∇f_t
        NF = (self.G * gf[:, None, :]).sum(2)                          # (A,3)
        d = (gf * gf).sum(1) + self.guard
        MF = (M * F[:, None, :]).sum(2)
        q = (MF * F).sum(1) / d
        dq = 2.0 * (MF - q[:, None] * NF) / d[:, None]                 # ∇_F q
        r = s - self.s0
        E = torch.zeros(B, dtype=dt, device=dev).index_add_(0, self.tri_item, self.w * q)
        E = E.index_add_(0, self.mesh.vert_item, self.reg_w * r * r)
        g = (2.0 * self.reg_w) * r
        # the global scale (a flat direction of Δ1 and J/S): pinned by the mean of r over the active vertices
        ra = r[self.av]
        mb = torch.zeros(B, dtype=dt, device=dev).index_add_(0, self.av_item, ra) / self.n_act
        E = E + self.scale_reg * mb * mb
        g = g.index_add(0, self.av, (2.0 * self.scale_reg * mb / self.n_act)[self.av_item])
        g = g.index_add_(0, self.faces.reshape(-1), (self.w[:, None] * D * dq).reshape(-1))
        sm = self._smooth_terms(s) if self.sm.numel() else None
        if sm is not None:
            R, Fs, dR, dS, S, ea, eb = sm
            E = E + self.smoothness * R
            g = g.index_add_(0, self.sm_faces.reshape(-1), (self.smoothness * Fs * dR).reshape(-1))   # Fs: dF/ds
        cr = None
        if self.cross is not None:
            Ec, gc, cr = self._cross_terms(s, hessian)
            E = E + Ec
            g = g.index_add_(0, self.cross[0].reshape(-1), gc.reshape(-1))
        if not hessian:
            return E, g, None
        Hq = (2.0 / d)[:, None, None] * (M - q[:, None, None] * self.N
                                         - NF[:, :, None] * dq[:, None, :] - dq[:, :, None] * NF[:, None, :])
        Hs = D[:, :, None] * Hq * D[:, None, :] + torch.diag_embed(D * dq)
        Hs = self.w[:, None, None] * Hs
        H = torch.zeros(self.hsize, dtype=dt, device=dev).index_add_(0, self.ix_tri, Hs.reshape(-1))
        H = H.index_add_(0, self.ix_reg, 2.0 * self.reg_w[self.av])
        lowl, lowr = [], []
        if sm is not None:
            l2, r2 = self._smooth_hessian(H, R, Fs, dR, dS, S, ea, eb)
            lowl.append(l2)
            lowr.append(r2)
        if cr is not None:
            ci, Hc = cr[0], cr[1]
            H = H.index_add_(0, self.ix_c, Hc.reshape(-1))
        # the scale term: rank 1 over each item's active slots; identity on the padding
        ind = 1.0 - self.pad_flat
        cs = (2.0 * self.scale_reg / self.n_act ** 2)[self.slot_item]
        lowl.append((cs * ind)[:, None])
        lowr.append(ind[:, None])
        L, Rt = torch.cat(lowl, 1), torch.cat(lowr, 1)
        k = L.shape[1]
        for its, Hg, vs in self._views(H):      # all low-rank parts in one product per size class
            n = Hg.shape[0]
            Hg.baddbmm_(L[vs].view(n, -1, k), Rt[vs].view(n, -1, k).transpose(1, 2))
        H.index_add_(0, self.hdiag, self.pad_flat)
        return E, g, H

    def _cross_terms(self, s: torch.Tensor, hessian: bool):
        """The crossing term of :func:`~torch_isc.pipeline.values.fit_geometry` per crossing
        edge ``(i, j)``: ``w (max(0, lim_i − u)² + max(0, lim_j − (ℓ − u))²)`` with
        ``u = ℓ m_i/(m_i + m_j)`` (``m = exp(s) + floor``). Returns its ``(B,)`` sum, the ``(C, 2)``
        gradients in ``s`` and, with ``hessian``, ``(item (C,), the (C, 2, 2) Hessians)``:
        ``E_uu ∇u ∇uᵀ + E_u ∇²u`` (``E_uu`` the hinge's second derivative, 0 past the kink)."""
        ce, c_item, cl, clim, cw = self.cross
        Dm = torch.exp(s[ce])                                          # (C,2) dm/ds
        m = Dm + self.floor[ce]
        tot = m.sum(1)
        u = cl * m[:, 0] / tot
        over0 = (clim[:, 0] - u).clamp_min(0)
        over1 = (clim[:, 1] - (cl - u)).clamp_min(0)
        E = torch.zeros(self.B, dtype=self.dt, device=self.dev).index_add_(0, c_item, cw * (over0 * over0 + over1 * over1))
        Eu = 2.0 * cw * (over1 - over0)
        um = torch.stack([cl * m[:, 1], -cl * m[:, 0]], 1) / (tot * tot)[:, None]     # du/dm
        us = um * Dm                                                   # du/ds
        g = Eu[:, None] * us
        if not hessian:
            return E, g, None
        Euu = 2.0 * cw * ((over0 > 0).to(self.dt) + (over1 > 0).to(self.dt))
        t3 = cl / (tot * tot * tot)
        h00, h01, h11 = -2.0 * t3 * m[:, 1], t3 * (m[:, 0] - m[:, 1]), 2.0 * t3 * m[:, 0]
        umm = torch.stack([torch.stack([h00, h01], 1), torch.stack([h01, h11], 1)], 1)   # d²u/dm²
        uss = Dm[:, :, None] * umm * Dm[:, None, :] + torch.diag_embed(um * Dm)
        H = Euu[:, None, None] * us[:, :, None] * us[:, None, :] + Eu[:, None, None] * uss
        return E, g, (c_item, H)

    def _smooth_terms(self, s: torch.Tensor):
        """(``Fs`` returned is ``∂F/∂s`` on the band faces.) ``R = J / S`` per item with ``J = Σ_e ℓ_e |∇f_a − ∇f_b|²`` over the band edges and
        ``S = Σ_e ℓ_e (|∇f_a|² + |∇f_b|²)/2 = Σ_t c_t |∇f_t|²``; the per-face gradients
        ``∂R/∂F_t`` (band faces) of it and of ``S``."""
        B, dt, dev = self.B, self.dt, self.dev
        Fs = self.sig[self.sm_faces] * torch.exp(s[self.sm_faces])     # (Ts,3) dF/ds
        gs = (self.sm_G * (Fs + self.sig[self.sm_faces] * self.floor[self.sm_faces])[..., None]).sum(1)   # (Ts,2)
        ea, eb = self.e_faces[:, 0], self.e_faces[:, 1]
        diff = gs[ea] - gs[eb]
        J = torch.zeros(B, dtype=dt, device=dev).index_add_(0, self.e_item, self.e_len * (diff * diff).sum(1))
        S = torch.zeros(B, dtype=dt, device=dev).index_add_(0, self.sm_item, self.sm_c * (gs * gs).sum(1))
        S = S.clamp_min(torch.finfo(dt).tiny)
        R = J / S
        dgr = torch.zeros_like(gs).index_add_(0, torch.cat([ea, eb]),
                                              torch.cat([2 * self.e_len[:, None] * diff, -2 * self.e_len[:, None] * diff]))
        dJ = (self.sm_G * dgr[:, None, :]).sum(2)                      # (Ts,3) per-face parts of ∇_F J
        dS = (self.sm_G * (2 * self.sm_c[:, None] * gs)[:, None, :]).sum(2)
        Si = S[self.sm_item]
        dR = (dJ - R[self.sm_item, None] * dS) / Si[:, None]
        return R, Fs, dR, dS, S, ea, eb

    def _smooth_hessian(self, H, R, Fs, dR, dS, S, ea, eb):
        """Add ``smoothness ·`` the Hessian of ``R`` in ``s`` to the flat ``H`` but its rank-2 part,
        returned as per-slot factors ``(left, right)`` (``Σ left rightᵀ`` per item):
        ``diag(F) ∇²_F R diag(F) + diag(F ⊙ ∇_F R)``,
        ``∇²_F R = (∇²J − R ∇²S)/S − (∇R ∇Sᵀ + ∇S ∇Rᵀ)/S`` (the last part rank 2 per item)."""
        dt, dev, w = self.dt, self.dev, self.smoothness
        Si = S[self.sm_item]
        # ∇²J: per band edge the 6x6 block 2ℓ [G_a; −G_b][G_a; −G_b]ᵀ, in s
        F6 = torch.cat([Fs[ea], Fs[eb]], 1)                             # (Eb,6)
        it = self.e_item
        blk = (2 * w * self.e_len / S[it])[:, None, None] * self.jump_gram * F6[:, :, None] * F6[:, None, :]
        H.index_add_(0, self.ix_jump, blk.reshape(-1))
        # −R ∇²S / S: per face −2 c_t R N_t / S, plus diag(F ⊙ ∇R)
        fb = (-2 * self.sm_c * R[self.sm_item] / Si)[:, None, None] * self.sm_N * Fs[:, :, None] * Fs[:, None, :]
        fb = w * (fb + torch.diag_embed(Fs * dR))
        H.index_add_(0, self.ix_sm, fb.reshape(-1))
        # rank 2: −(v uᵀ + u vᵀ)/S with v = F ⊙ ∇R, u = F ⊙ ∇S (per item block)
        v = torch.zeros(self.vsize, dtype=dt, device=dev).index_add_(0, self.ix_smv, (Fs * dR).reshape(-1))
        u = torch.zeros(self.vsize, dtype=dt, device=dev).index_add_(0, self.ix_smv, (Fs * dS).reshape(-1))
        c = (-w / S)[self.slot_item]
        return torch.stack([c * v, c * u], 1), torch.stack([u, v], 1)     # (vsize, 2) each: left, right factors

    def values(self, s: torch.Tensor) -> torch.Tensor:
        """``(V,)`` the nodal values ``σ ⊙ (exp(s) + floor)``."""
        return self.sig * (torch.exp(s) + self.floor)

    def energy(self, s: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
        """``(B,)`` the objective; ``M (T, 3, 3)`` the full moment tensor (differentiable by autograd)."""
        return self.terms(s, M[self.act])[0]

    def pad(self, x: torch.Tensor) -> torch.Tensor:
        """``(V,)`` -> the flat per-item block vector: the active vertices' entries (0 on padding)."""
        out = torch.zeros(self.vsize, dtype=x.dtype, device=x.device)
        return out.index_copy(0, self.av_slot, x[self.av])

    def unpad(self, X: torch.Tensor) -> torch.Tensor:
        """flat block vector -> ``(V,)`` (0 at inactive vertices)."""
        out = torch.zeros(self.s0.shape[0], dtype=X.dtype, device=X.device)
        return out.index_copy(0, self.av, X[self.av_slot])

    # ----------------------------------------------------------- solver
    def solve(self, M: torch.Tensor, max_iter: int = 100, step_tol: Optional[float] = None,
              max_step: float = 2.0, trace: Optional[list] = None, start: Optional[torch.Tensor] = None,
              state: Optional[tuple] = None) -> torch.Tensor:
        """``(V,)`` the minimizer ``s*`` (damped Newton, per-item damping and stopping).

        ``M``: the full ``(T, 3, 3)`` moments. ``start``, ``state``: the iterate and the
        per-item damping and first objective ``(mu, nu, E0)`` to go on from (default: ``s0`` and a fresh start). A
        problem made by :meth:`geometry` drops its finished items once at most half remain
        (a smaller problem is rebuilt for the others; per-item results do not change)."""
        Ma = M[self.act]
        s = self.s0.clone() if start is None else start.clone()
        B, dt, dev = self.B, self.dt, self.dev
        self.converged = torch.ones(B, dtype=torch.bool, device=dev)
        self.item_iterations = torch.zeros(B, dtype=torch.long, device=dev)
        if self.amax == 0:
            return s
        eps = torch.finfo(dt).eps
        step_tol = 0.1 * eps ** 0.5 if step_tol is None else step_tol
        avi = self.av_item
        if state is None:
            mu = torch.full((B,), getattr(self, "mu0", 1e-4), dtype=dt, device=dev)
            nu = torch.full((B,), 2.0, dtype=dt, device=dev)
        else:
            mu, nu = state[0].clone(), state[1].clone()
        done = torch.zeros(B, dtype=torch.bool, device=dev)
        n_act = self.n_act
        E, g, H = self.terms(s, Ma, hessian=True)

        def gmax(x):
            return torch.zeros(B, dtype=dt, device=dev).scatter_reduce(0, avi, x[self.av].abs(), "amax")

        def item_sum(x):                 # flat block vector -> (B,)
            return torch.zeros(B, dtype=dt, device=dev).index_add_(0, self.slot_item, x)

        lo = getattr(self, "lower", None)
        rounding_stop = lo is not None
        vi = self.mesh.vert_item

        def free_grad(s_, g_):
            # projected gradient: 0 where s sits on its lower bound and the descent runs below it
            return g_ if lo is None else torch.where((s_ <= lo) & (g_ > 0), torch.zeros_like(g_), g_)

        gp = free_grad(s, g)
        gn = gmax(gp)
        E0 = E.abs().clone() if state is None else state[2].clone()
        self.iterations = 0
        item_iters = torch.zeros(B, dtype=torch.long, device=dev)
        for it in budget.rounds(max_iter):
            done = done | (gn <= 256 * eps * E.abs())
            n_left = int((~done).sum())                        # the iteration's one host read
            if n_left == 0:
                break
            if getattr(self, "_inputs", None) is not None and 2 * n_left <= B and it > 0:
                return self._go_on_without_done(M, done, s, (mu, nu, E0), max_iter - it, step_tol, max_step, trace,
                                                item_iters, it)
            self.iterations = it + 1
            lam = mu * item_sum(H[self.hdiag].abs() * (1.0 - self.pad_flat)) / n_act
            # projected Newton: the bound vertices leave the system (their rows and columns)
            keep = None if lo is None else self.pad(((gp == g) | (s > lo)).to(dt))
            d = self.unpad(self._block_solve(H, -self.pad(gp), lam, keep))
            d = torch.where(done[vi], torch.zeros_like(d), d)
            # the damped Newton decrement gᵀ(H + λI)⁻¹g: what the (convex) damped model can still gain
            dec = torch.zeros(B, dtype=dt, device=dev).index_add_(0, vi, -gp * d)
            # a trust region in s (a factor e^2 per step): the iterates stay in s0's basin
            big = gmax(d)
            d = d * (max_step / big.clamp_min(max_step))[vi]
            s2 = s + d if lo is None else torch.maximum(s + d, lo)
            # the quadratic model's predicted decrease, for the damping update (gain ratio)
            dp = self.pad(s2 - s)
            pred = item_sum(-self.pad(g) * dp - 0.5 * dp * self._block_matvec(H, dp))
            E2, g2, H2 = self.terms(s2, Ma, hessian=True)
            gp2 = free_grad(s2, g2)
            gn2 = gmax(gp2)
            # near the optimum E changes at rounding level: there accept steps that shrink the gradient
            ok = ~done & torch.isfinite(E2) & ((E2 < E) | ((E2 <= E + 256 * eps * E.abs()) & (gn2 < gn)))
            step = gmax(s2 - s)
            okv = ok[vi]
            s = torch.where(okv, s2, s)
            g = torch.where(okv, g2, g)
            gp = torch.where(okv, gp2, gp)
            rho = (E - E2) / pred.clamp_min(torch.finfo(dt).tiny)
            E_old = E
            E = torch.where(ok, E2, E)
            gn = torch.where(ok, gn2, gn)
            H = torch.where(ok[self.h_item], H2, H)
            # an accepted, nearly undamped step this small leaves an error of about its square
            # a rejected step with the gradient at rounding level relative to the starting objective
            # or (float32: the objective's sums round at about 1e-7 of it) a nearly undamped
            # model whose whole predicted decrease is at rounding level: no step can do better
            done = (done | (ok & (step < step_tol) & (mu <= 1e-10)) | (~ok & (gn <= 1e4 * eps * E0)) | (mu > 1e12)
                    | (rounding_stop & (dec <= 16 * eps * E_old.abs()) & (mu <= 1e-3)))
            # damping: /10 where the quadratic model predicted the decrease well, kept where it
            # did so poorly, x2, x4, x8... on rejections (a ratio of quadratic forms is not convex)
            shrink = torch.where(rho > 0.5, 0.1, torch.where(rho > 0.1, 1.0, 2.0)).to(dt)
            mu = torch.where(ok, (mu * shrink).clamp_min(1e-15), mu * nu)
            nu = torch.where(ok, torch.full_like(nu, 2.0), nu * 2.0)
            item_iters = item_iters + (~done).long()
            if trace is not None:        # debugging: per iteration (E, |g|max, |step|max, mu, accepted)
                trace.append((E.clone(), gn.clone(), step.clone(), mu.clone(), ok.clone()))
        #: ``(B,)`` per item: it met a stopping rule (else ``max_iter`` stopped it), and its iterations
        self.converged = done | (gn <= 256 * eps * E.abs())
        self.item_iterations = item_iters
        return s

    def _go_on_without_done(self, M, done, s, state, max_iter, step_tol, max_step, trace, item_iters, it):
        """:meth:`solve`'s remaining iterations on the unfinished items alone."""
        keep = (~done).nonzero().squeeze(1)
        mesh, kv, kf = self.mesh.select_items(keep)
        count, signs, init, tol, mf, sm, cw, near, slack, reg, scale_reg = self._inputs
        sub = RefitProblem.geometry(mesh, count[kf], signs[kv], init[kv], tol[keep], mf, sm, cw,
                                    None if near is None else near[kv], None if slack is None else slack[keep],
                                    reg=reg, scale_reg=scale_reg)
        s_sub = sub.solve(M[kf], max_iter, step_tol=step_tol, max_step=max_step, trace=trace, start=s[kv],
                          state=tuple(x[keep] for x in state))
        self.converged = done.clone()
        self.converged[keep] = sub.converged
        self.item_iterations = item_iters.index_add(0, keep, sub.item_iterations)
        self.iterations = it + sub.iterations
        return s.index_copy(0, kv, s_sub)


class _ImplicitRefit(torch.autograd.Function):
    """``M (T, 3, 3) -> s* (V,)``; backward by the implicit function theorem (closed form)."""

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
        gM = torch.zeros_like(M)
        if pb.amax == 0:
            return gM, None, None
        Ma = M[pb.act]
        _, _, H = pb.terms(s, Ma, hessian=True)
        lam = pb.unpad(pb._block_solve(H, pb.pad(gs.to(pb.dt))))
        Dv = pb.sig[pb.faces] * torch.exp(s[pb.faces])                 # (A,3) dF/ds
        F = Dv + pb.sig[pb.faces] * pb.floor[pb.faces]
        gf = (pb.G * F[..., None]).sum(1)
        NF = (pb.G * gf[:, None, :]).sum(2)
        d = (gf * gf).sum(1) + pb.guard
        mu = lam[pb.faces] * Dv
        muNF = (mu * NF).sum(1)
        sym = 0.5 * (mu[:, :, None] * F[:, None, :] + F[:, :, None] * mu[:, None, :])
        dM = (2.0 * pb.w / d)[:, None, None] * (sym - (muNF / d)[:, None, None] * F[:, :, None] * F[:, None, :])
        gM[pb.act] = -dM.to(gM.dtype)
        return gM, None, None


def refit(curve: ImplicitCurve, points: torch.Tensor, point_item: Optional[torch.Tensor] = None,
          reg: float = 1e-4, rel_scale: float = 1e-2, smoothness: float = 1e-2, floor: float = 0.02,
          max_iter: int = 100) -> ImplicitCurve:
    """Re-fit the magnitudes of ``curve`` to ``points (N, 2)`` (``point_item (N,)``, default 0),
    mesh and signs held fixed; differentiable in the points (implicit differentiation).

    Points off their item's mesh are ignored; an item without points keeps its values; a NaN or
    infinite point is a :class:`PointSetError`.
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
    _check_refit_options(reg=reg, rel_scale=rel_scale, smoothness=smoothness, floor=floor, max_iter=max_iter)
    mesh = curve.mesh.detach()
    # the queries' checks: an (N, 2) real tensor, integer items in range (-1 meant the last item)
    point_item = curve._point_item(points, point_item)
    bad = ~torch.isfinite(points.detach()).all(1)
    if bool(bad.any()):            # as reconstruct: a NaN is a broken input, not a point off the mesh
        raise PointSetError(f"refit: points: {int(bad.sum())} row(s) hold NaN or Inf (first at row {int(bad.nonzero()[0])})")
    pts = points.to(mesh.dtype)
    with torch.no_grad():
        face, _ = locate_grid(mesh, pts, point_item)
    ok = face >= 0
    f = face[ok]
    p = pts[ok]
    bary = barycentric(mesh.verts, mesh.faces, f, p)                   # differentiable in the points
    mom = triangle_moments(mesh, p, f, bary)
    problem = RefitProblem(curve, mom.count, reg, rel_scale, smoothness, floor)
    s = _ImplicitRefit.apply(mom.M, problem, max_iter)
    new = problem.values(s)
    with torch.no_grad():
        has = torch.zeros(mesh.num_items, dtype=torch.bool, device=mesh.device)
        has[point_item[ok]] = True
    # an item without points on its mesh keeps its values (the regularizer alone moved them)
    return curve._like(curve.mesh, torch.where(has[mesh.vert_item], new, curve.values.to(new.dtype)))


def _check_refit_options(**kw) -> None:
    """One-line ``ValueError``s for :func:`refit`'s numeric options (NaN gave NaN values, a
    negative ``max_iter`` an unfitted curve)."""
    import numbers
    from torch_isc._helpers import finite_real
    for k in ("reg", "smoothness", "floor"):
        if not finite_real(kw[k]) or kw[k] < 0:
            raise ValueError(f"refit: {k} must be a finite number >= 0, got {kw[k]!r}")
    if not finite_real(kw["rel_scale"]) or kw["rel_scale"] <= 0:
        raise ValueError(f"refit: rel_scale must be a finite number > 0, got {kw['rel_scale']!r}")
    it = kw["max_iter"]
    if isinstance(it, bool) or not isinstance(it, numbers.Integral) or not 1 <= it <= 1_000_000:
        raise ValueError(f"refit: max_iter must be an integer in [1, 1000000], got {it!r}")


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
    for i, p in enumerate(sets):
        shape = tuple(torch.as_tensor(p).shape) if not torch.is_tensor(p) else tuple(p.shape)
        if len(shape) != 2 or shape[1] != 2:
            raise ValueError(f"attach_point_gradients: point set {i}: expected (N, 2) points, got shape {shape}")
    batch = ImplicitCurve.cat([ImplicitCurve(c.mesh.detach(), c.values.detach(), validate=False) for c in curves])
    dt, dev = batch.mesh.dtype, batch.mesh.device
    pts = torch.cat([torch.as_tensor(p).to(device=dev, dtype=dt).reshape(-1, 2) for p in sets])
    counts = torch.tensor([int(torch.as_tensor(p).reshape(-1, 2).shape[0]) for p in sets], device=dev)
    point_item = torch.repeat_interleave(torch.arange(len(sets), device=dev), counts)
    # the refit runs in each item's unit frame (a constant map, so the chain rule is exact):
    # in the caller's units its squares underflow below ~1e-150 and its fixed weights dominate
    # beyond ~1e20 (a circle of radius 1e30 got gradients 4e35 times too small)
    vi = batch.mesh.vert_item
    v64 = batch.mesh.verts.double()
    box = _segment_bbox(v64, vi, len(sets))
    lo, hi = box[:, :2], box[:, 2:]
    m = torch.maximum(lo.abs(), hi.abs()).amax(1).clamp_min(torch.finfo(torch.float64).tiny)
    centre = 0.5 * (lo + hi)
    size = torch.hypot((hi[:, 0] - lo[:, 0]) / m, (hi[:, 1] - lo[:, 1]) / m) * m      # no overflow near 1e308
    size = torch.where(size > 0, size, torch.ones_like(size))
    unit = ImplicitCurve(batch.mesh.with_verts(((v64 - centre[vi]) / size[vi, None]).to(dt)),
                         (batch.values.double() / size[vi]).to(dt), validate=False)
    pts_u = (pts - centre[point_item].to(dt)) / size[point_item, None].to(dt)
    new = refit(unit, pts_u, point_item, **refit_kw).values * size[vi].to(dt)
    vals = batch.values + (new - new.detach()) if keep_values else new
    out = []
    v0 = 0
    for x, c in zip(items, curves):
        n = c.values.shape[0]
        nc = c._like(c.mesh, vals[v0:v0 + n].to(c.values.dtype))
        v0 += n
        out.append(dataclasses.replace(x, curve=nc) if hasattr(x, "curve") else nc)
    return out
