"""Masks to curves: boundary points on the pixel cracks, their resampling, the mask as
inside/outside function (:class:`MaskOracle`) and the batched mask reconstruction."""
from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from torch_isc._helpers import finite_real, import_cv2
from torch_isc.images.arrays import ImageError, ImageLike, as_masks, binarize, default_names, image_list
from torch_isc.images.settings import as_image_config, image_config
from torch_isc.pipeline.config import ReconstructConfig

__all__ = ["mask_crack_contours", "resample_closed", "mask_to_points", "mask_points", "auto_threshold",
           "MaskOracle", "solve_masks", "reconstruct_masks", "grid_results"]


_DIRS = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]], np.int64)  # (dx, dy), y down
_CODE = np.full((3, 3), -1, np.int64)
_CODE[_DIRS[:, 1] + 1, _DIRS[:, 0] + 1] = np.arange(8)


def mask_crack_contours(mask: ImageLike, threshold: Optional[float] = None
                        ) -> Tuple[List[np.ndarray], np.ndarray]:
    """Boundary of one mask as closed polylines through the midpoints of its cracks.

    ``cv2.findContours(RETR_TREE, CHAIN_APPROX_NONE)`` traces every boundary pixel of every
    foreground component and hole (8-connected foreground). At each traced pixel the tracer
    passes the background neighbours between its predecessor and successor; the 4-neighbours
    among them are the pixel edges (cracks) that the contour follows, and their midpoints
    (pixel centre +- 1/2) replace the pixel, in order. The result lies on the boundary of the
    union of foreground pixel squares, in the pixel convention of this module, with the
    foreground on the left of the direction of travel (math orientation: outer contours
    counter-clockwise in ``(x, y)``, holes clockwise). A 1-pixel-wide stroke gives both of its
    sides; a single pixel gives its 4 crack midpoints.

    Returns:
        ``(contours, hierarchy)``: a list of ``(n_k, 2)`` float64 arrays and OpenCV's
        ``(N, 4)`` int32 ``[next, prev, first_child, parent]`` (RETR_TREE), ``N`` may be 0.

    >>> m = np.zeros((4, 5), bool); m[1:3, 1:4] = True
    >>> c, h = mask_crack_contours(m)
    >>> c[0].min(0).tolist(), c[0].max(0).tolist(), len(c[0])
    ([1.0, 1.0], [4.0, 3.0], 10)
    """
    cv2 = import_cv2()
    t = mask if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
    fg = binarize(t, threshold).detach().cpu().numpy()
    H, W = fg.shape
    padded = np.zeros((H + 2, W + 2), np.uint8)            # a background frame: contours may touch the edge
    padded[1:-1, 1:-1] = fg
    found = cv2.findContours(padded, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
    contours, hier = found[-2], found[-1]
    if hier is None or len(contours) == 0:
        return [], np.zeros((0, 4), np.int32)
    hier = hier.reshape(-1, 4).astype(np.int32)
    counts = np.array([len(c) for c in contours], np.int64)
    P = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.int64)    # padded cv coords
    cid = np.repeat(np.arange(len(contours)), counts)
    start = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(P.shape[0]) - start
    n = counts[cid]
    prev = P[start + (k - 1) % n]
    nxt = P[start + (k + 1) % n]
    dprev, dnext = prev - P, nxt - P
    single = n == 1
    cb = _CODE[np.clip(dprev[:, 1], -1, 1) + 1, np.clip(dprev[:, 0], -1, 1) + 1]
    cf = _CODE[np.clip(dnext[:, 1], -1, 1) + 1, np.clip(dnext[:, 0], -1, 1) + 1]
    cb = np.where(single, 0, cb)
    cf = np.where(single, 0, cf)
    # OpenCV traces with the foreground on the right of travel (y down), so the background
    # neighbours lie on the left: codes cf+1 .. cb-1 (increasing), passed in decreasing order
    span = (cb - cf - 1) % 8 + 1                          # number of codes strictly between, +1
    span = np.where(single, 8, span)                     # an isolated pixel: all around
    steps = np.arange(1, 8)                               # offsets from cb going down
    codes = (cb[:, None] - steps[None, :]) % 8            # (P, 7) in travel order
    between = steps[None, :] < span[:, None]
    if single.any():                                      # isolated pixel: 8 codes starting at 0
        codes = np.concatenate([codes, np.where(single, cb, -1)[:, None] % 8], 1)
        between = np.concatenate([between, single[:, None]], 1)
    d = _DIRS[codes]                                      # (P, K, 2)
    nb = P[:, None, :] + d
    is_bg = padded[nb[..., 1].clip(0, H + 1), nb[..., 0].clip(0, W + 1)] == 0
    take = between & (codes % 2 == 0) & is_bg
    centre = P.astype(np.float64) - 0.5                   # padded cv coords -> pixel-convention centre
    mid = centre[:, None, :] + 0.5 * d                    # (P, K, 2)
    pts = mid[take]
    owner = np.broadcast_to(cid[:, None], take.shape)[take]
    per = np.bincount(owner, minlength=len(contours))
    pieces = np.split(pts, np.cumsum(per)[:-1])
    # reverse: OpenCV's order has the foreground on the right; ours has it on the left
    return [np.ascontiguousarray(q[::-1]) for q in pieces], hier


