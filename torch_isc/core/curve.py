"""Implicit simplicial curves: nodal values on a packed mesh batch.

``C = {V, T, F}``: the curve of each item is the zero set of the function that is
linear on every triangle and takes the value ``F_i`` at vertex ``i``. Topology lives in
the signs of ``F`` (with the mesh), geometry in the magnitudes. Convention: ``f < 0``
inside, ``f > 0`` outside, and the outer boundary of each mesh is outside.
"""
from __future__ import annotations

import math
import numbers
import operator
from functools import cached_property
from typing import Optional, Sequence, Tuple

import torch

from torch_isc.core.extract import Polylines, extract_zero_set
from torch_isc.core.locate import barycentric, finite_rows, locate_grid
from torch_isc.core.mesh import InvalidMeshError, MeshBatch, pow2_unit
from torch_isc.core.points import PointSetError
from torch_isc.core.segments import segment_max

__all__ = ["ImplicitCurve", "InvalidValuesError", "check_values", "crossed_triangles", "max_orientation_fraction"]


class InvalidValuesError(ValueError):
    """Nodal values that are 0, NaN or Inf, or of the wrong shape."""


def check_values(values: torch.Tensor, num_verts: int, name: str = "values", sync: bool = True) -> None:
    """Raise :class:`InvalidValuesError` unless ``values`` is ``(num_verts,)``, finite and nonzero.

    With ``sync=False`` the content checks are device-side asserts (``torch._assert_async``,
    a ``RuntimeError`` naming the problem): no host synchronization on CUDA (on CPU they
    raise at once). The shape check never syncs."""
    if not torch.is_tensor(values):
        raise InvalidValuesError(f"{name} must be a ({num_verts},) tensor, got {type(values).__name__}")
    if values.dim() != 1 or values.shape[0] != num_verts:
        raise InvalidValuesError(f"{name} must have shape ({num_verts},), got {tuple(values.shape)}")
    v = values.detach()
    # a crossing divides by the difference of two values of opposite signs: beyond a quarter of
    # the dtype's largest it overflows and the crossing lands on the vertex (a wrong area, no error)
    top = torch.finfo(v.dtype).max / 4 if v.dtype.is_floating_point else float("inf")
    if not sync:
        torch._assert_async(torch.isfinite(v).all(), f"{name}: a value is NaN or Inf")
        torch._assert_async((v != 0).all(), f"{name}: a value is exactly 0; nodal values must be nonzero")
        torch._assert_async((v.abs() <= top).all(), f"{name}: a value is beyond a quarter of the largest {v.dtype}")
        return
    bad_nf = ~torch.isfinite(v)
    if bad_nf.any():
        raise InvalidValuesError(f"{name}: {int(bad_nf.sum())} value(s) are NaN or Inf (first at vertex {int(bad_nf.nonzero()[0])})")
    big = v.abs() > top
    if big.any():
        raise InvalidValuesError(f"{name}: {int(big.sum())} value(s) beyond {top:.3g}, a quarter of the largest "
                                 f"{str(v.dtype).replace('torch.', '')} (first at vertex {int(big.nonzero()[0])}): "
                                 f"their differences overflow; rescale them (the zero set depends on their ratios only)")
    zero = v == 0
    if zero.any():
        raise InvalidValuesError(f"{name}: {int(zero.sum())} value(s) are exactly 0 (first at vertex {int(zero.nonzero()[0])}); "
                                 "nodal values must be nonzero")


def _common_dtype(mesh: MeshBatch, values) -> Tuple[MeshBatch, torch.Tensor]:
    """Positions and values in one floating dtype, promoted as torch promotes ``verts * values``
    (float32 positions and float64 values: both float64; integer values, e.g. signs, take the
    positions' dtype). Every later step mixes the two: a mix failed deep inside
    (``index_add_`` of Double into Float) or silently computed in the lower precision."""
    if not isinstance(values, torch.Tensor):
        raise InvalidValuesError(f"values must be a torch.Tensor, got {type(values).__name__}")
    vd, md = values.dtype, mesh.verts.dtype
    if values.device != mesh.verts.device:
        raise InvalidValuesError(f"values are on {values.device}, the mesh on {mesh.verts.device}")
    if vd == md:
        return mesh, values
    if vd == torch.bool or vd.is_complex:
        raise InvalidValuesError(f"values must be real numbers, got dtype {vd}")
    common = torch.promote_types(vd, md) if vd.is_floating_point else md
    if common != md:
        mesh = mesh.with_verts(mesh.verts.to(common))
    if common != vd:
        values = values.to(common)
    return mesh, values


def _as_enclosed(enclosed, mesh: MeshBatch) -> Optional[torch.Tensor]:
    """``enclosed`` as ``(B,)`` bool on the mesh's device, or None (no item)."""
    if enclosed is None or enclosed is False:
        return None
    B = mesh.num_items
    if enclosed is True:
        return torch.ones(B, dtype=torch.bool, device=mesh.device)
    if not torch.is_tensor(enclosed) or enclosed.dtype != torch.bool or tuple(enclosed.shape) != (B,):
        got = f"shape {tuple(enclosed.shape)} {enclosed.dtype}" if torch.is_tensor(enclosed) else repr(enclosed)
        raise ValueError(f"enclosed: expected True, False or a ({B},) bool tensor, got {got:.60}")
    return enclosed.to(mesh.device)


