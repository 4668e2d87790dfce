"""The curves drawn over their source image, as PNG (pixel convention of
:mod:`torch_isc.images`: no offset to guess)."""
from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from torch_isc._helpers import import_cv2
from torch_isc.images import ImageLike, polyline_dicts
from torch_isc.io.files import PathLike, atomic_write
from torch_isc.io.png import png_bytes

__all__ = ["render_overlay", "encode_overlay", "write_overlay", "overlay_region", "MAX_OVERLAY_PIXELS"]


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


#: The largest overlay drawn, in output pixels (a zoom of a large region is refused above it).
MAX_OVERLAY_PIXELS = 100_000_000
#: ...and its longest side: PNG encoders refuse more than 10^6 pixels a row or column (libpng's
#: user limit; a 1x20000 image at zoom 64 passed the pixel count, then failed to encode)
MAX_OVERLAY_SIDE = 1_000_000


def overlay_region(shape, region=None):
    """``(x0, y0, x1, y1)`` integer pixel bounds of the part of an image of ``shape`` (H, W)
    that an overlay shows: ``region`` clipped to the image (None: all of it).

    A region that misses the image shows all of it.

    Raises:
        ValueError: an empty region (x0 >= x1 or y0 >= y1).

    >>> overlay_region((10, 20), (5, -3, 30, 4)), overlay_region((10, 20), (50, 50, 60, 60))
    ((5, 0, 20, 4), (0, 0, 20, 10))
    """
    H, W = int(shape[0]), int(shape[1])
    if region is None:
        return 0, 0, W, H
    x0, y0, x1, y1 = (int(v) for v in region)
    if not (x0 < x1 and y0 < y1):
        raise ValueError(f"overlay region {x0},{y0},{x1},{y1}: expected x0 < x1 and y0 < y1")
    c = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    if not (c[0] < c[2] and c[1] < c[3]):
        # a region that misses this image (a folder of images of several sizes): all of it is
        # shown, rather than failing the image's whole output set
        return 0, 0, W, H
    return c


def render_overlay(image: ImageLike, result, points: bool = False, scale: int = 1,
                   region=None) -> np.ndarray:
    """The curves of ``result`` drawn over ``image`` (gray ``(H, W)`` or BGR ``(H, W, 3)``):
    a ``(scale*h, scale*w, 3)`` uint8 BGR image, closed curves green, open chains orange,
    anti-aliased at sub-pixel precision (``cv2.polylines`` with a fixed-point shift).
    ``result``: any form of :func:`~torch_isc.images.polyline_dicts` (a result, its JSON dict...).
    ``points`` also marks a result's data points in red.

    ``scale`` (an integer zoom, each pixel a ``scale x scale`` block) and ``region``
    (``(x0, y0, x1, y1)`` in pixels, the part of the image shown, clipped to it;
    :func:`overlay_region`) let sub-pixel defects be seen: at a zoom of 8 or more the curve's
    vertices are also marked. The curve keeps its sub-pixel position in the zoomed frame: a
    point ``(x, y)`` is drawn at ``((x - x0) * scale, (y - y0) * scale)`` output pixels.

    >>> img = np.zeros((20, 20), np.uint8)
    >>> render_overlay(img, {"polylines": [{"closed": True, "points": [[5, 5], [15, 5], [15, 15]]}]}).shape
    (20, 20, 3)
    >>> render_overlay(img, {"polylines": []}, scale=4, region=(2, 3, 12, 8)).shape
    (20, 40, 3)
    """
    cv2 = import_cv2()
    scale = int(scale)
    if scale < 1:
        raise ValueError(f"overlay zoom must be an integer >= 1, got {scale}")
    img = _bgr(image)
    x0, y0, x1, y1 = overlay_region(img.shape, region)
    if (x1 - x0) * (y1 - y0) * scale * scale > MAX_OVERLAY_PIXELS:
        raise ValueError(f"overlay of {x1 - x0}x{y1 - y0} px at zoom {scale} is larger than "
                         f"{MAX_OVERLAY_PIXELS:.0e} pixels (choose a smaller --region or --zoom)")
    if max(x1 - x0, y1 - y0) * scale > MAX_OVERLAY_SIDE:
        raise ValueError(f"overlay of {x1 - x0}x{y1 - y0} px at zoom {scale} has a side of more than "
                         f"{MAX_OVERLAY_SIDE} pixels, more than PNG allows (choose a smaller --region or --zoom)")
    img = np.ascontiguousarray(img[y0:y1, x0:x1])
    if scale != 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    shift = 4
    pls = polyline_dicts(result)
    origin = np.array([x0, y0], np.float64)

    def fixed(p):
        a = p.detach().double().cpu().numpy() if isinstance(p, torch.Tensor) else np.asarray(p, np.float64)
        return np.rint(((a.reshape(-1, 2) - origin) * scale - 0.5) * (1 << shift)).astype(np.int32)

    closed = [fixed(pl["points"]) for pl in pls if pl["closed"]]
    opened = [fixed(pl["points"]) for pl in pls if not pl["closed"]]
    if closed:
        cv2.polylines(img, closed, True, (0, 200, 0), 1, cv2.LINE_AA, shift)
    if opened:
        cv2.polylines(img, opened, False, (0, 140, 255), 1, cv2.LINE_AA, shift)
    if scale >= 8:                          # the vertices, where the zoom leaves room for them
        for poly, colour in ((closed, (0, 255, 255)), (opened, (0, 255, 255))):
            for q in poly:
                inside = (q[:, 0] >= -(8 << shift)) & (q[:, 1] >= -(8 << shift)) & \
                         (q[:, 0] < (img.shape[1] + 8) << shift) & (q[:, 1] < (img.shape[0] + 8) << shift)
                for c in q[inside]:
                    cv2.circle(img, (int(c[0]), int(c[1])), 1 << shift, colour, -1, cv2.LINE_AA, shift)
    if points and isinstance(getattr(result, "points", None), torch.Tensor):
        pts = result.points.detach().double().cpu().numpy().reshape(-1, 2)
        for c in np.rint(((pts - origin) * scale - 0.5) * (1 << shift)).astype(np.int32):   # a figure option
            cv2.circle(img, (int(c[0]), int(c[1])), 1 << shift, (0, 0, 255), -1, cv2.LINE_AA, shift)
    return img


def encode_overlay(result, fh: BinaryIO, image: ImageLike, **kw) -> None:
    """:func:`render_overlay` as PNG into ``fh``."""
    fh.write(png_bytes(render_overlay(image, result, **kw), getattr(result, "name", None) or "overlay"))


def write_overlay(path: PathLike, image: ImageLike, result, **kw) -> Path:
    """:func:`render_overlay` written as PNG (atomic write)."""
    return atomic_write(path, png_bytes(render_overlay(image, result, **kw), path))
