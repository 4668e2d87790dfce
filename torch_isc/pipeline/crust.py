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

if TYPE_CHECKING:
    from torch_isc.core.mesh import MeshBatch
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["crust_segments", "crossing_counts", "crust_parity", "crust_coupling", "crust_stage", "CrustCache"]

#: neighbours looked at for the nearest one on the other side of a sample
CRUST_NEIGHBOURS = 8
#: candidates on each side along each Morton order (8 missed neighbours along a glyph's straight wall)
CRUST_WINDOW = 24


def crust_segments(points: torch.Tensor, item: torch.Tensor, num_items: int, max_length: float
                   ) -> Tuple[torch.Tensor, torch.Tensor]:
    """The NN-crust of each item's ``points (P, 2)``: ``(S, 2)`` long index pairs ``i < j``, each
    segment once, at most ``max_length`` times its item's median nearest-neighbour distance
    (returned too, ``(num_items,)``: the sample spacing). A point is joined to its nearest neighbour ``q`` and to
    its nearest neighbour ``r`` with ``(r − p)·(q − p) < 0`` (among its approximate
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
    keep &= (length <= max_length * spacing[item[a]]) & (a != b)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    # each segment once: the parity of crossings must not count a pair twice
    key = torch.where(keep, lo * P + hi, torch.full_like(lo, -1))
    key = torch.unique(key)
    key = key[key >= 0]
    seg = torch.stack([key // P, key % P], 1)
    return seg, spacing


def _orient(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def crossing_counts(mesh: "MeshBatch", p: torch.Tensor, q: torch.Tensor, item: torch.Tensor,
                    fp: torch.Tensor, fq: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(E,)`` how many of the segments ``p (S, 2) → q (S, 2)`` (of items ``item``, their ends in
    triangles ``fp``, ``fq``) cross each mesh edge. A segment is followed through the triangles
    holding its points at 0, 1/3, 2/3 and 1 of its length; one whose consecutive triangles are
    neither equal nor edge neighbours passes through triangles it cannot see, and counts for
    nothing (so no edge gets a partial count of it). Also ``(S,)`` bool: the segments followed."""
    from torch_isc.core.locate import locate_grid
    E = mesh.edges.shape[0]
    dt = mesh.dtype
    out = torch.zeros(E, dtype=torch.long, device=mesh.device)
    S = p.shape[0]
    if S == 0:
        return out, torch.zeros(0, dtype=torch.bool, device=mesh.device)
    p, q = p.to(dt), q.to(dt)
    mid = torch.cat([p + (q - p) / 3.0, p + (q - p) * (2.0 / 3.0)])
    fm, _ = locate_grid(mesh, mid, torch.cat([item, item]))
    faces = torch.stack([fp, fm[:S], fm[S:], fq], 1)                          # (S,4)
    ok = (faces >= 0).all(1)
    f = faces.clamp_min(0)
    nb = mesh.face_neighbors
    for k in range(3):
        same = f[:, k] == f[:, k + 1]
        adj = (nb[f[:, k]] == f[:, k + 1, None]).any(1)
        ok &= same | adj
    cand = mesh.face_edges[f].reshape(S, 12)
    cand, _ = torch.sort(cand, 1)
    first = torch.ones_like(cand, dtype=torch.bool)
    first[:, 1:] = cand[:, 1:] != cand[:, :-1]                                 # each edge once per segment
    v = mesh.verts.detach()
    e = mesh.edges[cand]                                                     # (S,12,2)
    ea, eb = v[e[..., 0]], v[e[..., 1]]
    P_, Q_ = p[:, None, :], q[:, None, :]
    cross = ((_orient(P_, Q_, ea) * _orient(P_, Q_, eb) < 0) & (_orient(ea, eb, P_) * _orient(ea, eb, Q_) < 0))
    cross &= first & ok[:, None]
    return out.index_add_(0, cand.reshape(-1), cross.reshape(-1).long()), ok


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
                 cache: "CrustCache | None" = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(E,)`` int8: ``1`` where a mesh edge crosses the crust an odd number of times (its ends
    on opposite sides), ``-1`` where an even, nonzero number, ``0`` elsewhere; and ``(B,)`` the
    items' sample spacing (0 where the rule is off). Only on items whose noise is at most
    ``noise_tolerances`` times their tolerance and ``noise_spacings`` times their sample spacing.
    ``cache``: a :class:`CrustCache` shared by the levels of one solve (the same result)."""
    mesh = ws.mesh
    E = mesh.edges.shape[0]
    par = torch.zeros(E, dtype=torch.int8, device=mesh.device)
    spacing = torch.zeros(ws.num_items, dtype=mesh.dtype, device=mesh.device)
    with torch.no_grad():
        clean = ws.noise <= noise_tolerances * ws.tol
        if cache is not None:
            got = cache.get(ws, clean, max_length)
            if got is None:
                return par, spacing
            seg, sp = got
            pts, it, face = ws.points, ws.point_item, ws.face
        else:
            sel = clean[ws.point_item].nonzero().squeeze(1)                     # one host read
            if sel.numel() < 2:
                return par, spacing
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
            return par, spacing
        k, _ = crossing_counts(mesh, pts[seg[:, 0]], pts[seg[:, 1]], it[seg[:, 0]], face[seg[:, 0]], face[seg[:, 1]])
        par = torch.where(k % 2 == 1, torch.ones_like(par), torch.where(k > 0, -torch.ones_like(par), par))
        return par, spacing


def crust_coupling(ws: "WorkingSet", weight: float, noise_tolerances: float, max_length: float,
                   noise_spacings: float = 0.1, cache: "CrustCache | None" = None) -> torch.Tensor:
    """``(E,)`` couplings added to ``H_e``: ``+weight`` on an edge that crosses the crust an odd
    number of times (its ends on opposite sides), ``−weight`` on one that crosses it an even,
    nonzero number of times, 0 elsewhere (:func:`crust_parity`)."""
    par, _ = crust_parity(ws, noise_tolerances, max_length, noise_spacings, cache)
    return float(weight) * par.to(ws.mesh.dtype)


def crust_stage(ws: "WorkingSet", H: torch.Tensor, cfg, cache: "CrustCache | None" = None) -> torch.Tensor:
    """``H`` plus :func:`crust_coupling` with ``cfg``'s settings (``TopologyConfig``); ``cache``
    keeps the crust of a solve from level to level."""
    if cfg.crust_weight <= 0:
        return H
    return H + crust_coupling(ws, cfg.crust_weight, cfg.crust_noise_tolerances, cfg.crust_max_length,
                              cfg.crust_noise_spacings, cache).to(H.dtype)