def _boundary_of_enclosed(mesh: MeshBatch, values: torch.Tensor, enclosed: Optional[torch.Tensor]):
    """``(ab (E, 2), bnd (E,), inside (E,))``: every edge oriented with its triangle on the left,
    whether it is a boundary edge of an ``enclosed`` item, and whether it is one with both ends
    inside (the edges of the inside holes)."""
    with torch.no_grad():
        e = mesh.edges
        ab = torch.where((mesh.edge_faces[:, 0] >= 0)[:, None], e, e.flip(1))
        bnd = mesh.is_boundary_edge
        bnd = (bnd & enclosed.to(e.device)[mesh.edge_item]) if enclosed is not None else torch.zeros_like(bnd)
        neg = values.detach() < 0
        return ab, bnd, bnd & neg[ab[:, 0]] & neg[ab[:, 1]]


def _check_enclosed(mesh: MeshBatch, values: torch.Tensor, enclosed: torch.Tensor) -> None:
    """What ``enclosed`` needs: single-signed boundary edges and an outside outermost boundary
    (checked at each item's leftmost vertex, which lies on it)."""
    with torch.no_grad():
        ab, bnd, _ = _boundary_of_enclosed(mesh, values, enclosed)
        neg = values.detach() < 0
        if bool((bnd & (neg[ab[:, 0]] != neg[ab[:, 1]])).any()):
            raise InvalidValuesError("enclosed: a boundary edge of the mesh joins an inside and an outside vertex "
                                     "(a hole must take one sign)")
        x = mesh.verts.detach()[:, 0]
        big = torch.finfo(x.dtype).max
        xmin = torch.full((mesh.num_items,), big, dtype=x.dtype, device=x.device).scatter_reduce(
            0, mesh.vert_item, x, "amin")
        left = (x == xmin[mesh.vert_item]) & neg & enclosed[mesh.vert_item]
        if bool(left.any()):
            raise InvalidValuesError("enclosed: the mesh's outermost boundary must be outside (f > 0)")
        # every region off the mesh must take one sign: just outside each boundary edge, the
        # parity of the inside loops around the point must be the edge's own sign (a second,
        # all-inside piece beside the first, or a plain piece inside an inside hole, failed it)
        idx = bnd.nonzero().squeeze(1)
        if idx.numel():
            ab = ab[idx]
            p, q = mesh.verts.detach()[ab[:, 0]], mesh.verts.detach()[ab[:, 1]]
            d = q - p
            out_n = torch.stack([d[:, 1], -d[:, 0]], 1)                # right of the edge: off the mesh
            probe = 0.5 * (p + q) + 1e-3 * out_n
            odd = _odd_crossings(_parity_index(mesh, values, enclosed), probe, mesh.edge_item[idx], enclosed)
            if bool((odd != neg[ab[:, 0]]).any()):
                raise InvalidValuesError("enclosed: a region off the mesh is bounded by inside and outside loops "
                                         "(or an outer boundary is inside); a hole must take one sign")


#: the most horizontal bands of one item's parity index, and the most slots a query chunk holds
_MAX_BANDS = 4096
_CHUNK_SLOTS = 1 << 22


def _parity_index(mesh: MeshBatch, values: torch.Tensor, enclosed: torch.Tensor):
    """The boundary edges of ``enclosed`` items with both ends inside, bucketed in horizontal
    bands per item (about two mean edge heights each, at most ``_MAX_BANDS`` an item), for
    :func:`_odd_crossings`; None when there are none. Three host reads."""
    with torch.no_grad():
        dev = mesh.device
        e = mesh.edges
        v = mesh.verts.detach()
        keep = _boundary_of_enclosed(mesh, values, enclosed)[2]
        keep &= v[e[:, 0], 1] != v[e[:, 1], 1]         # a horizontal edge never crosses a horizontal ray
        idx = keep.nonzero().squeeze(1)
        if idx.numel() == 0:
            return None
        a, b, it = v[e[idx, 0]], v[e[idx, 1]], mesh.edge_item[idx]
        B, dt = mesh.num_items, v.dtype
        ylo, yhi = torch.minimum(a[:, 1], b[:, 1]), torch.maximum(a[:, 1], b[:, 1])
        big = torch.finfo(dt).max
        y0 = torch.full((B,), big, dtype=dt, device=dev).scatter_reduce(0, it, ylo, "amin")
        y1 = torch.full((B,), -big, dtype=dt, device=dev).scatter_reduce(0, it, yhi, "amax")
        cnt = torch.zeros(B, dtype=torch.long, device=dev).index_add_(0, it, torch.ones_like(it))
        has = cnt > 0
        span = torch.where(has, y1 - y0, torch.ones_like(y0)).clamp_min(torch.finfo(dt).tiny)
        mean_dy = torch.zeros(B, dtype=dt, device=dev).index_add_(0, it, yhi - ylo) / cnt.clamp_min(1).to(dt)
        h = torch.maximum(2.0 * mean_dy, span / (_MAX_BANDS - 1)).clamp_min(torch.finfo(dt).tiny)
        nb = torch.where(has, torch.floor(span / h).long() + 1, torch.zeros_like(cnt))
        off = torch.cumsum(nb, 0) - nb
        b0 = torch.floor((ylo - y0[it]) / h[it]).long()
        b1 = torch.minimum(torch.floor((yhi - y0[it]) / h[it]).long(), nb[it] - 1)
        n_e = b1 - b0 + 1
        total = int(n_e.sum())
        rep = torch.repeat_interleave(torch.arange(idx.numel(), device=dev), n_e, output_size=total)
        start = torch.cumsum(n_e, 0) - n_e
        key = off[it[rep]] + b0[rep] + (torch.arange(total, device=dev) - start[rep])
        order = torch.argsort(key, stable=True)
        rep = rep[order]
        K = int(nb.sum())
        kcnt = torch.bincount(key, minlength=K)
        kstart = torch.cumsum(kcnt, 0) - kcnt
        return {"a": a, "b": b, "y0": y0, "h": h, "nb": nb, "off": off, "edge": rep, "kstart": kstart,
                "kcnt": kcnt, "kmax": int(kcnt.max())}


