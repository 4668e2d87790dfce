"""EstimateGeometry (Section 3.1): minimize Δ1 over the magnitudes, signs held fixed.

``F = σ ⊙ (exp(s) + floor)``: no value can change sign or reach 0, and ``floor`` (a
fraction of the item's mean starting magnitude) keeps magnitudes from collapsing toward
0, which would pull the zero set into spikes toward those vertices. ``M_t`` is assembled
once per partition, so an evaluation costs O(triangles), independent of the points.
"""
from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Tuple

import torch

from torch_isc.core.segments import segment_count, segment_sum

from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline import graphs
from torch_isc.pipeline.optim import batched_lbfgs, true_indices, unfused
from torch_isc.pipeline.evidence import TriangleMoments
from torch_isc.pipeline.knobs import check_section, knob
from torch_isc.pipeline.noise import take

if TYPE_CHECKING:
    from torch_isc.pipeline.evidence import Evidence
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["GeometryConfig", "GeometryObjective", "delta1_per_triangle", "vertex_data_distance", "vertex_data_distance_near", "fit_geometry", "run_fit", "estimate_values",
           "point_residuals"]


@dataclass
class GeometryConfig:
    """EstimateGeometry (flat keys of configs/default.yaml)."""
    lbfgs_iterations: int = knob(60, ge=0)
    lbfgs_history: int = knob(8, gt=0)
    #: step lengths the line search tries per round, in one stacked evaluation; 0: 1 on a CPU
    #: (bound by arithmetic), 3 elsewhere (bound by launches). Results do not depend on it
    lbfgs_trials: int = knob(0, ge=0)
    #: evaluate the objective through torch.compile (inductor); falls back to eager, with a
    #: warning, where compiling fails. Off: on this CPU the compile time is not won back
    compile: bool = knob(False)
    #: magnitudes stay above this fraction of the item's mean magnitude
    magnitude_floor: float = knob(0.02, ge=0, lt=1)
    #: weight of the penalty on jumps of grad f across interior edges; 0 disables
    smoothness: float = knob(1e-2, ge=0)
    #: weight of the dead-zoned curve-to-data term at the zero set's edge crossings; 0 disables
    crossing_weight: float = knob(1.0, ge=0)
    #: L-BFGS runs in ``x = s / c``, ``c`` per vertex the inverse square root of the Gauss-Newton
    #: diagonal of the objective at the start (Δ1's numerator and the smoothness term), i.e. a
    #: diagonal initial inverse Hessian: small triangles (fine levels) and many-point ones weigh
    #: alike; 0 disables; the value is the share of the item's mean diagonal added to every
    #: vertex's (vertices with no data and no band term keep a finite scale)
    precondition: float = knob(0.0, ge=0)

    def __post_init__(self):
        check_section(self)


