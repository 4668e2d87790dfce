"""Soft inside/outside and soft rasterization of implicit simplicial curves.

``soft_inside(p) = sigmoid(-sd(p) / tau)`` where ``sd`` is the *signed* Euclidean distance
to the item's zero set (negative inside, i.e. where ``f < 0``). It is continuous in the
point (``sd`` is 0 on the curve from both sides), finite with finite gradients everywhere,
and a point off its item's mesh is outside (its distance to the curve is finite, so the
value decays smoothly toward 0 as it moves away). ``mode="local"`` instead uses the
first-order distance ``f / |∇f_t|`` of the point's own triangle (cheaper, O(N), but
discontinuous across triangle edges away from the curve); off the mesh it is exactly 0
with zero gradient. No route ever indexes a triangle with ``face = -1``.
"""
from __future__ import annotations

import numbers
import operator
from typing import Optional, Sequence, Tuple, Union

import torch

from torch_isc.core.locate import barycentric, finite_rows, locate_grid
from torch_isc.core.mesh import _segment_bbox, pow2_unit
from torch_isc.core.segments import segment_max
from torch_isc.core.measures import check_curve, unit_distance

__all__ = ["soft_inside", "rasterize", "pixel_centers"]


def soft_inside(curve, points: torch.Tensor, tau: float, point_item: Optional[torch.Tensor] = None,
                mode: str = "distance") -> torch.Tensor:
    """``(N,)`` soft occupancy in ``(0, 1)`` of ``points (N, 2)`` (``point_item (N,)``, default 0).

    Differentiable in the points, the vertex positions and the values; values and gradients
    are finite everywhere (off the mesh included). ``tau`` is a distance (the width of the
    soft edge). See the module docstring for ``mode`` (``"distance"`` or ``"local"``).

    Example:
        >>> from torch_isc import ImplicitCurve, square_mesh
        >>> m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
        >>> c = ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)
        >>> p = torch.tensor([[0., 0.], [0.6, 0.], [0.7, 0.], [1.5, 0.]], dtype=torch.float64)   # the last one is off the mesh
        >>> soft_inside(c, p, tau=0.1)
        tensor([9.9753e-01, 5.0000e-01, 2.6894e-01, 1.2339e-04], dtype=torch.float64)
    """
    check_curve(curve, "soft_inside")
    _check_tau(tau, curve.mesh.device)
    mesh = curve.mesh
    point_item = curve._point_item(points, point_item)
    pts = points.to(mesh.dtype)
    if mesh.faces.shape[0] == 0:                   # no triangle (an all-black mask's curve): empty
        return torch.zeros(pts.shape[0], dtype=pts.dtype, device=pts.device)
    pts, ok = finite_rows(pts)                     # a NaN or infinite point is outside: 0, no gradient
    curve, sc = curve.unit_scaled()               # exact (see ImplicitCurve.unit_scaled)
    mesh = curve.mesh
    s_p = sc[point_item]
    pts = pts * s_p[:, None]
    with torch.no_grad():
        face, _ = locate_grid(mesh, pts, point_item)
        on = face >= 0
        fc = face.clamp_min(0)
        # off the mesh: outside, but in an inside hole of an enclosed item (a band mesh)
        hole = curve.off_mesh_inside(pts, point_item, ~on)
    bary = barycentric(mesh.verts, mesh.faces, fc, pts)          # fc: never -1
    f = (curve.values[mesh.faces[fc]] * bary).sum(1)
    if mode == "local":
        # f / |grad f| does not change when the values are multiplied by a power of two: bring
        # each item's into [0.5, 1) first, so |grad f|^2 neither overflows nor underflows
        with torch.no_grad():
            vmag = segment_max(curve.values.detach().abs(), mesh.vert_item, mesh.num_items, fill=0)
            sv = pow2_unit(vmag)[point_item]
        f = f * sv
        G = mesh.bary_gradients()[fc]
        g = (G * curve.values[mesh.faces[fc]][..., None]).sum(1) * sv[:, None]
        r = f / torch.sqrt((g * g).sum(1).clamp_min(torch.finfo(pts.dtype).tiny)) / s_p
        s = torch.sigmoid(-r / tau)
        return torch.where(ok, torch.where(on, s, hole.to(s.dtype)), torch.zeros_like(s))
    if mode != "distance":
        raise ValueError(f"mode must be 'distance' or 'local', got {mode!r}")
    d = unit_distance(curve, pts, point_item)[0] / s_p
    with torch.no_grad():
        sign = torch.where((on & (f < 0)) | hole, -1.0, 1.0).to(pts.dtype)
    s = torch.sigmoid(-sign * d / tau)
    return torch.where(ok, s, torch.zeros_like(s))


def _check_tau(tau, device=None) -> None:
    """A number ``tau`` must be a finite width > 0 (NaN gave NaN images, a negative one the
    inverted occupancy, 0 NaN on the curve); a tensor is the caller's (it may be learned), but
    it must be one number and on the curve's device (a CPU scalar goes anywhere)."""
    if torch.is_tensor(tau):
        if tau.numel() != 1 or tau.is_complex() or not tau.is_floating_point():
            raise ValueError(f"tau must be one real floating number, got a {tuple(tau.shape)} {tau.dtype} tensor")
        if device is not None and tau.device != device and not (tau.device.type == "cpu" and tau.dim() == 0):
            raise ValueError(f"tau is on {tau.device}, the curve on {device}")
        return
    if not (isinstance(tau, numbers.Real) and not isinstance(tau, bool) and 0 < tau < float("inf")):
        raise ValueError(f"tau must be a finite distance > 0, got {tau!r}")


