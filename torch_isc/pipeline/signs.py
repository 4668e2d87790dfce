"""EstimateTopology (Section 3.2): local line fits, edge weights, Ising model, annealing.

The 2×2 line fit is the only dimension-specific part; the Ising model on the mesh
graph, the colouring and the annealer work on any simplicial mesh's edge list.
"""
from __future__ import annotations

import warnings

from dataclasses import dataclass
from typing import Optional

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import hash_keys, hash_to_unit, mix32

__all__ = ["TriangleMoments", "triangle_moments", "pooled_moments", "line_fits", "crossing_reach", "edge_weights", "vertex_coloring",
           "anneal", "ising_energy", "sign_islands", "remove_small_islands"]


@dataclass
class TriangleMoments:
    """Per-triangle sums over the points inside it (eq. 3.2 and the line fit).

    Attributes:
        count: ``(T,)`` number of points. M: ``(T, 3, 3)`` mean of ``X_t(p) X_t(p)ᵀ``.
        centroid: ``(T, 2)`` mean point (triangle centroid where empty).
        scatter: ``(T, 2, 2)`` covariance of the points.
    """
    count: torch.Tensor
    M: torch.Tensor
    centroid: torch.Tensor
    scatter: torch.Tensor


def triangle_moments(mesh: MeshBatch, points: torch.Tensor, face: torch.Tensor, bary: torch.Tensor) -> TriangleMoments:
    """Scatter-add the moments of ``points (P, 2)`` located in ``face (P,)`` with ``bary (P, 3)``.

    Cost O(P); afterwards Δ1 costs O(T) per evaluation. Points with ``face < 0`` are ignored.
    """
    T = mesh.faces.shape[0]
    dt = mesh.dtype
    ok = face >= 0
    f, X = face[ok], bary[ok].to(dt)
    p = points[ok].to(dt)
    count = torch.zeros(T, dtype=dt, device=mesh.device).index_add_(0, f, torch.ones_like(f, dtype=dt))
    M = torch.zeros(T, 9, dtype=dt, device=mesh.device).index_add_(0, f, (X[:, :, None] * X[:, None, :]).reshape(-1, 9))
    # moments about the triangle centroid keep float32 accurate on small triangles
    tc = mesh.verts.detach()[mesh.faces].mean(1)
    q = p - tc[f]
    s1 = torch.zeros(T, 2, dtype=dt, device=mesh.device).index_add_(0, f, q)
    s2 = torch.zeros(T, 4, dtype=dt, device=mesh.device).index_add_(0, f, (q[:, :, None] * q[:, None, :]).reshape(-1, 4))
    n = count.clamp_min(1)
    mean = s1 / n[:, None]
    cov = s2.view(T, 2, 2) / n[:, None, None] - mean[:, :, None] * mean[:, None, :]
    return TriangleMoments(count, M.view(T, 3, 3) / n[:, None, None], tc + mean, cov)


def pooled_moments(mesh: MeshBatch, mom: TriangleMoments) -> TriangleMoments:
    """Moments of the points of each triangle and its (up to) three edge-neighbours.

    Combined exactly (parallel-axis rule on the per-triangle means and covariances), so
    small triangles keep their precision. ``M`` is not pooled (it is per-triangle)."""
    nb = mesh.face_neighbors
    T = nb.shape[0]
    idx = torch.cat([torch.arange(T, device=nb.device)[:, None], nb], 1)      # (T,4)
    ok = idx >= 0
    j = idx.clamp_min(0)
    n = torch.where(ok, mom.count[j], torch.zeros_like(mom.count[j]))      # (T,4)
    N = n.sum(1)
    m = mom.centroid[j]                                                     # (T,4,2)
    # offsets from the own centroid keep the sums small
    d = m - mom.centroid[:, None, :]
    mean_d = (n[..., None] * d).sum(1) / N.clamp_min(1)[:, None]
    dd = d - mean_d[:, None, :]
    C = (n[..., None, None] * (mom.scatter[j] + dd[..., :, None] * dd[..., None, :])).sum(1) / N.clamp_min(1)[:, None, None]
    return TriangleMoments(N, mom.M, mom.centroid + mean_d, C)


def line_fits(mesh: MeshBatch, mom: TriangleMoments):
    """Closed-form least-squares line in every triangle.

    Returns:
        L ``(T, 3)``: signed distances of the triangle's vertices to its line (the
        minimizer of ``Lᵀ M L / Lᵀ N L`` up to scale); eps ``(T,)``: mean squared distance
        of the points to the line (the local error of fit ``ε_t``); normal ``(T, 2)``.
    """
    lam, normal = mesh.kernel.hyperplane_fit(mom.scatter)
    tri = mesh.verts.detach()[mesh.faces]                    # (T,3,2)
    L = ((tri - mom.centroid[:, None, :]) * normal[:, None, :]).sum(-1)
    return L, lam, normal


