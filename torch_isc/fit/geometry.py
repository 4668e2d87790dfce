"""EstimateGeometry (Section 3.1): minimize Δ1 over the magnitudes, signs held fixed.

``F = σ ⊙ (exp(s) + floor)``: no value can change sign or reach 0, and ``floor`` (a
fraction of the item's mean starting magnitude) keeps magnitudes from collapsing toward
0, which would pull the zero set into spikes toward those vertices. ``M_t`` is assembled
once per partition, so an evaluation costs O(triangles), independent of the points.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from ..mesh import MeshBatch
from .optim import batched_lbfgs
from .topology import TriangleMoments

__all__ = ["delta1_per_triangle", "vertex_data_distance", "vertex_data_distance_near", "fit_geometry",
           "point_residuals"]


def _grad_norm2(mesh: MeshBatch, values: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    # |G_tᵀ F_t|² computed directly: as a quadratic form it can round below zero
    grad = (G * values[mesh.faces][..., None]).sum(1)
    return (grad * grad).sum(1), grad


def delta1_per_triangle(mesh: MeshBatch, M: torch.Tensor, values: torch.Tensor, G: torch.Tensor = None,
                        guard: float = 0.0) -> torch.Tensor:
    """``(T,)`` mean over the triangle's points of ``f(p)² / |∇f_t|²`` (``F_tᵀM_tF_t / |∇f_t|²``)."""
    G = mesh.bary_gradients() if G is None else G
    Ft = values[mesh.faces]
    num = torch.einsum("ti,tij,tj->t", Ft, M, Ft)
    g2, _ = _grad_norm2(mesh, values, G)
    return num / (g2 + guard)


def _located(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor):
    """``(V, verts, points, faces)``: the vertex count, the detached vertices, and the points
    that have a triangle (in the mesh's dtype) with their triangles."""
    v = mesh.verts.detach()
    ok = face >= 0
    return v.shape[0], v, points[ok].to(v.dtype), face[ok]


def vertex_data_distance(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor, max_hops: int = 256) -> torch.Tensor:
    """``(V,)`` an upper bound of each vertex's distance to the nearest data point of its item.

    Exact-ish near the data (points of the incident triangles), then relaxed along mesh
    edges (Bellman–Ford on the edge graph) for the vertices of empty regions.
    """
    with torch.no_grad():
        V, v, p, f = _located(mesh, points, face)
        dt = v.dtype
        vid = mesh.faces[f]                                   # (P,3)
        dist = (v[vid] - p[:, None, :]).norm(dim=2)
        d = torch.full((V,), float("inf"), dtype=dt, device=v.device)
        d = d.scatter_reduce(0, vid.reshape(-1), dist.reshape(-1), "amin")
        e = mesh.edges
        el = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
        src = torch.cat([e[:, 0], e[:, 1]])
        dst = torch.cat([e[:, 1], e[:, 0]])
        w = torch.cat([el, el])
        for _ in range(max_hops):
            nd = d.scatter_reduce(0, dst, d[src] + w, "amin")
            if torch.equal(nd, d):
                break
            d = nd
        # an item with no located point at all: unit magnitudes
        return torch.where(torch.isfinite(d), d, torch.ones_like(d))


