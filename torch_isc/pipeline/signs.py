"""EstimateTopology (Section 3.2): the vertex signs, from the Ising model of the line
evidence (edge weights of eq. 3.6, simulated annealing), or from an inside/outside oracle.

Dimension-free: the edge weights read the line fits through the mesh's kernel, and the
Ising model, the colouring and the annealer work on any simplicial mesh's edge list.
"""
from __future__ import annotations

import warnings

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Optional, Protocol, Sequence, Union

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.points import PointSetError
from torch_isc.core.segments import first_index, hash_keys, hash_to_unit, mix32, segment_max, segment_min
from torch_isc.pipeline.knobs import check_section, knob

if TYPE_CHECKING:
    from torch_isc.pipeline.evidence import Evidence, EvidenceConfig
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["TopologyConfig", "edge_weights", "vertex_coloring", "anneal", "ising_energy", "sign_islands",
           "remove_small_islands", "SignSource", "IsingSigns", "OracleSigns", "SignOracleError"]


@dataclass
class TopologyConfig:
    """The Ising estimate of the signs (flat keys of configs/default.yaml)."""
    #: confidence of an empty triangle, L = (1, 1, 1): "no curve crosses here"
    empty_weight: float = knob(1.0, ge=0)
    anneal_sweeps: int = knob(120, gt=0)
    anneal_t_start: float = knob(3.0, gt=0)
    anneal_t_end: float = knob(0.02, gt=0)
    #: start temperature at finer levels, warm-started from the previous signs
    anneal_warm_t_start: float = knob(0.3, gt=0)
    anneal_replicas: int = knob(4, gt=0)
    #: zero-temperature sweeps after the schedule
    anneal_greedy_sweeps: int = knob(4, ge=0)
    #: sign regions of fewer vertices (and no boundary vertex) are flipped; 0 or 1 disables
    min_island_vertices: int = knob(2, ge=0)
    #: coupling toward equal signs on an edge provably farther from the data than the tolerance
    #: allows (pipeline/support.py); 0 disables (the default: measured +1 of 192 on the broad
    #: suite beside the cluster moves, but it opened a loop inside a figure of data/family)
    unsupported_weight: float = knob(0.0, ge=0)
    #: ...the distance it starts at, in noise widths (never below the tolerance); the cluster
    #: moves' far vertices are those beyond it
    unsupported_noise_widths: float = knob(3.0, ge=0)
    #: rounds of cluster moves after annealing (pipeline/simplify.py); 0 disables
    cluster_rounds: int = knob(2, ge=0)

    def __post_init__(self):
        check_section(self)


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
    emax = segment_max(eps[fit], fi[fit], B, fill=-big)
    emin = segment_min(eps[fit], fi[fit], B, fill=big)
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
            nmax = segment_max(pr[src], dst, V, fill=-1)
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


def anneal(mesh: MeshBatch, H: torch.Tensor, init: torch.Tensor, fixed: torch.Tensor,
           cfg: Optional[TopologyConfig] = None, seed: int = 0, warm: bool = False) -> torch.Tensor:
    """Minimize the Ising energy ``Σ_e H_e F_i F_j`` over ``F ∈ {−1, 1}`` by simulated annealing.

    Vertices of one colour are never adjacent, so each colour class is updated in parallel
    (Metropolis) for the whole batch and all ``cfg.anneal_replicas`` at once. Temperatures fall
    geometrically from ``anneal_t_start`` to ``anneal_t_end`` over ``anneal_sweeps``; a few
    zero-temperature sweeps finish, and the replica of lowest energy is kept per item (ties to
    the lowest replica).

    With ``warm``, replica 0 starts from ``init`` at ``anneal_warm_t_start``, keeping
    what earlier levels found, while the other replicas start from +1 at ``t_start``: a
    cluster of wrong signs that single flips at low temperature cannot undo is redone.

    Args:
        init: ``(V,)`` ±1 start. fixed: ``(V,)`` bool, vertices held at their ``init`` value.
    Returns:
        ``(V,)`` ±1 signs (dtype of ``H``).
    """
    cfg = TopologyConfig() if cfg is None else cfg
    sweeps, t_start, t_end = cfg.anneal_sweeps, cfg.anneal_t_start, cfg.anneal_t_end
    greedy_sweeps = cfg.anneal_greedy_sweeps
    warm_t_start = cfg.anneal_warm_t_start if warm else None
    with torch.no_grad():
        dev, dt = H.device, H.dtype
        V = mesh.verts.shape[0]
        R = max(int(cfg.anneal_replicas), 1)
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


# ------------------------------------------------------------------- where signs come from
class SignSource(Protocol):
    """Where the vertex signs of a level come from (Section 3.2): estimated from the data
    (:class:`IsingSigns`) or read from an inside/outside oracle (:class:`OracleSigns`)."""

    def signs(self, ws: "WorkingSet", ev: "Evidence", level: int) -> torch.Tensor:
        """``(V,)`` ±1 signs of the working set's vertices."""
        ...

    def marks(self, ws: "WorkingSet", values: torch.Tensor, min_len: torch.Tensor) -> Optional[torch.Tensor]:
        """``(T,)`` bool, triangles the source wants split beyond the test (or None)."""
        ...


