"""Topological simplification of an annealed sign pattern by cluster moves on the same Ising
energy.

Annealing flips one vertex at a time. A channel of wrong signs two vertices wide across a
neck, a bridge of a few vertices between two close curves or a speck of several vertices is a
local minimum for single flips (each vertex alone agrees with its partner in the cluster),
however much the energy would drop if the cluster flipped as a whole. So after annealing,
candidate clusters are flipped whole when that lowers the energy ``Σ_e H_e F_i F_j``:

- sign regions (connected vertices of one sign, no pinned vertex): removing a speck, filling
  a small hole or cutting a sliver the data do not support;
- far clusters: connected vertices of one sign that are all farther from the data than the
  tolerance allows (their stars hold no data within reach). A channel through a stroke is
  connected to the outside through the vertices beside the walls, so it is no region of its
  own; its vertices inside the stroke, away from the walls, are such a cluster.

The energy change of flipping a cluster ``C`` is ``−2 Σ H_ij F_i F_j`` over the edges that leave
``C`` (edges inside it keep their product), so every cluster's change is one scatter-add.
Clusters of one sign and one family never share an edge (an edge between two of them would
have joined them), so they are flipped together and their changes add up; the families and
signs take turns, a fixed number of rounds. Every move lowers the energy, so the result is
never worse than the annealer's by the model's own measure.

Then the speck rule (:func:`open_signs`, :func:`open_stage`), which is not an energy move: a
sign region's depth (its deepest vertex's distance to the zero set) is the barrier of removing
it, the persistence of its extremum in distance units. A region shallower than a few
tolerances (or noise widths) is below what the data resolve: if one vertex of the other sign
separates it from another region of its sign (a tip cut off its body, an arm pinched off at
a sharp inner corner), that vertex joins them; otherwise it flips (a speck, a sliver hole).
Either way its loop goes; joining keeps its data on the curve.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import edge_components

if TYPE_CHECKING:
    from torch_isc.pipeline.signs import TopologyConfig
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["cluster_flip_change", "descend_clusters", "zero_set_distance", "ball_cover", "open_signs", "open_stage", "surrounded_regions"]


def cluster_flip_change(edges: torch.Tensor, H: torch.Tensor, signs: torch.Tensor, lab: torch.Tensor) -> torch.Tensor:
    """``(V,)`` indexed by label: the Ising energy change of flipping every vertex of that
    label's cluster (alone), ``−2 Σ H_ij F_i F_j`` over the edges with one end in it."""
    with torch.no_grad():
        a, b = edges[:, 0], edges[:, 1]
        cut = lab[a] != lab[b]
        t = -2.0 * H[cut] * signs[a[cut]] * signs[b[cut]]
        out = torch.zeros(signs.shape[0], dtype=H.dtype, device=H.device)
        return out.index_add_(0, lab[a[cut]], t).index_add_(0, lab[b[cut]], t)


def descend_clusters(mesh: MeshBatch, H: torch.Tensor, signs: torch.Tensor, pinned: torch.Tensor,
                     far: torch.Tensor, rounds: int) -> torch.Tensor:
    """``signs (V,)`` after ``rounds`` rounds of cluster moves (see the module): in each round,
    for the sign regions and then the far clusters (``far (V,)`` bool), first of the negative
    and then of the positive vertices, flip every cluster without a ``pinned`` vertex whose
    flip lowers the energy of the couplings ``H (E,)``."""
    with torch.no_grad():
        e = mesh.edges
        V = signs.shape[0]
        s = signs.clone()
        tiny = 1e-9 * H.abs().amax().clamp_min(torch.finfo(H.dtype).tiny) if H.numel() else 0.0
        for _ in range(int(rounds)):
            for use_far in (False, True):
                for sgn in (-1.0, 1.0):
                    mine = s == sgn
                    if use_far:
                        mine = mine & far
                    join = mine[e[:, 0]] & mine[e[:, 1]]
                    lab = edge_components(V, e, join)
                    dE = cluster_flip_change(e, H, s, lab)
                    blocked = torch.zeros(V, dtype=torch.bool, device=s.device).index_fill_(0, lab[pinned], True)
                    flip = mine & (dE[lab] < -tiny) & ~blocked[lab]
                    s = torch.where(flip, -s, s)
        return s


