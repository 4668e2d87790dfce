"""Implicit simplicial curves: nodal values on a packed mesh batch.

``C = {V, T, F}``: the curve of each item is the zero set of the function that is
linear on every triangle and takes the value ``F_i`` at vertex ``i``. Topology lives in
the signs of ``F`` (with the mesh), geometry in the magnitudes. Convention: ``f < 0``
inside, ``f > 0`` outside, and the outer boundary of each mesh is outside.
"""
from __future__ import annotations

from functools import cached_property
from typing import Optional, Tuple

import torch

from torch_isc.core.extract import Polylines, extract_zero_set
from torch_isc.core.locate import barycentric, locate_grid
from torch_isc.core.mesh import InvalidMeshError, MeshBatch

__all__ = ["ImplicitCurve", "InvalidValuesError", "check_values"]


class InvalidValuesError(ValueError):
    """Nodal values that are 0, NaN or Inf, or of the wrong shape."""


def check_values(values: torch.Tensor, num_verts: int, name: str = "values") -> None:
    if values.dim() != 1 or values.shape[0] != num_verts:
        raise InvalidValuesError(f"{name} must have shape ({num_verts},), got {tuple(values.shape)}")
    v = values.detach()
    bad_nf = ~torch.isfinite(v)
    if bad_nf.any():
        raise InvalidValuesError(f"{name}: {int(bad_nf.sum())} value(s) are NaN or Inf (first at vertex {int(bad_nf.nonzero()[0])})")
    zero = v == 0
    if zero.any():
        raise InvalidValuesError(f"{name}: {int(zero.sum())} value(s) are exactly 0 (first at vertex {int(zero.nonzero()[0])}); "
                                 "nodal values must be nonzero")