class IsingSigns:
    """Signs that minimize the Ising energy of the line evidence (eqs. 3.5-3.6), annealed;
    sign regions below the mesh's resolution are then flipped.

    Args:
        topology: the annealing and island settings. evidence: the line-fit settings. seed:
            the annealing's random seed.
    """

    def __init__(self, topology: TopologyConfig, evidence: "EvidenceConfig", seed: int = 0):
        self.cfg, self.evidence, self.seed = topology, evidence, seed

    def signs(self, ws: "WorkingSet", ev: "Evidence", level: int) -> torch.Tensor:
        from torch_isc.pipeline.evidence import local_fits
        with torch.no_grad():
            mesh = ws.mesh
            fits = local_fits(mesh, ev.moments, ev.fits, self.evidence)
            H = edge_weights(mesh, fits.L, fits.eps, ev.moments.count, self.evidence.min_points_fit,
                             self.cfg.empty_weight, pooled_count=fits.support, reach=fits.reach,
                             noise2=ws.noise ** 2)
            far = None
            if self.cfg.unsupported_weight > 0 or self.cfg.cluster_rounds > 0:
                from torch_isc.pipeline.support import support_coupling
                cpl, far = support_coupling(ws, self.cfg.unsupported_weight, self.cfg.unsupported_noise_widths)
                H = H + cpl
            fixed = mesh.is_boundary_vert
            init = torch.where(fixed, torch.ones_like(ws.signs), ws.signs)
            s = anneal(mesh, H, init, fixed, self.cfg, self.seed, warm=level > 0)
            if self.cfg.cluster_rounds > 0:
                from torch_isc.pipeline.simplify import descend_clusters
                s = descend_clusters(mesh, H, s, fixed, far, self.cfg.cluster_rounds)
            return remove_small_islands(mesh, s, fixed, self.cfg.min_island_vertices)

    def marks(self, ws: "WorkingSet", values: torch.Tensor, min_len: torch.Tensor) -> Optional[torch.Tensor]:
        return None


class OracleSigns:
    """Signs read from inside/outside oracles, asked in the caller's coordinates; boundary
    vertices are outside. The oracle also marks triangles next to an interior edge (longer
    than ``min_len`` of its item) at whose midpoint it and the piecewise-linear function
    disagree: vertex signs alone cannot see a thin stroke or a gap passing between vertices.

    Args:
        oracles: one callable per caller's item, ``oracle(points (M, 2)) -> (M,)`` bool (True
            inside), or one batched callable ``oracle(points (M, 2), item (M,)) -> (M,)``.
    """

    def __init__(self, oracles: Union[Callable, Sequence[Optional[Callable]]]):
        self.oracles = oracles

    def inside(self, ws: "WorkingSet", x: torch.Tensor, item: torch.Tensor) -> torch.Tensor:
        """``(M,)`` bool at normalized points ``x (M, 2)`` of working items ``item (M,)``
        (non-decreasing)."""
        b = ws.items[item]
        xc = ws.caller_points(x, item)
        if callable(self.oracles):                                  # batched: one call for all items
            inside = torch.as_tensor(self.oracles(xc, b), device=x.device).bool().reshape(-1)
            if inside.shape[0] != xc.shape[0]:
                raise SignOracleError(f"sign oracle returned {inside.shape[0]} values for {xc.shape[0]} points")
            return inside
        out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        counts = torch.bincount(item, minlength=ws.num_items)
        starts = first_index(counts).tolist()
        for b, s0, n in zip(ws.items.tolist(), starts, counts.tolist()):   # one call per item
            o = self.oracles[b]
            if o is None:
                raise SignOracleError(f"item {b}: sign oracles must be given for every item or none")
            if n:
                got = torch.as_tensor(o(xc[s0:s0 + n]), device=x.device).bool().reshape(-1)
                if got.shape[0] != n:
                    raise SignOracleError(f"item {b}: sign oracle returned {got.shape[0]} values for {n} points")
                out[s0:s0 + n] = got
        return out

    def signs(self, ws: "WorkingSet", ev: "Evidence", level: int) -> torch.Tensor:
        mesh = ws.mesh
        inside = self.inside(ws, mesh.verts, mesh.vert_item)
        out = torch.where(inside, -1.0, 1.0).to(ws.dtype)
        out[mesh.is_boundary_vert] = 1.0
        return out

    def marks(self, ws: "WorkingSet", values: torch.Tensor, min_len: torch.Tensor) -> Optional[torch.Tensor]:
        mesh = ws.mesh
        e = mesh.edges
        v = mesh.verts.detach()
        inside = self.inside(ws, 0.5 * (v[e[:, 0]] + v[e[:, 1]]), mesh.edge_item)
        pl_inside = (values[e[:, 0]] + values[e[:, 1]]) < 0
        long = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1) > min_len[mesh.edge_item]
        bad = (inside != pl_inside) & long & ~mesh.is_boundary_edge
        out = torch.zeros(mesh.faces.shape[0], dtype=torch.bool, device=v.device)
        ef = mesh.edge_faces[bad].reshape(-1)
        out[ef[ef >= 0]] = True
        return out


class SignOracleError(PointSetError):
    """A sign oracle that answered with the wrong number of values, or was missing."""