def crossing_reach(mesh: MeshBatch, mom: TriangleMoments, L: torch.Tensor, normal: torch.Tensor,
                   slack: float = 1.0) -> torch.Tensor:
    """``(T, 3)`` bool: where the fitted line crosses edge ``k`` (corners k+1, k+2), is the
    crossing within the extent of the triangle's points along the line?

    Points spread along a segment of half-length ``h`` have variance ``h²/3`` along it, so
    the extent is ``h = √(3 λ_max)`` (plus ``slack ×`` the residual spread ``√ε``)."""
    lam_max, lam_min = mesh.kernel.principal_spread(mom.scatter)
    h = torch.sqrt(3.0 * lam_max)
    # the curve runs on about half a sample spacing (h / (n-1)) past the last point
    half = h * (1.0 + 1.0 / (mom.count - 1).clamp_min(1)) + slack * torch.sqrt(lam_min)
    tang = torch.stack([-normal[:, 1], normal[:, 0]], 1)
    x, _ = mesh.kernel.edge_crossings(mesh.verts.detach()[mesh.faces], L)     # (T,3,2)
    u = ((x - mom.centroid[:, None, :]) * tang[:, None, :]).sum(-1)
    return u.abs() <= half[:, None]


def edge_weights(mesh: MeshBatch, L: torch.Tensor, eps: torch.Tensor, count: torch.Tensor,
                 min_points: int, empty_weight: float, pooled_count: Optional[torch.Tensor] = None,
                 reach: Optional[torch.Tensor] = None, noise2: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Edge weights ``H_e`` of eq. 3.6 (``(E,)``).

    Triangles whose fit rests on ``min_points`` or more points contribute
    ``w_t = (ε_max−ε_t)/(ε_max−ε_min)`` (extremes per item). A fit on fewer points is not
    meaningful: such a triangle gives no evidence, unless it is empty, in which case it
    contributes ``L = (1,1,1)`` with ``empty_weight``. With ``pooled_count`` (the points
    behind pooled fits, see :func:`pooled_moments`), ``L, eps`` are the pooled fits and a
    triangle counts as empty only when its neighbourhood is empty too. ``reach`` ``(T, 3)``
    (see :func:`crossing_reach`) drops the crossing evidence of edge ``k`` where the line
    crosses it outside the extent of its points.
    """
    dt = L.dtype
    B = mesh.num_items
    support = count if pooled_count is None else pooled_count
    fit = support >= min_points
    empty = (count == 0) & ~fit
    fi = mesh.face_item
    big = torch.finfo(dt).max
    emax = torch.full((B,), -big, dtype=dt, device=L.device).scatter_reduce(0, fi[fit], eps[fit], "amax")
    emin = torch.full((B,), big, dtype=dt, device=L.device).scatter_reduce(0, fi[fit], eps[fit], "amin")
    if noise2 is not None:
        # fits within the noise are all equally good: dense noisy data would otherwise spread
        # tiny differences of near-noise errors over the whole range [0, 1]
        emin = torch.maximum(emin, noise2.to(dt))
    span = (emax - emin)[fi]
    w = torch.where(span > 0, (emax[fi] - eps) / span.clamp_min(torch.finfo(dt).tiny), torch.ones_like(eps)).clamp(0, 1)
    w = torch.where(fit, w, torch.zeros_like(w))
    w = torch.where(empty, torch.full_like(w, float(empty_weight)), w)
    sig = torch.where(empty[:, None], torch.ones_like(L), torch.where(L >= 0, 1.0, -1.0).to(dt))
    ea, eb = mesh.kernel.edge_corners
    prod = sig[:, ea] * sig[:, eb]
    if reach is not None:
        # a line testifies to a crossing only where its points are, not where it is extrapolated
        prod = torch.where((prod < 0) & ~reach, torch.zeros_like(prod), prod)
    H = torch.zeros(mesh.edges.shape[0], dtype=dt, device=L.device)
    H.index_add_(0, mesh.face_edges.reshape(-1), (-prod * w[:, None]).reshape(-1))
    return H


# ------------------------------------------------------------------- Ising model
def vertex_coloring(mesh: MeshBatch, active: Optional[torch.Tensor] = None, max_colors: int = 64) -> torch.Tensor:
    """Greedy colouring (Jones–Plassmann with hashed priorities): adjacent vertices get
    different colours; ``-1`` for inactive vertices. Depends only on each item's own mesh."""
    with torch.no_grad():
        V = mesh.verts.shape[0]
        dev = mesh.device
        local = torch.arange(V, device=dev) - mesh.verts_first_idx[mesh.vert_item]
        prio = mix32(local * 2654435761 + 12345) * V + local        # unique within an item
        color = torch.full((V,), -1, dtype=torch.long, device=dev)
        todo = torch.ones(V, dtype=torch.bool, device=dev) if active is None else active.clone()
        e = mesh.edges
        src = torch.cat([e[:, 0], e[:, 1]])
        dst = torch.cat([e[:, 1], e[:, 0]])
        while bool(todo.any()):
            pr = torch.where(todo, prio, torch.full_like(prio, -1))
            nmax = torch.full((V,), -1, dtype=torch.long, device=dev).scatter_reduce(0, dst, pr[src], "amax")
            pick = todo & (prio > nmax)
            used = torch.zeros(V, max_colors + 1, dtype=torch.bool, device=dev)
            cs = color[src]
            has = cs >= 0
            used[dst[has], cs[has]] = True
            free = torch.argmax((~used).to(torch.int8), 1)
            color[pick] = free[pick]
            todo &= ~pick
        return color


def _coupling_rows(mesh: MeshBatch, H: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Sparse CSR ``(len(rows), V)`` matrix of the couplings ``H_e`` between each vertex of
    ``rows`` and its neighbours, so that the local fields of those vertices are one sparse
    product ``W @ signs`` (a gather-multiply-sum over padded neighbour lists costs ~10x more)."""
    first, nbrs = mesh.vert_neighbors
    V = mesh.verts.shape[0]
    deg = first[rows + 1] - first[rows]
    crow = torch.zeros(rows.shape[0] + 1, dtype=torch.long, device=H.device)
    crow[1:] = torch.cumsum(deg, 0)
    owner = torch.repeat_interleave(rows, deg)
    slot = torch.arange(int(crow[-1]), device=H.device) - torch.repeat_interleave(crow[:-1], deg)
    col = nbrs[first[owner] + slot]                  # ascending within a row (CSR adjacency is sorted)
    lo, hi = torch.minimum(owner, col), torch.maximum(owner, col)
    eid = torch.searchsorted(mesh.edges[:, 0] * V + mesh.edges[:, 1], lo * V + hi)
    with warnings.catch_warnings():                  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore")
        return torch.sparse_csr_tensor(crow, col, H[eid], size=(rows.shape[0], V))


def ising_energy(mesh: MeshBatch, H: torch.Tensor, signs: torch.Tensor) -> torch.Tensor:
    """``Σ_e H_e F_i F_j`` per item; ``signs (V,)`` or ``(V, R)`` -> ``(B,)`` or ``(B, R)``."""
    e = mesh.edges
    s = signs if signs.dim() == 2 else signs[:, None]
    t = H[:, None] * s[e[:, 0]] * s[e[:, 1]]
    out = torch.zeros(mesh.num_items, s.shape[1], dtype=H.dtype, device=H.device).index_add_(0, mesh.edge_item, t)
    return out if signs.dim() == 2 else out[:, 0]


def anneal(mesh: MeshBatch, H: torch.Tensor, init: torch.Tensor, fixed: torch.Tensor, sweeps: int,
           t_start: float, t_end: float, replicas: int = 4, seed: int = 0, greedy_sweeps: int = 4,
           warm_t_start: Optional[float] = None) -> torch.Tensor:
    """Minimize the Ising energy ``Σ_e H_e F_i F_j`` over ``F ∈ {−1, 1}`` by simulated annealing.

    Vertices of one colour are never adjacent, so each colour class is updated in parallel
    (Metropolis) for the whole batch and all ``replicas`` at once. Temperatures fall
    geometrically from ``t_start`` to ``t_end``; a few zero-temperature sweeps finish, and the
    replica of lowest energy is kept per item (ties to the lowest replica).

    With ``warm_t_start``, replica 0 starts from ``init`` at that (low) temperature, keeping
    what earlier levels found, while the other replicas start from +1 at ``t_start``: a
    cluster of wrong signs that single flips at low temperature cannot undo is redone.

    Args:
        init: ``(V,)`` ±1 start. fixed: ``(V,)`` bool, vertices held at their ``init`` value.
    Returns:
        ``(V,)`` ±1 signs (dtype of ``H``).
    """
    with torch.no_grad():
        dev, dt = H.device, H.dtype
        V = mesh.verts.shape[0]
        R = max(int(replicas), 1)
        color = vertex_coloring(mesh, ~fixed)
        ncol = int(color.max()) + 1 if V and (color >= 0).any() else 0
        groups = [(color == c).nonzero().squeeze(1) for c in range(ncol)]
        s = init.to(dt)[:, None].repeat(1, R)
        t0 = torch.full((R,), float(t_start), dtype=dt, device=dev)
        if warm_t_start is not None:
            s[:, 1:] = torch.where(fixed, init.to(dt), torch.ones_like(init, dtype=dt))[:, None]
            t0[0] = min(float(warm_t_start), float(t_start))
        local = torch.arange(V, device=dev) - mesh.verts_first_idx[mesh.vert_item]
        rep = torch.arange(R, device=dev)
        total = int(sweeps) + int(greedy_sweeps)
        ratio = (t_end / t0) ** (1.0 / max(int(sweeps) - 1, 1))
        # per colour class, gathered once: neighbour weights, neighbour ids, and the hash of
        # the keys that do not change between sweeps (seed, local vertex, replica)
        prep = []
        for g in groups:
            if g.numel() == 0:
                continue
            n = g.shape[0]
            h0 = hash_keys(torch.zeros(n, R, dtype=torch.long, device=dev), torch.full((n, R), int(seed), device=dev),
                            local[g][:, None].expand(-1, R), rep[None, :].expand(n, -1))
            prep.append((g, _coupling_rows(mesh, H, g), h0))
        # the random numbers of a block of sweeps are hashed in one op per colour (the
        # block bounds the memory: about 2**22 numbers at a time)
        block = max(1, min(int(sweeps), (1 << 22) // max(V * R, 1)))
        temps = [t0 * ratio ** k for k in range(int(sweeps))]
        uniforms: list = []
        for k in range(total):
            if k < sweeps and k % block == 0:
                ks = torch.arange(k, min(k + block, int(sweeps)), device=dev) * 64
                # Metropolis: accept when u < exp(-dE / T), i.e. dE < -T log u (a threshold >= 0)
                tk = torch.stack(temps[k:k + ks.shape[0]])[:, None, :]
                uniforms = [-tk * torch.log(hash_to_unit(hash_keys(h0[None], (ks + c)[:, None, None].expand(
                    -1, *h0.shape)), dt)) for c, (_, _, h0) in enumerate(prep)]
            for c, (g, W, h0) in enumerate(prep):
                sg = s[g]
                dE = -2.0 * sg * (W @ s)                           # energy change of a flip (local field)
                acc = dE < (uniforms[c][k % block] if k < sweeps else 0.0)
                s[g] = torch.where(acc, -sg, sg)
        E = ising_energy(mesh, H, s)                              # (B, R)
        best = torch.argmin(E, 1)                                 # first minimum
        return s.gather(1, best[mesh.vert_item][:, None]).squeeze(1)


def sign_islands(mesh: MeshBatch, signs: torch.Tensor) -> torch.Tensor:
    """``(V,)`` long: a label per vertex, equal for vertices joined by a path of edges whose
    ends have the same sign (the label is the smallest vertex index of the region). Label
    propagation with pointer jumping: a few tensor ops per round, rounds ~ log of the regions'
    diameters in practice."""
    with torch.no_grad():
        V = signs.shape[0]
        e = mesh.edges
        same = (signs[e[:, 0]] < 0) == (signs[e[:, 1]] < 0)
        a, b = e[same, 0], e[same, 1]
        lab = torch.arange(V, device=signs.device)
        while True:
            m = torch.minimum(lab[a], lab[b])
            new = lab.scatter_reduce(0, a, m, "amin").scatter_reduce(0, b, m, "amin")
            new = new[new]                                 # pointer jumping
            if torch.equal(new, lab):
                return lab
            lab = new


def remove_small_islands(mesh: MeshBatch, signs: torch.Tensor, keep: torch.Tensor, min_vertices: int) -> torch.Tensor:
    """Flip every sign region of fewer than ``min_vertices`` vertices that holds no ``keep``
    vertex (the reconstruction passes the fixed boundary). A region that small is below the
    mesh's resolution: the zero set around a single vertex is a loop within its star (a
    pinched-off wedge tip, a speck around an outlier), which the data cannot place. Where the
    data do hold a feature, the test still finds its points far from the curve and refines,
    and the next level anneals it with more vertices; a feature the refinement stops short of
    (fewer than ``min_points_fit`` points, or the size floor) is lost.
    """
    if min_vertices <= 1:
        return signs
    with torch.no_grad():
        lab = sign_islands(mesh, signs)
        size = torch.bincount(lab, minlength=signs.shape[0])
        pinned = torch.zeros_like(size, dtype=torch.bool).index_fill_(0, lab[keep], True)
        flip = (size[lab] < min_vertices) & ~pinned[lab]
        return torch.where(flip, -signs, signs)