def vertex_data_distance_near(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
    """``(V,)`` each vertex's distance to the nearest data point located in its star or in a
    triangle edge-adjacent to its star (inf where there is none).

    Unlike :func:`vertex_data_distance` it is never relaxed along mesh edges, so where it is
    finite it is the true nearest distance unless a nearer point lies farther out than the
    star's edge-neighbours (rare: the triangle there would separate them)."""
    with torch.no_grad():
        V, v, p, f = _located(mesh, points, face)
        dt = v.dtype
        nb = mesh.face_neighbors[f]                            # (P,3)
        tri = torch.cat([f[:, None], nb], 1)                   # (P,4)
        has = tri >= 0
        vid = mesh.faces[tri.clamp_min(0)].reshape(p.shape[0], 12)
        dist = (v[vid] - p[:, None, :]).norm(dim=2)
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


def fit_geometry(mesh: MeshBatch, mom: TriangleMoments, signs: torch.Tensor, init_mag: torch.Tensor,
                 tol: torch.Tensor, iterations: int, history: int, magnitude_floor: float,
                 smoothness: float, data_dist: Optional[torch.Tensor] = None,
                 slack: Optional[torch.Tensor] = None, crossing_weight: float = 0.0
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
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
    B = mesh.num_items
    vi, fi = mesh.vert_item, mesh.face_item
    dt = mesh.dtype
    with torch.no_grad():
        G = mesh.bary_gradients()
        nb = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(0, fi, mom.count)
        wt = mom.count / nb[fi].clamp_min(1)
        nv = torch.bincount(vi, minlength=B).to(dt)
        mean_mag = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(0, vi, init_mag) / nv.clamp_min(1)
        floor = (magnitude_floor * mean_mag)[vi]
        s0 = torch.log((init_mag - floor).clamp_min(1e-3 * mean_mag[vi]).clamp_min(torch.finfo(dt).tiny))
        # penalize gradient jumps in the band where the curve can be: edges next to data or
        # to a sign change (elsewhere f is far from 0 and its kinks do not move the curve)
        fneg = signs[mesh.faces] < 0
        band_t = (mom.count > 0) | (fneg.any(1) & ~fneg.all(1))
        interior = ~mesh.is_boundary_edge
        ef_all = mesh.edge_faces.clamp_min(0)
        interior = interior & (band_t[ef_all[:, 0]] | band_t[ef_all[:, 1]])
        ef = mesh.edge_faces[interior]
        e = mesh.edges[interior]
        el = (mesh.verts.detach()[e[:, 0]] - mesh.verts.detach()[e[:, 1]]).norm(dim=1)
        eitem = mesh.edge_item[interior]
        guard = (1e-10 * mean_mag) ** 2
        inv_tol2 = 1.0 / (tol * tol)
        cross = crossing_weight > 0 and data_dist is not None and slack is not None
        if cross:
            ce = mesh.edges[signs[mesh.edges[:, 0]] != signs[mesh.edges[:, 1]]]
            c_item = mesh.vert_item[ce[:, 0]]
            c_len = (mesh.verts.detach()[ce[:, 0]] - mesh.verts.detach()[ce[:, 1]]).norm(dim=1)
            # how close to each end the crossing may come before it is provably off the data
            c_lim = (data_dist[ce] - slack[c_item][:, None]).clamp_min(0)
            c_lim = torch.where(torch.isfinite(c_lim), c_lim, torch.zeros_like(c_lim))
            n_cross = torch.bincount(c_item, minlength=B).to(dt)
            c_w = crossing_weight / n_cross.clamp_min(1)[c_item]

    def values_of(s):
        return signs * (torch.exp(s.clamp(-60.0, 60.0)) + floor)

    T = mesh.faces.shape[0]
    guard_t = guard[fi]

    def objective(s, items=None):
        F = values_of(s)
        if items is None:
            es, efs = None, ef
            faces, Gs, Ms, fis, wts, gds = mesh.faces, G, mom.M, fi, wt, guard_t
        else:                                   # only the faces and edges of these items
            fs = items[fi].nonzero().squeeze(1)
            es = items[eitem].nonzero().squeeze(1)
            remap = torch.full((T,), -1, dtype=torch.long, device=mesh.device)
            remap[fs] = torch.arange(fs.shape[0], device=mesh.device)
            efs = remap[ef[es]]
            faces, Gs, Ms, fis, wts, gds = mesh.faces[fs], G[fs], mom.M[fs], fi[fs], wt[fs], guard_t[fs]
        Ft = F[faces]
        grad = (Gs * Ft[..., None]).sum(1)             # (T,2)
        g2 = (grad * grad).sum(1)
        num = ((Ft[:, :, None] * Ms).sum(1) * Ft).sum(1)    # Ft' M Ft
        d1 = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(0, fis, wts * num / (g2 + gds))
        obj = d1 * inv_tol2
        if cross and ce.shape[0]:
            if items is None:
                ci, cl, clim, cw, cit = ce, c_len, c_lim, c_w, c_item
            else:
                cs = items[c_item].nonzero().squeeze(1)
                ci, cl, clim, cw, cit = ce[cs], c_len[cs], c_lim[cs], c_w[cs], c_item[cs]
            m = F[ci].abs()
            a = cl[:, None] * m / m.sum(1, keepdim=True)
            over = (clim - a).clamp_min(0)
            pen = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(0, cit, cw * (over * over).sum(1))
            obj = obj + pen * inv_tol2
        if smoothness > 0 and efs.shape[0]:
            jump = ((grad[efs[:, 0]] - grad[efs[:, 1]]) ** 2).sum(1)
            size = 0.5 * (g2[efs[:, 0]] + g2[efs[:, 1]])
            ei, w = (eitem, el) if es is None else (eitem[es], el[es])
            J = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(0, ei, w * jump)
            S = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(0, ei, w * size)
            obj = obj + smoothness * J / S.clamp_min(torch.finfo(dt).tiny)
        return obj

    s, _, _ = batched_lbfgs(objective, s0, vi, B, iterations=iterations, history=history, masked=True)
    with torch.no_grad():
        F = values_of(s)
        d1 = torch.zeros(B, dtype=dt, device=mesh.device).index_add_(
            0, fi, wt * delta1_per_triangle(mesh, mom.M, F, G, guard[fi]))
    return F, d1
