"""Zero-set extraction: the polylines of ``{f = 0}`` of a piecewise-linear function.

Every triangle whose vertex signs differ holds one segment joining the crossing points
of its two sign-changing edges. Neighbouring triangles share the crossing point of their
common edge, so the segments chain: each crossed edge is a node with one successor. Loops
and chains are labelled and ordered with pointer doubling (``O(log n)`` tensor steps over
the whole batch, no Python loop over segments).

Orientation: a loop keeps the negative side (inside) on its left, i.e. runs
counter-clockwise around an inside region and clockwise around a hole.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List

import torch

from torch_isc.core.mesh import MeshBatch

__all__ = ["Polylines", "extract_zero_set"]


@dataclass
class Polylines:
    """Packed polylines of a batch.

    Attributes:
        points: ``(Q, 2)`` all vertices, polyline by polyline (a closed loop does not
            repeat its first vertex).
        first: ``(K,)`` index of each polyline's first point. counts: ``(K,)``.
        closed: ``(K,)`` bool. item: ``(K,)`` item index of each polyline (ascending).
        edge: ``(Q,)`` the mesh edge each point lies on.
        num_items: ``B``.
    """
    points: torch.Tensor
    first: torch.Tensor
    counts: torch.Tensor
    closed: torch.Tensor
    item: torch.Tensor
    edge: torch.Tensor
    num_items: int

    def __len__(self) -> int:
        return int(self.first.shape[0])

    def per_item_counts(self) -> torch.Tensor:
        """``(B,)`` number of polylines of each item."""
        return torch.bincount(self.item, minlength=self.num_items)

    def num_closed(self) -> torch.Tensor:
        return torch.bincount(self.item[self.closed], minlength=self.num_items)

    def num_open(self) -> torch.Tensor:
        return torch.bincount(self.item[~self.closed], minlength=self.num_items)

    def polyline_list(self) -> List[torch.Tensor]:
        return list(torch.split(self.points, self.counts.tolist()))

    def item_lists(self) -> List[List[dict]]:
        """Per item, a list of ``{"closed": bool, "points": (n, 2) tensor}``."""
        out: List[List[dict]] = [[] for _ in range(self.num_items)]
        for pl, c, b in zip(self.polyline_list(), self.closed.tolist(), self.item.tolist()):
            out[b].append({"closed": bool(c), "points": pl})
        return out

    def transform(self, scale: torch.Tensor, shift: torch.Tensor) -> "Polylines":
        """Map every item's points by ``p * scale[b] + shift[b]`` (``scale (B,)``, ``shift (B, 2)``)."""
        pi = torch.repeat_interleave(self.item, self.counts)
        pts = self.points * scale[pi, None] + shift[pi]
        return Polylines(pts, self.first, self.counts, self.closed, self.item, self.edge, self.num_items)


