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

Last, the enclosure rule (:func:`enclosed_vertices`, :func:`enclose_stage`), the converse: a
vertex with no curve in its star that a closed ring of unexplained points goes all the way
round (a satellite of 7-9 points, which line fits cannot describe) takes the other sign.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import segment_median, edge_components
from torch_isc.pipeline import budget, graphs

if TYPE_CHECKING:
    from torch_isc.pipeline.signs import TopologyConfig
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["cluster_flip_change", "descend_clusters", "zero_set_distance", "ball_cover", "open_signs", "open_stage", "surrounded_regions", "occupied_sectors",
           "enclosed_vertices", "enclose_stage"]


def cluster_flip_change(edges: torch.Tensor, H: torch.Tensor, signs: torch.Tensor, lab: torch.Tensor) -> torch.Tensor:
    """``(V,)`` indexed by label: the Ising energy change of flipping every vertex of that
    label's cluster (alone), ``−2 Σ H_ij F_i F_j`` over the edges with one end in it."""
    with torch.no_grad():
        a, b = edges[:, 0], edges[:, 1]
        la, lb = lab[a], lab[b]
        # every edge, the uncut ones adding +0 (the same sums, in the same order): no mask
        # indexing, so no host read
        t = torch.where(la != lb, -2.0 * H * signs[a] * signs[b], torch.zeros((), dtype=H.dtype, device=H.device))
        out = torch.zeros(signs.shape[0], dtype=H.dtype, device=H.device)
        return out.index_add_(0, la, t).index_add_(0, lb, t)


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
        for _ in budget.rounds(rounds):
            for use_far in (False, True):
                for sgn in (-1.0, 1.0):
                    mine = s == sgn
                    if use_far:
                        mine = mine & far
                    join = mine[e[:, 0]] & mine[e[:, 1]]
                    lab = edge_components(V, e, join)
                    dE = cluster_flip_change(e, H, s, lab)
                    # the labels of the pinned vertices (the others write a dummy slot V)
                    blocked = torch.zeros(V + 1, dtype=torch.bool, device=s.device).index_fill_(
                        0, torch.where(pinned, lab, V), True)
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
        d = graphs.iterate(lambda d: d.scatter_reduce(0, a, d[b] + w, "amin").scatter_reduce(0, b, d[a] + w, "amin"),
                           d, rounds, "region distance")
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
        q = graphs.iterate(lambda q: q.scatter_reduce(0, a, q[b] - w, "amax").scatter_reduce(0, b, q[a] - w, "amax"),
                           q, rounds, "ball cover")
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
        occ = occupied_sectors(points.detach().to(v.dtype)[:, None, :] - cen[pl], pl, use, V, sectors)
        return region & (occ >= need)[lab]


def occupied_sectors(rel: torch.Tensor, owner: torch.Tensor, use: torch.Tensor, n: int, sectors: int) -> torch.Tensor:
    """``(n,)`` how many of ``sectors`` equal angular sectors each owner's points occupy: ``rel
    (P, k, 2)`` the points' offsets from their owners' centres, ``owner (P, k)`` the owners (in
    ``[0, n)``), ``use (P, k)`` which pairs count."""
    ang = torch.atan2(rel[..., 1], rel[..., 0])
    sec = ((ang + torch.pi) * (sectors / (2 * torch.pi))).long().clamp(0, sectors - 1)
    occ = torch.zeros(n * sectors, dtype=torch.long, device=rel.device).scatter_reduce(
        0, (owner * sectors + sec).reshape(-1), use.long().reshape(-1), "amax")
    return occ.view(n, sectors).sum(1)


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


#: the enclosure's ring may hold no chord longer than this many times its median chord
ENCLOSE_UNEVEN = 5.0