def _sum_last(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(-1)`` over a last dim of 2 or 3; on a CPU as ``(x0 + x1) + x2``: the reduction's
    own order (the same bits), 5-15x faster than a reduction over so short a dim (elsewhere the
    reduction: one launch)."""
    if not unfused(x):
        return x.sum(-1)
    s = x[..., 0] + x[..., 1]
    return s + x[..., 2] if x.shape[-1] == 3 else s


def _sum_rows(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(-2)`` over a dim of 3 (the corners of a face), as :func:`_sum_last`."""
    if not unfused(x):
        return x.sum(-2)
    return (x[..., 0, :] + x[..., 1, :]) + x[..., 2, :]


def _take(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[:, index]`` for ``x (K, N, ...)`` and an index of any shape, by ``index_select``
    (the same values; on a CPU about 3x faster than advanced indexing)."""
    out = x.index_select(1, index.reshape(-1))
    return out.view(x.shape[0], *index.shape, *x.shape[2:])


def _add_cols(x: torch.Tensor, index: torch.Tensor, src: torch.Tensor) -> torch.Tensor:
    """``x.index_add(1, index, src)`` for ``x (K, N, ...)``: the same bits (each entry gets its
    terms in index order), as an index_add along dim 0 when ``K == 1``."""
    if x.shape[0] == 1:
        return x[0].index_add(0, index, src[0])[None]
    return x.index_add(1, index, src)


def _grad_norm2(mesh: MeshBatch, values: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    return _grad_norm2_g(G, values[mesh.faces])


def _grad_norm2_g(G: torch.Tensor, Ft: torch.Tensor) -> torch.Tensor:
    # |G_tᵀ F_t|² computed directly: as a quadratic form it can round below zero
    grad = (G * Ft[..., None]).sum(1)
    return (grad * grad).sum(1), grad


def delta1_per_triangle(mesh: MeshBatch, M: torch.Tensor, values: torch.Tensor, G: torch.Tensor = None,
                        guard: float = 0.0) -> torch.Tensor:
    """``(T,)`` mean over the triangle's points of ``f(p)² / |∇f_t|²`` (``F_tᵀM_tF_t / |∇f_t|²``)."""
    return _delta1_faces(mesh.faces, M, values, mesh.bary_gradients() if G is None else G, guard)


def _delta1_faces(faces: torch.Tensor, M: torch.Tensor, values: torch.Tensor, G: torch.Tensor, guard) -> torch.Tensor:
    """:func:`delta1_per_triangle` on the triangles ``faces (T, 3)`` with their ``M, G``."""
    Ft = values[faces]
    num = torch.einsum("ti,tij,tj->t", Ft, M, Ft)
    g2, _ = _grad_norm2_g(G, Ft)
    return num / (g2 + guard)


def _located(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor):
    """``(V, verts, points, faces, ok)``: the vertex count, the detached vertices, the points
    (in the mesh's dtype), their triangles (0 where they have none) and whether they have one
    (masks, not boolean indexing: no host read)."""
    v = mesh.verts.detach()
    ok = face >= 0
    return v.shape[0], v, points.to(v.dtype), face.clamp_min(0), ok


#: hops of the edge relaxation between two convergence checks (each check is a host read)
_HOPS_PER_CHECK = 8


def vertex_data_distance(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor, max_hops: int = 256) -> torch.Tensor:
    """``(V,)`` an upper bound of each vertex's distance to the nearest data point of its item.

    Exact-ish near the data (points of the incident triangles), then relaxed along mesh
    edges (Bellman–Ford on the edge graph) for the vertices of empty regions.
    """
    with torch.no_grad():
        V, v, p, f, ok = _located(mesh, points, face)
        dt = v.dtype
        vid = mesh.faces[f]                                   # (P,3)
        dist = (v[vid] - p[:, None, :]).norm(dim=2)
        dist = torch.where(ok[:, None], dist, torch.full_like(dist, float("inf")))
        d = torch.full((V,), float("inf"), dtype=dt, device=v.device)
        d = d.scatter_reduce(0, vid.reshape(-1), dist.reshape(-1), "amin")
        e = mesh.edges
        el = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
        src = torch.cat([e[:, 0], e[:, 1]])
        dst = torch.cat([e[:, 1], e[:, 0]])
        w = torch.cat([el, el])
        # a hop after convergence changes nothing, so checking every few hops (and stopping
        # after max_hops all the same) gives the same distances with fewer host reads
        hops = 0
        while hops < max_hops:
            for _ in range(min(_HOPS_PER_CHECK, max_hops - hops)):
                prev, d = d, d.scatter_reduce(0, dst, d[src] + w, "amin")
                hops += 1
            if torch.equal(prev, d):                           # the last hop changed nothing
                break
        # an item with no located point at all: unit magnitudes
        return torch.where(torch.isfinite(d), d, torch.ones_like(d))


def vertex_data_distance_near(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
    """``(V,)`` each vertex's distance to the nearest data point located in its star or in a
    triangle edge-adjacent to its star (inf where there is none).

    Unlike :func:`vertex_data_distance` it is never relaxed along mesh edges, so where it is
    finite it is the true nearest distance unless a nearer point lies farther out than the
    star's edge-neighbours (rare: the triangle there would separate them)."""
    with torch.no_grad():
        V, v, p, f, ok = _located(mesh, points, face)
        dt = v.dtype
        nb = take(mesh.face_neighbors, f)                      # (P,3)
        tri = torch.cat([f[:, None], nb], 1)                   # (P,4)
        has = (tri >= 0) & ok[:, None]
        vid = take(mesh.faces, tri.clamp_min(0)).reshape(p.shape[0], 12)
        dist = (take(v, vid) - p[:, None, :]).norm(dim=2)
        dist = torch.where(has.repeat_interleave(3, 1), dist, torch.full_like(dist, float("inf")))
        d = torch.full((V,), float("inf"), dtype=dt, device=v.device)
        return d.scatter_reduce(0, vid.reshape(-1), dist.reshape(-1), "amin")


def point_residuals(mesh: MeshBatch, values: torch.Tensor, face: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """``(P,)`` ``f(p)² / |∇f_t(p)|²``, the squared approximate distance of each point to the
    curve (inf for points with no triangle)."""
    G = mesh.bary_gradients()
    g2, _ = _grad_norm2(mesh, values, G)
    ok = face >= 0
    fc = face.clamp_min(0)
    f = (values[mesh.faces[fc]] * bary.nan_to_num()).sum(1)
    r = f * f / g2[fc].clamp_min(torch.finfo(values.dtype).tiny)
    return torch.where(ok, r, torch.full_like(r, float("inf")))


class GeometryObjective:
    """The per-item objective of :func:`fit_geometry` in the log-magnitudes ``s (V,)``, with its
    gradient written out by hand.

    ``F = signs ⊙ (exp(s) + floor)`` and the objective of item ``b`` is
    ``(Δ1 + crossing) / tol² + smoothness · J / S`` (see :func:`fit_geometry`). :meth:`value`
    is plain tensor code (autograd can differentiate it: the tests check the hand-written
    :meth:`value_and_grad` against it in float64); the optimizer calls
    :meth:`value_and_grad`, which costs about half the tensor ops of a backward pass, and the
    method is bound by op count on small meshes.
    """

    def __init__(self, mesh: MeshBatch, mom: TriangleMoments, signs: torch.Tensor, init_mag: torch.Tensor,
                 tol: torch.Tensor, cfg: GeometryConfig, data_dist: Optional[torch.Tensor] = None,
                 slack: Optional[torch.Tensor] = None):
        magnitude_floor, smoothness, crossing_weight = cfg.magnitude_floor, cfg.smoothness, cfg.crossing_weight
        B = mesh.num_items
        vi, fi = mesh.vert_item, mesh.face_item
        dt = mesh.dtype
        dev = mesh.device
        self.B, self.dt, self.dev, self.signs, self.smoothness = B, dt, dev, signs, smoothness
        self.vi = vi
        self.compiled = cfg.compile
        with torch.no_grad():
            self.item_zero = torch.zeros(B, dtype=dt, device=dev)
            G = mesh.bary_gradients()
            nb = segment_sum(mom.count, fi, B)
            wt = mom.count / nb[fi].clamp_min(1)
            nv = segment_count(vi, B).to(dt)
            mean_mag = segment_sum(init_mag, vi, B) / nv.clamp_min(1)
            self.floor = (magnitude_floor * mean_mag)[vi]
            self.s0 = torch.log((init_mag - self.floor).clamp_min(1e-3 * mean_mag[vi])
                                .clamp_min(torch.finfo(dt).tiny))
            # penalize gradient jumps in the band where the curve can be: edges next to data or
            # to a sign change (elsewhere f is far from 0 and its kinks do not move the curve)
            fneg = signs[mesh.faces] < 0
            band_t = (mom.count > 0) | (fneg.any(1) & ~fneg.all(1))
            interior = ~mesh.is_boundary_edge
            ef_all = mesh.edge_faces.clamp_min(0)
            interior = interior & (band_t[ef_all[:, 0]] | band_t[ef_all[:, 1]])
            v = mesh.verts.detach()
            self.cross = crossing_weight > 0 and data_dist is not None and slack is not None
            crossed = signs[mesh.edges[:, 0]] != signs[mesh.edges[:, 1]]
            # only the faces with points (Δ1) or on a band edge (the jump of ∇f) enter the
            # objective: an empty face's Δ1 term is 0 · finite, so leaving it out changes no sum
            # (the faces of the band edges by index_fill with a dummy slot T for the others: a
            # boolean-mask selection would be a host read)
            T = mesh.faces.shape[0]
            used = torch.cat([mom.count > 0, torch.zeros(1, dtype=torch.bool, device=dev)]).index_fill_(
                0, torch.where(interior[:, None], ef_all, T).reshape(-1), True)[:T]
            # the variables that can move: the corners of those faces and the crossings' ends (a
            # vertex of none has a zero gradient at every step, so L-BFGS never moves it)
            nuse = torch.zeros(signs.shape[0], dtype=torch.long, device=dev).index_add_(
                0, mesh.faces.reshape(-1), used.long().repeat_interleave(3))
            if self.cross:
                nuse = nuse.index_add_(0, mesh.edges.reshape(-1), crossed.long().repeat_interleave(2))
            vused = nuse > 0
            # the four selections from one host read
            n_int, n_cross, n_used, n_var = torch.stack([interior.sum(), (crossed if self.cross else interior).sum(),
                                                         used.sum(), vused.sum()]).tolist()
            self._vars = None if n_var == signs.shape[0] else (true_indices(vused, n_var), torch.cumsum(vused, 0) - 1)
            ii = true_indices(interior, n_int)
            e = mesh.edges[ii]
            kf = true_indices(used, n_used)
            fmap = torch.cumsum(used, 0) - 1
            self.inv_tol2 = 1.0 / (tol * tol)
            # per face: vertices, gradients, moments, weight (Δ1 in units of tol²), guard
            fi = fi[kf]
            self.face_ids = kf                  # the mesh's index of each of the objective's faces
            self.faces, self.G, self.M, self.fi = mesh.faces[kf], G[kf], mom.M[kf], fi
            wt = wt[kf]
            self.wt = wt * self.inv_tol2[fi]
            self.wt_raw = wt
            self.guard = ((1e-10 * mean_mag) ** 2)[fi]
            self.ef = fmap[mesh.edge_faces[ii]]
            self.ef_ab = torch.cat([self.ef[:, 0], self.ef[:, 1]])
            self.el = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
            self.eitem = mesh.edge_item[ii]
            if self.cross:
                ce = mesh.edges[true_indices(crossed, n_cross)]
                c_item = vi[ce[:, 0]]
                self.cross = ce.shape[0] > 0
                self.ce, self.c_item = ce, c_item
                self.c_len = (v[ce[:, 0]] - v[ce[:, 1]]).norm(dim=1)
                # how close to each end the crossing may come before it is provably off the data
                c_lim = (data_dist[ce] - slack[c_item][:, None]).clamp_min(0)
                self.c_lim = torch.where(torch.isfinite(c_lim), c_lim, torch.zeros_like(c_lim))
                per_item = segment_count(c_item, B).to(dt)
                self.c_w = (crossing_weight / per_item.clamp_min(1)[c_item]) * self.inv_tol2[c_item]
            self._constants()
            # the variable scale of the preconditioned fit (None: L-BFGS runs in s itself)
            self.pc = None
            if cfg.precondition > 0:
                h = self.gauss_newton_diagonal(self.s0)
                mean_h = segment_sum(h, vi, B) / nv.clamp_min(1)
                h = h + cfg.precondition * mean_h[vi]
                self.pc = torch.where(h > 0, h.clamp_min(torch.finfo(dt).tiny).rsqrt(), torch.ones_like(h))

    def variables(self) -> Tuple["GeometryObjective", Optional[torch.Tensor]]:
        """``(sub, kv)``: the same objective in the variables ``s[kv]`` alone, the vertices that
        can move (``kv``: None when that is all of them, ``sub`` then this objective). Every
        per-item sum of the fit runs in entry order, so leaving out entries whose every term is
        zero changes no bit of the result: ``s0`` with ``s0[kv]`` set to ``sub``'s minimizer is
        this objective's."""
        if self._vars is None:
            return self, None
        kv, vmap = self._vars
        with torch.no_grad():
            sub = object.__new__(GeometryObjective)
            sub.__dict__.update(self.__dict__)
            sub._vars = None
            sub.vi, sub.signs, sub.floor, sub.s0 = self.vi[kv], self.signs[kv], self.floor[kv], self.s0[kv]
            sub.pc = None if self.pc is None else self.pc[kv]
            sub.faces = vmap[self.faces]
            if self.cross:
                sub.ce = vmap[self.ce]
            sub._constants()
        return sub, kv

    def delta1(self, F: torch.Tensor) -> torch.Tensor:
        """``(T',)`` :func:`delta1_per_triangle` of the values ``F (V,)`` on the objective's faces."""
        return _delta1_faces(self.faces, self.M, F, self.G, self.guard)

    def _constants(self) -> None:
        """What every evaluation would otherwise recompute (exact rewrites: products by ±1 and 2,
        sign patterns), from the fields above; :meth:`restrict` makes them again."""
        self.sfloor = self.signs * self.floor                 # F = sfloor + signs·e = signs·(e + floor)
        self.wt2, self.m2wt = 2.0 * self.wt, -2.0 * self.wt
        # ∇f_t and M_t F_t from one product and one sum over the face's vertices (M_t transposed:
        # the same products M_t[k, i] F_i, summed in the same order)
        self.GM = torch.cat([self.G, self.M.transpose(1, 2)], -1)     # (T,3,5)
        self.G0, self.G1 = self.G[..., 0].contiguous(), self.G[..., 1].contiguous()   # (T,3) each
        # every per-item sum of an evaluation in one scatter: column 0 the faces' w·q, 1 and 2
        # the band edges' el·jump and el·size, 3 the crossings' w·over² (each column still
        # gets its entries in order, so its sums keep their bits)
        self.smooth = self.smoothness > 0 and self.ef.shape[0] > 0
        ws, idx = [self.wt], [self.fi * 4]
        if self.smooth:
            ws += [self.el, 0.5 * self.el]
            idx += [self.eitem * 4 + 1, self.eitem * 4 + 2]
        if self.cross:
            ws.append(self.c_w)
            idx.append(self.c_item * 4 + 3)
        self.sum_w, self.sum_idx = torch.cat(ws), torch.cat(idx)
        if self.cross:
            self.ce4 = torch.cat([self.ce, self.ce.flip(1)], 1)   # both ends, then swapped
            self.cw2 = 2.0 * self.c_w
            self.sgn_c = torch.stack([self.signs[self.ce[:, 0]], -self.signs[self.ce[:, 1]]], -1)

    def gauss_newton_diagonal(self, s: torch.Tensor) -> torch.Tensor:
        """``(V,)`` the diagonal of the objective's Gauss-Newton Hessian in ``s`` at ``s (V,)``:
        per triangle ``2 w M_t / |∇f_t|²`` (the numerator's curvature, the denominator frozen)
        and per interior band edge ``2 λ ℓ D_eᵀD_e / S`` (``D_e F`` the jump of ``∇f`` across it,
        ``S`` frozen), in ``F``, times ``(dF/ds)² = exp(2s)``. The crossing term is left out
        (a dead zone: zero at most starts)."""
        with torch.no_grad():
            e = torch.exp(s.clamp(-60.0, 60.0))
            F = torch.addcmul(self.sfloor, self.signs, e)
            g2, _ = _grad_norm2_g(self.G, F[self.faces])
            Mii = torch.diagonal(self.M, dim1=1, dim2=2)                       # (T,3)
            h = torch.zeros_like(F).index_add_(0, self.faces.reshape(-1),
                                               (Mii * (self.wt2 / (g2 + self.guard))[:, None]).reshape(-1))
            if self.smoothness > 0 and self.ef.shape[0]:
                a, b = self.ef[:, 0], self.ef[:, 1]
                fa, fb = self.faces[a], self.faces[b]
                Ga, Gb = self.G[a], self.G[b]                                  # (E,3,2)
                eq = (fa[:, :, None] == fb[:, None, :]).to(F.dtype)          # shared vertices
                Da = Ga - eq @ Gb                                              # columns of D_e at a's vertices
                Db = Gb * (1.0 - eq.sum(1))[..., None]                         # at b's own vertex
                S = self._segsum((self.el * (g2[a] + g2[b]))[None], self.eitem)[0] * 0.5
                w = (2.0 * self.smoothness) * self.el / S.clamp_min(torch.finfo(F.dtype).tiny)[self.eitem]
                h = h.index_add_(0, torch.cat([fa, fb], 1).reshape(-1),
                                 (torch.cat([(Da * Da).sum(-1), (Db * Db).sum(-1)], 1) * w[:, None]).reshape(-1))
            return h * e * e

    def _evaluate_pre(self, x: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The objective and gradient in the scaled variable ``x = s / pc``."""
        f, g = self._evaluate(x * self.pc)
        return f, g * self.pc

    def _restricted_pre(self, items: torch.Tensor):
        sub = self.restrict(items)
        return sub._evaluate_pre, sub._restricted_pre

    def _evaluate(self, s: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        if self.compiled:
            fn = _compiled_value_and_grad()
            if fn is not None:
                try:
                    return fn(self, s)
                except Exception as exc:          # no inductor, no compiler: eager from now on
                    _COMPILED[0] = None
                    warnings.warn(f"torch.compile of the geometry objective failed ({type(exc).__name__}: "
                                  f"{exc}); running it eagerly", RuntimeWarning, stacklevel=2)
        return self.value_and_grad(s)

    def values(self, s: torch.Tensor) -> torch.Tensor:
        """``(V,)`` the nodal values ``F`` of the log-magnitudes ``s``."""
        return self.signs * (torch.exp(s.clamp(-60.0, 60.0)) + self.floor)

    def restrict(self, items: torch.Tensor) -> "GeometryObjective":
        """The objective of the items ``items (B,)`` bool alone, items renumbered in order and
        their vertices, faces, edges and crossings kept in order (so every per-item sum, hence
        every value, is bit-identical to the whole batch's). One host read (the sizes)."""
        with torch.no_grad():
            sub = object.__new__(GeometryObjective)
            sub.__dict__.update(self.__dict__)
            renum = torch.cumsum(items, 0) - 1
            owners = [self.vi, self.fi, self.eitem] + ([self.c_item] if self.cross else [])
            kept = [items[o] for o in owners]
            sizes = torch.stack([items.sum()] + [k.sum() for k in kept]).tolist()
            idx = [true_indices(k, c) for k, c in zip([items] + kept, sizes)]
            b, v, f, e = idx[:4]
            vmap, fmap = torch.cumsum(kept[0], 0) - 1, torch.cumsum(kept[1], 0) - 1
            sub.B = sizes[0]
            sub.item_zero = self.item_zero[b]
            sub.vi, sub.signs, sub.floor = renum[self.vi[v]], self.signs[v], self.floor[v]
            sub.s0, sub.wt_raw, sub.inv_tol2 = self.s0[v], self.wt_raw[f], self.inv_tol2[b]
            sub.pc = None if self.pc is None else self.pc[v]
            sub.faces, sub.fi = vmap[self.faces[f]], renum[self.fi[f]]
            sub.G, sub.M, sub.wt, sub.guard = self.G[f], self.M[f], self.wt[f], self.guard[f]
            sub.face_ids = self.face_ids[f]
            sub.ef, sub.el, sub.eitem = fmap[self.ef[e]], self.el[e], renum[self.eitem[e]]
            sub.ef_ab = torch.cat([sub.ef[:, 0], sub.ef[:, 1]])
            if self.cross:
                c = idx[4]
                sub.ce, sub.c_item = vmap[self.ce[c]], renum[self.c_item[c]]
                sub.c_len, sub.c_lim, sub.c_w = self.c_len[c], self.c_lim[c], self.c_w[c]
            sub._constants()
        return sub

    def _restricted(self, items: torch.Tensor):
        """:func:`batched_lbfgs`'s ``restrict``: the sub-objective's evaluation and restrict."""
        sub = self.restrict(items)
        return sub._evaluate, sub._restricted

    def _segsum(self, x: torch.Tensor, seg: torch.Tensor) -> torch.Tensor:
        """``(K, B, ...)`` per item sums of ``x (K, N, ...)`` (B read off a tensor: a symbolic size
        when compiled)."""
        return x.new_zeros((x.shape[0], self.item_zero.shape[0]) + x.shape[2:]).index_add_(1, seg, x)

    def value(self, s: torch.Tensor) -> torch.Tensor:
        """``(B,)`` the objective of every item (differentiable by autograd); ``s (K, V)``
        gives ``(K, B)``."""
        one = s.dim() == 1
        s = s[None] if one else s
        faces, G, M, fi, wt, guard, ef, el, eitem = (self.faces, self.G, self.M, self.fi, self.wt, self.guard,
                                                      self.ef, self.el, self.eitem)
        F = self.values(s)
        Ft = F[:, faces]
        grad = (G * Ft[..., None]).sum(-2)
        g2 = (grad * grad).sum(-1)
        num = ((Ft[..., :, None] * M).sum(-2) * Ft).sum(-1)
        obj = self._segsum(wt * num / (g2 + guard), fi)
        if self.cross:
            ce, cl, clim, cw, cit = self.ce, self.c_len, self.c_lim, self.c_w, self.c_item
            m = F[:, ce].abs()
            a = cl[:, None] * m / m.sum(-1, keepdim=True)
            over = (clim - a).clamp_min(0)
            obj = obj + self._segsum(cw * (over * over).sum(-1), cit)
        if self.smoothness > 0 and ef.shape[0]:
            jump = ((grad[:, ef[:, 0]] - grad[:, ef[:, 1]]) ** 2).sum(-1)
            size = 0.5 * (g2[:, ef[:, 0]] + g2[:, ef[:, 1]])
            J = self._segsum(el * jump, eitem)
            S = self._segsum(el * size, eitem)
            obj = obj + self.smoothness * J / S.clamp_min(torch.finfo(self.dt).tiny)
        return obj[0] if one else obj

    def value_and_grad(self, s: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(B,)`` objectives and ``(V,)`` their gradient with respect to ``s``; ``s (K, V)``
        (several points, e.g. the line search's trials, in one call) gives ``(K, B)`` and
        ``(K, V)``. Fixed shapes: every item, every face, no host read."""
        one = s.dim() == 1
        s = s[None] if one else s
        K = s.shape[0]
        faces, G, guard, ef, eitem = self.faces, self.G, self.guard, self.ef, self.eitem
        e = torch.exp(s.clamp(-60.0, 60.0))
        F = torch.addcmul(self.sfloor, self.signs, e)        # (K,V) signs·(e + floor), exactly
        Ft = _take(F, faces)                                 # (K,T,3)
        GMF = _sum_rows(self.GM * Ft[..., None])             # (K,T,5) ∇f_t, then M_t F_t
        grad, MF = GMF[..., :2], GMF[..., 2:]
        g2 = _sum_last(grad * grad)
        num = _sum_last(MF * Ft)
        rden = (g2 + guard).reciprocal()
        q = num * rden
        terms = [q]                                          # the per-entry terms of the per-item sums
        if self.smooth:
            E = ef.shape[0]
            # ∇f and |∇f|² of both faces of every band edge in one gather: a's rows, then b's
            gg = _take(torch.cat([grad, g2[..., None]], -1), self.ef_ab)   # (K,2E,3)
            diff = gg[:, :E, :2] - gg[:, E:, :2]
            terms += [_sum_last(diff * diff), gg[:, :E, 2] + gg[:, E:, 2]]   # jump, size (times 2)
        if self.cross:
            cl, clim = self.c_len, self.c_lim
            m4 = _take(F, self.ce4).abs()                    # (K,C,4) |F| at both ends, then swapped
            m, mf = m4[..., :2], m4[..., 2:]
            msum = _sum_last(m)
            a = cl[:, None] * m / msum[..., None]
            over = (clim - a).clamp_min(0)
            terms.append(_sum_last(over * over))
        # w·q per face, el·jump and el·size per band edge, w·over² per crossing: one scatter
        sums = F.new_zeros((K, self.item_zero.shape[0] * 4)).index_add_(
            1, self.sum_idx, self.sum_w * torch.cat(terms, 1)).view(K, -1, 4)
        obj = sums[..., 0]
        # d(num/den)/dF_t = 2 (M F − q G ∇f) / den, the G ∇f part added with the smoothness one
        qr = self.m2wt * q * rden                            # d obj / d ∇f_t = qr ∇f_t, then smoothness
        dFt = (self.wt2 * rden)[..., None] * MF
        if self.smooth:
            J, S = sums[..., 1], sums[..., 2].clamp_min(torch.finfo(self.dt).tiny)
            obj = obj + self.smoothness * J / S
            r = (2.0 * self.smoothness) / S                  # 2 · d obj / d jump, per item
            # per edge, times el: d obj / d jump for a's side and b's (negated), d obj / d size
            c = _take(torch.stack([r, -r, -self.smoothness * J / (S * S)], -1), eitem) * self.el[:, None]
        # (dj + cs·ga, cs·gb − dj) with dj = 2 d obj / d jump · (ga − gb), for a's rows then b's
        if unfused(F):
            # one component of ∇f at a time (on a CPU broadcasting over a dim of 2 and index_adds
            # of rows of 2 are several times slower; the same products and sums)
            dg = [qr * grad[..., 0], qr * grad[..., 1]]
            if self.smooth:
                cs, cj = c[:, None, :, 2], c[..., :2].transpose(1, 2)      # (K,1,E), (K,2,E)
                for k in range(2):
                    upd = cs * gg[..., k].view(K, 2, E) + cj * diff[:, None, :, k]
                    dg[k] = _add_cols(dg[k], self.ef_ab, upd.view(K, 2 * E))
            dFt = dFt + (self.G0 * dg[0][..., None] + self.G1 * dg[1][..., None])
        else:
            dgrad = qr[..., None] * grad                     # (K,T,2)
            if self.smooth:
                upd = (c[:, None, :, 2, None] * gg[..., :2].view(K, 2, E, 2)
                       + c[..., :2].transpose(1, 2)[..., None] * diff[:, None])
                dgrad = dgrad.index_add(1, self.ef_ab, upd.view(K, 2 * E, 2))
            dFt = dFt + (G * dgrad[..., None, :]).sum(-1)
        dF = torch.zeros_like(F).index_add_(1, faces.reshape(-1), dFt.reshape(K, -1))
        if self.cross:
            obj = obj + sums[..., 3]
            # a_0 = ℓ m_0/(m_0+m_1), a_1 = ℓ − a_0: d obj/d m_0 = (h_0 − h_1) ℓ m_1/Σ², h_k = −2 w over_k
            h = self.cw2 * (over[..., 1] - over[..., 0]) * cl / (msum * msum)
            # d obj/d F at both ends: (h m_1, −h m_0), times the signs
            dF = dF.index_add(1, self.ce.reshape(-1), ((h[..., None] * mf) * self.sgn_c).reshape(K, -1))
        # d e/d s = e where the clamp let s through (−60 < s < 60), 0 elsewhere: clamp's own
        # backward (where it zeroes, the product it replaces, · +0, had no other value but ±0)
        ds = torch.ops.aten.hardtanh_backward(dF * self.signs * e, s, -60.0, 60.0)
        return (obj[0], ds[0]) if one else (obj, ds)


_COMPILED: list = []


def _compiled_value_and_grad():
    """``torch.compile`` of :meth:`GeometryObjective.value_and_grad` (dynamic shapes: one
    compile serves every level and batch), made once; None where it cannot be made."""
    if not _COMPILED:
        try:
            _COMPILED.append(torch.compile(GeometryObjective.value_and_grad, dynamic=True))
        except Exception as exc:
            _COMPILED.append(None)
            warnings.warn(f"torch.compile is unavailable ({type(exc).__name__}: {exc}); the geometry "
                          "objective runs eagerly", RuntimeWarning, stacklevel=3)
    return _COMPILED[0]


def fit_geometry(mesh: MeshBatch, mom: TriangleMoments, signs: torch.Tensor, init_mag: torch.Tensor,
                 tol: torch.Tensor, cfg: GeometryConfig, data_dist: Optional[torch.Tensor] = None,
                 slack: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Fit the magnitudes of every item, each with its own L-BFGS (batch-independent).

    The per-item objective is ``Δ1 / tol² + smoothness · J`` where ``J`` (dimensionless) is the
    length-weighted squared jump of ``∇f`` across interior edges over its mean squared size:
    within the tolerance the smoother function wins, which removes zero-set spikes in
    triangles without data.

    ``Δ1`` only measures data-to-curve distances, so a zero set that runs far from every data
    point (a spike or notch toward a vertex whose magnitude collapsed, or whose neighbour's
    exploded) costs nothing. With ``crossing_weight > 0`` a curve-to-data term is added at the
    zero set's crossings of mesh edges: on an edge ``(i, j)`` whose signs differ, the crossing
    lies at ``a_i = ℓ |F_i| / (|F_i| + |F_j|)`` from ``v_i``, and by the triangle inequality its
    distance to the data is at least ``d_i − a_i`` (``d_i``: ``v_i``'s distance to the nearest
    data point). The term is the mean over crossings of ``max(0, d_i − a_i − slack)²`` (both
    ends), in the units of ``Δ1``: a dead zone of ``slack`` (the tolerance the item is tested
    at) leaves every curve within it alone, so it fires only where the curve is provably
    farther from the data than the test allows.

    Args:
        mom: triangle moments of the current partition. signs: ``(V,)`` ±1.
        init_mag: ``(V,)`` positive start. tol: ``(B,)`` tolerance per item (distance).
        data_dist: ``(V,)`` vertex distances to the data (inf: unknown, no term), see
        :func:`vertex_data_distance_near`. slack: ``(B,)`` dead zone (distance).
    Returns:
        values ``(V,)`` and Δ1 per item ``(B,)``.
    """
    obj = GeometryObjective(mesh, mom, signs, init_mag, tol, cfg, data_dist, slack)
    s = run_fit(obj, cfg)[0]
    with torch.no_grad():
        F = obj.values(s)
        d1 = segment_sum(obj.wt_raw * obj.delta1(F), obj.fi, mesh.num_items)
    return F, d1


def run_fit(obj: GeometryObjective, cfg: GeometryConfig, iterations: Optional[int] = None, rel_tol: float = 1e-7):
    """The batched L-BFGS of ``obj`` from its start (in the scaled variable where ``obj.pc`` is
    set): ``s (V,)``, the objectives ``(B,)`` and the iterations each item ran ``(B,)``. The
    fit runs in the variables that can move (:meth:`GeometryObjective.variables`)."""
    whole = obj
    obj, kv = whole.variables()
    pre = obj.pc is not None
    # a compiled objective is not recorded into CUDA graphs: a recompilation (a new working
    # set's shapes) cannot run inside a capture
    with graphs.use(False) if obj.compiled else contextlib.nullcontext():
        x, f, it = batched_lbfgs(obj._evaluate_pre if pre else obj._evaluate, obj.s0 / obj.pc if pre else obj.s0,
                                 obj.vi, obj.B, iterations=cfg.lbfgs_iterations if iterations is None else iterations,
                                 history=cfg.lbfgs_history, with_grad=True, rel_tol=rel_tol, stacked=True,
                                 trials=cfg.lbfgs_trials or (1 if obj.dev.type == "cpu" else 3),
                                 restrict=obj._restricted_pre if pre else obj._restricted)
    x = x * obj.pc if pre else x
    return (x if kv is None else whole.s0.index_copy(0, kv, x)), f, it


def estimate_values(ws: "WorkingSet", ev: "Evidence", cfg: GeometryConfig, slack: torch.Tensor
                    ) -> Tuple[torch.Tensor, torch.Tensor]:
    """The geometry stage: magnitudes fitted to the working set's points with its signs fixed,
    started at each vertex's distance to the data. ``slack (B,)``: the crossing term's dead
    zone (the tolerance each item is tested at). Returns values ``(V,)`` and Δ1 ``(B,)``."""
    with torch.no_grad():
        init_mag = vertex_data_distance(ws.mesh, ws.points, ws.face)
        near = vertex_data_distance_near(ws.mesh, ws.points, ws.face) if cfg.crossing_weight > 0 else None
    values, d1 = fit_geometry(ws.mesh, ev.moments, ws.signs, init_mag, ws.tol, cfg, data_dist=near, slack=slack)
    return values.detach(), d1
