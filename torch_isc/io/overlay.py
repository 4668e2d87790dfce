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

__all__ = ["render_overlay", "encode_overlay", "write_overlay"]


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
    anti-aliased at sub-pixel precision (``cv2.polylines`` with a fixed-point shift).
    ``result``: any form of :func:`~torch_isc.images.polyline_dicts` (a result, its JSON dict...).
    ``points`` also marks a result's data points in red.

    >>> img = np.zeros((20, 20), np.uint8)
    >>> render_overlay(img, {"polylines": [{"closed": True, "points": [[5, 5], [15, 5], [15, 15]]}]}).shape
    (20, 20, 3)
    """
    cv2 = import_cv2()
    img = _bgr(image)
    if scale != 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    shift = 4
    pls = polyline_dicts(result)

    def fixed(p):
        a = p.detach().double().cpu().numpy() if isinstance(p, torch.Tensor) else np.asarray(p, np.float64)
        return np.rint((a.reshape(-1, 2) * scale - 0.5) * (1 << shift)).astype(np.int32)

    closed = [fixed(pl["points"]) for pl in pls if pl["closed"]]
    opened = [fixed(pl["points"]) for pl in pls if not pl["closed"]]
    if closed:
        cv2.polylines(img, closed, True, (0, 200, 0), 1, cv2.LINE_AA, shift)
    if opened:
        cv2.polylines(img, opened, False, (0, 140, 255), 1, cv2.LINE_AA, shift)
    if points and isinstance(getattr(result, "points", None), torch.Tensor):
        pts = result.points.detach().double().cpu().numpy().reshape(-1, 2)
        for c in np.rint((pts * scale - 0.5) * (1 << shift)).astype(np.int32):   # a figure option, not a hot path
            cv2.circle(img, (int(c[0]), int(c[1])), 1 << shift, (0, 0, 255), -1, cv2.LINE_AA, shift)
    return img


def encode_overlay(result, fh: BinaryIO, image: ImageLike, **kw) -> None:
    """:func:`render_overlay` as PNG into ``fh``."""
    fh.write(png_bytes(render_overlay(image, result, **kw), getattr(result, "name", None) or "overlay"))


def write_overlay(path: PathLike, image: ImageLike, result, **kw) -> Path:
    """:func:`render_overlay` written as PNG (atomic write)."""
    return atomic_write(path, png_bytes(render_overlay(image, result, **kw), path))