def enclosed_vertices(mesh: MeshBatch, signs: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                      clearance: torch.Tensor, chord: float = 1.5, rings: int = 2, min_points: int = 6,
                      depth: "torch.Tensor | None" = None) -> torch.Tensor:
    """``(V,)`` bool: vertices that a ring of unexplained data encloses while no curve passes
    near them.

    The unexplained points are those (``points (P, 2)``, ``face (P,)`` their triangles, −1 for
    none) in triangles the signs do not cross: no curve passes through their triangle. About a vertex ``v``, take the unexplained points in the triangles with a
    corner at most ``rings`` edges from ``v`` (``rings = 1``: its star and its neighbours'
    stars), ``r`` the nearest one's distance. ``v`` fires when (1) it is no boundary vertex and
    every neighbour has its sign, (2) it sees at least ``min_points`` such points and ``r >=
    clearance (V,)`` (it lies off the data, not in a noise band), and (3) going round ``v`` by
    angle, every two consecutive points (the last and the first too) are at most ``chord · r``
    apart, at most :data:`ENCLOSE_UNEVEN` times their median chord apart, and at most
    ``2 asin(chord / 2)`` apart in angle (97° at 1.5; the chord alone bounds the angle only up
    to 180°, and a tight cluster on one side has short chords). So (3) asks
    for a closed ring of samples around ``v``: two walls of a stroke (a gap between their ends
    of twice ``r``) or scattered outliers (chords as long as their distance) are no such ring.
    Data all around a vertex with no curve near is a small closed curve the signs have missed
    (a satellite of a few points, a small counter): the vertex takes the other sign, so its
    region is on the other side of that curve whichever side the surrounding is on. With
    ``depth (V,)`` (each vertex's distance to the zero set, :func:`zero_set_distance`) the
    farthest point of the ring must be nearer than the zero set: the noisy points round a
    coarse curve, outside its crossed triangles, ring the curve's centre too."""
    with torch.no_grad():
        V = signs.shape[0]
        P = points.shape[0]
        dev = signs.device
        e = mesh.edges
        neg = signs < 0
        cut = neg[e[:, 0]] != neg[e[:, 1]]
        # no boolean-mask indexing (a host read each): the ends of uncut edges go to a dummy row V
        crossed = torch.zeros(V + 1, dtype=torch.bool, device=dev)
        crossed = crossed.index_fill_(0, torch.where(cut, e[:, 1], V), True).index_fill_(
            0, torch.where(cut, e[:, 0], V), True)[:V]
        fn = neg[mesh.faces]
        face_cut = fn.any(1) & ~fn.all(1)
        ok = face >= 0
        idx = (ok & ~face_cut[face.clamp_min(0)]).nonzero().squeeze(1)     # one host read
        first, nbrs = mesh.vert_neighbors
        M = max(P, 1)
        key = torch.unique(mesh.faces[face[idx]].reshape(-1) * M + idx.repeat_interleave(3))
        for _ in range(int(rings)):
            # receivers: each vertex so far and its neighbours ((vertex, point) pairs, once)
            recv, pid = key // M, key % M
            deg = first[recv + 1] - first[recv]
            rep = pid.repeat_interleave(deg)
            start = torch.repeat_interleave(first[recv] - torch.cumsum(deg, 0) + deg, deg, output_size=rep.shape[0])
            nb = nbrs[start + torch.arange(rep.shape[0], device=dev)]
            key = torch.unique(torch.cat([key, nb * M + rep]))
        recv, pts = key // M, key % M
        v = mesh.verts.detach()
        x = points.detach().to(v.dtype)[pts]
        d = x - v[recv]
        dist = d.norm(dim=1)
        near = torch.full((V,), float("inf"), dtype=v.dtype, device=dev).scatter_reduce(0, recv, dist, "amin")
        far = torch.zeros(V, dtype=v.dtype, device=dev).scatter_reduce(0, recv, dist, "amax")
        # round each vertex by angle: consecutive chords, and the closing one (last to first)
        ang = torch.atan2(d[:, 1], d[:, 0]) + torch.pi                      # [0, 2 pi]
        order = torch.argsort(recv.to(v.dtype) * 8.0 + ang)
        recv, x, ang = recv[order], x[order], ang[order]
        n = recv.shape[0]
        big = torch.zeros(V, dtype=v.dtype, device=dev)
        gap = torch.zeros(V, dtype=v.dtype, device=dev)
        if n:
            same = recv[1:] == recv[:-1]
            zero = torch.zeros_like(dist[1:])
            big.scatter_reduce_(0, recv[1:], torch.where(same, (x[1:] - x[:-1]).norm(dim=1), zero), "amax")
            gap.scatter_reduce_(0, recv[1:], torch.where(same, ang[1:] - ang[:-1], zero), "amax")
            head = torch.ones(n, dtype=torch.bool, device=dev)
            head[1:] = ~same
            tail = torch.ones(n, dtype=torch.bool, device=dev)
            tail[:-1] = ~same
            # the first and last row of each vertex, written without boolean-mask indexing (a
            # host read each): the other rows go to a dummy row V
            rh = torch.where(head, recv, V)
            rt = torch.where(tail, recv, V)
            hx = torch.zeros(V + 1, 2, dtype=v.dtype, device=dev).index_copy_(0, rh, x)[:V]
            tx = torch.zeros(V + 1, 2, dtype=v.dtype, device=dev).index_copy_(0, rt, x)[:V]
            ha = torch.zeros(V + 1, dtype=v.dtype, device=dev).index_copy_(0, rh, ang)[:V]
            ta = torch.zeros(V + 1, dtype=v.dtype, device=dev).index_copy_(0, rt, ang)[:V]
            big = torch.maximum(big, (hx - tx).norm(dim=1))
            gap = torch.maximum(gap, ha + 2 * torch.pi - ta)
        count = torch.zeros(V, dtype=torch.long, device=dev).index_add_(0, recv, torch.ones_like(recv))
        # the chord bounds the angle between two points only up to pi: the gap is asked too
        max_gap = 2 * math.asin(min(chord / 2, 1.0))
        hit = (~mesh.is_boundary_vert & ~crossed & (count >= max(int(min_points), 3)) & (near >= clearance.to(v.dtype))
               & (big <= chord * near) & (gap <= max_gap))
        if n:
            # a ring of samples is spaced about evenly; separate clusters round v (small rings
            # of a grid, blobs of a scatter) leave a few chords many times their typical one
            # (6-12 times, against 1-3 for a sampled ring, noisy or not)
            # (the chords between two vertices' rows go to a dummy segment V: no host read)
            med = segment_median((x[1:] - x[:-1]).norm(dim=1), torch.where(same, recv[1:], V), V + 1)[:V]
            hit = hit & (big <= ENCLOSE_UNEVEN * med)
        if depth is not None:
            # the ring lies inside the vertex's own region, nearer than the zero set: noisy
            # points round a coarse curve (outside its crossed triangles) ring its centre too
            hit = hit & (far < depth.to(v.dtype))
        return hit


def enclose_stage(ws: "WorkingSet", signs: torch.Tensor, cfg: "TopologyConfig") -> torch.Tensor:
    """``signs`` with :func:`enclosed_vertices` flipped (chords of ``enclose_chord`` times the
    ring's distance, points within ``enclose_rings`` edges, off the data by
    ``enclose_noise_widths`` noise widths)."""
    mesh = ws.mesh
    clear = (cfg.enclose_noise_widths * ws.noise).to(signs.dtype)[mesh.vert_item]
    cap = torch.full_like(signs, float("inf"))
    depth = zero_set_distance(mesh, signs, cap, int(cfg.open_rounds))
    hit = enclosed_vertices(mesh, signs, ws.points, ws.face, clear, float(cfg.enclose_chord),
                            int(cfg.enclose_rings), int(cfg.enclose_min_points), depth)
    return torch.where(hit, -signs, signs)
