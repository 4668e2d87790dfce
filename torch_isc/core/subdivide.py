"""AdaptivelySubdivideMesh (Section 3.4, Fig. 7), on the whole packed batch.

1. mark the vertices of marked triangles; 2. a new vertex at the midpoint of every edge
with both ends marked; 3. a triangle with three marked vertices splits into four, one
with two into two (through the midpoint of the edge joining them), others stay. The
result is conforming by construction and every child keeps the parent's orientation.
Only bookkeeping: positions of new vertices are midpoints (differentiable in the old
ones), everything else is index arithmetic under ``no_grad``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import first_index, segment_any, segment_sum

__all__ = ["Subdivision", "subdivide"]


@dataclass
class Subdivision:
    """What a subdivision did.

    Attributes:
        mesh: the new mesh (items still contiguous).
        children: ``(T_old, 4)`` new triangle indices of each old triangle, ascending, -1 padded.
        old_to_new_vert: ``(V_old,)`` new index of each old vertex.
        new_vert_edge: ``(V_new,)`` for a vertex created on an old edge, that edge; -1 for old vertices.
    """
    mesh: MeshBatch
    children: torch.Tensor
    old_to_new_vert: torch.Tensor
    new_vert_edge: torch.Tensor

    def interpolate(self, old_values: torch.Tensor, old_edges: torch.Tensor) -> torch.Tensor:
        """Carry per-vertex values ``(V_old, ...)`` over: new vertices get the mean of their edge's ends."""
        V = self.new_vert_edge.shape[0]
        out = old_values.new_zeros((V,) + tuple(old_values.shape[1:]))
        out = out.index_copy(0, self.old_to_new_vert, old_values)
        # as many new vertices as the sizes say: no host read for their count
        nv = torch.nonzero_static(self.new_vert_edge >= 0, size=V - self.old_to_new_vert.shape[0]).squeeze(1)
        e = old_edges[self.new_vert_edge[nv]]
        return out.index_copy(0, nv, 0.5 * (old_values[e[:, 0]] + old_values[e[:, 1]]))


def subdivide(mesh: MeshBatch, marked: torch.Tensor) -> Subdivision:
    """Subdivide the marked triangles ``marked (T,)`` bool (and what conformity requires)."""
    dev = mesh.device
    with torch.no_grad():
        V, T = mesh.verts.shape[0], mesh.faces.shape[0]
        vmark = segment_any(marked[:, None].expand(T, 3).reshape(-1), mesh.faces.reshape(-1), V)
        e = mesh.edges
        split = vmark[e[:, 0]] & vmark[e[:, 1]]
        # provisional index: old vertices, then one per split edge (in edge order, so item
        # order); then stable sort by item
        mid_of_edge = torch.where(split, V - 1 + torch.cumsum(split.long(), 0), -1)
        mids = mid_of_edge[mesh.face_edges]                        # (T,3) midpoint opposite corner k
        cand, nchild = mesh.kernel.split_children(mesh.faces, mids, vmark[mesh.faces])
        n_new, n_faces = torch.stack([split.sum(), nchild.sum()]).tolist()      # the one host read
        split_ids = torch.nonzero_static(split, size=n_new).squeeze(1)          # ascending: item order
        item_all = torch.cat([mesh.vert_item, mesh.edge_item[split_ids]])
        perm = torch.sort(item_all, stable=True).indices           # new order -> provisional index
        rank = torch.empty_like(perm)
        rank[perm] = torch.arange(perm.shape[0], device=dev)       # provisional -> new index

        K = cand.shape[1]
        slot = torch.arange(K, device=dev)[None, :] < nchild[:, None]   # (T,K)
        kept = torch.nonzero_static(slot.reshape(-1), size=n_faces).squeeze(1)
        new_faces = rank[cand.reshape(-1, cand.shape[2])[kept]]          # row-major: parent order kept
        first = first_index(nchild)
        children = torch.where(slot, first[:, None] + torch.arange(K, device=dev)[None, :], torch.full_like(slot, -1, dtype=torch.long))

        new_vert_edge = torch.full((V + n_new,), -1, dtype=torch.long, device=dev)
        new_vert_edge[V:] = split_ids
        new_vert_edge = new_vert_edge[perm]
        B = mesh.num_items
        vpi = mesh.verts_per_item + segment_sum(split.long(), mesh.edge_item, B)
        fpi = segment_sum(nchild, mesh.face_item, B)
    mid_pos = 0.5 * (mesh.verts[e[split_ids, 0]] + mesh.verts[e[split_ids, 1]])
    verts = torch.cat([mesh.verts, mid_pos], 0)[perm]
    new_mesh = MeshBatch(verts, new_faces, vpi, fpi, check_sizes=False)
    return Subdivision(new_mesh, children, rank[:V], new_vert_edge)
