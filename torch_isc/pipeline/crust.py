"""Sample-chain evidence for clean data: the parity of crossings of the nearest-neighbour crust.

Line fits per triangle see nothing true where a triangle holds points of two walls (a neck,
a sharp tip, two curves a few sample spacings apart): one line runs between the walls, its
error is large and its weight small, and the annealer then fills the feature or cuts it. On
clean data (noise well below the tolerance) the samples themselves say where the curve runs:
the curve passes from each sample to its nearest neighbour, and to its nearest neighbour on
the other side (the NN-crust of Dey and Kumar). Every mesh edge that crosses an odd number of
such segments joins vertices on opposite sides of the curve; one that crosses an even number
(both walls of a neck) joins vertices on the same side. Both become couplings of the Ising
energy (eq. 3.5), beside the line evidence.

Noisy data make the crust zig-zag, so the rule only runs on items whose estimated noise is a
small fraction of the tolerance and of the sample spacing. A segment longer than a few median sample spacings (an
outlier's link, a jump across a sampling gap) says nothing and is dropped.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Tuple

import torch

from torch_isc.core.segments import segment_median, segment_sum
from torch_isc.pipeline.noise import take

if TYPE_CHECKING:
    from torch_isc.core.mesh import MeshBatch
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["crust_segments", "crossing_counts", "crust_parity", "crust_sides", "crust_contradictions", "crust_coupling",
           "CrustCache"]

#: neighbours looked at for the nearest one on the other side of a sample
CRUST_NEIGHBOURS = 8
#: candidates on each side along each Morton order (8 missed neighbours along a glyph's straight wall)
CRUST_WINDOW = 24
#: a segment longer than the item's limit is kept when at most this many times both its ends'
#: nearest-neighbour distances (the samples of a sparse small component: evenly spaced samples
#: have chain segments about 1x theirs; scattered outliers inside a curve chained at 3x)
CHAIN_RATIO = 1.5


def crust_segments(points: torch.Tensor, item: torch.Tensor, num_items: int, max_length: float
                   ) -> Tuple[torch.Tensor, torch.Tensor]:
    """The NN-crust of each item's ``points (P, 2)``: ``(S, 2)`` long index pairs ``i < j``, each
    segment once, at most ``max_length`` times its item's median nearest-neighbour distance
    (returned too, ``(num_items,)``: the sample spacing), or at most :data:`CHAIN_RATIO` times
    both its ends' nearest-neighbour distances with two kept segments at each end (the chain of
    a sparse component). A point is joined to its nearest neighbour ``q`` and to its nearest
    neighbour ``r`` with ``(r − p)·(q − p) < 0`` (among its approximate
    :data:`CRUST_NEIGHBOURS` nearest)."""
    from torch_isc.pipeline.noise import approximate_knn
    P = points.shape[0]
    dev = points.device
    if P < 2:
        return torch.zeros(0, 2, dtype=torch.long, device=dev), torch.zeros(num_items, dtype=points.dtype, device=dev)
    from torch_isc.pipeline.denoise import refine_knn
    # the Morton candidates stop at quadtree cell walls, where a chain of samples would break
    # (a straight stroke crossing a wall in both orders): a wide window, then neighbour descent
    nbr, d2 = approximate_knn(points, item, CRUST_NEIGHBOURS, CRUST_WINDOW)
    nbr, d2 = refine_knn(points, nbr, d2, hops=2)
    ok = torch.isfinite(d2)
    q = nbr[:, 0]
    dq = (points[q] - points)
    side = ((points[nbr] - points[:, None, :]) * dq[:, None, :]).sum(-1) < 0
    side &= ok
    side[:, 0] = False
    has_r = side.any(1)
    r = torch.gather(nbr, 1, side.to(torch.uint8).argmax(1, keepdim=True)).squeeze(1)
    idx = torch.arange(P, device=dev)
    a = torch.cat([idx, idx])
    b = torch.cat([q, r])
    keep = torch.cat([ok[:, 0], has_r])
    # the spacing of the item's samples: the median distance to the nearest neighbour
    d1 = torch.where(ok[:, 0], d2[:, 0], torch.zeros_like(d2[:, 0])).sqrt()
    spacing = segment_median(d1, item, num_items)
    length = (points[a] - points[b]).norm(dim=1)
    keep &= a != b
    near = keep & (length <= max_length * spacing[item[a]])
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    # a sparse component (a few samples on a small circle beside a dense curve) has its own
    # spacing: a longer segment is kept when it is at most CHAIN_RATIO times both its ends'
    # nearest-neighbour distances (a jump from a curve to an outlier, or across a sampling gap,
    # has an end whose neighbour is near) and both ends have two kept segments (a chain, not a
    # pair of outliers)
    local = keep & ~near & (length <= CHAIN_RATIO * torch.minimum(d1[a], d1[b]))
    both = torch.unique(torch.where(near | local, lo * P + hi, torch.full_like(lo, -1)))
    both = both[both >= 0]
    deg = torch.zeros(P, dtype=torch.long, device=dev)
    deg.index_add_(0, torch.cat([both // P, both % P]), torch.ones(2 * both.shape[0], dtype=torch.long, device=dev))
    local &= (deg[lo] >= 2) & (deg[hi] >= 2)
    # each segment once: the parity of crossings must not count a pair twice
    key = torch.where(near | local, lo * P + hi, torch.full_like(lo, -1))
    key = torch.unique(key)
    key = key[key >= 0]
    seg = torch.stack([key // P, key % P], 1)
    return seg, spacing


#: crossings of the chain closer than this many sample spacings to an edge's end, or to each
#: other, mark nothing (:func:`crust_contradictions`)
CONTRADICTION_MARGIN = 0.5
#: the contradiction splits run on items whose noise is at most this many (configured)
#: tolerances and sample spacings, below the coupling's gate: on noisier items the crust's
#: zig-zags read as contradictions and split the mesh for nothing (the benchmark's shapes took
#: 1.25-1.3x the time with the splits under the coupling's gate, with the same topology)
REFINE_NOISE = 0.1
#: rounds of the walk between host reads of whether any segment still walks
WALK_CHECK = 8
#: triangles a crust segment may pass through before it is given up (it then counts for nothing)
WALK_STEPS = 32


def _walk(mesh: "MeshBatch", p: torch.Tensor, q: torch.Tensor, fp: torch.Tensor, fq: torch.Tensor, steps: int):
    """Walk each segment ``p (S, 2) → q (S, 2)`` from triangle ``fp`` through the triangles it
    passes, leaving each by the edge it meets last (the exit of a line through a convex cell),
    until it ends inside one. Returns ``(S, steps)`` the edges left by (-1 past the end), where
    each is crossed as a fraction of the way from its lower vertex index to its higher, and
    ``(S,)`` bool: the walk ended (not at the boundary, not stalled through a vertex, within
    ``steps``). Fixed shapes: ``steps`` rounds over every segment, the ended ones masked."""
    S, dt, dev = p.shape[0], mesh.dtype, mesh.device
    v = mesh.verts.detach()
    d = q - p
    alive = (fp >= 0) & (fq >= 0)
    done = torch.zeros(S, dtype=torch.bool, device=dev)
    cur = fp.clamp_min(0)
    last = torch.full((S,), -float("inf"), dtype=dt, device=dev)
    crossed = torch.full((S, steps), -1, dtype=torch.long, device=dev)
    where = torch.zeros((S, steps), dtype=dt, device=dev)
    fe, nb, faces = mesh.face_edges, mesh.face_neighbors, mesh.faces
    for k in range(steps):
        if k % WALK_CHECK == 0 and k > 0 and not bool((alive & ~done).any()):
            break                                                        # one host read per WALK_CHECK rounds
        f = take(faces, cur)                                             # (S,3)
        ia, ib = f.roll(-1, 1), f.roll(1, 1)                             # the edge opposite corner j
        a, b = take(v, ia), take(v, ib)
        e = b - a
        w = a - p[:, None, :]
        den = d[:, None, 0] * e[..., 1] - d[:, None, 1] * e[..., 0]
        ok = den != 0
        sden = torch.where(ok, den, torch.ones_like(den))
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / sden       # along the segment
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / sden   # along the edge, from a
        t = torch.where(ok & (u >= 0) & (u <= 1), t, torch.full_like(t, -float("inf")))
        te, j = t.max(1)
        run = alive & ~done
        ends = run & (te >= 1)                                            # q lies in this triangle
        done |= ends
        go = run & ~ends
        cj = cur * 3 + j                                                 # [cur, j] of a (T, 3) table
        nxt = nb.reshape(-1).index_select(0, cj)
        alive &= ~(go & (~(te > last) | (nxt < 0)))                       # stalled, or left the mesh
        go &= alive
        uj = u.gather(1, j[:, None]).squeeze(1)
        uj = torch.where(ia.gather(1, j[:, None]).squeeze(1) < ib.gather(1, j[:, None]).squeeze(1), uj, 1 - uj)
        crossed[:, k] = torch.where(go, fe.reshape(-1).index_select(0, cj), crossed[:, k])
        where[:, k] = torch.where(go, uj, where[:, k])
        last = torch.where(go, te, last)
        cur = torch.where(go, nxt, cur)
    return crossed, where, alive & done


def crossing_counts(mesh: "MeshBatch", p: torch.Tensor, q: torch.Tensor, item: torch.Tensor,
                    fp: torch.Tensor, fq: torch.Tensor, steps: int = WALK_STEPS, extent: bool = False):
    """``(E,)`` how many of the segments ``p (S, 2) → q (S, 2)`` (of items ``item``, their ends in
    triangles ``fp``, ``fq``) cross each mesh edge, each segment walked through the mesh
    (:func:`_walk`); a segment whose walk does not end (the mesh boundary, a stall through a
    vertex, more than ``steps`` triangles) counts for nothing, so no edge gets a partial count of
    it. Also ``(S,)`` bool: the segments followed. With ``extent``, also ``(E, 2)`` the first
    and last crossing along each edge (fractions from its lower vertex index; 1, 0 where none)."""
    E = mesh.edges.shape[0]
    dev = mesh.device
    out = torch.zeros(E, dtype=torch.long, device=dev)
    S = p.shape[0]
    span = torch.stack([torch.ones(E, dtype=mesh.dtype, device=dev), torch.zeros(E, dtype=mesh.dtype, device=dev)], 1)
    if S == 0:
        none = torch.zeros(0, dtype=torch.bool, device=dev)
        return (out, none, span) if extent else (out, none)
    crossed, where, followed = _walk(mesh, p.to(mesh.dtype), q.to(mesh.dtype), fp, fq, steps)
    keep = (crossed >= 0) & followed[:, None]
    hit = crossed[keep]
    out.index_add_(0, hit, torch.ones_like(hit))
    if not extent:
        return out, followed
    at = where[keep]
    span[:, 0].scatter_reduce_(0, hit, at, "amin")
    span[:, 1].scatter_reduce_(0, hit, at, "amax")
    return out, followed, span


class CrustCache:
    """The crust segments of one solve's items, made at its first level (the points do not
    change from level to level; only the mesh the parity is counted on does): later levels of
    the same solve take the rows of their items instead of a new neighbour search. Holds the
    first working set's item ids, each item's first point there, the segments (in that point
    numbering) and each item's spacing."""

    def __init__(self):
        self.items = None

    def get(self, ws: "WorkingSet", clean: torch.Tensor, max_length: float):
        """``(seg (S, 2), sp (B,))`` as :func:`crust_segments` gives them for the points of the
        ``clean (B,)`` items of ``ws`` (the same segments; the order may differ, which no
        count depends on), or None when no item is clean."""
        B, dev = ws.num_items, ws.device
        if self.items is None:
            self.items, self.start = ws.items, _starts(ws.point_item, B)
            self.rows = int(ws.items.max()) + 1                              # one host read per solve
            sel = clean[ws.point_item].nonzero().squeeze(1)                 # one host read
            if sel.numel() < 2:
                self.seg = torch.zeros(0, 2, dtype=torch.long, device=dev)
                self.sp = torch.zeros(B, dtype=ws.points.dtype, device=dev)
            else:
                seg, self.sp = crust_segments(ws.points[sel], ws.point_item[sel], B, max_length)
                self.seg = sel[seg]                                          # the first level's point numbering
            self.seg_item = ws.point_item[self.seg[:, 0]]
        # each working item's row in the first level's items (a solve's items only leave)
        rows = torch.full((self.rows,), -1, dtype=torch.long, device=dev)
        rows[self.items] = torch.arange(self.items.shape[0], device=dev)
        row = rows[ws.items]
        sp = torch.where(clean, self.sp[row], torch.zeros_like(self.sp[row]))
        # the segments of the clean working items, renumbered into this level's points
        here = torch.full((self.items.shape[0],), -1, dtype=torch.long, device=dev)
        here[row] = torch.arange(B, device=dev)
        b = here[self.seg_item]
        keep = (b >= 0) & clean[b.clamp_min(0)]
        idx = keep.nonzero().squeeze(1)                                      # one host read
        if idx.numel() == 0:
            return None
        b = b[idx]
        seg = self.seg[idx] - self.start[self.seg_item[idx], None] + _starts(ws.point_item, B)[b, None]
        return seg, sp