#: the most samples :func:`resample_closed` makes (a spacing of 1e-9 px asked for 1.5 TB)
MAX_RESAMPLED = 1 << 27
#: the finest contour spacing of :func:`mask_to_points` and the CLI, in pixels: 100 points a pixel
#: (1e-3 made a 128x128 disc take 28 s and 0.9 GB, 1e-4 more than a minute and 1.7 GB)
MIN_SPACING = 0.01


def _check_spacing(spacing) -> None:
    if not finite_real(spacing):
        raise ImageError(f"spacing must be a finite number, got {spacing!r:.40}")


def _check_interpolation(interpolation) -> None:
    if interpolation not in ("nearest", "bilinear"):
        raise ImageError(f"interpolation must be 'nearest' or 'bilinear', got {interpolation!r:.40}")


def resample_closed(points: torch.Tensor, counts: torch.Tensor, spacing: float
                    ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Resample packed closed polylines to a uniform spacing along each one.

    Args:
        points: ``(P, 2)`` the vertices of all polylines, one after the other.
        counts: ``(C,)`` vertices per polyline.
        spacing: target distance between samples; each polyline of length ``L`` gets
            ``max(3, round(L / spacing))`` samples at equal arc-length steps (``<= 0``: no change).

    Returns:
        ``(points (Q, 2), counts (C,))`` on the input's device and dtype.

    >>> sq = torch.tensor([[0., 0], [4, 0], [4, 4], [0, 4]])
    >>> q, c = resample_closed(sq, torch.tensor([4]), 1.0)
    >>> c.tolist(), q[:3].tolist()
    ([16], [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    """
    _check_spacing(spacing)
    if spacing <= 0 or points.shape[0] == 0:
        return points, counts
    dev, dt = points.device, points.dtype
    counts = counts.to(dev, torch.long)
    C = counts.shape[0]
    first = torch.cumsum(counts, 0) - counts
    cid = torch.repeat_interleave(torch.arange(C, device=dev), counts)
    k = torch.arange(points.shape[0], device=dev) - first[cid]
    nxt = first[cid] + (k + 1) % counts[cid]
    seg = (points[nxt] - points).double().norm(dim=1)                 # segment k: vertex k -> k+1
    length = torch.zeros(C, dtype=torch.float64, device=dev).index_add_(0, cid, seg)
    n_new = torch.clamp(torch.round(length / spacing), min=3).long()
    # a global, increasing arc length: polyline c occupies [offset_c, offset_c + length_c)
    offset = torch.cumsum(length + 1.0, 0) - (length + 1.0)
    cum = torch.cumsum(seg, 0) - seg
    cum = cum - (torch.cumsum(length, 0) - length)[cid] + offset[cid]  # start of each segment
    total = int(n_new.sum())                      # one host read: the output's size, bounded
    if total > MAX_RESAMPLED:
        raise ImageError(f"spacing {spacing:g}: {total} samples, more than {MAX_RESAMPLED} (use a larger spacing)")
    qid = torch.repeat_interleave(torch.arange(C, device=dev), n_new, output_size=total)
    qfirst = torch.cumsum(n_new, 0) - n_new
    j = torch.arange(total, device=dev) - qfirst[qid]
    s = offset[qid] + length[qid] * j.double() / n_new[qid].double()
    idx = torch.searchsorted(cum.contiguous(), s.contiguous(), right=True) - 1
    idx = torch.maximum(idx, first[qid])
    t = ((s - cum[idx]) / seg[idx].clamp_min(1e-300)).clamp(0, 1)[:, None]
    a, b = points[idx].double(), points[nxt[idx]].double()
    return (a + t * (b - a)).to(dt), n_new


def mask_to_points(masks: Union[ImageLike, Sequence[ImageLike]], spacing: float = 1.0,
                   threshold: Optional[float] = None, dtype: Optional[torch.dtype] = None) -> List[torch.Tensor]:
    """Boundary points of a batch of masks, on the pixel cracks, resampled along the contours.

    Args:
        masks: a list of 2D masks (bool, uint8, float...; sizes may differ) or a
            ``(B, H, W)`` stack; foreground is ``value > threshold`` (see :func:`as_masks`).
        spacing: distance in pixels between consecutive points along a contour (``<= 0``: the
            raw crack midpoints, about 0.7 to 1 pixel apart).
        dtype: output dtype (default: the masks' floating dtype, else torch's default).

    Returns:
        one ``(N_b, 2)`` tensor per mask (pixel convention, on the masks' device). A mask
        without foreground, or entirely foreground, is fine here: ``N_b`` is 0 for no
        foreground, and a full mask gives its frame.

    >>> m = np.zeros((10, 10), np.uint8); m[2:8, 3:7] = 1
    >>> p = mask_to_points([m], spacing=2.0)[0]
    >>> p.shape, p[:, 0].min().item(), p[:, 1].max().item()
    (torch.Size([9, 2]), 3.0, 8.0)
    """
    if not finite_real(spacing) or 0 < spacing < MIN_SPACING:
        raise ImageError(f"spacing must be <= 0 (the crack midpoints) or a number of pixels >= {MIN_SPACING}, "
                         f"got {spacing!r:.40}")
    ts = image_list(masks, "mask")
    out: List[torch.Tensor] = []
    for t in ts:       # one findContours per image (OpenCV has no batched tracer)
        odt = dtype or (t.dtype if t.dtype.is_floating_point else torch.get_default_dtype())
        contours, _ = mask_crack_contours(t, threshold)
        if not contours:
            out.append(torch.zeros(0, 2, dtype=odt, device=t.device))
            continue
        pts = torch.from_numpy(np.concatenate(contours)).to(t.device)
        cnt = torch.tensor([len(c) for c in contours], device=t.device)
        q, _ = resample_closed(pts, cnt, spacing)
        out.append(q.to(odt))
    return out


# =============================================================================== the oracle
class MaskOracle:
    """A batch of masks as the inside/outside function of a reconstruction (Section 3.2).

    ``oracle(points (M, 2) float, item (M,) long) -> (M,) bool``: True where the point lies in
    a foreground pixel of mask ``item`` (the pixel containing it: ``(x, y)`` falls in pixel
    ``(floor(y), floor(x))``); points outside the image are outside. This is the batched
    oracle form of :func:`torch_isc.reconstruct_batch`; the masks are held packed (no padding),
    one lookup for all points of all items.

    Args:
        masks: as for :func:`as_masks`.
        threshold: as for :func:`as_masks`.
        interpolation: ``"nearest"`` (the pixel's value; the boundary is the crack polygon)
            or ``"bilinear"`` (the mask interpolated between pixel centres, thresholded at 1/2:
            the boundary is the polygon through the crack midpoints, which cuts the staircase
            corners like the boundary points do).

    >>> o = MaskOracle([np.eye(2, dtype=bool)])
    >>> o(torch.tensor([[0.5, 0.5], [1.5, 0.5], [-1.0, 0.0]]), torch.zeros(3, dtype=torch.long)).tolist()
    [True, False, False]
    """

    def __init__(self, masks: Union[ImageLike, Sequence[ImageLike]], threshold: Optional[float] = None,
                 interpolation: str = "bilinear"):
        _check_interpolation(interpolation)
        ms = as_masks(masks, threshold)
        self.interpolation = interpolation
        self.device = ms[0].device if ms else torch.device("cpu")
        self.height = torch.tensor([m.shape[0] for m in ms], dtype=torch.long, device=self.device)
        self.width = torch.tensor([m.shape[1] for m in ms], dtype=torch.long, device=self.device)
        sizes = self.height * self.width
        self.offset = torch.cumsum(sizes, 0) - sizes
        self.flat = torch.cat([m.reshape(-1) for m in ms]) if ms else torch.zeros(0, dtype=torch.bool)

    def __len__(self) -> int:
        return int(self.height.shape[0])

    def _lookup(self, item: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        H, W = self.height[item], self.width[item]
        ok = (i >= 0) & (j >= 0) & (i < H) & (j < W)
        idx = self.offset[item] + i.clamp(min=0) * W + j.clamp(min=0)
        idx = torch.where(ok, idx, torch.zeros_like(idx))
        return ok & self.flat[idx] if self.flat.numel() else ok & False

    def values(self, points: torch.Tensor, item: torch.Tensor) -> torch.Tensor:
        """``(M,)`` the mask's value at the points in ``[0, 1]`` (nearest or bilinear)."""
        p = torch.as_tensor(points).to(self.device, torch.float64)
        item = torch.as_tensor(item).to(self.device, torch.long)
        if self.interpolation == "nearest":
            return self._lookup(item, p[:, 1].floor().long(), p[:, 0].floor().long()).double()
        u, v = p[:, 0] - 0.5, p[:, 1] - 0.5                 # pixel centres at integers
        j0, i0 = u.floor(), v.floor()
        fu, fv = u - j0, v - i0
        j0, i0 = j0.long(), i0.long()
        val = torch.zeros_like(u)
        for di, dj, w in ((0, 0, (1 - fv) * (1 - fu)), (0, 1, (1 - fv) * fu), (1, 0, fv * (1 - fu)), (1, 1, fv * fu)):
            val = val + w * self._lookup(item, i0 + di, j0 + dj).double()
        return val

    def __call__(self, points: torch.Tensor, item: torch.Tensor) -> torch.Tensor:
        v = self.values(points, item)
        return v >= 0.5 if self.interpolation == "bilinear" else v > 0.5


def auto_threshold(image: np.ndarray) -> float:
    """The foreground threshold of a mask read from a file as gray values in [0, 1]: midway
    between the two levels of a two-level image (so 0/1 label PNGs and 0/255 masks both work),
    else 0.5.

    >>> auto_threshold(np.array([[0, 1 / 255]])), auto_threshold(np.array([[0.0, 0.2, 1.0]]))
    (0.00196078431372549, 0.5)
    """
    a = np.asarray(image)
    if a.size == 0:
        return 0.5
    lo, hi = a.min(), a.max()      # two levels iff every value is one of the extremes (no sort)
    if lo != hi and bool(((a == lo) | (a == hi)).all()):
        return float(np.array([lo, hi], dtype=np.float64).mean())
    return 0.5


def mask_points(mask: ImageLike, spacing: float = 1.0, threshold: Optional[float] = None,
                name: str = "mask") -> Tuple[torch.Tensor, int]:
    """:func:`mask_to_points` of one mask, plus its number of boundaries (contours).

    Raises:
        ImageError: no foreground pixel (``"<name>: empty mask ..."``).
    """
    t = mask if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
    contours, _ = mask_crack_contours(t, threshold)
    if not contours:
        raise ImageError(f"{name}: empty mask (no foreground pixel above the threshold)")
    p = torch.from_numpy(np.concatenate(contours)).to(t.device)
    q, _ = resample_closed(p, torch.tensor([len(c) for c in contours], device=t.device), spacing)
    return q.to(t.dtype if t.dtype.is_floating_point else torch.get_default_dtype()), len(contours)


def solve_masks(points: Sequence[torch.Tensor], masks: Sequence[ImageLike], n_boundaries: Optional[Sequence[int]],
                config: ReconstructConfig, names: Sequence[str], threshold: Optional[float] = None,
                use_oracle: bool = True, interpolation: str = "bilinear", retry: bool = True) -> list:
    """The reconstruction step of :func:`reconstruct_masks`, for boundary points already made
    (:func:`mask_points`): one batched solve, the mask as oracle, and the retry of the masks
    whose count of closed curves differs from ``n_boundaries``."""
    from torch_isc.pipeline.loop import initial_cover, reconstruct_batch

    oracle = MaskOracle(list(masks), threshold, interpolation) if use_oracle else None
    results = reconstruct_batch(list(points), config, list(names), oracle)
    if n_boundaries is None:
        return results
    redo = [] if not retry else [b for b, r in enumerate(results) if r.num_closed != n_boundaries[b] or r.num_open > 0]
    for b in redo:          # rare: one solve per mask, each with its own starting mesh
        p = points[b]
        diag = float((p.max(0).values - p.min(0).values).double().norm())
        side = initial_cover(config.mesh) * diag              # the initial mesh's side, in pixels
        r0 = config.mesh.initial_resolution
        res = max(r0, int(math.ceil(side / _RETRY_EDGE_PX)))
        res = min(res, max(r0, int(math.sqrt(config.limits.max_triangles / 6 / 4))))
        cfg = config.replace(tolerance=config.test.tolerance / 2, initial_resolution=res)
        sub = MaskOracle([masks[b]], threshold, interpolation) if use_oracle else None
        r = reconstruct_batch([p], cfg, [names[b]], sub)[0]
        if r.num_closed == n_boundaries[b] and r.num_open == 0:
            results[b] = r
    for r, nb in zip(results, n_boundaries):       # the flag grid_results and the CLI give
        r.boundaries = nb
        r.count_ok = count_matches(r, nb)
    return results


def count_matches(result, boundaries: Optional[int]) -> bool:
    """Whether ``result`` has ``boundaries`` closed curves and no open chain (True when the
    count is unknown): the mask's borders, as ``cv2.findContours`` counts them."""
    return boundaries is None or (result.num_closed == boundaries and result.num_open == 0)


#: Edge length in pixels of the starting mesh of a retry (:func:`solve_masks`).
_RETRY_EDGE_PX = 4.0


def reconstruct_masks(masks: Union[ImageLike, Sequence[ImageLike]], config: Optional[ReconstructConfig] = None,
                      spacing: float = 1.0, threshold: Optional[float] = None, use_oracle: bool = True,
                      names: Optional[Sequence[str]] = None, interpolation: str = "bilinear",
                      retry: bool = True) -> list:
    """Reconstruct the boundary curves of a batch of binary masks (one batched solve).

    Boundary points from :func:`mask_to_points`; with ``use_oracle`` (default) the vertex
    signs come from the mask (:class:`MaskOracle`), so the curves keep the mask's topology
    (thin strokes, close curves), otherwise the topology is estimated from the points.

    The mask also says how many boundaries there are (its contours). With ``retry``, a mask
    whose curve has another number of closed curves, or an open chain (the mesh too coarse for
    a feature a few pixels wide: a stroke, the tip of a narrow notch), is solved once more
    from a starting mesh of triangles about 4 pixels wide with half the tolerance, and the new
    curve is kept when its count is right. Strokes one pixel wide stay out of reach (their
    pixels may touch only at corners, which no sampled inside/outside function resolves).

    Args:
        config: default :func:`image_config` (tolerance 0.5 pixel, no noise widening).
        spacing, threshold: see :func:`mask_to_points`; interpolation: see :class:`MaskOracle`.
        names: labels for errors and results (default ``"mask b"``).

    Returns:
        one :class:`~torch_isc.pipeline.result.ReconstructionResult` per mask, in pixel
        coordinates; ``result.boundaries`` is the mask's number of borders (its contours) and
        ``result.count_ok`` whether the curve has as many closed curves and no open chain (a
        sampled inside/outside function can miss the mask's borders: 4-px checkerboards give 5
        curves for cv2's 3; :func:`grid_results` and :func:`find_contours` are exact).

    A mask with no foreground pixel has no boundary to sample: its result has no curve (that
    of :func:`grid_results`), as ``cv2.findContours`` gives no contour.
    """
    # the options first: a bad one is found before any mask is read or solved
    _check_spacing(spacing)
    _check_interpolation(interpolation)
    for key, val in (("retry", retry), ("use_oracle", use_oracle)):
        if not isinstance(val, (bool, np.bool_)):
            raise ImageError(f"{key} must be True or False, got {val!r:.40}")
    cfg = as_image_config(config, "mask")
    ts = image_list(masks, "mask")
    labels = default_names(names, len(ts), "mask")
    empty = [not bool(binarize(t, threshold).any()) for t in ts]
    keep = [b for b, e in enumerate(empty) if not e]
    out: list = [None] * len(ts)
    if keep:
        prepared = [mask_points(ts[b], spacing, threshold, labels[b]) for b in keep]
        solved = solve_masks([p for p, _ in prepared], [ts[b] for b in keep], [n for _, n in prepared], cfg,
                             [labels[b] for b in keep], threshold, use_oracle, interpolation, retry)
        for b, r in zip(keep, solved):
            out[b] = r
    if len(keep) < len(ts):
        idx = [b for b, e in enumerate(empty) if e]
        for b, r in zip(idx, grid_results([ts[b] for b in idx], [labels[b] for b in idx], threshold=threshold,
                                          config=cfg)):
            out[b] = r
    return out



def grid_results(masks: Union[ImageLike, Sequence[ImageLike]], names: Optional[Sequence[str]] = None,
                 connectivity: int = 8, smooth: int = 12, threshold: Optional[float] = None,
                 config: Optional[ReconstructConfig] = None) -> list:
    """Mask mode's fast path: the curves of a batch of masks from one solve on their pixel-centre
    grids (:func:`torch_isc.images.grid.trace_masks`), one
    :class:`~torch_isc.pipeline.result.ReconstructionResult` per mask.

    Each result's polylines are the mask's borders in OpenCV's ``RETR_TREE`` order (foreground on
    their left), its curve the item's band mesh with the fitted values, ``stats`` empty and
    ``converged`` True; ``result.boundaries`` is the mask's number of borders and
    ``result.count_ok`` whether the curve has as many closed curves (always, by construction;
    a flag for the outputs), ``result.cv_contours`` the ``(contours, hierarchy)`` of
    :func:`~torch_isc.images.find_contours` (RETR_TREE, float32) for the contours file.
    A mask with no foreground pixel gives a result with no curve (``boundaries`` 0, hierarchy
    None), as ``cv2.findContours`` gives no contour.
    """
    from torch_isc.images.grid import padded_groups

    ts = [binarize(t, threshold) for t in image_list(masks, "mask")]
    labels = default_names(names, len(ts), "mask")
    cfg = as_image_config(config, "mask")
    out: list = []
    # one solve per run of masks whose padded grid stays bounded (a 1 x N mask beside an N x 1
    # one would pad to N x N each)
    for b0, b1 in padded_groups([tuple(t.shape) for t in ts]):
        out.extend(_grid_group(ts[b0:b1], labels[b0:b1], connectivity, smooth, cfg))
    return out


def _grid_group(ts, labels, connectivity, smooth, cfg) -> list:
    """:func:`grid_results` of masks ``ts`` solved together."""
    from torch_isc.core.curve import ImplicitCurve
    from torch_isc.images.contours import grid_contours
    from torch_isc.images.grid import trace_masks
    from torch_isc.pipeline.result import ReconstructionResult

    gc = trace_masks(ts, connectivity, smooth)
    cvs = grid_contours(gc, "tree")
    mesh = gc.mesh
    vfirst = mesh.verts_first_idx.tolist() + [mesh.verts.shape[0]]
    ffirst = mesh.faces_first_idx.tolist() + [mesh.faces.shape[0]]
    out = []
    for b, (lab, (cs, h)) in enumerate(zip(labels, cvs)):
        v0, v1, f0, f1 = vfirst[b], vfirst[b + 1], ffirst[b], ffirst[b + 1]
        from torch_isc.core.mesh import MeshBatch
        sub = MeshBatch(mesh.verts[v0:v1], mesh.faces[f0:f1] - v0, mesh.verts_per_item[b:b + 1],
                        mesh.faces_per_item[b:b + 1])
        # a band mesh: the uniform regions it encloses take their boundary's sign (areas, inside)
        curve = ImplicitCurve(sub, gc.values[v0:v1], validate=False, enclosed=True)
        # polylines: OpenCV's order, our orientation (foreground on the left), our coordinates
        pls = [{"closed": True, "points": torch.from_numpy(np.ascontiguousarray(c.reshape(-1, 2)[::-1].astype(np.float64) + 0.5))}
               for c in cs]
        r = ReconstructionResult(curve=curve, points=torch.zeros(0, 2, dtype=torch.float64), stats=[], config=cfg,
                                 converged=True, limit=None, name=lab, _polylines=pls)
        r.boundaries = len(cs)
        r.count_ok = True
        r.cv_contours = (cs, h)
        out.append(r)
    return out
