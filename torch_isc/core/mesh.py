"""Packed batches of 2D triangle meshes.

A :class:`MeshBatch` holds the meshes of ``B`` items in *packed* form, the way
PyTorch3D's ``Meshes`` does: the vertices of all items concatenated into one
``(V, 2)`` tensor, the triangles into one ``(T, 3)`` tensor of *global* vertex
indices, each item's rows contiguous, with per-item counts and first indices and
a per-row item index. A single mesh is a batch of one.

Everything combinatorial (edges, adjacency, boundary) is computed lazily under
``torch.no_grad`` and cached; only vertex positions carry autograd.

Conventions: triangle ``(i, j, k)`` is positively oriented when the determinant
of eq. 2.2 (twice its signed area) is > 0. Edge ``k`` of a triangle is the edge
*opposite* its vertex ``k``: ``(v[(k+1)%3], v[(k+2)%3])``.
"""
from __future__ import annotations

import math
from functools import cached_property
from typing import List, Optional, Sequence, Tuple

import torch

from torch_isc.core.segments import first_index, segment_any, segment_count, segment_max, segment_rows
from torch_isc.core.simplex import TRIANGLES

__all__ = ["MeshBatch", "hexagon_mesh", "square_mesh", "InvalidMeshError"]


class InvalidMeshError(ValueError):
    """A mesh that violates the ISC requirements (orientation, manifoldness, ...)."""


def pow2_unit(mag: torch.Tensor) -> torch.Tensor:
    """``2^-e`` for each ``mag = m 2^e`` (``0.5 <= m < 1``): the power of two that brings a
    magnitude into ``[0.5, 1)``, exactly (1 for 0)."""
    return torch.ldexp(torch.ones_like(mag), -torch.frexp(mag)[1])