def _image_size(height, width) -> Tuple[int, int]:
    size = []
    for name, v in (("height", height), ("width", width)):
        try:
            n = operator.index(v)             # int, numpy and 0-d integer tensors; not 8.5
        except TypeError:
            n = -1
        if n < 0 or isinstance(v, bool):
            raise ValueError(f"{name} must be an integer >= 0, got {v!r:.40}")
        size.append(n)
    return size[0], size[1]


def pixel_centers(height: int, width: int, extent: torch.Tensor) -> torch.Tensor:
    """``(B, H, W, 2)`` pixel centres: pixel ``(i, j)`` of item ``b`` is at
    ``(xmin + (j + 1/2) dx, ymin + (i + 1/2) dy)``, ``dx = (xmax - xmin) / W``,
    ``dy = (ymax - ymin) / H`` (row ``i`` grows with ``y``; flip rows to show y up).
    ``extent``: a ``(B, 4)`` floating tensor."""
    height, width = _image_size(height, width)
    if not torch.is_tensor(extent) or extent.dim() != 2 or extent.shape[1] != 4 or not extent.is_floating_point():
        got = f"a {tuple(extent.shape)} {extent.dtype} tensor" if torch.is_tensor(extent) else type(extent).__name__
        raise ValueError(f"extent must be a (B, 4) floating tensor, got {got}")
    ext = extent
    dev, dt = ext.device, ext.dtype
    i = (torch.arange(height, device=dev, dtype=dt) + 0.5) / height
    j = (torch.arange(width, device=dev, dtype=dt) + 0.5) / width
    x = ext[:, 0, None] + j[None] * (ext[:, 2] - ext[:, 0])[:, None]       # (B,W)
    y = ext[:, 1, None] + i[None] * (ext[:, 3] - ext[:, 1])[:, None]       # (B,H)
    B = ext.shape[0]
    return torch.stack([x[:, None, :].expand(B, height, width), y[:, :, None].expand(B, height, width)], -1)


#: the most pixels one :func:`rasterize` call renders (all items together): each costs about
#: 1.2 KB of intermediate and saved tensors (float64 at 1000 x 1000, scripts/benchmark_raster.py),
#: so 2**23 pixels are about 10 GB; a larger image is rendered in tiles (an ``extent`` per call)
MAX_RASTER_PIXELS = 1 << 23


def rasterize(curve, height: int, width: int, tau: float,
              extent: Union[None, Sequence[float], torch.Tensor] = None, mode: str = "distance") -> torch.Tensor:
    """``(B, H, W)`` soft occupancy images of every item of a packed batch.

    Args:
        height, width: image size. tau: soft edge width (a distance).
        extent: ``(xmin, ymin, xmax, ymax)`` for all items, or a ``(B, 4)`` tensor; default
            each item's mesh bounding box. Pixel layout: :func:`pixel_centers`.
        mode: see :func:`soft_inside`.

    Example:
        >>> from torch_isc import ImplicitCurve, square_mesh
        >>> m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
        >>> c = ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)
        >>> (rasterize(c, 4, 4, tau=1e-3) > 0.5).int()
        tensor([[[0, 0, 0, 0],
                 [0, 1, 1, 0],
                 [0, 1, 1, 0],
                 [0, 0, 0, 0]]], dtype=torch.int32)
    """
    check_curve(curve, "rasterize")
    height, width = _image_size(height, width)
    _check_tau(tau, curve.mesh.device)
    mesh = curve.mesh
    B, dt, dev = mesh.num_items, mesh.dtype, mesh.device
    if B * height * width > MAX_RASTER_PIXELS:
        big = [f"{v}" if v < 10 ** 12 else f"about 10^{len(str(v)) - 1}" for v in (height, width)]
        raise ValueError(f"height x width x items = {big[0]} x {big[1]} x {B}: more than {MAX_RASTER_PIXELS} pixels "
                         f"(render fewer items or a smaller image at a time)")
    if extent is None:
        # in the graph: the pixel grid moves with the vertices (a detached box gave gradients
        # that ignored it: -1.03 by finite differences against 13.31 for a uniform scaling)
        ext = _segment_bbox(mesh.verts, mesh.vert_item, mesh.num_items)
    else:
        try:
            ext = torch.as_tensor(extent, dtype=dt, device=dev)
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"extent must be 4 numbers or a ({B}, 4) tensor, got {extent!r:.60}") from None
        if ext.dim() == 1 and ext.numel() == 4:
            ext = ext[None].expand(B, 4)
        if ext.shape != (B, 4):
            raise ValueError(f"extent must be 4 numbers or a ({B}, 4) tensor, got shape {tuple(ext.shape)}")
        if not bool((torch.isfinite(ext).all(1) & (ext[:, 2] > ext[:, 0]) & (ext[:, 3] > ext[:, 1])).all()):
            raise ValueError("extent must be finite (xmin, ymin, xmax, ymax) with xmin < xmax and ymin < ymax")
    pts = pixel_centers(height, width, ext).reshape(-1, 2)
    item = torch.arange(B, device=dev).repeat_interleave(height * width)
    return soft_inside(curve, pts, tau, item, mode=mode).view(B, height, width)