# ------------------------------------------------------------------- opening at the noise's scale
def zero_set_distance(mesh: MeshBatch, signs: torch.Tensor, cap: torch.Tensor, rounds: int) -> torch.Tensor:
    """``(V,)`` each vertex's distance to the zero set along paths of edges within its own sign
    region, capped at ``cap (V,)``: ``ℓ/2`` at the ends of an edge of length ``ℓ`` that changes
    sign (the crossing of equal magnitudes), then ``rounds`` rounds of ``d_v = min(d_v, d_u +
    |uv|)`` over the edges whose ends agree (a fixed count: no host read). A region with no
    sign change keeps ``cap``."""
    with torch.no_grad():
        e = mesh.edges
        v = mesh.verts.detach()
        a, b = e[:, 0], e[:, 1]
        ell = (v[a] - v[b]).norm(dim=1).to(cap.dtype)
        same = signs[a] == signs[b]
        half = torch.where(same, torch.full_like(ell, float("inf")), 0.5 * ell)
        d = cap.clone()
        d = d.scatter_reduce(0, a, half, "amin").scatter_reduce(0, b, half, "amin")
        w = torch.where(same, ell, torch.full_like(ell, float("inf")))
        for _ in range(int(rounds)):
            d = d.scatter_reduce(0, a, d[b] + w, "amin").scatter_reduce(0, b, d[a] + w, "amin")
        return torch.minimum(d, cap)


def ball_cover(mesh: MeshBatch, signs: torch.Tensor, depth: torch.Tensor, radius: torch.Tensor,
               rounds: int) -> torch.Tensor:
    """``(V,)`` bool: is the vertex inside a ball of radius at least ``radius (V,)`` that fits in
    its sign region? The balls are centred at the core vertices (``depth >= radius``) with
    radius ``depth``; the remaining radius ``q_v = max_c (depth_c − path(c, v))`` spreads along
    the edges whose ends agree for ``rounds`` rounds, and a vertex is covered where ``q_v >= 0``.
    The uncovered vertices are what a morphological opening of radius ``radius`` removes."""
    with torch.no_grad():
        e = mesh.edges
        v = mesh.verts.detach()
        a, b = e[:, 0], e[:, 1]
        ell = (v[a] - v[b]).norm(dim=1).to(depth.dtype)
        w = torch.where(signs[a] == signs[b], ell, torch.full_like(ell, float("inf")))
        q = torch.where(depth >= radius, depth, torch.full_like(depth, -float("inf")))
        for _ in range(int(rounds)):
            q = q.scatter_reduce(0, a, q[b] - w, "amax").scatter_reduce(0, b, q[a] - w, "amax")
        return q >= 0


def _specks(e: torch.Tensor, V: int, mine: torch.Tensor, cov: torch.Tensor, pinned: torch.Tensor) -> torch.Tensor:
    """``(V,)`` bool: the vertices of the regions of ``mine`` with no ``cov`` and no ``pinned`` vertex."""
    lab = edge_components(V, e, mine[e[:, 0]] & mine[e[:, 1]])
    z = torch.zeros(V, dtype=torch.long, device=mine.device)
    # scatters, not boolean indexing: no host read
    keep = z.scatter_reduce(0, lab, (mine & (cov | pinned)).long(), "amax") > 0
    return mine & ~keep[lab]


def _bridges(e: torch.Tensor, V: int, mine: torch.Tensor, speck: torch.Tensor, pinned: torch.Tensor) -> torch.Tensor:
    """``(V,)`` bool: the vertices not of ``mine`` (and not pinned) adjacent to a ``speck`` region
    and to another region of ``mine``."""
    lab = edge_components(V, e, mine[e[:, 0]] & mine[e[:, 1]])
    src = torch.cat([e[:, 0], e[:, 1]])
    dst = torch.cat([e[:, 1], e[:, 0]])
    into = mine[src] & ~mine[dst]
    big = torch.full((V,), V, dtype=lab.dtype, device=lab.device)
    lo = big.scatter_reduce(0, dst, torch.where(into, lab[src], V), "amin")
    hi = torch.full_like(big, -1).scatter_reduce(0, dst, torch.where(into, lab[src], -1), "amax")
    near = torch.zeros(V, dtype=torch.long, device=mine.device).scatter_reduce(
        0, dst, (into & speck[src]).long(), "amax") > 0
    return ~mine & ~pinned & near & (hi > lo) & (lo < V)