class MeshBatch:
    """A batch of triangle meshes in packed form.

    Args:
        verts: ``(V, 2)`` vertex positions of all items, item by item.
        faces: ``(T, 3)`` long, global vertex indices, item by item.
        verts_per_item: ``(B,)`` long, number of vertices of each item.
        faces_per_item: ``(B,)`` long, number of triangles of each item.

    Example:
        >>> m = hexagon_mesh(torch.zeros(2, 2), torch.ones(2), resolution=2)
        >>> m.num_items, m.faces.shape
        (2, torch.Size([48, 3]))
        >>> bool((m.signed_areas() > 0).all())
        True
    """

    #: the simplex kernel (triangle geometry, line fits, zero-set pieces, split rule)
    kernel = TRIANGLES

    def __init__(self, verts: torch.Tensor, faces: torch.Tensor,
                 verts_per_item: torch.Tensor, faces_per_item: torch.Tensor, check_sizes: bool = True):
        if verts.dim() != 2 or verts.shape[1] != 2:
            raise InvalidMeshError(f"verts must have shape (V, 2), got {tuple(verts.shape)}")
        if faces.dim() != 2 or faces.shape[1] != 3:
            raise InvalidMeshError(f"faces must have shape (T, 3), got {tuple(faces.shape)}")
        if check_sizes and (faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool):
            raise InvalidMeshError(f"faces must be integer vertex indices, got {faces.dtype}")
        dev = verts.device
        self.verts = verts
        self.faces = faces.to(device=dev, dtype=torch.long)
        self.verts_per_item = torch.as_tensor(verts_per_item, dtype=torch.long, device=dev)
        self.faces_per_item = torch.as_tensor(faces_per_item, dtype=torch.long, device=dev)
        # the check reads the counts on the host (a synchronization on a GPU): callers that built
        # the counts with the packed tensors pass check_sizes=False
        if check_sizes:
            if self.verts_per_item.dim() != 1 or self.faces_per_item.shape != self.verts_per_item.shape:
                raise InvalidMeshError(f"verts_per_item and faces_per_item must be two (B,) tensors, got shapes "
                                       f"{tuple(self.verts_per_item.shape)} and {tuple(self.faces_per_item.shape)}")
            # index ranges and finiteness are validate()'s (a full pass); the counts are read here anyway
            z = torch.zeros((), dtype=torch.long, device=dev)
            nv, nf, neg = torch.stack([
                self.verts_per_item.sum(), self.faces_per_item.sum(),
                torch.minimum(self.verts_per_item.min(), self.faces_per_item.min())
                if self.verts_per_item.numel() else z]).tolist()
            if neg < 0:
                raise InvalidMeshError("verts_per_item / faces_per_item hold a negative count")
            if nv != verts.shape[0] or nf != faces.shape[0]:
                raise InvalidMeshError("verts_per_item / faces_per_item do not add up to the packed sizes")

    # ------------------------------------------------------------------ basics
    @property
    def num_items(self) -> int:
        return int(self.verts_per_item.shape[0])

    @property
    def device(self) -> torch.device:
        return self.verts.device

    @property
    def dtype(self) -> torch.dtype:
        return self.verts.dtype

    @cached_property
    def verts_first_idx(self) -> torch.Tensor:
        """``(B,)`` index of each item's first vertex in the packed tensor."""
        return first_index(self.verts_per_item)

    @cached_property
    def faces_first_idx(self) -> torch.Tensor:
        """``(B,)`` index of each item's first triangle in the packed tensor."""
        return first_index(self.faces_per_item)

    @cached_property
    def vert_item(self) -> torch.Tensor:
        """``(V,)`` item index of every vertex."""
        return torch.repeat_interleave(torch.arange(self.num_items, device=self.device), self.verts_per_item,
                                       output_size=self.verts.shape[0])

    @cached_property
    def face_item(self) -> torch.Tensor:
        """``(T,)`` item index of every triangle."""
        return torch.repeat_interleave(torch.arange(self.num_items, device=self.device), self.faces_per_item,
                                       output_size=self.faces.shape[0])

    def with_verts(self, verts: torch.Tensor) -> "MeshBatch":
        """Same topology, new positions; the combinatorial caches are shared."""
        if verts.shape != self.verts.shape:
            raise InvalidMeshError(f"new verts have shape {tuple(verts.shape)}, expected {tuple(self.verts.shape)}")
        new = MeshBatch.__new__(MeshBatch)
        new.__dict__.update({k: v for k, v in self.__dict__.items() if k in _TOPOLOGY_CACHES})
        new.verts = verts
        new.faces = self.faces
        new.verts_per_item = self.verts_per_item
        new.faces_per_item = self.faces_per_item
        return new

    def detach(self) -> "MeshBatch":
        return self.with_verts(self.verts.detach())

    def to(self, device=None, dtype=None) -> "MeshBatch":
        return MeshBatch(self.verts.to(device=device, dtype=dtype), self.faces.to(device),
                         self.verts_per_item.to(device), self.faces_per_item.to(device), check_sizes=False)

    # ------------------------------------------------------------ list views
    def verts_list(self) -> List[torch.Tensor]:
        return list(torch.split(self.verts, self.verts_per_item.tolist()))

    def faces_list(self) -> List[torch.Tensor]:
        """Faces of each item with *local* vertex indices."""
        out = torch.split(self.faces - self.vert_offset_of_face[:, None], self.faces_per_item.tolist())
        return list(out)

    @cached_property
    def vert_offset_of_face(self) -> torch.Tensor:
        return self.verts_first_idx[self.face_item]

    def items_list(self, counts: Optional[Tuple[Sequence[int], Sequence[int]]] = None) -> List["MeshBatch"]:
        """One single-item batch per item, as views of the packed tensors (faces with local
        indices): the host reads the item sizes once, not once per item (not at all when the
        caller gives them: ``counts = (verts per item, faces per item)`` as host integers)."""
        if counts is None:
            counts = torch.stack([self.verts_per_item, self.faces_per_item]).tolist()
        nv, nf = counts
        local = self.faces - self.vert_offset_of_face[:, None]
        out, v0, f0 = [], 0, 0
        for b in range(len(nv)):
            out.append(MeshBatch(self.verts[v0:v0 + nv[b]], local[f0:f0 + nf[b]], self.verts_per_item[b:b + 1],
                                 self.faces_per_item[b:b + 1], check_sizes=False))
            v0, f0 = v0 + nv[b], f0 + nf[b]
        return out

    def __getitem__(self, b: int) -> "MeshBatch":
        b = int(b)
        if not -self.num_items <= b < self.num_items:
            raise IndexError(f"item {b} out of range for a batch of {self.num_items}")
        b %= self.num_items                                 # negative indices count from the end
        v0, nv = int(self.verts_first_idx[b]), int(self.verts_per_item[b])
        f0, nf = int(self.faces_first_idx[b]), int(self.faces_per_item[b])
        return MeshBatch(self.verts[v0:v0 + nv], self.faces[f0:f0 + nf] - v0,
                         self.verts_per_item[b:b + 1], self.faces_per_item[b:b + 1])

    def __len__(self) -> int:
        return self.num_items

    def __repr__(self) -> str:
        return (f"MeshBatch(items={self.num_items}, verts={self.verts.shape[0]}, "
                f"faces={self.faces.shape[0]}, dtype={self.dtype}, device={self.device})")

    @staticmethod
    def from_list(verts: Sequence[torch.Tensor], faces: Sequence[torch.Tensor]) -> "MeshBatch":
        """Pack per-item ``(V_b, 2)`` vertices and ``(T_b, 3)`` local-index faces."""
        if len(verts) != len(faces) or len(verts) == 0:
            raise InvalidMeshError("from_list needs as many face lists as vertex lists, at least one")
        nv = torch.tensor([v.shape[0] for v in verts], dtype=torch.long)
        nf = torch.tensor([f.shape[0] for f in faces], dtype=torch.long)
        off = first_index(nv)
        dev = verts[0].device
        fs = torch.cat([f.to(dev).long() + int(o) for f, o in zip(faces, off)], 0)
        return MeshBatch(torch.cat(list(verts), 0), fs, nv.to(dev), nf.to(dev))

    @staticmethod
    def cat(meshes: Sequence["MeshBatch"]) -> "MeshBatch":
        """Concatenate batches item-wise."""
        vs, fs, nvs, nfs, off = [], [], [], [], 0
        for m in meshes:
            vs.append(m.verts)
            fs.append(m.faces + off)
            nvs.append(m.verts_per_item)
            nfs.append(m.faces_per_item)
            off += m.verts.shape[0]
        return MeshBatch(torch.cat(vs), torch.cat(fs), torch.cat(nvs), torch.cat(nfs), check_sizes=False)

    def select_items(self, items: torch.Tensor, sizes: Optional[Tuple[int, int]] = None
                     ) -> Tuple["MeshBatch", torch.Tensor, torch.Tensor]:
        """Sub-batch of the given items (indices in any order, or a boolean mask), kept in
        item order. Returns the mesh, the kept vertex indices and the kept face indices (into
        this batch's packed tensors).

        ``sizes``: the kept vertex and face counts, when the caller has read them already; then
        ``items`` must be ascending indices without repeats and nothing is read on the host
        (otherwise the items are put in order and the sizes read, in two host reads)."""
        with torch.no_grad():
            if sizes is None:
                items = items.nonzero().squeeze(1) if items.dtype == torch.bool else torch.unique(items)
            nv, nf = self.verts_per_item[items], self.faces_per_item[items]
            if sizes is None:
                sizes = tuple(torch.stack([nv.sum(), nf.sum()]).tolist())
            NV, NF = sizes
            vkeep = segment_rows(self.verts_first_idx[items], nv, NV)
            fkeep = segment_rows(self.faces_first_idx[items], nf, NF)
            remap = torch.full((self.verts.shape[0],), -1, dtype=torch.long, device=self.device)
            remap[vkeep] = torch.arange(NV, device=self.device)
            faces = remap[self.faces[fkeep]]
        m = MeshBatch(self.verts[vkeep], faces, nv, nf, check_sizes=False)
        return m, vkeep, fkeep

    # ---------------------------------------------------------- geometry
    def unit_scale(self) -> torch.Tensor:
        """``(B,)`` each item's power of two that brings its largest coordinate into
        ``[0.5, 1)`` (1 for an item at the origin). Multiplying by it is exact: products of
        coordinates computed after it neither overflow nor underflow (a triangle of 1e-160 has
        a determinant of 1e-320, below the smallest normal), and their ratios keep their bits."""
        with torch.no_grad():
            mag = segment_max(self.verts.detach().abs().amax(1), self.vert_item, self.num_items, fill=0)
            return pow2_unit(mag)

    def unit_verts(self) -> torch.Tensor:
        """``(V, 2)`` the positions times :meth:`unit_scale` (detached): orientation tests on
        them hold at any scale."""
        return self.verts.detach() * self.unit_scale()[self.vert_item][:, None]

    def signed_areas(self, verts: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``(T,)`` the determinants of eq. 2.2 (twice the signed areas); differentiable."""
        v = self.verts if verts is None else verts
        return self.kernel.volumes(v[self.faces])

    def bary_gradients(self, verts: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``(T, 3, 2)`` the constant gradients of the barycentric coordinates (rows of ``G_t``)."""
        v = self.verts if verts is None else verts
        return self.kernel.bary_gradients(v[self.faces])

    def quality(self, verts: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``(T,)`` shape quality in (−∞, 1]: 4√3·area / Σ edge², 1 for equilateral."""
        v = self.verts if verts is None else verts
        return self.kernel.quality(v[self.faces])

    def item_bbox(self) -> torch.Tensor:
        """``(B, 4)`` xmin, ymin, xmax, ymax of each item's vertices."""
        return _segment_bbox(self.verts.detach(), self.vert_item, self.num_items)

    # ---------------------------------------------------------- topology
    @cached_property
    def _edge_data(self):
        with torch.no_grad():
            T = self.faces.shape[0]
            V = max(self.verts.shape[0], 1)
            a = self.faces.roll(-1, 1).reshape(-1)          # edge opposite k = (v[k+1], v[k+2])
            b = self.faces.roll(1, 1).reshape(-1)           # (roll: faces[:, [1, 2, 0]], [2, 0, 1], faster)
            lo, hi = torch.minimum(a, b), torch.maximum(a, b)
            key = lo * V + hi
            uniq, inv, counts = torch.unique(key, return_inverse=True, return_counts=True)
            edges = torch.stack([uniq // V, uniq % V], 1)
            face_edges = inv.view(T, 3)
            E = edges.shape[0]
            # two slots per edge: the face in which the edge runs lo->hi, and the one hi->lo
            forward = (a < b).view(T, 3)
            slot = torch.where(forward, 0, 1)
            edge_faces = torch.full((E, 2), -1, dtype=torch.long, device=self.device)
            fid = torch.arange(T, device=self.device)[:, None].expand(T, 3)
            # detect a non-manifold or inconsistently oriented mesh: two faces on one slot
            slot_count = torch.zeros((E, 2), dtype=torch.long, device=self.device)
            slot_count.view(-1).index_add_(0, (face_edges * 2 + slot).reshape(-1),
                                           torch.ones(3 * T, dtype=torch.long, device=self.device))
            edge_faces.view(-1).scatter_(0, (face_edges * 2 + slot).reshape(-1), fid.reshape(-1))
            return edges, face_edges, edge_faces, counts, slot_count

    @property
    def edges(self) -> torch.Tensor:
        """``(E, 2)`` long, each undirected edge once, ``edges[:,0] < edges[:,1]``; sorted, so
        each item's edges are contiguous."""
        return self._edge_data[0]

    @property
    def face_edges(self) -> torch.Tensor:
        """``(T, 3)`` edge index of the edge opposite each triangle corner."""
        return self._edge_data[1]

    @property
    def edge_faces(self) -> torch.Tensor:
        """``(E, 2)`` the triangle in which the edge runs low->high, and the one in which
        it runs high->low; -1 where there is none (boundary)."""
        return self._edge_data[2]

    @cached_property
    def edge_item(self) -> torch.Tensor:
        return self.vert_item.index_select(0, self.edges[:, 0].contiguous())

    @cached_property
    def edges_per_item(self) -> torch.Tensor:
        return segment_count(self.edge_item, self.num_items)

    @cached_property
    def face_neighbors(self) -> torch.Tensor:
        """``(T, 3)`` the triangle across the edge opposite each corner, -1 on the boundary."""
        with torch.no_grad():
            ef = self.edge_faces[self.face_edges]             # (T,3,2)
            me = torch.arange(self.faces.shape[0], device=self.device)[:, None]
            return torch.where(ef[..., 0] == me, ef[..., 1], ef[..., 0])

    @cached_property
    def is_boundary_edge(self) -> torch.Tensor:
        """``(E,)`` bool."""
        return (self.edge_faces < 0).any(1)

    @cached_property
    def is_boundary_vert(self) -> torch.Tensor:
        """``(V,)`` bool."""
        E = self.edges.shape[0]
        return segment_any(self.is_boundary_edge[:, None].expand(E, 2).reshape(-1), self.edges.reshape(-1),
                           self.verts.shape[0])

    @cached_property
    def degrees(self) -> torch.Tensor:
        """``(V,)`` long, number of edges at each vertex."""
        return segment_count(self.edges.reshape(-1), self.verts.shape[0])

    @cached_property
    def vert_neighbors(self) -> Tuple[torch.Tensor, torch.Tensor]:
        """CSR adjacency: ``(first (V+1,), nbrs (2E,))``; the neighbours of ``v`` are
        ``nbrs[first[v]:first[v+1]]``."""
        with torch.no_grad():
            src = torch.cat([self.edges[:, 0], self.edges[:, 1]])
            dst = torch.cat([self.edges[:, 1], self.edges[:, 0]])
            order = torch.argsort(src * max(self.verts.shape[0], 1) + dst)
            first = torch.zeros(self.verts.shape[0] + 1, dtype=torch.long, device=self.device)
            first[1:] = torch.cumsum(self.degrees, 0)
            return first, dst[order]

    @cached_property
    def boundary_edge_dir(self) -> torch.Tensor:
        """``(V, 2)`` for a non-corner boundary vertex the unit direction of its boundary
        side, zero elsewhere (used to let such vertices slide along the boundary)."""
        return self._boundary_data[1]

    @cached_property
    def is_corner_vert(self) -> torch.Tensor:
        """``(V,)`` bool, boundary vertices where the outer boundary turns."""
        return self._boundary_data[0]

    @cached_property
    def _boundary_data(self):
        with torch.no_grad():
            V = self.verts.shape[0]
            # every edge, the interior ones sent to a spare row V (masks, not boolean
            # indexing: no host read; the boundary edges keep their order)
            isb = self.is_boundary_edge
            be = torch.where(isb[:, None], self.edges, V)
            v = self.verts.detach()
            d = v[self.edges[:, 1]] - v[self.edges[:, 0]]
            d = d / d.norm(dim=1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)
            # sign the direction consistently with the boundary-vertex pair, sum |cross| per vertex
            acc = torch.zeros(V + 1, 2, 2, dtype=v.dtype, device=v.device)
            outer = d[:, :, None] * d[:, None, :]
            acc.index_add_(0, be[:, 0], outer)
            acc.index_add_(0, be[:, 1], outer)
            acc = acc[:V]
            # two collinear boundary edges give a rank-1 sum of outer products
            det = acc[:, 0, 0] * acc[:, 1, 1] - acc[:, 0, 1] * acc[:, 1, 0]
            tr = acc[:, 0, 0] + acc[:, 1, 1]
            corner = self.is_boundary_vert & (det > 1e-6 * tr.clamp_min(1e-30) ** 2)
            direc = torch.zeros(V + 1, 2, dtype=v.dtype, device=v.device)
            direc.index_copy_(0, be[:, 0], d)
            direc.index_copy_(0, be[:, 1], d)
            direc = torch.where((corner | ~self.is_boundary_vert)[:, None], 0.0, direc[:V])
            return corner, direc

    # ---------------------------------------------------------- validity
    def validate(self, min_det: float = 0.0) -> None:
        """Raise :class:`InvalidMeshError` unless every item is a positively oriented,
        edge-manifold, consistently oriented triangle mesh."""
        with torch.no_grad():
            V = self.verts.shape[0]
            if self.faces.numel() and (self.faces.min() < 0 or self.faces.max() >= V):
                raise InvalidMeshError("a triangle refers to a vertex that does not exist")
            if not torch.isfinite(self.verts).all():
                raise InvalidMeshError("vertex positions contain NaN or Inf")
            if (self.vert_item[self.faces] != self.face_item[:, None]).any():
                raise InvalidMeshError("a triangle uses vertices of another item")
            f = self.faces
            if ((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])).any():
                raise InvalidMeshError("a triangle repeats a vertex")
            det = self.signed_areas(self.unit_verts() if min_det == 0 else None)
            bad = det <= min_det
            if bad.any():
                t = int(bad.nonzero()[0])
                raise InvalidMeshError(
                    f"{int(bad.sum())} triangle(s) not positively oriented (e.g. triangle {t}, det {float(det[t]):.3g})")
            counts, slot_count = self._edge_data[3], self._edge_data[4]
            if (counts > 2).any():
                raise InvalidMeshError("an edge is shared by more than two triangles")
            if (slot_count > 1).any():
                raise InvalidMeshError("two triangles traverse a shared edge in the same direction")

    def validate_async(self, min_det: float = 0.0) -> None:
        """The checks that a change of vertex positions can break (finite positions,
        positive orientation), as device-side asserts (``torch._assert_async``): no host
        synchronization on CUDA, where a failure surfaces at a later synchronizing call
        (on CPU it raises at once). The combinatorial checks of :meth:`validate` are not
        repeated (:meth:`with_verts` cannot break them)."""
        with torch.no_grad():
            torch._assert_async(torch.isfinite(self.verts).all(), "vertex positions contain NaN or Inf")
            torch._assert_async((self.signed_areas(self.unit_verts() if min_det == 0 else None) > min_det).all(),
                                "a triangle is not positively oriented")

    def is_valid(self, min_det: float = 0.0) -> bool:
        try:
            self.validate(min_det)
        except InvalidMeshError:
            return False
        return True


_TOPOLOGY_CACHES = {"verts_first_idx", "faces_first_idx", "vert_item", "face_item", "_edge_data",
                    "edge_item", "edges_per_item", "face_neighbors", "is_boundary_edge",
                    "is_boundary_vert", "degrees", "vert_neighbors", "vert_offset_of_face",
                    "_boundary_data", "is_corner_vert", "boundary_edge_dir"}


def _segment_bbox(x: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    big = torch.finfo(x.dtype).max
    lo = torch.full((n, 2), big, dtype=x.dtype, device=x.device)
    hi = torch.full((n, 2), -big, dtype=x.dtype, device=x.device)
    idx = seg[:, None].expand(-1, 2)
    lo = lo.scatter_reduce(0, idx, x, "amin")
    hi = hi.scatter_reduce(0, idx, x, "amax")
    return torch.cat([lo, hi], 1)


# ---------------------------------------------------------------- initial meshes
def _replicate(tv: torch.Tensor, tf: torch.Tensor, center: torch.Tensor, scale: torch.Tensor) -> MeshBatch:
    B = center.shape[0]
    nv, nf = tv.shape[0], tf.shape[0]
    verts = (tv[None] * scale.view(B, 1, 1) + center[:, None, :]).reshape(B * nv, 2)
    offs = (torch.arange(B, device=center.device) * nv).view(B, 1, 1)
    faces = (tf[None] + offs).reshape(B * nf, 3)
    full = lambda n: torch.full((B,), n, dtype=torch.long, device=center.device)  # noqa: E731
    return MeshBatch(verts, faces, full(nv), full(nf), check_sizes=False)


#: the most triangles :func:`hexagon_mesh` or :func:`square_mesh` builds in one call (all items)
MAX_BUILT_TRIANGLES = 1 << 31


def _builder_args(name: str, center, size, size_name: str, resolution, triangles) -> int:
    """Check a mesh builder's arguments; the resolution as an int. ``triangles(r)``: per item."""
    import operator

    try:
        r = operator.index(resolution)
    except TypeError:
        raise ValueError(f"{name}: resolution must be an integer >= 1, got {resolution!r:.30}") from None
    if r < 1 or isinstance(resolution, bool):
        raise ValueError(f"{name}: resolution must be an integer >= 1, got {resolution!r:.30}")
    if not (torch.is_tensor(center) and center.dim() == 2 and center.shape[1] == 2 and center.is_floating_point()):
        raise ValueError(f"{name}: center must be a floating (B, 2) tensor, got "
                         f"{tuple(center.shape) if torch.is_tensor(center) else type(center).__name__}")
    B = center.shape[0]
    if not (torch.is_tensor(size) and tuple(size.shape) == (B,)):
        raise ValueError(f"{name}: {size_name} must be a ({B},) tensor, got "
                         f"{tuple(size.shape) if torch.is_tensor(size) else type(size).__name__}")
    if B * triangles(r) > MAX_BUILT_TRIANGLES:
        raise ValueError(f"{name}: {B} item(s) of resolution {r} are {B * triangles(r)} triangles, more than "
                         f"{MAX_BUILT_TRIANGLES}")
    return r


def hexagon_mesh(center: torch.Tensor, radius: torch.Tensor, resolution: int = 1) -> MeshBatch:
    """Regular hexagons cut into ``6·resolution²`` equilateral triangles, one per item.

    Args:
        center: ``(B, 2)`` centres. radius: ``(B,)`` circumradii (centre to corner).
        resolution: triangles along each hexagon side.

    Example:
        >>> m = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 1)
        >>> m.verts.shape, m.faces.shape
        (torch.Size([7, 2]), torch.Size([6, 3]))
    """
    r = _builder_args("hexagon_mesh", center, radius, "radius", resolution, lambda k: 6 * k * k)
    dev, dt = center.device, center.dtype
    # triangular lattice in axial coordinates (q, s), |q|,|s|,|q+s| <= r
    q, s = torch.meshgrid(torch.arange(-r, r + 1, device=dev), torch.arange(-r, r + 1, device=dev), indexing="ij")
    q, s = q.reshape(-1), s.reshape(-1)
    keep = (q + s).abs() <= r
    q, s = q[keep], s[keep]
    idx = torch.full((2 * r + 1, 2 * r + 1), -1, dtype=torch.long, device=dev)
    idx[q + r, s + r] = torch.arange(q.shape[0], device=dev)
    # lattice vectors a=(1,0), b=(1/2, √3/2): corners of the hexagon at distance r
    x = (q.to(dt) + 0.5 * s.to(dt)) / r
    y = (math.sqrt(3.0) / 2.0) * s.to(dt) / r
    tv = torch.stack([x, y], 1)
    # up triangles (q,s),(q+1,s),(q,s+1); down triangles (q+1,s),(q+1,s+1),(q,s+1)
    Q, S = torch.meshgrid(torch.arange(-r, r, device=dev), torch.arange(-r, r, device=dev), indexing="ij")
    Q, S = Q.reshape(-1), S.reshape(-1)

    def at(a, b):
        ok = (a >= -r) & (a <= r) & (b >= -r) & (b <= r)
        out = torch.full_like(a, -1)
        out[ok] = idx[a[ok] + r, b[ok] + r]
        return out

    up = torch.stack([at(Q, S), at(Q + 1, S), at(Q, S + 1)], 1)
    dn = torch.stack([at(Q + 1, S), at(Q + 1, S + 1), at(Q, S + 1)], 1)
    tf = torch.cat([up, dn], 0)
    tf = tf[(tf >= 0).all(1)]
    return _replicate(tv, tf, center, radius.to(dt))


def square_mesh(center: torch.Tensor, half_width: torch.Tensor, resolution: int = 1) -> MeshBatch:
    """Squares cut into ``resolution²`` cells of two triangles each, one per item.

    Diagonals alternate in a checkerboard so the mesh has no preferred direction.

    Args:
        center: ``(B, 2)``. half_width: ``(B,)``. resolution: cells per side.
    """
    n = _builder_args("square_mesh", center, half_width, "half_width", resolution, lambda k: 2 * k * k)
    dev, dt = center.device, center.dtype
    t = torch.linspace(-1.0, 1.0, n + 1, device=dev, dtype=dt)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    tv = torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)
    I, J = torch.meshgrid(torch.arange(n, device=dev), torch.arange(n, device=dev), indexing="ij")
    I, J = I.reshape(-1), J.reshape(-1)
    v00 = I * (n + 1) + J
    v01, v10, v11 = v00 + 1, v00 + (n + 1), v00 + (n + 1) + 1
    even = ((I + J) % 2 == 0)[:, None]
    a = torch.where(even, torch.stack([v00, v01, v11], 1), torch.stack([v00, v01, v10], 1))
    b = torch.where(even, torch.stack([v00, v11, v10], 1), torch.stack([v01, v11, v10], 1))
    tf = torch.cat([a, b], 0)
    return _replicate(tv, tf, center, half_width.to(dt))
