"""Images to curves: binary masks and grayscale images in, implicit simplicial curves out.

Pixel convention (used by every function here, by the CLI and by the outputs): ``x`` to the
right, ``y`` down, in pixels; pixel ``(row i, column j)`` covers the square
``[j, j+1] x [i, i+1]``, so its centre is ``(j + 0.5, i + 0.5)`` and the whole image of width
``W`` and height ``H`` is ``[0, W] x [0, H]``. A curve point ``(x, y)`` is drawn on the image at
column ``x``, row ``y`` without any offset. OpenCV puts pixel centres at integers instead: an
OpenCV point ``(u, v)`` is ``(u + 0.5, v + 0.5)`` here (:func:`to_cv_contours` converts back).

Pipeline:

- :func:`mask_to_points` -- ``cv2.findContours`` (every boundary pixel, all contours) traces the
  foreground; each traced boundary pixel is replaced by the midpoints of its pixel edges that
  face the background (the *cracks*), in tracing order. The points lie on the boundary between
  foreground and background pixels, not on the pixel centres of one side, so the reconstructed
  curve can be sub-pixel accurate. The crack midpoints of a contour are then resampled to a
  uniform spacing along the contour (:func:`resample_closed`).
- :func:`edge_points` -- kornia's Canny edges of a batch of grayscale images, each edge pixel
  refined to sub-pixel along the gradient (a parabola through the gradient magnitude).
- :class:`MaskOracle` -- the mask as the inside/outside function of Section 3.2: the
  reconstruction reads the vertex signs from the mask instead of estimating the topology.
- :func:`reconstruct_masks` / :func:`reconstruct_edges` -- the batched reconstructions, with the
  pixel defaults of :func:`image_config`.
- :func:`to_cv_contours` -- results as OpenCV contours with a ``RETR_TREE`` / ``RETR_CCOMP``
  hierarchy; :func:`find_contours` is a drop-in for ``cv2.findContours``.
- :func:`read_image`, :func:`render_overlay`, :func:`write_overlay` -- files.

Example:
    >>> import cv2, numpy as np
    >>> mask = np.zeros((64, 64), np.uint8)
    >>> _ = cv2.circle(mask, (31, 31), 20, 255, -1)        # OpenCV centre 31 = our 31.5
    >>> res = reconstruct_masks([mask])[0]
    >>> res.num_closed, res.num_open
    (1, 0)
    >>> contours, hierarchy = to_cv_contours(res)
    >>> len(contours), hierarchy.shape
    (1, (1, 1, 4))
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.io import read_file_bytes

__all__ = [
    "IMAGE_SUFFIXES", "IMAGE_CONFIG", "MASK_CONFIG", "EDGE_CONFIG", "ImageError", "image_config", "read_image", "as_masks",
    "mask_crack_contours", "resample_closed", "mask_to_points", "mask_points", "auto_threshold", "solve_masks", "edge_points", "MaskOracle",
    "reconstruct_masks", "reconstruct_edges", "to_cv_contours", "contour_hierarchy", "find_contours",
    "render_overlay", "write_overlay", "write_contours", "load_contours",
]

#: File suffixes read as images (lower case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

#: Reconstruction settings for masks, in pixels (applied by :func:`image_config`): the test
#: tolerance is half a pixel (the quantization step of a mask's boundary), absolute; and no
#: noise-based widening of it (``noise_factor: 0``): a mask's boundary has no noise beyond the
#: quantization, and the noise estimate (line fits at each point's neighbours) would read the
#: two sides of a stroke a few pixels wide as noise and stop refining before the stroke is resolved.
MASK_CONFIG: Dict[str, Any] = {"tolerance": 0.5, "tolerance_mode": "absolute", "noise_factor": 0.0}
#: Settings for Canny edge points: half a pixel, absolute; the noise estimate stays on (edge
#: points do jitter).
EDGE_CONFIG: Dict[str, Any] = {"tolerance": 0.5, "tolerance_mode": "absolute"}
IMAGE_CONFIG = {"mask": MASK_CONFIG, "edges": EDGE_CONFIG}

ImageLike = Union[np.ndarray, torch.Tensor]


class ImageError(ValueError):
    """An image that cannot be used (unreadable, empty mask...); the message is one line
    naming the image."""


def image_config(base: Optional[ReconstructConfig] = None, keep: Sequence[str] = (),
                 mode: str = "mask") -> ReconstructConfig:
    """``base`` (default config when None) with the pixel settings of :data:`MASK_CONFIG`
    (``mode="mask"``) or :data:`EDGE_CONFIG` (``mode="edges"``), except the keys in ``keep``
    (e.g. those a user set explicitly).

    >>> cfg = image_config()
    >>> cfg.tolerance, cfg.tolerance_mode, cfg.noise_factor
    (0.5, 'absolute', 0.0)
    """
    base = base if base is not None else ReconstructConfig()
    return base.replace(**{k: v for k, v in IMAGE_CONFIG[mode].items() if k not in set(keep)})


# =============================================================================== reading
def _cv2():
    import cv2

    return cv2


def read_image(path: Union[str, os.PathLike]) -> np.ndarray:
    """Read an image file as grayscale ``(H, W)`` float32 in ``[0, 1]``.

    Colour is converted to gray (OpenCV weights); an alpha channel, when present and not
    fully opaque, multiplies the gray value (a transparent background reads as black).
    8-bit, 16-bit and float images are scaled to ``[0, 1]``.

    Raises:
        ImageError: missing file, unreadable / truncated / not an image (one line, naming it).
    """
    cv2 = _cv2()
    p = Path(path)
    raw = np.frombuffer(read_file_bytes(p, ImageError, "an image"), dtype=np.uint8)
    if raw.size == 0:
        raise ImageError(f"{p}: empty file, not an image")
    img = None
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)     # a corrupt file is reported once, by us, not by OpenCV too
    try:
        img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    finally:
        log.setLogLevel(level)
    if img is None or img.size == 0:
        raise ImageError(f"{p}: not a readable image (unknown format, truncated or corrupt)")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    elif np.issubdtype(img.dtype, np.floating):
        scale = 1.0
    else:
        scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
    g = img.astype(np.float32) / np.float32(scale)
    if g.ndim == 3:
        alpha = g[:, :, 3] if g.shape[2] == 4 else None
        g = cv2.cvtColor(np.ascontiguousarray(g[:, :, :3]), cv2.COLOR_BGR2GRAY)
        if alpha is not None and (alpha < 1).any():
            g = g * alpha
    if not np.isfinite(g).all():
        raise ImageError(f"{p}: image has NaN or Inf values")
    if g.ndim != 2:
        raise ImageError(f"{p}: unsupported image layout {tuple(img.shape)}")
    return np.ascontiguousarray(np.clip(g, 0.0, 1.0), dtype=np.float32)


# =============================================================================== masks
def _image_list(images: Union[ImageLike, Sequence[ImageLike]], what: str = "image") -> List[torch.Tensor]:
    """A batch of 2D images as a list of ``(H_b, W_b)`` tensors: accepts a list of 2D
    arrays/tensors (sizes may differ) or one ``(B, H, W)`` / ``(B, 1, H, W)`` array."""
    if isinstance(images, (np.ndarray, torch.Tensor)):
        t = torch.as_tensor(images) if isinstance(images, np.ndarray) else images
        if t.dim() == 4 and t.shape[1] == 1:
            t = t[:, 0]
        if t.dim() == 2:
            raise ImageError(f"expected a batch of {what}s (B, H, W) or a list; wrap a single {what} in a list")
        if t.dim() != 3:
            raise ImageError(f"expected {what}s of shape (B, H, W) or (B, 1, H, W), got {tuple(t.shape)}")
        return list(t.unbind(0))
    out = []
    for b, im in enumerate(images):
        t = torch.as_tensor(np.asarray(im)) if not isinstance(im, torch.Tensor) else im
        if t.dim() == 3 and t.shape[0] == 1:
            t = t[0]
        if t.dim() != 2:
            raise ImageError(f"{what} {b}: expected a 2D (H, W) array, got shape {tuple(t.shape)}")
        if t.shape[0] == 0 or t.shape[1] == 0:
            raise ImageError(f"{what} {b}: empty image of shape {tuple(t.shape)}")
        out.append(t)
    return out


def _binarize(t: torch.Tensor, threshold: Optional[float]) -> torch.Tensor:
    """Foreground ``(H, W)`` bool: ``t > threshold``. Default (None): a bool mask as it is,
    an integer mask nonzero (OpenCV's rule for ``findContours``), a float mask above 0.5."""
    if t.dtype == torch.bool:
        return t
    if threshold is None:
        threshold = 0.5 if t.dtype.is_floating_point else 0
    return t > threshold


def as_masks(masks: Union[ImageLike, Sequence[ImageLike]], threshold: Optional[float] = None) -> List[torch.Tensor]:
    """Binary masks ``[(H_b, W_b) bool]`` from a list of 2D arrays/tensors or a ``(B, H, W)``
    stack: a pixel is foreground when its value is above ``threshold`` (default: nonzero for
    integer masks, as ``cv2.findContours`` reads them; above 0.5 for float masks in [0, 1];
    bool masks as they are).

    >>> [m.sum().item() for m in as_masks([np.eye(3), np.full((2, 4), 1, np.uint8)])]
    [3, 8]
    """
    return [_binarize(t, threshold) for t in _image_list(masks, "mask")]


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
    cv2 = _cv2()
    t = mask if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
    fg = _binarize(t, threshold).detach().cpu().numpy()
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
    qid = torch.repeat_interleave(torch.arange(C, device=dev), n_new)
    qfirst = torch.cumsum(n_new, 0) - n_new
    j = torch.arange(int(n_new.sum()), device=dev) - qfirst[qid]
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
    ts = _image_list(masks, "mask")
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
        if interpolation not in ("nearest", "bilinear"):
            raise ValueError(f"interpolation must be 'nearest' or 'bilinear', got {interpolation!r}")
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


# =============================================================================== edges
def _bilinear(img: torch.Tensor, b: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``img (B, H, W)`` sampled bilinearly at pixel-convention points ``q (K, 2)`` of images
    ``b (K,)`` (pixel centres at +1/2; the border value extends outward)."""
    H, W = img.shape[-2:]
    u, v = q[:, 0] - 0.5, q[:, 1] - 0.5
    j0, i0 = u.floor(), v.floor()
    fu, fv = u - j0, v - i0
    j0, i0 = j0.long(), i0.long()
    acc = torch.zeros_like(u)
    for di, dj, w in ((0, 0, (1 - fv) * (1 - fu)), (0, 1, (1 - fv) * fu), (1, 0, fv * (1 - fu)), (1, 1, fv * fu)):
        acc = acc + w * img[b, (i0 + di).clamp(0, H - 1), (j0 + dj).clamp(0, W - 1)]
    return acc


def edge_points(images: Union[ImageLike, Sequence[ImageLike]], low_threshold: float = 0.1,
                high_threshold: float = 0.2, sigma: float = 1.0, kernel_size: Optional[int] = None,
                spacing: float = 1.0, subpixel: bool = True) -> List[torch.Tensor]:
    """Edge points of a batch of grayscale images (kornia's Canny).

    Images of the same size run through ``kornia.filters.canny`` as one ``(B, 1, H, W)``
    batch; images of different sizes form separate batches (no padding, so an image's edges do
    not depend on its batch). Values are used as they are for floats (expected in ``[0, 1]``),
    uint8 is divided by 255.

    Args:
        images: a list of 2D images (sizes may differ) or a ``(B, H, W)`` / ``(B, 1, H, W)`` stack.
        low_threshold, high_threshold: Canny hysteresis thresholds on the gradient magnitude
            (of the image in [0, 1], after Gaussian smoothing).
        sigma: Gaussian smoothing; ``kernel_size`` defaults to ``2 * ceil(2 sigma) + 1``.
        spacing: points closer than this are merged (one point, their mean, per cell of a
            ``spacing``-pixel grid) when ``spacing > 1``.
        subpixel: move each edge pixel's centre to the peak of a parabola fitted to the
            gradient magnitude at -1, 0, +1 pixel along the gradient direction.

    Returns:
        one ``(N_b, 2)`` tensor per image (pixel convention; the images' device, their
        floating dtype or torch's default).

    >>> im = np.zeros((32, 32), np.float32); im[8:24, 8:24] = 1
    >>> p = edge_points([im])[0]
    >>> err = ((p - 16).abs().max(1).values - 8).abs()      # distance to the square's sides
    >>> round(err.median().item(), 3), bool(err.max() < 0.7)
    (0.0, True)
    """
    import kornia

    ts = _image_list(images, "image")
    out: List[Optional[torch.Tensor]] = [None] * len(ts)
    ks = kernel_size if kernel_size is not None else 2 * int(math.ceil(2 * sigma)) + 1
    groups: Dict[Tuple[int, int], List[int]] = {}
    for b, t in enumerate(ts):
        groups.setdefault((int(t.shape[0]), int(t.shape[1])), []).append(b)
    for (H, W), idx in groups.items():
        x = torch.stack([ts[b] for b in idx])
        odt = x.dtype if x.dtype.is_floating_point else torch.get_default_dtype()
        if x.dtype == torch.uint8:
            x = x.to(odt) / 255.0
        elif x.dtype == torch.bool or not x.dtype.is_floating_point:
            x = x.to(odt)
        x = x[:, None]
        _, edges = kornia.filters.canny(x, low_threshold, high_threshold, (ks, ks), (sigma, sigma))
        e = edges[:, 0] > 0
        bi, ii, jj = e.nonzero(as_tuple=True)
        pts = torch.stack([jj, ii], 1).to(odt) + 0.5
        if subpixel and bi.numel():
            g = kornia.filters.spatial_gradient(kornia.filters.gaussian_blur2d(x, (ks, ks), (sigma, sigma)),
                                                normalized=False)[:, 0]     # (b, 2, H, W)
            mag = g.pow(2).sum(1).sqrt()
            gx, gy = g[bi, 0, ii, jj], g[bi, 1, ii, jj]
            n = torch.stack([gx, gy], 1)
            n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-12)
            m0 = mag[bi, ii, jj]
            mp, mm = _bilinear(mag, bi, pts + n), _bilinear(mag, bi, pts - n)
            den = mm - 2 * m0 + mp
            off = torch.where(den < 0, 0.5 * (mm - mp) / den.clamp(max=-1e-12), torch.zeros_like(den))
            pts = pts + off.clamp(-0.5, 0.5)[:, None] * n
        if spacing > 1 and bi.numel():
            cell = torch.floor(pts / spacing).long()
            key = (bi * (H // max(1, int(spacing)) + 2) + cell[:, 1]) * (W // max(1, int(spacing)) + 2) + cell[:, 0]
            uniq, inv = torch.unique(key, return_inverse=True)
            acc = torch.zeros(uniq.shape[0], 2, dtype=pts.dtype, device=pts.device).index_add_(0, inv, pts)
            cnt = torch.zeros(uniq.shape[0], dtype=pts.dtype, device=pts.device).index_add_(
                0, inv, torch.ones_like(pts[:, 0]))
            pts = acc / cnt[:, None]
            bi = torch.zeros(uniq.shape[0], dtype=torch.long, device=pts.device).index_reduce_(
                0, inv, bi, "amax", include_self=False)
        counts = torch.bincount(bi, minlength=len(idx)).tolist()
        for b, q in zip(idx, pts.split(counts)):
            out[b] = q
    return out  # type: ignore[return-value]


# =============================================================================== reconstruction
def _names(names, n, what):
    return list(names) if names is not None else [f"{what} {b}" for b in range(n)]


def auto_threshold(image: np.ndarray) -> float:
    """The foreground threshold of a mask read from a file as gray values in [0, 1]: midway
    between the two levels of a two-level image (so 0/1 label PNGs and 0/255 masks both work),
    else 0.5.

    >>> auto_threshold(np.array([[0, 1 / 255]])), auto_threshold(np.array([[0.0, 0.2, 1.0]]))
    (0.00196078431372549, 0.5)
    """
    levels = np.unique(np.asarray(image))
    if levels.size == 2:
        return float(levels.astype(np.float64).mean())
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
    from torch_isc.pipeline.loop import reconstruct_batch

    oracle = MaskOracle(list(masks), threshold, interpolation) if use_oracle else None
    results = reconstruct_batch(list(points), config, list(names), oracle)
    if not retry or n_boundaries is None:
        return results
    redo = [b for b, r in enumerate(results) if r.num_closed != n_boundaries[b] or r.num_open > 0]
    for b in redo:          # rare: one solve per mask, each with its own starting mesh
        p = points[b]
        diag = float((p.max(0).values - p.min(0).values).double().norm())
        hexagon_side = (0.5 + config.margin) * 2 / math.sqrt(3) * diag
        res = max(config.initial_resolution, int(math.ceil(hexagon_side / _RETRY_EDGE_PX)))
        res = min(res, max(config.initial_resolution, int(math.sqrt(config.max_triangles / 6 / 4))))
        cfg = config.replace(tolerance=config.tolerance / 2, initial_resolution=res)
        sub = MaskOracle([masks[b]], threshold, interpolation) if use_oracle else None
        r = reconstruct_batch([p], cfg, [names[b]], sub)[0]
        if r.num_closed == n_boundaries[b] and r.num_open == 0:
            results[b] = r
    return results


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
        one :class:`~torch_isc.pipeline.result.ReconstructionResult` per mask, in pixel coordinates.

    Raises:
        ImageError: a mask with no foreground pixel (naming it).
    """
    cfg = config if config is not None else image_config()
    ts = _image_list(masks, "mask")
    labels = _names(names, len(ts), "mask")
    prepared = [mask_points(t, spacing, threshold, lab) for t, lab in zip(ts, labels)]
    return solve_masks([p for p, _ in prepared], ts, [n for _, n in prepared], cfg, labels, threshold,
                       use_oracle, interpolation, retry)


def reconstruct_edges(images: Union[ImageLike, Sequence[ImageLike]], config: Optional[ReconstructConfig] = None,
                      names: Optional[Sequence[str]] = None, **edge_kw) -> list:
    """Reconstruct curves from the Canny edges of a batch of grayscale images, with topology
    estimation (an edge map has no inside/outside). ``edge_kw`` go to :func:`edge_points`;
    ``config`` defaults to ``image_config(mode="edges")``.

    Raises:
        ImageError: an image with fewer than 3 edge pixels (naming it).
    """
    from torch_isc.pipeline.loop import reconstruct_batch

    cfg = config if config is not None else image_config(mode="edges")
    ts = _image_list(images, "image")
    labels = _names(names, len(ts), "image")
    pts = edge_points(ts, **edge_kw)
    for p, lab in zip(pts, labels):
        if p.shape[0] < 3:
            raise ImageError(f"{lab}: no edges found (flat image, or thresholds too high)")
    return reconstruct_batch(pts, cfg, labels)


# =============================================================================== OpenCV contours
def _closed_polylines(src) -> List[np.ndarray]:
    """Closed polylines (float64 numpy) from a result, a list of results' polylines dicts, a
    list of ``(points, closed)`` or of arrays (taken as closed)."""
    pls = src.polylines if hasattr(src, "polylines") else src
    out = []
    for pl in pls:
        if isinstance(pl, dict):
            pts, closed = pl["points"], bool(pl["closed"])
        elif isinstance(pl, (tuple, list)) and len(pl) == 2 and isinstance(pl[1], (bool, np.bool_)):
            pts, closed = pl
        else:
            pts, closed = pl, True
        if not closed:
            continue
        a = pts.detach().double().cpu().numpy() if isinstance(pts, torch.Tensor) else np.asarray(pts, np.float64)
        a = a.reshape(-1, 2)
        if a.shape[0] >= 2 and np.array_equal(a[0], a[-1]):
            a = a[:-1]
        if a.shape[0] >= 3:
            out.append(a)
    return out


def _containment(polys: List[np.ndarray]) -> np.ndarray:
    """``inside[a, b]`` (bool, N x N): the first vertex of polygon b lies inside polygon a
    (even-odd crossing test, only for pairs whose bounding boxes nest; chunked)."""
    N = len(polys)
    inside = np.zeros((N, N), bool)
    if N < 2:
        return inside
    counts = np.array([len(p) for p in polys])
    V = np.concatenate(polys)
    first = np.cumsum(counts) - counts
    owner = np.repeat(np.arange(N), counts)
    k = np.arange(V.shape[0]) - first[owner]
    A, B = V, V[first[owner] + (k + 1) % counts[owner]]
    lo = np.stack([np.minimum.reduceat(V, first)[:, 0], np.minimum.reduceat(V, first)[:, 1]], 1)
    hi = np.stack([np.maximum.reduceat(V, first)[:, 0], np.maximum.reduceat(V, first)[:, 1]], 1)
    q = V[first]                                                     # one vertex per polygon
    cand = ((q[None, :, :] > lo[:, None, :]) & (q[None, :, :] < hi[:, None, :])).all(2)
    np.fill_diagonal(cand, False)
    pa, pb = np.nonzero(cand)
    if pa.size == 0:
        return inside
    seg_first = first[pa]
    n_seg = counts[pa]
    chunk = max(1, (1 << 21) // max(1, int(n_seg.max())))
    for s in range(0, pa.size, chunk):
        a_, b_, f_, n_ = pa[s:s + chunk], pb[s:s + chunk], seg_first[s:s + chunk], n_seg[s:s + chunk]
        rep = np.repeat(np.arange(a_.size), n_)
        si = np.repeat(f_, n_) + (np.arange(rep.size) - np.repeat(np.cumsum(n_) - n_, n_))
        x, y = q[b_[rep], 0], q[b_[rep], 1]
        ax, ay, bx, by = A[si, 0], A[si, 1], B[si, 0], B[si, 1]
        straddle = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = ax + (y - ay) * (bx - ax) / (by - ay)
        cross = straddle & (x < xc)
        odd = np.bincount(rep, weights=cross, minlength=a_.size).astype(np.int64) % 2 == 1
        inside[a_[odd], b_[odd]] = True
    return inside


def contour_hierarchy(polys: List[np.ndarray], mode: str = "tree") -> np.ndarray:
    """OpenCV hierarchy ``(N, 4)`` int32 ``[next, prev, first_child, parent]`` of closed,
    non-crossing polygons, from their containment.

    ``mode="tree"`` (``cv2.RETR_TREE``): the full nesting tree. ``mode="ccomp"``
    (``cv2.RETR_CCOMP``): two levels, the outer boundaries of components (even depth) at the top,
    each hole (odd depth) under its component; an island inside a hole is a top-level contour
    again. ``next``/``prev`` link contours with the same parent, in list order; -1 for none.

    >>> sq = lambda a, b: np.array([[a, a], [b, a], [b, b], [a, b]], float)
    >>> contour_hierarchy([sq(0, 9), sq(1, 8), sq(2, 7)], "tree").tolist()
    [[-1, -1, 1, -1], [-1, -1, 2, 0], [-1, -1, -1, 1]]
    >>> contour_hierarchy([sq(0, 9), sq(1, 8), sq(2, 7)], "ccomp").tolist()
    [[2, -1, 1, -1], [-1, -1, -1, 0], [-1, 0, -1, -1]]
    """
    if mode not in ("tree", "ccomp"):
        raise ValueError(f"mode must be 'tree' or 'ccomp', got {mode!r}")
    N = len(polys)
    h = np.full((N, 4), -1, np.int32)
    if N == 0:
        return h
    inside = _containment(polys)
    depth = inside.sum(0)
    # parent: the containing polygon of largest depth
    key = np.where(inside, depth[:, None] * N + np.arange(N)[:, None], -1)
    best = key.max(0)
    parent = np.where(best >= 0, best % N, -1)
    if mode == "ccomp":
        parent = np.where(depth % 2 == 1, parent, -1)
    order = np.lexsort((np.arange(N), parent))           # grouped by parent, list order within
    par_sorted = parent[order]
    same_next = np.r_[par_sorted[1:] == par_sorted[:-1], False]
    same_prev = np.r_[False, par_sorted[1:] == par_sorted[:-1]]
    h[order, 0] = np.where(same_next, np.r_[order[1:], -1], -1)
    h[order, 1] = np.where(same_prev, np.r_[-1, order[:-1]], -1)
    h[:, 3] = parent
    firsts = order[~same_prev]
    has_par = parent[firsts] >= 0
    h[parent[firsts[has_par]], 2] = firsts[has_par]
    return h


def to_cv_contours(src, mode: str = "tree", dtype=np.float32) -> Tuple[List[np.ndarray], np.ndarray]:
    """Curves as OpenCV contours, so code written for ``cv2.findContours`` can use them.

    Args:
        src: a :class:`~torch_isc.pipeline.result.ReconstructionResult`, its ``polylines``, or a list of
            ``(n, 2)`` closed polygons, in the pixel convention of this module. Open chains are
            left out (OpenCV contours are closed).
        mode: ``"tree"`` (like ``cv2.RETR_TREE``) or ``"ccomp"`` (``cv2.RETR_CCOMP``).
        dtype: ``np.float32`` (sub-pixel; fine for ``cv2.contourArea``, ``pointPolygonTest``,
            ``fitEllipse``...) or ``np.int32`` (rounded; what ``cv2.drawContours`` needs).

    Returns:
        ``(contours, hierarchy)``: a list of ``(n, 1, 2)`` arrays in OpenCV's coordinates
        (pixel centres at integers: our ``(x, y)`` becomes ``(x - 0.5, y - 0.5)``), oriented
        as OpenCV orients them (outer boundaries clockwise on screen with y down, i.e. negative
        ``cv2.contourArea(c, oriented=True)``; holes the other way), ordered as OpenCV's
        raster scan finds them (by topmost, then leftmost vertex), each starting at that vertex;
        and the ``(1, N, 4)`` int32 hierarchy ``[next, prev, first_child, parent]`` (``None``
        when there is no contour, as OpenCV returns).

    >>> sq = np.array([[1., 1], [5, 1], [5, 5], [1, 5]])
    >>> c, h = to_cv_contours([sq, sq[::-1] * 0.5 + 1.5])
    >>> c[0][:2, 0].tolist(), h.tolist()
    ([[0.5, 0.5], [0.5, 4.5]], [[[-1, -1, 1, -1], [-1, -1, -1, 0]]])
    """
    polys = _closed_polylines(src)
    if not polys:
        return [], None  # type: ignore[return-value]
    # raster order of OpenCV: by the topmost, then leftmost vertex
    starts = [int(np.lexsort((p[:, 0], p[:, 1]))[0]) for p in polys]
    tops = np.array([[p[s, 1], p[s, 0]] for p, s in zip(polys, starts)])
    order = np.lexsort((tops[:, 1], tops[:, 0]))
    polys = [np.roll(polys[i], -starts[i], 0) for i in order]
    h = contour_hierarchy(polys, mode)
    depth_parity = np.zeros(len(polys), np.int64)
    inside = _containment(polys)
    depth_parity = inside.sum(0) % 2
    out = []
    for p, par in zip(polys, depth_parity):
        x, y = p[:, 0], p[:, 1]
        area2 = float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())
        # OpenCV: outer (even depth) negative shoelace area, holes positive
        want_neg = par == 0
        if (area2 > 0) == want_neg:
            p = np.concatenate([p[:1], p[1:][::-1]])
        q = p - 0.5
        q = np.rint(q).astype(np.int32) if np.issubdtype(np.dtype(dtype), np.integer) else q.astype(dtype)
        out.append(np.ascontiguousarray(q.reshape(-1, 1, 2)))
    return out, h[None]


def find_contours(mask: ImageLike, mode: str = "tree", config: Optional[ReconstructConfig] = None,
                  dtype=np.float32, **kw) -> Tuple[List[np.ndarray], np.ndarray]:
    """A sub-pixel stand-in for ``cv2.findContours(mask, RETR_TREE or RETR_CCOMP, ...)``:
    :func:`reconstruct_masks` on one mask, then :func:`to_cv_contours`.

    >>> m = np.zeros((40, 40), np.uint8); m[5:35, 5:35] = 1; m[15:25, 15:25] = 0
    >>> c, h = find_contours(m, "ccomp")
    >>> len(c), h[0, :, 3].tolist()
    (2, [-1, 0])
    """
    res = reconstruct_masks([mask], config, **kw)[0]
    return to_cv_contours(res, mode, dtype)


# =============================================================================== files
def _bgr(image: ImageLike) -> np.ndarray:
    a = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if a.dtype == bool:
        a = a.astype(np.float32)
    if a.dtype != np.uint8:
        a = a.astype(np.float64)
        hi = 255.0 if a.size and a.max() > 1.0 else 1.0
        a = np.clip(a / hi * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, 2)
    return np.ascontiguousarray(a[:, :, :3])


def render_overlay(image: ImageLike, result, points: bool = False, scale: int = 1) -> np.ndarray:
    """The curves of ``result`` drawn over ``image`` (gray ``(H, W)`` or BGR ``(H, W, 3)``):
    a ``(scale*H, scale*W, 3)`` uint8 BGR image, closed curves green, open chains orange,
    anti-aliased at sub-pixel precision (``cv2.polylines`` with a fixed-point shift), in the
    pixel convention (no offset to guess). ``points`` also marks the data points in red.

    >>> img = np.zeros((20, 20), np.uint8)
    >>> render_overlay(img, {"polylines": [{"closed": True, "points": [[5, 5], [15, 5], [15, 15]]}]}).shape
    (20, 20, 3)
    """
    cv2 = _cv2()
    img = _bgr(image)
    if scale != 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    shift = 4
    pls = result["polylines"] if isinstance(result, dict) else result.polylines

    def fixed(p):
        a = p.detach().double().cpu().numpy() if isinstance(p, torch.Tensor) else np.asarray(p, np.float64)
        return np.rint((a.reshape(-1, 2) * scale - 0.5) * (1 << shift)).astype(np.int32)

    closed = [fixed(pl["points"]) for pl in pls if pl["closed"]]
    opened = [fixed(pl["points"]) for pl in pls if not pl["closed"]]
    if closed:
        cv2.polylines(img, closed, True, (0, 200, 0), 1, cv2.LINE_AA, shift)
    if opened:
        cv2.polylines(img, opened, False, (0, 140, 255), 1, cv2.LINE_AA, shift)
    if points and not isinstance(result, dict):
        pts = result.points.detach().double().cpu().numpy().reshape(-1, 2)
        for c in np.rint((pts * scale - 0.5) * (1 << shift)).astype(np.int32):
            cv2.circle(img, (int(c[0]), int(c[1])), 1 << shift, (0, 0, 255), -1, cv2.LINE_AA, shift)
    return img


def write_overlay(path: Union[str, os.PathLike], image: ImageLike, result, **kw) -> Path:
    """:func:`render_overlay` written as PNG (atomic write)."""
    from torch_isc.io import atomic_write

    ok, buf = _cv2().imencode(".png", render_overlay(image, result, **kw))
    if not ok:  # pragma: no cover
        raise OSError(f"{path}: PNG encoding failed")
    return atomic_write(path, buf.tobytes())


#: Version of the contour ``.npz`` layout of :func:`write_contours`.
CONTOURS_FORMAT = 1


def write_contours(path: Union[str, os.PathLike], result, mode: str = "tree") -> Path:
    """Write the curves as OpenCV contours (see :func:`to_cv_contours`) to a compressed
    ``.npz`` (atomic): ``points (P, 2)`` float32 in OpenCV coordinates, ``counts (N,)``
    vertices per contour, ``hierarchy (N, 4)`` int32, ``mode``. :func:`load_contours` reads it
    back as ``(contours, hierarchy)``."""
    from torch_isc.io import atomic_write

    contours, h = to_cv_contours(result, mode)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]) if contours else np.zeros((0, 2), np.float32)
    arrays = {
        "points": pts.astype(np.float32), "counts": np.array([len(c) for c in contours], np.int64),
        "hierarchy": (h[0] if h is not None else np.zeros((0, 4), np.int32)).astype(np.int32),
        "mode": np.array(mode), "format": np.array(CONTOURS_FORMAT, np.int64),
    }
    return atomic_write(path, lambda fh: np.savez_compressed(fh, **arrays))


def load_contours(path: Union[str, os.PathLike], dtype=np.float32) -> Tuple[List[np.ndarray], Optional[np.ndarray]]:
    """Read a file of :func:`write_contours`: ``(contours [(n, 1, 2)], hierarchy (1, N, 4) or None)``."""
    with np.load(path, allow_pickle=False) as z:
        pts, counts, h = z["points"], z["counts"], z["hierarchy"]
    pieces = np.split(pts, np.cumsum(counts)[:-1]) if counts.size else []
    if np.issubdtype(np.dtype(dtype), np.integer):
        pieces = [np.rint(p).astype(np.int32) for p in pieces]
    return [p.reshape(-1, 1, 2).astype(dtype) for p in pieces], (h[None] if counts.size else None)