def surrounded_regions(mesh: MeshBatch, region: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                       sectors: int = 8, need: int = 5) -> torch.Tensor:
    """``(V,)`` bool: the vertices of ``region (V,)`` whose connected region (along edges whose
    ends are both in ``region``) has data all around it: the points in triangles incident to
    its vertices (``points (P, 2)``, ``face (P,)`` their triangles, −1 for none) occupy at least
    ``need`` of ``sectors`` equal angular sectors about the region's vertex centroid. A small
    closed curve sampled by its own points is surrounded; a sliver hole at an inner corner or
    a speck beside a stroke sees data on one or two sides only."""
    with torch.no_grad():
        V = region.shape[0]
        e = mesh.edges
        lab = edge_components(V, e, region[e[:, 0]] & region[e[:, 1]])
        v = mesh.verts.detach()
        w = region.to(v.dtype)
        cnt = torch.zeros(V, dtype=v.dtype, device=v.device).index_add_(0, lab, w)
        cen = torch.zeros(V, 2, dtype=v.dtype, device=v.device).index_add_(0, lab, v * w[:, None])
        cen = cen / cnt.clamp_min(1.0)[:, None]
        ok = face >= 0
        tri = mesh.faces[face.clamp_min(0)]                              # (P,3)
        pl = lab[tri]                                                    # (P,3) region of each corner
        use = region[tri] & ok[:, None]
        d = points.detach().to(v.dtype)[:, None, :] - cen[pl]
        ang = torch.atan2(d[..., 1], d[..., 0])
        sec = ((ang + torch.pi) * (sectors / (2 * torch.pi))).long().clamp(0, sectors - 1)
        occ = torch.zeros(V * sectors, dtype=torch.long, device=v.device).scatter_reduce(
            0, (pl * sectors + sec).reshape(-1), use.long().reshape(-1), "amax")
        return region & (occ.view(V, sectors).sum(1) >= need)[lab]


def open_signs(mesh: MeshBatch, signs: torch.Tensor, pinned: torch.Tensor, radius: torch.Tensor,
               rounds: int, whole_regions: bool = False, merge: bool = False,
               data: "tuple | None" = None) -> torch.Tensor:
    """``signs (V,)`` after a morphological opening of radius ``radius (V,)`` (per vertex, its
    item's), first of the negative and then of the positive vertices: a vertex that no ball of
    that radius inside its sign region covers (a speck, a bridge, a channel, a tip thinner
    than two radii) takes the other sign, unless ``pinned``. With ``whole_regions`` only the
    sign regions with no covered vertex at all (specks, small holes) flip; with ``merge`` too, a
    speck first joins another region of its sign across a vertex of the other sign next to both.

    The depth of a region (its deepest vertex's distance to the zero set) is the barrier of
    removing it: the change of a distance-like ``f`` that would make it vanish, the persistence
    of its extremum. A region, bridge or channel whose barrier is below the noise is noise.
    With ``data = (points (P, 2), face (P,))`` a speck that its data surround
    (:func:`surrounded_regions`: a small closed curve drawn by its own points) is kept: shallow
    is not noise when the data go all around it."""
    with torch.no_grad():
        s = signs.clone()
        e = mesh.edges
        V = s.shape[0]
        for sgn in (-1.0, 1.0):
            depth = zero_set_distance(mesh, s, 2.0 * radius, rounds)
            cov = ball_cover(mesh, s, depth, radius, rounds)
            mine = s == sgn
            if whole_regions:
                speck = _specks(e, V, mine, cov, pinned)
                if merge:
                    # a speck one vertex of the other sign away from another region of its sign
                    # (a tip cut off its body) joins it through that vertex: the topology is the
                    # same as without the speck, and the speck's data stay on the curve; two
                    # specks joined are still a speck
                    bridge = _bridges(e, V, mine, speck, pinned)
                    s = torch.where(bridge, -s, s)
                    mine = s == sgn
                    speck = _specks(e, V, mine, cov & ~bridge, pinned)
                if data is not None:
                    speck = speck & ~surrounded_regions(mesh, speck, data[0], data[1])
                flip = speck
            else:
                flip = mine & ~cov & ~pinned
            s = torch.where(flip, -s, s)
        return s


def open_stage(ws: "WorkingSet", signs: torch.Tensor, pinned: torch.Tensor, cfg: "TopologyConfig") -> torch.Tensor:
    """:func:`open_signs` of the working set's annealed ``signs`` with the ``open_*`` knobs of
    ``cfg``: the radius of an item is ``open_noise_widths`` noise widths or ``open_tolerances``
    tolerances, whichever is more."""
    mesh = ws.mesh
    r = torch.maximum(cfg.open_noise_widths * ws.noise, cfg.open_tolerances * ws.tol)
    data = (ws.points, ws.face) if cfg.open_keep_surrounded else None
    return open_signs(mesh, signs, pinned, r.to(signs.dtype)[mesh.vert_item], cfg.open_rounds,
                      cfg.open_whole_regions, cfg.open_merge, data)
