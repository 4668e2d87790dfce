"""Grayscale images to curves through their Canny edges (kornia), refined to sub-pixel."""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np  # noqa: F401  (the doctests use it)
import torch

from torch_isc.images.arrays import ImageError, ImageLike, default_names, image_list
from torch_isc.images.settings import as_image_config, image_config
from torch_isc.pipeline.config import ReconstructConfig

__all__ = ["edge_points", "reconstruct_edges"]


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


#: the smallest Gaussian sigma of the edge detector, in pixels (narrower is no blur at all)
MIN_SIGMA = 1e-3


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

    for name, v, lo in (("sigma", sigma, 0.0), ("spacing", spacing, -1.0), ("low_threshold", low_threshold, -1.0),
                        ("high_threshold", high_threshold, -1.0)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= lo or v > 1e6:
            raise ImageError(f"edge_points: {name} must be a finite number{' > 0' if lo == 0 else ''} "
                             f"(at most 1e6), got {v!r}")
    if sigma < MIN_SIGMA:           # kornia's float32 kernel: 1e-300 is 0 there
        raise ImageError(f"edge_points: sigma must be at least {MIN_SIGMA} pixels, got {sigma!r}")
    if kernel_size is not None and (isinstance(kernel_size, bool) or not isinstance(kernel_size, int)
                                    or kernel_size < 1 or kernel_size % 2 == 0 or kernel_size > 4001):
        raise ImageError(f"edge_points: kernel_size must be an odd integer in [1, 4001], got {kernel_size!r}")
    ts = image_list(images, "image")
    out: List[Optional[torch.Tensor]] = [None] * len(ts)
    ks = kernel_size if kernel_size is not None else 2 * int(math.ceil(2 * sigma)) + 1
    need = max(2, ks // 2 + 1)          # kornia pads the Gaussian by ks // 2 (reflect) on each side
    for b, t in enumerate(ts):
        if min(t.shape) < need:
            raise ImageError(f"image {b}: {t.shape[1]}x{t.shape[0]} px is too small for Canny edges with sigma "
                             f"{sigma:g} (kernel {ks}): at least {need}x{need} px")
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
            bi = torch.zeros(uniq.shape[0], dtype=torch.long, device=pts.device).scatter_reduce_(
                0, inv, bi, "amax", include_self=False)
        counts = torch.bincount(bi, minlength=len(idx)).tolist()
        for b, q in zip(idx, pts.split(counts)):
            out[b] = q
    return out  # type: ignore[return-value]



def reconstruct_edges(images: Union[ImageLike, Sequence[ImageLike]], config: Optional[ReconstructConfig] = None,
                      names: Optional[Sequence[str]] = None, **edge_kw) -> list:
    """Reconstruct curves from the Canny edges of a batch of grayscale images, with topology
    estimation (an edge map has no inside/outside). ``edge_kw`` go to :func:`edge_points`;
    ``config`` defaults to ``image_config(mode="edges")``.

    Raises:
        ImageError: an image with fewer than 3 edge pixels (naming it).
    """
    from torch_isc.pipeline.loop import reconstruct_batch

    cfg = as_image_config(config, "edges")
    ts = image_list(images, "image")
    labels = default_names(names, len(ts), "image")
    pts = edge_points(ts, **edge_kw)
    for p, lab in zip(pts, labels):
        if p.shape[0] < 3:
            raise ImageError(f"{lab}: no edges found (flat image, or thresholds too high)")
    return reconstruct_batch(pts, cfg, labels)