def _starts(point_item: torch.Tensor, B: int) -> torch.Tensor:
    """``(B,)`` the first point of each item (points packed item by item)."""
    from torch_isc.core.segments import first_index
    return first_index(torch.zeros(B, dtype=torch.long, device=point_item.device).index_add_(0, point_item, torch.ones_like(point_item)))


def crust_parity(ws: "WorkingSet", noise_tolerances: float, max_length: float, noise_spacings: float = 0.1,
                 cache: "CrustCache | None" = None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(E,)`` int8: ``1`` where a mesh edge crosses the crust an odd number of times (its ends
    on opposite sides), ``-1`` where an even, nonzero number, ``0`` elsewhere; and ``(B,)`` the
    items' sample spacing (0 where the rule is off). Only on items whose noise is at most
    ``noise_tolerances`` times their tolerance and ``noise_spacings`` times their sample spacing.
    ``cache``: a :class:`CrustCache` shared by the levels of one solve (the same result).
    Also ``(E, 2)`` the first and last crossing along each edge (fractions from its lower vertex
    index; 1, 0 where none)."""
    mesh = ws.mesh
    E = mesh.edges.shape[0]
    par = torch.zeros(E, dtype=torch.int8, device=mesh.device)
    spacing = torch.zeros(ws.num_items, dtype=mesh.dtype, device=mesh.device)
    span = torch.stack([torch.ones(E, dtype=mesh.dtype, device=mesh.device), torch.zeros(E, dtype=mesh.dtype, device=mesh.device)], 1)
    with torch.no_grad():
        clean = ws.noise <= noise_tolerances * ws.tol
        if cache is not None:
            got = cache.get(ws, clean, max_length)
            if got is None:
                return par, spacing, span
            seg, sp = got
            pts, it, face = ws.points, ws.point_item, ws.face
        else:
            sel = clean[ws.point_item].nonzero().squeeze(1)                     # one host read
            if sel.numel() < 2:
                return par, spacing, span
            pts = ws.points[sel]
            it = ws.point_item[sel]
            face = ws.face[sel]
            seg, sp = crust_segments(pts, it, ws.num_items, max_length)
        # ...and whose noise is small against their sample spacing too: a noisy sample's crust
        # zig-zags (a scan quantized to a grid a third of its spacing gave wrong regions)
        clean &= ws.noise <= noise_spacings * sp.to(ws.noise.dtype)
        seg = seg[clean[it[seg[:, 0]]]]
        spacing = torch.where(clean, sp.to(mesh.dtype), spacing)
        if seg.shape[0] == 0:
            return par, spacing, span
        k, _, span = crossing_counts(mesh, pts[seg[:, 0]], pts[seg[:, 1]], it[seg[:, 0]], face[seg[:, 0]], face[seg[:, 1]],
                                     extent=True)
        par = torch.where(k % 2 == 1, torch.ones_like(par), torch.where(k > 0, -torch.ones_like(par), par))
        return par, spacing, span


def crust_sides(mesh: "MeshBatch", par: torch.Tensor, spacing: torch.Tensor) -> torch.Tensor:
    """``(V,)``: each vertex's side of the crust by the even-odd rule, ``+1`` outside and ``-1``
    inside, on the items whose crust is closed; ``0`` elsewhere.

    The side of a vertex is the boundary's (outside) times ``-1`` per odd edge of any mesh path
    to it (``par`` of :func:`crust_parity`). Where every crust chain closes, every path gives
    the same answer; an open chain (a sampling gap, an outlier's spur, a segment the walk did not
    finish) makes a loop of edges around its end odd. So the parities are solved as components
    of the doubled graph (a vertex's two sides, joined across even edges side to side and
    across odd edges crosswise), and an item counts only where no vertex's two sides meet.
    Any odd triangle (a chain's end, or a sample on a vertex, where one segment's walk ends in
    another triangle than the next one starts from) turns the whole item off: leaving out only
    the edges around such triangles let the inside of a randomly sampled star (many chain ends
    at the coarse levels) join the outside through a sampling gap, consistently and wrongly.
    ``spacing (B,)``: the items' sample spacing, 0 where the crust is off (no side there)."""
    with torch.no_grad():
        from torch_isc.core.segments import edge_components, segment_any, segment_min
        V = mesh.verts.shape[0]
        e = mesh.edges
        odd = par == 1
        a = torch.cat([e[:, 0], e[:, 0] + V])
        b = torch.cat([torch.where(odd, e[:, 1] + V, e[:, 1]), torch.where(odd, e[:, 1], e[:, 1] + V)])
        lab = edge_components(2 * V, torch.stack([a, b], 1), torch.ones_like(a, dtype=torch.bool))
        plus, minus = lab[:V], lab[V:]
        item = mesh.vert_item
        B = mesh.num_items
        bad = segment_any(plus == minus, item, B)
        # the outside's component: that of the item's boundary vertices (all one when closed)
        big = torch.iinfo(lab.dtype).max
        out = segment_min(torch.where(mesh.is_boundary_vert, plus, torch.full_like(plus, big)), item, B, fill=big)
        ok = ~bad & (spacing > 0) & (out < big)
        side = torch.where(plus == out[item], 1, torch.where(minus == out[item], -1, 0))
        return torch.where(ok[item], side, torch.zeros_like(side)).to(mesh.dtype)


def crust_contradictions(ws: "WorkingSet", values: torch.Tensor, spacings: float, noise_tolerances: float,
                         max_length: float, noise_spacings: float = 0.1, cache: "CrustCache | None" = None,
                         parity=None) -> torch.Tensor:
    """``(T,)`` bool: the triangles whose longest edge is above ``spacings`` sample spacings and
    that have an edge the crust (:func:`crust_parity`) says the mesh gets wrong: crossed an odd
    number of times with equal signs at its ends, or an even, nonzero number of times (both
    walls of a feature thinner than the edge: whatever its ends' signs, the mesh cannot draw
    both there). Crossings within :data:`CONTRADICTION_MARGIN` sample spacings of the edge's
    ends, or of each other, do not count.

    On clean data the chain of samples says which edges the curve crosses. Where the signs
    disagree, a later rule flipped a region the samples enclose (the one-vertex gap between two
    close curves, read as a speck) or the mesh is too coarse for the energy to follow the chain;
    an edge across both walls of a gap joins the two curves whatever the signs. Either way the
    mesh must be finer there (issue 13: two circles three sample spacings apart merged).
    ``parity``: ``(mesh, par, spacing, span)`` of :func:`crust_parity`, reused
    when made on this mesh (the sign source's, from earlier in the level)."""
    mesh = ws.mesh
    with torch.no_grad():
        if parity is not None and parity[0] is mesh:
            par, spacing, span = parity[1:]                              # this level's, from the signs
        else:
            par, spacing, span = crust_parity(ws, noise_tolerances, max_length, noise_spacings, cache)
        neg = values.detach() < 0
        e = mesh.edges
        differ = neg[e[:, 0]] != neg[e[:, 1]]
        v = mesh.verts.detach()
        L = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
        margin = CONTRADICTION_MARGIN * spacing[mesh.edge_item]
        # a crossing within the margin of an edge's end (a vertex between the chain's chord and
        # the curve's arc) or two within the margin of each other (the chain's corner at a
        # sample) say nothing a finer mesh could resolve
        clear = torch.minimum(span[:, 0], 1 - span[:, 1]) * L > margin
        wide = (span[:, 1] - span[:, 0]) * L > margin
        # an edge crossing the chain twice (or 2k times) spans a feature thinner than itself:
        # whatever its ends' signs, the mesh cannot draw both walls there
        bad = ((par == 1) & ~differ & clear) | ((par == -1) & wide)
        hit = bad[mesh.face_edges].any(1)
        longest = mesh.kernel.longest_edge(v[mesh.faces])
        quiet = (ws.noise <= REFINE_NOISE * ws.tol) & (ws.noise <= REFINE_NOISE * spacing.to(ws.noise.dtype))
        return hit & (longest > spacings * spacing[mesh.face_item]) & quiet[mesh.face_item]


def crust_coupling(ws: "WorkingSet", weight: float, noise_tolerances: float, max_length: float,
                   noise_spacings: float = 0.1, cache: "CrustCache | None" = None) -> torch.Tensor:
    """``(E,)`` couplings added to ``H_e``: ``+weight`` on an edge that crosses the crust an odd
    number of times (its ends on opposite sides), ``−weight`` on one that crosses it an even,
    nonzero number of times, 0 elsewhere (:func:`crust_parity`)."""
    par = crust_parity(ws, noise_tolerances, max_length, noise_spacings, cache)[0]
    return float(weight) * par.to(ws.mesh.dtype)
