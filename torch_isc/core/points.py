"""Packed batches of 2D point sets: the input of the pipeline.

A :class:`PointBatch` holds ``B`` point sets the way :class:`~torch_isc.core.mesh.MeshBatch`
holds meshes: all points in one ``(P, 2)`` tensor, item by item, with a per-point item index
and per-item counts. :func:`prepare_points` turns the caller's point sets into the batch the
loop works on: checked, exact repeats merged, and each item normalized (bounding box centred,
diagonal 1) in float64 so that results do not depend on translation or scale.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence, Union

import numpy as np
import torch

from torch_isc._helpers import one_line, printable
from torch_isc.core.segments import first_index, segment_count, segment_max, segment_min, segment_sum

__all__ = ["PointsLike", "PointSetError", "item_label", "PointBatch", "check_points", "distinct_points", "collinear_items",
           "prepare_points", "check_extent", "output_dtypes"]


PointsLike = Union[torch.Tensor, np.ndarray, Sequence[Sequence[float]]]


class PointSetError(ValueError):
    """A point set that cannot be reconstructed (too few points, NaN, wrong shape...)."""


def item_label(name: object) -> str:
    """How a named item is shown in messages: one line (control characters escaped), at most
    200 characters."""
    return printable(name, limit=200)


#: numpy dtypes (native byte order) kept as they are, as the tensors they would be; the other
#: real ones (longdouble, object numbers, strings of numbers) become float64, and uint16-64 become
#: int64 (below, as torch's do)
_NUMPY_AS = {np.dtype(t).str: np.dtype(t) for t in (np.float16, np.float32, np.float64, np.int8, np.int16, np.int32,
                                                     np.int64, np.uint8, np.uint16, np.uint32, np.uint64)}
_UNSIGNED = tuple(getattr(torch, n) for n in ("uint16", "uint32", "uint64") if hasattr(torch, n))


def check_points(x: PointsLike, label: str, finite: bool = True) -> torch.Tensor:
    """``x`` as a tensor of shape ``(N, 2)``, real, dense, not empty and (with ``finite``) with
    finite coordinates; else :class:`PointSetError` naming ``label``. The finiteness check reads
    the device: a batch checks all its sets at once instead (:func:`prepare_points`)."""
    if isinstance(x, torch.Tensor):
        if x.layout != torch.strided:
            raise PointSetError(f"{label}: expected a dense (strided) tensor, got layout {x.layout}")
        if x.device.type == "meta":
            raise PointSetError(f"{label}: a meta tensor holds no values")
        if x.is_quantized:
            raise PointSetError(f"{label}: expected real coordinates, got a quantized tensor")
    else:
        if isinstance(x, np.ma.MaskedArray) and bool(np.ma.getmaskarray(x).any()):
            raise PointSetError(f"{label}: a masked array with {int(np.ma.getmaskarray(x).sum())} masked "
                                f"value(s): drop or fill them first")
        try:
            a = np.asarray(x)
            if a.dtype.kind in "cbmMV":       # complex, bool, dates, raw bytes: as a tensor of them would be
                raise PointSetError(f"{label}: expected real coordinates, got dtype {a.dtype}")
            # the dtype the equal tensor has, so that the outputs' dtype follows the input's
            a = np.asarray(a, dtype=_NUMPY_AS.get(a.dtype.newbyteorder("=").str, np.float64))
        except (TypeError, ValueError, OverflowError) as e:
            if isinstance(e, PointSetError):
                raise
            raise PointSetError(f"{label}: not an array of numbers ({one_line(e, type(e).__name__)[:200]})") from None
        # torch takes neither negative strides (a[::-1]) nor, without a warning, read-only memory
        if any(st < 0 for st in a.strides) or not a.flags.writeable:
            a = a.copy()
        x = torch.from_numpy(a)
    if x.dim() != 2 or x.shape[1] != 2:
        raise PointSetError(f"{label}: expected points of shape (N, 2), got {tuple(x.shape)}")
    if x.dtype.is_floating_point and x.element_size() == 1:
        # float8: a storage format torch does not promote or reduce; its values are exact in float32
        x = x.float()
    if x.dtype in _UNSIGNED:
        # torch reduces and compares few of these; int64 holds them all but the top half of uint64
        wide = x.dtype == torch.uint64 and bool((x.view(torch.int64) < 0).any())
        x = x.to(torch.float64 if wide else torch.int64)
    if not (x.dtype.is_floating_point or x.dtype in (torch.int16, torch.int32, torch.int64, torch.uint8, torch.int8)):
        raise PointSetError(f"{label}: expected real coordinates, got dtype {x.dtype}")
    if x.shape[0] == 0:
        raise PointSetError(f"{label}: no points")
    if finite:
        bad = ~torch.isfinite(x.double()).all(1)
        if bad.any():
            raise PointSetError(f"{label}: {int(bad.sum())} point(s) have NaN or Inf coordinates")
    return x


def _pack64(sets: Sequence[torch.Tensor]) -> torch.Tensor:
    """``(P, 2)`` float64: the sets one after another, cast once when they share a dtype
    (exact for the inputs' float32/float64/integer values)."""
    if len({p.dtype for p in sets}) == 1:
        return torch.cat(list(sets)).to(torch.float64)
    return torch.cat([p.to(torch.float64) for p in sets])


def _item_index(sizes: Sequence[int], device) -> torch.Tensor:
    """``(P,)`` the item of each row of sets of ``sizes`` rows packed one after another."""
    n = torch.tensor(list(sizes), device=device)
    return torch.repeat_interleave(torch.arange(len(sizes), device=device), n, output_size=sum(sizes))


def _check_finite(x: torch.Tensor, item: torch.Tensor, labels: Sequence[str]) -> None:
    """Every set's coordinates finite (``x (P, 2)`` packed, ``item (P,)``), checked for the
    whole batch with one host read (a second one names the first bad set)."""
    bad = (~torch.isfinite(x).all(1)).long()
    if int(bad.sum()):
        for lab, k in zip(labels, segment_sum(bad, item, len(labels)).tolist()):
            if k:
                raise PointSetError(f"{lab}: {k} point(s) have NaN or Inf coordinates")


def distinct_points(sets: Sequence[torch.Tensor], labels: Sequence[str]):
    """The point *sets*: every item's points without exact repeats, in the order of first
    occurrence, packed in float64 (exact for the inputs' float32/float64/integer values).
    Repeats say nothing about the curve, but they would fool the noise estimate (a point's
    nearest neighbours would be its own copies: noise 0, tolerance floor gone) and the
    point-count guards of the test, and noisy data would be refined into spurious loops.

    Returns ``(points (P, 2) float64, point_item (P,), counts (B,), source (P,))``, for the
    whole batch at once: rows ``(item, x, y)`` sorted by three stable sorts (``unique(dim=0)``
    is several times slower), equal neighbours grouped; ``source`` is each kept point's index
    in its caller's set (a key that a merge elsewhere in the set does not shift)."""
    x = _pack64(sets)
    return _distinct_packed(x, _item_index([p.shape[0] for p in sets], x.device), len(sets), labels)


def _distinct_packed(x: torch.Tensor, item: torch.Tensor, B: int, labels: Sequence[str]):
    """:func:`distinct_points` of the packed float64 rows ``x (P, 2)`` of items ``item (P,)``
    (ascending), with one host read."""
    dev = x.device
    o = torch.argsort(x[:, 1], stable=True)
    o = o[torch.argsort(x[o, 0], stable=True)]
    o = o[torch.argsort(item[o], stable=True)]
    xs, its = x[o], item[o]
    new = torch.ones(o.shape[0], dtype=torch.bool, device=dev)
    new[1:] = (its[1:] != its[:-1]) | (xs[1:] != xs[:-1]).any(1)
    gid = torch.cumsum(new.long(), 0) - 1
    counts = segment_sum(new.long(), its, B)
    G, n_few = torch.stack([gid[-1] + 1, (counts < 3).sum()]).tolist()
    if n_few:
        b = int((counts < 3).nonzero()[0, 0])
        raise PointSetError(f"{labels[b]}: needs at least 3 distinct points, got {int(counts[b])}")
    start = first_index(segment_count(item, B))
    if G == x.shape[0]:
        return x, item, counts, torch.arange(x.shape[0], device=dev) - start[item]
    first = segment_min(o, gid, G, fill=x.shape[0])
    keep = first.sort().values                       # item-major, first occurrence within an item
    return x[keep], item[keep], counts, keep - start[item[keep]]


#: points of one item closer than this fraction of its diagonal are repeats too (about 8 float32
#: ulps of the normalized coordinates, 1/8 of the finest tolerance float32 resolves): a set given
#: twice with a 1e-9 jitter has its nearest-neighbour spacings collapsed to the jitter, so the
#: crust (segments of a few median spacings) and the noise estimate see nothing of the curve
NEAR_REPEAT = 2.0 ** -20


def merge_near_repeats(norm64: torch.Tensor, point_item: torch.Tensor, counts: torch.Tensor,
                       source: torch.Tensor, B: int, labels: Sequence[str], radius: float = NEAR_REPEAT):
    """Merge the points of an item that share a cell of side ``radius`` of the normalized
    ``norm64 (P, 2)`` (float64, each item's bounding box centred, diagonal 1), on four grids
    offset by half a cell in x, y or both: two points less than ``radius / 2`` apart on each
    axis share a cell of at least one of them. Each cell keeps its first point (in the item's
    order), so a dense scan is thinned to one point per cell, never collapsed along a chain.
    Returns ``(norm64, point_item, counts, source)`` of the points kept (the inputs when
    nothing merges; a host read per grid)."""
    if norm64.shape[0] == 0:
        return norm64, point_item, counts, source
    keep = torch.arange(norm64.shape[0], device=norm64.device)
    for shift in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        off = torch.tensor(shift, dtype=norm64.dtype, device=norm64.device)
        q = torch.floor(norm64[keep] / radius + off).long() + (1 << 20)    # |x| <= 0.5: 0 < q < 2^21
        it = point_item[keep]
        cell = (q[:, 0] << 21) | q[:, 1]
        o = torch.argsort(cell)
        o = o[torch.argsort(it[o], stable=True)]                          # item-major (any B)
        its, cs = it[o], cell[o]
        new = torch.ones(o.shape[0], dtype=torch.bool, device=o.device)
        new[1:] = (its[1:] != its[:-1]) | (cs[1:] != cs[:-1])
        gid = torch.cumsum(new.long(), 0) - 1
        G = int(gid[-1]) + 1
        if G < o.shape[0]:
            keep = keep[segment_min(o, gid, G, fill=o.shape[0]).sort().values]
    if keep.shape[0] == norm64.shape[0]:
        return norm64, point_item, counts, source
    item = point_item[keep]
    new_counts = segment_count(item, B)
    few = new_counts < 3
    if bool(few.any()):
        b = int(few.nonzero()[0, 0])
        raise PointSetError(f"{labels[b]}: needs at least 3 distinct points, got {int(new_counts[b])} "
                            f"(points closer than {radius:.2g} of the diagonal are one point)")
    return norm64[keep], item, new_counts, source[keep]


#: far outliers: points farther from the item's median centre than this many times the median
#: distance to it ...
FAR_OUTLIER_FACTOR = 16.0
#: ... are dropped when they are at most this fraction of the item's distinct points (or 4 points),
#: so a second cluster of real data (more points) is kept; the result counts them (``far_outliers``)
FAR_OUTLIER_FRACTION = 0.01
FAR_OUTLIER_MIN_ALLOWED = 4


def _sorted_median(x: torch.Tensor, item: torch.Tensor, first: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """``(B,)`` the lower median of ``x`` per item of the packed, item-major rows, exactly (no
    key that would round differently with the item's place in the batch): a sort by value, its
    order among equal values irrelevant (they are equal), then a stable sort by item."""
    o1 = torch.argsort(x)
    order = o1[torch.argsort(item[o1], stable=True)]
    mid = first + (counts - 1).clamp_min(0) // 2
    return x[order[mid.clamp_max(x.numel() - 1)]]


def drop_far_outliers(pts64: torch.Tensor, point_item: torch.Tensor, counts: torch.Tensor,
                      source: torch.Tensor, B: int):
    """Drop the few points lying far from the bulk of their item. One point 1e12 away from a
    ring of radius 1 makes the bounding box 1e12 wide: the ring would be a dot in it (no curve);
    one 100 radii away already leaves it unresolved at the default tolerance. Returns the
    packed rows kept ``(pts64, point_item, counts, source)`` and the host list of the number
    dropped per item (one host read)."""
    if pts64.shape[0] == 0:
        return pts64, point_item, counts, source, [0] * B
    # in units of the item's largest coordinate: no overflow near 1e308
    m = pts64.abs().amax(1).new_zeros(B).scatter_reduce(0, point_item, pts64.abs().amax(1), "amax")
    u = pts64 / m.clamp_min(torch.finfo(torch.float64).tiny)[point_item, None]
    first = first_index(counts)
    med = torch.stack([_sorted_median(u[:, 0], point_item, first, counts),
                       _sorted_median(u[:, 1], point_item, first, counts)], 1)
    d = torch.hypot(u[:, 0] - med[point_item, 0], u[:, 1] - med[point_item, 1])
    d50 = _sorted_median(d, point_item, first, counts)
    far = (d > FAR_OUTLIER_FACTOR * d50[point_item]) & (d50[point_item] > 0)
    n_far = segment_sum(far.long(), point_item, B)
    allowed = torch.maximum((counts.double() * FAR_OUTLIER_FRACTION).floor().long(), torch.full_like(counts, FAR_OUTLIER_MIN_ALLOWED))
    ok = (n_far > 0) & (n_far <= allowed) & (counts - n_far >= 3)
    dropped = torch.where(ok, n_far, torch.zeros_like(n_far))
    host = dropped.tolist()
    if not any(host):
        return pts64, point_item, counts, source, host
    keep = ~(far & ok[point_item])
    return pts64[keep], point_item[keep], counts - dropped, source[keep], host


#: a point set's diagonal must span at least this many rounding steps (eps x its largest
#: coordinate) of its dtype, else :class:`PointSetError`: float64 at an offset of 1e15 steps by
#: 0.125 to 0.25, so a shape there must be at least ~2 across
MIN_RESOLVED_STEPS = 8.0


def collinear_items(pts64: torch.Tensor, point_item: torch.Tensor, B: int, slack: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: every point of the item lies within ``slack`` of one line (float64,
    normalized coordinates). Measured as the largest distance to the principal axis, so no
    cancellation in an eigenvalue limits the precision."""
    n = segment_count(point_item, B).to(pts64.dtype)
    mean = torch.zeros(B, 2, dtype=pts64.dtype, device=pts64.device).index_add_(0, point_item, pts64) / n[:, None]
    d = pts64 - mean[point_item]
    cov = torch.zeros(B, 3, dtype=pts64.dtype, device=pts64.device).index_add_(
        0, point_item, torch.stack([d[:, 0] * d[:, 0], d[:, 0] * d[:, 1], d[:, 1] * d[:, 1]], 1))
    theta = 0.5 * torch.atan2(2 * cov[:, 1], cov[:, 0] - cov[:, 2])        # principal direction
    normal = torch.stack([-theta.sin(), theta.cos()], 1)
    off = (d * normal[point_item]).sum(1).abs()
    worst = segment_max(off, point_item, B, fill=0)
    return worst <= slack




@dataclass
class PointBatch:
    """Packed point sets with their normalization.

    Attributes:
        points: ``(P, 2)`` normalized points (working dtype), item by item.
        point_item: ``(P,)`` long, each point's item.
        counts: ``(B,)`` long, points per item.
        center: ``(B, 2)`` float64 and scale: ``(B,)`` float64, the frame of each item: a caller's
            point ``x`` is ``points * scale + center``.
        flat: ``(B,)`` bool, items whose points lie on one line (no region to enclose).
        raw: the caller's point sets as given (checked tensors).
        labels: a name per item for messages.
        source: ``(P,)`` long, each point's index in its caller's set (None: its index in the
            item), the key of per-point hashes (a merged repeat does not shift the others').
        far_outliers: per item, how many distinct points :func:`drop_far_outliers` dropped (host ints).
    """
    points: torch.Tensor
    point_item: torch.Tensor
    counts: torch.Tensor
    center: torch.Tensor
    scale: torch.Tensor
    flat: torch.Tensor
    raw: List[torch.Tensor]
    labels: List[str]
    source: Optional[torch.Tensor] = None
    far_outliers: Optional[List[int]] = None

    @property
    def num_items(self) -> int:
        return int(self.counts.shape[0])

    @property
    def first_idx(self) -> torch.Tensor:
        """``(B,)`` the first point of each item."""
        return first_index(self.counts)

    def points_list(self) -> List[torch.Tensor]:
        """The normalized points of each item."""
        return list(torch.split(self.points, self.counts.tolist()))


def prepare_points(point_sets: Sequence[PointsLike], names: Optional[Sequence[Optional[str]]] = None,
                   dtype: torch.dtype = torch.float32, drop_far: bool = True) -> PointBatch:
    """Check, merge repeats, pack and normalize ``point_sets`` (each ``(N_b, 2)``); with
    ``drop_far``, leave out far outliers (:func:`drop_far_outliers`; not with a sign oracle,
    which knows a far speck is real).

    Raises :class:`PointSetError` naming the first bad set.

    Example:
        >>> pb = prepare_points([torch.tensor([[0., 0.], [2., 0.], [0., 2.], [0., 0.]])])
        >>> pb.counts.tolist(), pb.scale.tolist(), pb.center.tolist()
        ([3], [2.8284271247461903], [[1.0, 1.0]])
    """
    names = list(names) if names is not None else [None] * len(point_sets)
    if len(names) != len(point_sets):
        raise PointSetError(f"names: {len(names)} name(s) for {len(point_sets)} point set(s)")
    labels = [item_label(n) if n is not None else f"point set {i}" for i, n in enumerate(names)]
    raw = [check_points(p, lab, finite=False) for p, lab in zip(point_sets, labels)]
    device = raw[0].device
    for p, lab in zip(raw, labels):
        if p.device != device:
            raise PointSetError(f"{lab}: on {p.device}, but the batch is on {device}")
    B = len(raw)
    with torch.no_grad():
        x64 = _pack64(raw)
        item = _item_index([p.shape[0] for p in raw], device)
        _check_finite(x64, item, labels)
        pts64, point_item, counts, source = _distinct_packed(x64, item, B, labels)
        far = [0] * B
        if drop_far:
            pts64, point_item, counts, source, far = drop_far_outliers(pts64, point_item, counts, source, B)
        # normalize in float64, then cast: large offsets (1e7) must not cost precision
        big = torch.finfo(torch.float64).max
        idx2 = point_item[:, None].expand(-1, 2)
        lo = torch.full((B, 2), big, dtype=torch.float64, device=device).scatter_reduce(0, idx2, pts64, "amin")
        hi = torch.full((B, 2), -big, dtype=torch.float64, device=device).scatter_reduce(0, idx2, pts64, "amax")
        reach = torch.maximum(lo.abs(), hi.abs()).amax(1)
        center64 = 0.5 * (lo + hi)
        scale64 = (hi - lo).norm(dim=1)
        norm64 = (pts64 - center64[point_item]) / scale64[point_item, None]
        # extreme magnitudes (squares that overflow or underflow float64, sums that overflow):
        # the same frame computed in units of the item's largest coordinate
        plain = (reach < 1e150) & ((hi - lo).amax(1) > 1e-150)
        if not bool(plain.all()):
            m = reach.clamp_min(torch.finfo(torch.float64).tiny)
            lo_m, hi_m = lo / m[:, None], hi / m[:, None]
            c_m = 0.5 * (lo_m + hi_m)
            d_m = torch.hypot(hi_m[:, 0] - lo_m[:, 0], hi_m[:, 1] - lo_m[:, 1])
            center64 = torch.where(plain[:, None], center64, c_m * m[:, None])
            scale64 = torch.where(plain, scale64, d_m * m)
            mi = m[point_item, None]
            safe64 = (pts64 / mi - c_m[point_item]) / d_m[point_item, None]
            norm64 = torch.where(plain[point_item, None], norm64, safe64)
            bad = (~torch.isfinite(scale64)) | (scale64 <= 0) | (~torch.isfinite(center64).all(1))
            if bool(bad.any()):
                b = int(bad.nonzero()[0, 0])
                raise PointSetError(f"{labels[b]}: coordinates too large for float64 (largest magnitude "
                                    f"{float(reach[b]):.3g}: the bounding box's diagonal overflows)")
        # the input's rounding at its own magnitude (eps * largest coordinate: 1 to 2 ulps; 0 for
        # integers). A set a few such steps across is a handful of grid nodes: refuse it by name
        # rather than answer from rounding (a circle of radius 0.5 at an offset of 1e15, where
        # float64 steps by 0.125, is 11 ulps across and still reconstructed)
        ulp = torch.tensor([torch.finfo(p.dtype).eps if p.dtype.is_floating_point else 0.0 for p in raw],
                           dtype=torch.float64, device=device)
        # integers are exact until the float64 packing rounds them (beyond 2^53)
        ulp = torch.where((ulp == 0) & (reach > 2.0 ** 53), torch.finfo(torch.float64).eps, ulp)
        step = ulp * reach
        coarse = (scale64 > 0) & (scale64 < MIN_RESOLVED_STEPS * step)      # one point: no curve, not an error
        if bool(coarse.any()):
            b = int(coarse.nonzero()[0, 0])
            raise PointSetError(
                f"{labels[b]}: the points span {float(scale64[b]):.3g} at coordinates of magnitude {float(reach[b]):.3g}, "
                f"only {float(scale64[b] / step[b]):.1f} rounding steps of "
                f"{str(raw[b].dtype if raw[b].dtype.is_floating_point else torch.float64).replace('torch.', '')} "
                f"there (at least {MIN_RESOLVED_STEPS:g} needed): subtract the offset first")
        # points on one line (up to the rounding of the input: each coordinate is off by at most
        # half a step, the fitted axis by about as much) enclose no region: such an item stops at
        # level 0 with no curve (limit "no_curve"), not with a loop the data cannot support
        norm64, point_item, counts, source = merge_near_repeats(norm64, point_item, counts, source, B, labels)
        flat = collinear_items(norm64, point_item, B, 1e-12 + 2 * step / scale64)
        return PointBatch(norm64.to(dtype), point_item, counts, center64, scale64, flat, raw, labels, source, far)


def output_dtypes(raw: Sequence[torch.Tensor], dtype: torch.dtype) -> List[torch.dtype]:
    """The precision of each set's outputs: its floating dtype (integers: ``dtype``) promoted
    with the working ``dtype``; worked out once per distinct input dtype."""
    memo = {}
    for d in dict.fromkeys(p.dtype for p in raw):
        memo[d] = torch.promote_types(d if d.is_floating_point else dtype, dtype)
    return [memo[p.dtype] for p in raw]


def check_extent(batch: PointBatch, cover: float, dtype: torch.dtype) -> None:
    """Raise :class:`PointSetError` naming the first item whose mesh, reaching ``cover``
    diagonals from the centre of its points, would not fit in its output precision (the
    caller's floating dtype promoted with ``dtype``, float64 at most): its outputs would
    hold Inf."""
    with torch.no_grad():
        far = batch.center.abs().amax(1) + 2.0 * cover * batch.scale
        for b, (f, odt) in enumerate(zip(far.tolist(), output_dtypes(batch.raw, dtype))):
            top = torch.finfo(odt).max
            if not f < top:
                raise PointSetError(f"{batch.labels[b]}: coordinates too large: the mesh around the points "
                                    f"reaches {f:.3g}, beyond the largest {str(odt).replace('torch.', '')} "
                                    f"({top:.3g})")
