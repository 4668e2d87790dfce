"""The working set of the loop: what the stages read and write for the unfinished items.

It owns the packed mesh, the nodal values and signs, the packed points with their triangle,
barycentrics and local frames, and per item the map to the caller's item, the frame
(centre, scale) and the priors (tolerance, noise). Fields are declared per kind (per item,
vertex, triangle, point), so dropping finished items and following a subdivision touch every
field of a kind the same way: a new per-point tensor is one more name in :attr:`POINT_FIELDS`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch

from torch_isc.core.locate import locate_children
from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import first_index, segment_count, segment_rows
from torch_isc.core.subdivide import Subdivision

__all__ = ["WorkingSet"]


@dataclass
class WorkingSet:
    """The unfinished items between two stages (``B`` items, ``V`` vertices, ``T`` triangles,
    ``P`` points, all packed item by item).

    Attributes:
        mesh: the :class:`MeshBatch` of the items (normalized coordinates).
        values: ``(V,)`` nodal values. signs: ``(V,)`` ±1.
        marked: ``(T,)`` bool, the triangles the last test marked.
        points: ``(P, 2)`` normalized points. point_item: ``(P,)`` their working item.
        face: ``(P,)`` their triangle. bary: ``(P, 3)`` their barycentric coordinates.
        frames: ``(P, 5)`` their local tangent and neighbourhood reach (noise estimate), then the
            denoising fit's tangent.
        items: ``(B,)`` the caller's index of each working item.
        center: ``(B, 2)`` float64, scale: ``(B,)`` float64: the frame (caller = normalized *
            scale + center). tol: ``(B,)`` tolerance, noise: ``(B,)`` noise (normalized units).
        flat: ``(B,)`` bool, items whose points lie on one line.
    """
    mesh: MeshBatch
    values: torch.Tensor
    signs: torch.Tensor
    marked: torch.Tensor
    points: torch.Tensor
    point_item: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor
    frames: torch.Tensor
    items: torch.Tensor
    center: torch.Tensor
    scale: torch.Tensor
    tol: torch.Tensor
    noise: torch.Tensor
    flat: torch.Tensor
    #: ``(P, 2)`` or None: other positions of the points that the sign evidence reads instead
    #: (the denoised points when only the signs see them, or the raw ones when only the fit does)
    sign_points: Optional[torch.Tensor] = None
    #: ``(P,)`` long or None: each point's blob label (pipeline/blobs.py; −1: in none), None
    #: when the batch has no blob
    blob: Optional[torch.Tensor] = None
    #: None, or the number of blobs of the solve when ``blob`` holds rows ``0..blob_count−1``
    #: (made once per solve: the blob stages then read nothing on the host; a row whose
    #: items have left is empty)
    blob_count: Optional[int] = None

    ITEM_FIELDS = ("items", "center", "scale", "tol", "noise", "flat")
    VERT_FIELDS = ("values", "signs")
    FACE_FIELDS = ("marked",)
    POINT_FIELDS = ("points", "face", "bary", "frames")      # point_item and face are remapped

    @property
    def num_items(self) -> int:
        return self.mesh.num_items

    @property
    def device(self) -> torch.device:
        return self.mesh.device

    @property
    def dtype(self) -> torch.dtype:
        return self.mesh.dtype

    def replace(self, **changes) -> "WorkingSet":
        return dataclasses.replace(self, **changes)

    def select(self, keep: torch.Tensor) -> "WorkingSet":
        """The working set of the items ``keep (K,)`` (ascending working indices): every
        per-item, per-vertex, per-triangle and per-point field restricted to them, point
        triangles and items renumbered."""
        with torch.no_grad():
            B, T = self.num_items, self.mesh.faces.shape[0]
            dev = self.device
            m = self.mesh
            npi = segment_count(self.point_item, B)           # points are packed item by item
            nv, nf, npk = m.verts_per_item[keep], m.faces_per_item[keep], npi[keep]
            NV, NF, NP = torch.stack([nv.sum(), nf.sum(), npk.sum()]).tolist()     # one host read
            mesh, kv, kf = m.select_items(keep, (NV, NF))
            kp = segment_rows(first_index(npi)[keep], npk, NP)
            remap_f = torch.full((T,), -1, dtype=torch.long, device=dev)
            remap_f[kf] = torch.arange(NF, device=dev)
            new_item = torch.full((B,), -1, dtype=torch.long, device=dev)
            new_item[keep] = torch.arange(keep.shape[0], device=dev)
            out = {k: getattr(self, k)[keep] for k in self.ITEM_FIELDS}
            out.update({k: getattr(self, k)[kv] for k in self.VERT_FIELDS})
            out.update({k: getattr(self, k)[kf] for k in self.FACE_FIELDS})
            out.update({k: getattr(self, k)[kp] for k in self.POINT_FIELDS})
            if self.sign_points is not None:
                out["sign_points"] = self.sign_points[kp]
            if self.blob is not None:
                out["blob"] = self.blob[kp]
                out["blob_count"] = self.blob_count
            f = out["face"]
            out["face"] = torch.where(f >= 0, remap_f[f.clamp_min(0)], f)
            out["point_item"] = new_item[self.point_item[kp]]
        return WorkingSet(mesh=mesh, **out)

    @staticmethod
    def cat(sets: "list[WorkingSet]") -> "WorkingSet":
        """The items of ``sets`` in one working set, in order (meshes packed one after the
        other, point triangles and items renumbered). Sizes come from the tensors' shapes: no
        host read."""
        if len(sets) == 1:
            return sets[0]
        with torch.no_grad():
            out = {k: torch.cat([getattr(w, k) for w in sets]) for k in
                   WorkingSet.ITEM_FIELDS + WorkingSet.VERT_FIELDS + WorkingSet.FACE_FIELDS + WorkingSet.POINT_FIELDS}
            faces, items, f0, b0 = [], [], 0, 0
            for w in sets:
                faces.append(torch.where(w.face >= 0, w.face + f0, w.face))
                items.append(w.point_item + b0)
                f0, b0 = f0 + w.mesh.faces.shape[0], b0 + w.num_items
            out["face"], out["point_item"] = torch.cat(faces), torch.cat(items)
            if all(w.blob is not None for w in sets):
                out["blob"] = torch.cat([w.blob for w in sets])
                counts = {w.blob_count for w in sets}
                # rows of one solve share their numbering; other labels are counted when used
                out["blob_count"] = counts.pop() if len(counts) == 1 else None
        return WorkingSet(mesh=MeshBatch.cat([w.mesh for w in sets]), **out)

    def follow(self, sd: Subdivision) -> "WorkingSet":
        """The working set on the subdivided mesh ``sd.mesh`` (of this set's mesh): values
        carried over (new vertices take their edge's mean), signs read from them, points
        handed from each parent triangle to the child that holds it. ``marked`` is cleared."""
        values = sd.interpolate(self.values, self.mesh.edges)
        signs = torch.where(values < 0, -1.0, 1.0).to(self.dtype)
        face, bary = locate_children(sd.mesh, self.points, self.face, sd.children)
        marked = torch.zeros(sd.mesh.faces.shape[0], dtype=torch.bool, device=self.device)
        return self.replace(mesh=sd.mesh, values=values, signs=signs, marked=marked, face=face, bary=bary)

    def caller_points(self, x: torch.Tensor, item: torch.Tensor) -> torch.Tensor:
        """``(M, 2)`` float64: normalized points ``x`` of working items ``item`` in the caller's
        coordinates."""
        return x.detach().double() * self.scale[item, None] + self.center[item]

    @staticmethod
    def start(mesh: MeshBatch, points: torch.Tensor, point_item: torch.Tensor, face: torch.Tensor,
              bary: torch.Tensor, frames: torch.Tensor, center: torch.Tensor, scale: torch.Tensor,
              tol: torch.Tensor, noise: torch.Tensor, flat: torch.Tensor,
              items: Optional[torch.Tensor] = None, sign_points: Optional[torch.Tensor] = None,
              blob: Optional[torch.Tensor] = None) -> "WorkingSet":
        """The working set at level 0: all items, signs +1, values unset (+1)."""
        dev, dt = mesh.device, mesh.dtype
        B = mesh.num_items
        ones = torch.ones(mesh.verts.shape[0], dtype=dt, device=dev)
        return WorkingSet(mesh=mesh, values=ones, signs=ones.clone(),
                          marked=torch.zeros(mesh.faces.shape[0], dtype=torch.bool, device=dev), points=points,
                          point_item=point_item, face=face, bary=bary, frames=frames,
                          items=torch.arange(B, device=dev) if items is None else items, center=center,
                          scale=scale, tol=tol, noise=noise, flat=flat, sign_points=sign_points, blob=blob)