class ImplicitCurve:
    """A batch of implicit simplicial curves.

    Args:
        mesh: :class:`MeshBatch`, positively oriented.
        values: ``(V,)`` nonzero nodal values (may require grad).
        validate: check the mesh and values (default True).

    Example:
        >>> from torch_isc.core.mesh import hexagon_mesh
        >>> mesh = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 2)
        >>> values = mesh.verts.norm(dim=1) - 0.6             # a signed distance to a circle
        >>> c = ImplicitCurve(mesh, values)
        >>> c.num_components().tolist()
        [1]
        >>> c.inside(torch.tensor([[0.0, 0.0], [0.9, 0.0]])).tolist()
        [True, False]
    """

    def __init__(self, mesh: MeshBatch, values: torch.Tensor, validate: bool = True):
        if validate:
            mesh.validate()
            check_values(values, mesh.verts.shape[0])
        self.mesh = mesh
        self.values = values

    # --------------------------------------------------------------- basics
    @property
    def num_items(self) -> int:
        return self.mesh.num_items

    @property
    def signs(self) -> torch.Tensor:
        """``(V,)`` ±1 (the topology)."""
        return torch.sign(self.values.detach())

    def __getitem__(self, b: int) -> "ImplicitCurve":
        m = self.mesh[b]
        v0 = int(self.mesh.verts_first_idx[b])
        return ImplicitCurve(m, self.values[v0:v0 + m.verts.shape[0]], validate=False)

    def __len__(self) -> int:
        return self.num_items

    def __repr__(self) -> str:
        return f"ImplicitCurve(items={self.num_items}, verts={self.mesh.verts.shape[0]}, faces={self.mesh.faces.shape[0]})"

    def detach(self) -> "ImplicitCurve":
        return ImplicitCurve(self.mesh.detach(), self.values.detach(), validate=False)

    # --------------------------------------------------------------- evaluation
    def face_gradients(self) -> torch.Tensor:
        """``(T, 2)`` the constant gradient ``∇f_t = G_tᵀ F_t`` on each triangle."""
        G = self.mesh.bary_gradients()
        return (G * self.values[self.mesh.faces][..., None]).sum(1)

    def eval_at(self, face: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """``f`` at points given by their triangle ``face (P,)`` and ``bary (P, 3)``."""
        return (self.values[self.mesh.faces[face.clamp_min(0)]] * bary).sum(1)

    def locate(self, points: torch.Tensor, point_item: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
        point_item = self._point_item(points, point_item)
        return locate_grid(self.mesh, points, point_item)

    def __call__(self, points: torch.Tensor, point_item: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``f(points)``: ``points (P, 2)``, ``point_item (P,)`` (default: all item 0).

        Differentiable in vertex positions, values and points. Points outside their
        item's mesh get ``+inf`` (outside)."""
        point_item = self._point_item(points, point_item)
        face, _ = locate_grid(self.mesh, points, point_item)
        bary = barycentric(self.mesh.verts, self.mesh.faces, face, points.to(self.mesh.dtype))
        f = self.eval_at(face, torch.nan_to_num(bary))
        return torch.where(face >= 0, f, torch.full_like(f, float("inf")))

    def inside(self, points: torch.Tensor, point_item: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``(P,)`` bool, ``f < 0``; points off the mesh are outside."""
        with torch.no_grad():
            return self(points, point_item) < 0

    def _point_item(self, points, point_item):
        if point_item is None:
            if self.num_items != 1:
                raise ValueError("point_item is required for a batch of more than one curve")
            point_item = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
        return point_item

    # --------------------------------------------------------------- zero set
    def zero_set(self) -> Polylines:
        """The polylines of every item (see :mod:`torch_isc.core.extract`). Differentiable."""
        return extract_zero_set(self.mesh, self.values)

    @cached_property
    def _zero_set_detached(self) -> Polylines:
        with torch.no_grad():
            return extract_zero_set(self.mesh.detach(), self.values.detach())

    def num_components(self) -> torch.Tensor:
        """``(B,)`` number of connected components of each item's zero set."""
        return self._zero_set_detached.per_item_counts()

    # --------------------------------------------------------------- deformation
    def deform(self, verts: torch.Tensor, tol: Optional[float] = None) -> "ImplicitCurve":
        """Move the mesh vertices, keeping the topology of every item.

        Refused (:class:`InvalidMeshError`) if a triangle would lose its positive
        orientation, a boundary corner would move, or another boundary vertex would
        leave its boundary side.
        """
        if verts.shape != self.mesh.verts.shape:
            raise InvalidMeshError(f"deform: verts must have shape {tuple(self.mesh.verts.shape)}, got {tuple(verts.shape)}")
        new = self.mesh.with_verts(verts)
        with torch.no_grad():
            if not torch.isfinite(verts).all():
                raise InvalidMeshError("deform: new vertex positions contain NaN or Inf")
            det = new.signed_areas()
            if (det <= 0).any():
                raise InvalidMeshError(f"deform: {int((det <= 0).sum())} triangle(s) would lose their positive orientation")
            old = self.mesh.verts.detach()
            bbox = self.mesh.item_bbox()
            diag = (bbox[:, 2:] - bbox[:, :2]).norm(dim=1)[self.mesh.vert_item]
            t = (tol if tol is not None else 1e3 * torch.finfo(old.dtype).eps) * diag
            move = verts.detach() - old
            corner = self.mesh.is_corner_vert
            if (move[corner].norm(dim=1) > t[corner]).any():
                raise InvalidMeshError("deform: a corner of the outer boundary would move")
            side = self.mesh.is_boundary_vert & ~corner
            d = self.mesh.boundary_edge_dir
            off = (move[:, 0] * d[:, 1] - move[:, 1] * d[:, 0]).abs()
            if (off[side] > t[side]).any():
                raise InvalidMeshError("deform: a boundary vertex would leave the outer boundary")
        return ImplicitCurve(new, self.values, validate=False)

    def rescale(self, magnitudes: torch.Tensor) -> "ImplicitCurve":
        """New magnitudes ``(V,)`` (> 0), the signs kept: a constant-topology change of geometry."""
        check_values(magnitudes, self.mesh.verts.shape[0], "magnitudes")
        if (magnitudes.detach() < 0).any():
            raise InvalidValuesError("magnitudes must be positive")
        return ImplicitCurve(self.mesh, self.signs * magnitudes, validate=False)