def _crossing_points(verts: torch.Tensor, values: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    a, b = edges[:, 0], edges[:, 1]
    fa, fb = values[a], values[b]
    t = fa / (fa - fb)
    return verts[a] + t[:, None] * (verts[b] - verts[a])


def extract_zero_set(mesh: MeshBatch, values: torch.Tensor, with_points: bool = True) -> Polylines:
    """Polylines of the zero set of the function with nodal ``values (V,)`` on ``mesh``.

    Differentiable in the vertex positions and the values (crossing points are linear
    interpolations along edges). Values must be nonzero. With ``with_points=False`` only the
    loops are traced (``points`` is left empty, ``(0, 2)``): for a caller that places the
    crossings itself.

    Example:
        >>> from torch_isc.core.mesh import hexagon_mesh
        >>> m = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 1)
        >>> vals = torch.ones(7); vals[3] = -1          # vertex 3 is the centre
        >>> pl = extract_zero_set(m, vals)
        >>> len(pl), bool(pl.closed[0]), pl.points.shape
        (1, True, torch.Size([6, 2]))
    """
    dev = mesh.device
    with torch.no_grad():
        neg = values.detach() < 0
        # index_select, not x[idx]: the same gather, 3-5x faster on CPU (torch's advanced indexing)
        fneg = neg.index_select(0, mesh.faces.reshape(-1)).view(mesh.faces.shape)   # (T,3)
        nneg = fneg.sum(1)
        mixed = (nneg > 0) & (nneg < 3)
        tid = mixed.nonzero().squeeze(1)
        fn = fneg.index_select(0, tid)
        lone_neg = nneg[tid] == 1
        # the lone vertex: the negative one if one is negative, else the positive one
        lone = torch.where(lone_neg, torch.argmax(fn.to(torch.int8), 1), torch.argmin(fn.to(torch.int8), 1))
        fe = mesh.face_edges.index_select(0, tid)
        e_m1 = fe.gather(1, ((lone + 2) % 3)[:, None]).squeeze(1)   # edge (m, m+1)
        e_m2 = fe.gather(1, ((lone + 1) % 3)[:, None]).squeeze(1)   # edge (m+2, m)
        src = torch.where(lone_neg, e_m1, e_m2)
        dst = torch.where(lone_neg, e_m2, e_m1)

        E = mesh.edges.shape[0]
        crossed = torch.zeros(E, dtype=torch.bool, device=dev)
        crossed[src] = True
        crossed[dst] = True
        node_edge = crossed.nonzero().squeeze(1)                # ascending: items contiguous
        N = node_edge.shape[0]
        node_of_edge = torch.full((E,), -1, dtype=torch.long, device=dev)
        node_of_edge[node_edge] = torch.arange(N, device=dev)
        nxt = torch.full((N,), -1, dtype=torch.long, device=dev)
        nxt[node_of_edge[src]] = node_of_edge[dst]

        ar = torch.arange(N, device=dev)
        is_tail = nxt < 0
        jump = torch.where(is_tail, ar, nxt)
        iters = max(1, math.ceil(math.log2(N + 1)) + 1)
        # chains: every node reaches its tail; loops never reach a tail
        j = jump.clone()
        if bool(is_tail.any()):
            for _ in range(iters):
                j = j.index_select(0, j)
            on_chain = is_tail[j]
        else:                       # closed loops only (a mask's curves): no tail to reach
            on_chain = torch.zeros_like(is_tail)
        # loops: label by the smallest node of the loop
        mn, jj = ar.clone(), jump.clone()
        for _ in range(iters):
            mn = torch.minimum(mn, mn.index_select(0, jj))
            jj = jj.index_select(0, jj)
        comp = torch.where(on_chain, j, mn)
        # cut each loop just before its smallest node, then rank by distance to the cut
        brk = is_tail | (~on_chain & (jump == comp))
        nxt2 = torch.where(brk, ar, jump)
        d = (~brk).long()
        jj = nxt2.clone()
        for _ in range(iters):
            d = d + d.index_select(0, jj)
            jj = jj.index_select(0, jj)
        order = torch.argsort(comp * (N + 1) + (N - d), stable=True)
        comp_sorted = comp[order]
        starts = torch.ones(N, dtype=torch.bool, device=dev)
        if N > 1:
            starts[1:] = comp_sorted[1:] != comp_sorted[:-1]
        first = starts.nonzero().squeeze(1)
        counts = torch.diff(torch.cat([first, torch.tensor([N], device=dev)]))
        closed = ~on_chain[order[first]] if N else torch.zeros(0, dtype=torch.bool, device=dev)
        edge_ordered = node_edge[order]
        item = mesh.edge_item[edge_ordered[first]] if N else torch.zeros(0, dtype=torch.long, device=dev)
    pts = _crossing_points(mesh.verts, values, mesh.edges[edge_ordered]) if with_points else mesh.verts.new_zeros((0, 2))
    return Polylines(pts, first, counts, closed, item, edge_ordered, mesh.num_items)