def _odd_crossings(ix, points: torch.Tensor, point_item: torch.Tensor, enclosed: torch.Tensor) -> torch.Tensor:
    """``(P,)`` bool: whether the ray from each point toward +x crosses an odd number of the
    indexed edges of its item (half-open in y, so a vertex on the ray counts once)."""
    P = points.shape[0]
    dev = points.device
    out = torch.zeros(P, dtype=torch.bool, device=dev)
    if ix is None or P == 0:
        return out
    with torch.no_grad():
        a, b = ix["a"], ix["b"]
        q = points.detach().to(a.dtype)
        it = point_item
        bf = torch.floor((q[:, 1] - ix["y0"][it]) / ix["h"][it])
        valid = torch.isfinite(q).all(1) & enclosed.to(dev)[it] & (bf >= 0) & (bf < ix["nb"][it].to(bf.dtype))
        key = ix["off"][it] + torch.where(valid, bf, torch.zeros_like(bf)).long()
        kmax = max(ix["kmax"], 1)
        slot = torch.arange(kmax, device=dev)
        step = max(1, _CHUNK_SLOTS // kmax)
        for lo in range(0, P, step):
            k, ok, qq = key[lo:lo + step], valid[lo:lo + step], q[lo:lo + step]
            n = ix["kcnt"][k]
            use = (slot[None] < n[:, None]) & ok[:, None]
            j = ix["edge"][(ix["kstart"][k][:, None] + slot[None]).clamp_max(ix["edge"].numel() - 1)]
            A, Bv = a[j], b[j]                                             # (n, kmax, 2)
            py, px = qq[:, 1:2], qq[:, 0:1]
            cross = (A[..., 1] > py) != (Bv[..., 1] > py)
            t = (py - A[..., 1]) / torch.where(cross, Bv[..., 1] - A[..., 1], torch.ones_like(py))
            xc = A[..., 0] + t * (Bv[..., 0] - A[..., 0])
            out[lo:lo + step] = ((use & cross & (xc > px)).sum(1) % 2) == 1
    return out


class ImplicitCurve:
    """A batch of implicit simplicial curves.

    Args:
        mesh: :class:`MeshBatch`, positively oriented.
        values: ``(V,)`` nonzero nodal values (may require grad). When their dtype differs from
            the positions', both are promoted to the wider floating dtype (integer values take
            the positions' dtype); bool or complex values are an :class:`InvalidValuesError`.
        validate: ``True`` (default): check the mesh and the values with clear errors
            (:class:`InvalidMeshError`, :class:`InvalidValuesError`); on CUDA, when the
            values or positions require grad (the differentiable path), only the checks a
            change of positions/values can break run, as device-side asserts with no host
            sync. ``"async"``: always that. ``"sync"``: always the full checks. ``False``: none.
        enclosed: ``True`` or a ``(B,)`` bool tensor: for those items, a region the mesh
            encloses without covering it (a hole of the mesh) takes the sign of its boundary,
            which must be single-signed, and the mesh's outermost boundary must be outside: a
            band mesh around the curve (mask mode, :func:`torch_isc.images.grid_results`).
            Areas, centroids, ``inside`` and the soft occupancy then count the holes. Default:
            everything off the mesh is outside.

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

    def __init__(self, mesh: MeshBatch, values, validate=True, enclosed=None):
        mesh, values = _common_dtype(mesh, values)
        enclosed = _as_enclosed(enclosed, mesh)
        if validate:
            sync = validate == "sync" or (validate is True and not (
                values.is_cuda and (values.requires_grad or mesh.verts.requires_grad)))
            if sync:
                mesh.validate()
            else:
                mesh.validate_async()
            check_values(values, mesh.verts.shape[0], sync=sync)
            if enclosed is not None and sync:
                _check_enclosed(mesh, values, enclosed)
        self.mesh = mesh
        self.values = values
        #: ``(B,)`` bool or None: the items whose mesh holes take their boundary's sign
        self.enclosed = enclosed

    def _like(self, mesh: MeshBatch, values: torch.Tensor) -> "ImplicitCurve":
        """A curve on ``mesh`` with ``values`` and this one's ``enclosed`` items (no checks)."""
        return ImplicitCurve(mesh, values, validate=False, enclosed=self.enclosed)

    def unit_scaled(self) -> Tuple["ImplicitCurve", torch.Tensor]:
        """``(curve, s (B,))``: this curve with each item's positions multiplied by the power of
        two ``s_b`` that brings its largest coordinate into ``[0.5, 1)``. Multiplying by a power
        of two is exact, so signs, barycentrics and every ratio keep their bits, while the
        products of coordinates (triangle areas, squared lengths) no longer overflow or
        underflow: the queries compute there (lengths and distances divided by ``s`` after,
        areas by ``s²``), so they hold over the whole float range (a 1e200 curve's centre was
        "outside"). Differentiable (``s`` is a constant)."""
        s = self.mesh.unit_scale()
        return self._like(self.mesh.with_verts(self.mesh.verts * s[self.mesh.vert_item][:, None]), self.values), s

    # --------------------------------------------------------------- basics
    @property
    def num_items(self) -> int:
        return self.mesh.num_items

    @property
    def signs(self) -> torch.Tensor:
        """``(V,)`` ±1 (the topology)."""
        return torch.sign(self.values.detach())

    def __getitem__(self, b) -> "ImplicitCurve":
        """Item ``b`` (an integer, negative from the end) or the items of a slice, as a curve."""
        B = self.num_items
        if isinstance(b, slice):
            idx = list(range(B))[b]
            if not idx:
                raise IndexError(f"the slice {b} selects no item of {B}")
            if idx != sorted(idx):
                raise IndexError(f"the slice {b} is not in item order (select with a positive step)")
            sel = torch.tensor(idx, dtype=torch.long, device=self.mesh.device)
            m, vk, _ = self.mesh.select_items(sel)
            enc = None if self.enclosed is None else self.enclosed[sel]
            return ImplicitCurve(m, self.values[vk], validate=False, enclosed=enc)
        try:
            b = operator.index(b)
        except TypeError:
            raise TypeError(f"a curve's items are indexed by an integer or a slice, got {type(b).__name__}") from None
        m = self.mesh[b]
        v0 = int(self.mesh.verts_first_idx[b])
        enc = None if self.enclosed is None else self.enclosed[b:b + 1] if b >= 0 else self.enclosed[b:][:1]
        return ImplicitCurve(m, self.values[v0:v0 + m.verts.shape[0]], validate=False, enclosed=enc)

    def __len__(self) -> int:
        return self.num_items

    def __repr__(self) -> str:
        return f"ImplicitCurve(items={self.num_items}, verts={self.mesh.verts.shape[0]}, faces={self.mesh.faces.shape[0]})"

    def detach(self) -> "ImplicitCurve":
        return self._like(self.mesh.detach(), self.values.detach())

    @property
    def device(self) -> torch.device:
        return self.values.device

    @property
    def dtype(self) -> torch.dtype:
        return self.values.dtype

    def to(self, device=None, dtype=None) -> "ImplicitCurve":
        """The curve on another device and/or floating dtype (differentiable, like ``Tensor.to``).

        Example:
            >>> from torch_isc.core.mesh import hexagon_mesh
            >>> m = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 2)
            >>> ImplicitCurve(m, m.verts.norm(dim=1) - 0.6).to(dtype=torch.float64).values.dtype
            torch.float64
        """
        if dtype is not None and (not isinstance(dtype, torch.dtype) or not dtype.is_floating_point
                                  or dtype.is_complex):
            raise ValueError(f"to: dtype must be a real floating torch dtype, got {dtype!r}")
        mesh = self.mesh.with_verts(self.mesh.verts) if device is None else self.mesh.to(device)
        mesh = mesh.with_verts(mesh.verts.to(dtype=dtype)) if dtype is not None else mesh
        values = self.values.to(device=device, dtype=dtype)
        if dtype is not None and dtype != self.values.dtype:
            # a narrower dtype must keep every sign and finite number: float16 made 1e-9 values 0
            # (no curve) and 1e6 values inf (NaN areas)
            with torch.no_grad():
                old, new = self.values.detach().to(values.device), values.detach()
                lost = ((new == 0) & (old != 0)) | (~torch.isfinite(new) & torch.isfinite(old))
                lost_v = ~torch.isfinite(mesh.verts.detach()).all(1) & torch.isfinite(self.mesh.verts.detach().to(
                    mesh.verts.device)).all(1)
                if bool(lost.any() | lost_v.any()):
                    raise ValueError(f"to: {dtype} cannot hold this curve: "
                                     f"{int(lost.sum())} value(s) and {int(lost_v.sum())} vertex(es) become 0 or "
                                     f"infinite (rescale the values or keep a wider dtype)")
        enc = None if self.enclosed is None else self.enclosed.to(values.device)
        return ImplicitCurve(mesh, values, validate=False, enclosed=enc)

    @staticmethod
    def cat(curves: Sequence["ImplicitCurve"]) -> "ImplicitCurve":
        """Pack the items of several curves (batches) into one batch, in order (differentiable).

        Example:
            >>> from torch_isc.core.mesh import hexagon_mesh
            >>> m = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 2)
            >>> a = ImplicitCurve(m, m.verts.norm(dim=1) - 0.6)
            >>> ImplicitCurve.cat([a, a, a]).num_components().tolist()
            [1, 1, 1]
        """
        curves = list(curves)
        if not curves:
            raise ValueError("cat needs at least one curve")
        for k, c in enumerate(curves):
            if not isinstance(c, ImplicitCurve):
                raise TypeError(f"cat: item {k} is a {type(c).__name__}, not an ImplicitCurve")
            if c.values.device != curves[0].values.device:
                raise ValueError(f"cat: curve {k} is on {c.values.device}, curve 0 on {curves[0].values.device}")
        enc = None
        if any(c.enclosed is not None for c in curves):
            enc = torch.cat([c.enclosed.to(c.values.device) if c.enclosed is not None else
                             torch.zeros(c.num_items, dtype=torch.bool, device=c.values.device) for c in curves])
        return ImplicitCurve(MeshBatch.cat([c.mesh for c in curves]), torch.cat([c.values for c in curves]),
                             validate=False, enclosed=enc)

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
        sc, s = self.unit_scaled()
        return locate_grid(sc.mesh, points * s.to(points.dtype)[point_item][:, None], point_item)

    def __call__(self, points: torch.Tensor, point_item: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``f(points)``: ``points (P, 2)``, ``point_item (P,)`` (default: all item 0).

        Differentiable in vertex positions, values and points. Points outside their
        item's mesh get ``+inf`` (outside), or ``-inf`` in an inside hole of an ``enclosed`` item."""
        point_item = self._point_item(points, point_item)
        if self.mesh.faces.shape[0] == 0:          # no triangle (an all-black mask's curve): outside
            return torch.full((points.shape[0],), float("inf"), dtype=self.values.dtype, device=points.device)
        points, ok = finite_rows(points)
        sc, s = self.unit_scaled()
        points = points.to(self.mesh.dtype) * s[point_item][:, None]
        face, _ = locate_grid(sc.mesh, points, point_item)
        bary = barycentric(sc.mesh.verts, sc.mesh.faces, face, points)
        f = self.eval_at(face, torch.nan_to_num(bary))
        off = torch.full_like(f, float("inf"))
        if self.enclosed is not None:
            off = torch.where(sc.off_mesh_inside(points, point_item, face < 0), -off, off)
        return torch.where((face >= 0) & ok, f, torch.where(ok, off, torch.full_like(off, float("inf"))))

    def inside(self, points: torch.Tensor, point_item: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``(P,)`` bool, ``f < 0``; points off the mesh are outside (but in the inside holes
        of ``enclosed`` items)."""
        with torch.no_grad():
            return self(points, point_item) < 0

    def _point_item(self, points, point_item):
        """``point_item`` (default all 0) after checking both arguments of a query: a wrong
        shape gave torch's broadcast errors, a float item an IndexError, and an item of -1
        silently meant the last curve."""
        if (not torch.is_tensor(points) or points.dim() != 2 or points.shape[1] != 2 or points.is_complex()
                or points.dtype == torch.bool):
            got = f"shape {tuple(points.shape)} {points.dtype}" if torch.is_tensor(points) else type(points).__name__
            raise PointSetError(f"points: expected a real (N, 2) tensor, got {got}")
        dev = self.values.device
        if points.device != dev:
            raise PointSetError(f"points: on {points.device}, the curve on {dev} (move them with .to(curve.device))")
        if point_item is not None and torch.is_tensor(point_item) and point_item.device != dev:
            raise PointSetError(f"point_item: on {point_item.device}, the curve on {dev}")
        if point_item is None:
            if self.num_items != 1:
                raise ValueError("point_item is required for a batch of more than one curve")
            return torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
        n = points.shape[0]
        if (not torch.is_tensor(point_item) or point_item.shape != (n,) or point_item.is_floating_point()
                or point_item.is_complex() or point_item.dtype == torch.bool):
            got = (f"shape {tuple(point_item.shape)} {point_item.dtype}" if torch.is_tensor(point_item)
                   else type(point_item).__name__)
            raise PointSetError(f"point_item: expected an integer ({n},) tensor, got {got}")
        if n:
            lo, hi = (int(v) for v in torch.aminmax(point_item))
            if lo < 0 or hi >= self.num_items:
                raise PointSetError(f"point_item: items must be in [0, {self.num_items}), got {lo if lo < 0 else hi}")
        return point_item.long()

    def off_mesh_inside(self, points: torch.Tensor, point_item: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
        """``(P,)`` bool: which of the points flagged ``off (P,)`` (not on their item's mesh)
        lie in an inside hole of an ``enclosed`` item: an odd number of the item's inside
        boundary edges cross the ray from the point toward +x (the holes' sign by parity, the
        same count the area's boundary term makes). Edges are bucketed in horizontal bands, so
        a point meets only the edges of its band. NaN points are outside."""
        out = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        if self.enclosed is None:
            return out
        return off & _odd_crossings(self._parity, points, point_item, self.enclosed)

    @cached_property
    def _parity(self):
        """The banded inside-boundary edges (:func:`_parity_index`), made on the first query."""
        return _parity_index(self.mesh, self.values, self.enclosed)

    def hole_edges(self) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The boundary of the inside holes of ``enclosed`` items: ``(E, 2)`` vertex pairs (every
        edge of the mesh, each oriented with its triangle on the left), ``(E,)`` float weights
        (1 on a boundary edge of an enclosed item with both ends inside, else 0) and ``(E,)`` the
        edge's item. An inside hole's area is ``-Σ w (a × b) / 2`` over its edges."""
        ab, _, inside = _boundary_of_enclosed(self.mesh, self.values, self.enclosed)
        return ab, inside.to(self.mesh.verts.dtype), self.mesh.edge_item

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
    def deform(self, verts: torch.Tensor, tol: Optional[float] = None, clamp: bool = False,
               safety: float = 0.9):
        """Move the mesh vertices to ``verts (V, 2)``, keeping the topology of every item.

        ``clamp=False`` (strict): refused (:class:`InvalidMeshError`) if a triangle would
        lose its positive orientation, a boundary corner would move, or another boundary
        vertex would leave its boundary side (``tol``: allowed slack, relative to the item's
        bounding-box diagonal). Returns the curve.

        ``clamp=True`` (safe motion, never raises for a bad move): the displacement
        ``d = verts - V`` is first made admissible (corners fixed, other boundary vertices
        projected onto their boundary side's direction), then every item ``b`` moves by the
        fraction ``t_b ∈ [0, 1]`` of it: ``t_b = min(1, safety · t*_b)``, ``t*_b`` the first
        ``t > 0`` at which a triangle's determinant ``det(t) = c + b t + a t²`` (closed-form
        roots) reaches 0. Since ``det > 0`` on ``[0, t*)`` every triangle stays positively
        oriented (a fixed-shape re-check halves ``t_b`` where rounding says otherwise, no host
        sync). An item whose displacement is not finite does not move. Differentiable in
        ``verts`` (and the old positions); ``t_b`` is detached. Returns ``(curve, t (B,))``.

        Example:
            >>> from torch_isc.core.mesh import hexagon_mesh
            >>> m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 1)
            >>> c = ImplicitCurve(m, m.verts.norm(dim=1) - 0.5)
            >>> target = m.verts.clone(); target[3] = torch.tensor([2.0, 0.0])   # centre far out
            >>> moved, t = c.deform(target, clamp=True)
            >>> t                           # it would flatten triangles at x = 1 (t = 1/2): 0.9 of that
            tensor([0.4500], dtype=torch.float64)
            >>> bool((moved.mesh.signed_areas() > 0).all())
            True
        """
        if not torch.is_tensor(verts) or not verts.is_floating_point():
            got = f"a {verts.dtype} tensor" if torch.is_tensor(verts) else type(verts).__name__
            raise InvalidMeshError(f"deform: verts must be a real floating tensor, got {got}")
        if verts.device != self.mesh.device:
            raise InvalidMeshError(f"deform: verts are on {verts.device}, the curve on {self.mesh.device}")
        if verts.shape != self.mesh.verts.shape:
            raise InvalidMeshError(f"deform: verts must have shape {tuple(self.mesh.verts.shape)}, got {tuple(verts.shape)}")
        common = torch.promote_types(verts.dtype, self.mesh.verts.dtype)
        if common != self.mesh.verts.dtype:            # float64 positions for a float32 curve: both float64
            return self.to(dtype=common).deform(verts, tol, clamp, safety)
        verts = verts.to(common)
        # a NaN tol passed every boundary check (comparisons with NaN are False)
        if tol is not None and not (isinstance(tol, numbers.Real) and 0 <= tol < float("inf")):
            raise InvalidMeshError(f"deform: tol must be a finite number >= 0, got {tol!r}")
        if not (isinstance(safety, numbers.Real) and 0 < safety <= 1):
            raise InvalidMeshError(f"deform: safety must be in (0, 1], got {safety!r}")
        if clamp:
            return self._deform_clamped(verts, safety)
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
        return self._like(new, self.values)

    def admissible_displacement(self, disp: torch.Tensor) -> torch.Tensor:
        """``(V, 2)`` the displacement ``disp`` with boundary corners held and the other
        boundary vertices projected onto their boundary side (differentiable, linear)."""
        m = self.mesh
        d = m.boundary_edge_dir
        side = (m.is_boundary_vert & ~m.is_corner_vert)[:, None]
        along = (disp * d).sum(1, keepdim=True) * d
        out = torch.where(side, along, disp)
        return torch.where(m.is_corner_vert[:, None], torch.zeros_like(out), out)

    def _deform_clamped(self, verts: torch.Tensor, safety: float):
        m = self.mesh
        old = m.verts
        disp = self.admissible_displacement(verts - old)
        B = m.num_items
        with torch.no_grad():
            dd = disp.detach()
            bad = torch.zeros(B, dtype=torch.bool, device=m.device).index_put_(
                (m.vert_item,), ~torch.isfinite(dd).all(1), accumulate=True)
            finite = ~bad
            dd = torch.where(finite[m.vert_item][:, None], dd, torch.zeros_like(dd))
            t = max_orientation_fraction(m, dd, safety)
            t = torch.where(finite, t, torch.zeros_like(t))
            v0 = old.detach()
            for _ in range(8):        # rounding guard, fixed shape: halve items that still fail
                det = m.signed_areas(v0 + t[m.vert_item][:, None] * dd)
                fail = torch.zeros(B, dtype=torch.bool, device=m.device).index_put_(
                    (m.face_item,), det <= 0, accumulate=True)
                t = torch.where(fail, 0.5 * t, t)
            t = torch.where(fail, torch.zeros_like(t), t)
        disp = torch.where(torch.isfinite(disp), disp, torch.zeros_like(disp))
        new = m.with_verts(old + t[m.vert_item][:, None] * disp)
        return self._like(new, self.values), t

    def rescale(self, magnitudes: torch.Tensor, validate=True) -> "ImplicitCurve":
        """New magnitudes ``(V,)`` (> 0), the signs kept: a constant-topology change of geometry.

        ``validate``: as in the constructor (on CUDA with grad: device-side asserts, no sync)."""
        if not torch.is_tensor(magnitudes):
            raise InvalidValuesError(f"magnitudes must be a ({self.mesh.verts.shape[0]},) tensor, got "
                                     f"{type(magnitudes).__name__}")
        if magnitudes.device != self.mesh.device:
            raise InvalidValuesError(f"magnitudes are on {magnitudes.device}, the curve on {self.mesh.device}")
        if validate:
            sync = validate == "sync" or (validate is True and not (magnitudes.is_cuda and magnitudes.requires_grad))
            check_values(magnitudes, self.mesh.verts.shape[0], "magnitudes", sync=sync)
            if sync:
                if (magnitudes.detach() < 0).any():
                    raise InvalidValuesError("magnitudes must be positive")
            else:
                torch._assert_async((magnitudes.detach() > 0).all(), "magnitudes must be positive")
        return self._like(self.mesh, self.signs * magnitudes)

    # --------------------------------------------------------------- refinement / topology moves
    def refine_band(self, rings: int = 0) -> "ImplicitCurve":
        """Subdivide the triangles the zero set crosses (plus ``rings`` rings of neighbours).

        Uses the paper's rule (Fig. 7, :func:`torch_isc.core.subdivide.subdivide`); a new
        vertex at an edge midpoint takes the mean of the edge's values, i.e. the value of the
        piecewise-linear ``f`` there. Guarantees, at the moment of refinement: old vertices
        keep their values (so their sign pattern); ``f`` is unchanged as a function, so the
        zero set is unchanged as a set and the topology is the same (a midpoint whose mean
        is exactly 0 gets a value of ``eps`` times its edge's magnitude, sign +, which moves
        the zero set by a rounding-level amount). What it buys: the band now has vertices
        near the curve whose positions and magnitudes shape it in finer detail (and whose
        signs :meth:`flip_simple` can change). Differentiable in positions and values.

        Example:
            >>> from torch_isc.core.mesh import hexagon_mesh
            >>> m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 2)
            >>> c = ImplicitCurve(m, m.verts.norm(dim=1) - 0.6)
            >>> f = c.refine_band()
            >>> f.mesh.faces.shape[0] > m.faces.shape[0], f.num_components().tolist()
            (True, [1])
        """
        from torch_isc.core.subdivide import subdivide
        if isinstance(rings, bool) or not isinstance(rings, numbers.Integral) or rings < 0:
            raise InvalidMeshError(f"refine_band: rings must be an integer >= 0, got {rings!r:.40}")
        m = self.mesh
        sd = subdivide(m, crossed_triangles(m, self.values, int(rings)))
        vals = sd.interpolate(self.values, m.edges)
        with torch.no_grad():
            ends = m.edges[sd.new_vert_edge.clamp_min(0)]
            scale = self.values.detach()[ends].abs().amax(1)
            zero = (vals.detach() == 0) & (sd.new_vert_edge >= 0)
        vals = torch.where(zero, torch.finfo(vals.dtype).eps * scale, vals)
        return self._like(sd.mesh, vals)

    def simple_vertices(self) -> torch.Tensor:
        """``(V,)`` bool: interior vertices whose sign can flip without changing the topology.

        A vertex is *simple* when the signs around its link (the cycle of its neighbours)
        form exactly one run of each sign (two sign changes): flipping it then adds to (or
        removes from) the inside region a disc glued along one arc, a homotopy-preserving
        move (the PL form of digital topology's simple points). Boundary vertices are never
        simple (the outer boundary stays outside)."""
        m = self.mesh
        with torch.no_grad():
            neg = self.values.detach() < 0
            f = m.faces
            a, b = neg[f[:, [1, 2, 0]]], neg[f[:, [2, 0, 1]]]          # link edge opposite corner k
            changes = torch.zeros(m.verts.shape[0], dtype=torch.long, device=m.device)
            changes.index_add_(0, f.reshape(-1), (a != b).reshape(-1).long())
            return (changes == 2) & ~m.is_boundary_vert

    def flip_simple(self, candidates: Optional[torch.Tensor] = None, grow: bool = True, ratio: float = 1.0):
        """Flip the signs of simple vertices, keeping every item's topology.

        Args:
            candidates: ``(V,)`` bool, the vertices that may flip (default: the vertices of
                the sign-changing triangles). Only simple ones (:meth:`simple_vertices`) of
                the right sign flip: positive ones when ``grow`` (the inside grows),
                negative ones otherwise; among adjacent ones only the one of smallest
                ``|f|`` (ties: lowest index), so the flipped set is independent and the
                moves compose (a flip does not change another flipped vertex's link).
            ratio: a flipped vertex's new value is ``-ratio · f_v`` (differentiable), ``ratio`` in ``(0, 1e6]``.

        Returns ``(curve, flipped (V,) bool)``. The zero set jumps across the flipped
        vertices (by less when their ``|f|`` is small), its topology is the same.

        Example:
            >>> from torch_isc.core.mesh import hexagon_mesh
            >>> from torch_isc.core.measures import area
            >>> m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
            >>> c = ImplicitCurve(m, m.verts.norm(dim=1) - 0.2)
            >>> g, flipped = c.flip_simple()
            >>> int(flipped.sum()) > 0, bool(area(g) > area(c)), g.num_components().tolist()
            (True, True, [1])
        """
        m = self.mesh
        r = (float(ratio.detach()) if torch.is_tensor(ratio) and ratio.numel() == 1 and not ratio.dtype.is_complex
             and ratio.dtype != torch.bool else ratio)    # a one-element tensor (a learned ratio) too
        # bounded without reading the values (no host read in the band stage's spike rounds)
        if isinstance(r, bool) or not isinstance(r, numbers.Real) or not math.isfinite(r) or not 0 < r <= 1e6:
            raise InvalidValuesError(f"flip_simple: ratio must be a number in (0, 1e6] (the flipped value is "
                                     f"-ratio * f), got {ratio!r:.40}")
        if candidates is not None and not (torch.is_tensor(candidates) and candidates.dtype == torch.bool
                                           and tuple(candidates.shape) == (m.verts.shape[0],)):
            got = (f"a {tuple(candidates.shape)} {candidates.dtype} tensor" if torch.is_tensor(candidates)
                   else type(candidates).__name__)
            raise InvalidValuesError(f"flip_simple: candidates must be a ({m.verts.shape[0]},) bool tensor, got {got}")
        if candidates is not None and candidates.device != m.device:
            raise InvalidValuesError(f"flip_simple: candidates are on {candidates.device}, the curve on {m.device}")
        with torch.no_grad():
            v = self.values.detach()
            if candidates is None:
                mixed = crossed_triangles(m, v)
                candidates = torch.zeros(v.shape[0], dtype=torch.bool, device=m.device)
                candidates[m.faces[mixed].reshape(-1)] = True
            ok = candidates & self.simple_vertices() & ((v > 0) if grow else (v < 0))
            # independent set: a vertex flips if no adjacent candidate has a smaller key
            order = torch.argsort(v.abs(), stable=True)
            key = torch.empty_like(order)
            key[order] = torch.arange(order.shape[0], device=m.device)
            big = torch.iinfo(torch.long).max
            k = torch.where(ok, key, torch.full_like(key, big))
            e = m.edges
            nb_min = torch.full_like(k, big).scatter_reduce(0, torch.cat([e[:, 0], e[:, 1]]),
                                                            torch.cat([k[e[:, 1]], k[e[:, 0]]]), "amin")
            flip = ok & (k < nb_min)
        vals = torch.where(flip, -ratio * self.values, self.values)
        return self._like(m, vals), flip


def crossed_triangles(mesh: MeshBatch, values: torch.Tensor, rings: int = 0) -> torch.Tensor:
    """``(T,)`` bool: the triangles whose corners have both signs of ``values (V,)`` (the zero
    set crosses them), plus ``rings`` rings of edge neighbours."""
    with torch.no_grad():
        fneg = values.detach()[mesh.faces] < 0
        marked = fneg.any(1) & ~fneg.all(1)
        if rings > 0:
            nb = mesh.face_neighbors
            # past the mesh's diameter a ring adds nothing: stop when one does not (one host
            # read a ring after the first 8; a huge ``rings`` is bounded by the mesh, not by itself)
            for r in range(int(rings)):
                grown = marked | (marked[nb.clamp_min(0)] & (nb >= 0)).any(1)
                if r >= 8 and torch.equal(grown, marked):
                    break
                marked = grown
        return marked


def max_orientation_fraction(mesh: MeshBatch, disp: torch.Tensor, safety: float = 0.9) -> torch.Tensor:
    """``(B,)`` the largest ``t ∈ [0, 1]`` (times ``safety`` below the first root) such that
    moving every vertex by ``t · disp`` keeps every triangle of the item positively oriented.

    Per triangle ``det(t) = c + b t + a t²`` with ``c = det(0) > 0``; its first positive root
    comes from the numerically stable quadratic formula (``q = -(b + sign(b)√Δ)/2``, roots
    ``q/a`` and ``c/q``); no real positive root: no limit."""
    with torch.no_grad():
        # in a frame of powers of two (exact): the positions of each item into [0.5, 1), its
        # displacement too where it is larger (a displacement of 1e154 made a t² overflow and
        # the item stood still); the roots scale back by the displacement's factor
        s = mesh.unit_scale()
        dmag = segment_max(disp.detach().abs().amax(1), mesh.vert_item, mesh.num_items, fill=0)
        k = torch.minimum(pow2_unit(dmag * s), torch.ones_like(s))
        v = mesh.verts.detach() * s[mesh.vert_item][:, None]
        f = mesh.faces
        p, d = v[f], (disp.detach() * (s * k)[mesh.vert_item][:, None])[f]
        u, w = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        du, dw = d[:, 1] - d[:, 0], d[:, 2] - d[:, 0]

        def cr(x, y):
            return x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]

        c = cr(u, w)
        b = cr(u, dw) + cr(du, w)
        a = cr(du, dw)
        disc = b * b - 4 * a * c
        sq = torch.sqrt(disc.clamp_min(0))
        sgn = torch.where(b >= 0, torch.ones_like(b), -torch.ones_like(b))
        q = -0.5 * (b + sgn * sq)
        inf = torch.full_like(c, float("inf"))
        r1 = torch.where(a != 0, q / torch.where(a != 0, a, torch.ones_like(a)), inf)
        r2 = torch.where(q != 0, c / torch.where(q != 0, q, torch.ones_like(q)), inf)
        r1 = torch.where((r1 > 0) & (disc >= 0), r1, inf)
        r2 = torch.where((r2 > 0) & (disc >= 0), r2, inf)
        root = torch.minimum(r1, r2)
        tmin = torch.full((mesh.num_items,), float("inf"), dtype=v.dtype, device=v.device)
        tmin = tmin.scatter_reduce(0, mesh.face_item, root, "amin") * k
        return (safety * tmin).clamp(max=1.0)
