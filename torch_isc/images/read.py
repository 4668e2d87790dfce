"""Image files decoded as grayscale arrays."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

import numpy as np

from torch_isc._helpers import import_cv2, read_file_bytes
from torch_isc.images.arrays import ImageError

__all__ = ["IMAGE_SUFFIXES", "read_image", "decode_image"]

#: File suffixes read as images (lower case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def read_image(path: Union[str, os.PathLike]) -> np.ndarray:
    """Read an image file as grayscale ``(H, W)`` float32 in ``[0, 1]`` (see :func:`decode_image`).

    Raises:
        ImageError: missing file, unreadable / truncated / not an image (one line, naming it).
    """
    p = Path(path)
    return decode_image(read_file_bytes(p, ImageError, "an image"), p)


def decode_image(data: bytes, name: object = "image") -> np.ndarray:
    """The bytes of an image file (any format OpenCV decodes) as grayscale ``(H, W)`` float32
    in ``[0, 1]``; ``name`` (e.g. the path) starts every error message.

    Colour is converted to gray (OpenCV weights); an alpha channel, when present and not
    fully opaque, multiplies the gray value (a transparent background reads as black).
    8-bit, 16-bit and float images are scaled to ``[0, 1]``.

    >>> import cv2
    >>> decode_image(cv2.imencode(".png", np.full((2, 3), 255, np.uint8))[1].tobytes()).tolist()
    [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]
    """
    cv2 = import_cv2()
    p = name
    raw = np.frombuffer(data, dtype=np.uint8)
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

