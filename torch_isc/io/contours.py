"""The closed curves as OpenCV contours with their hierarchy, in an uncompressed ``.npz`` (float32
coordinates compress poorly: ``np.savez`` is 10 times faster than ``savez_compressed`` for 1.5
times the bytes; :func:`load_contours` reads both); the
layout (``points``, ``counts``, ``hierarchy``, ``mode``, ``format``) is
:func:`torch_isc.images.contour_arrays`, read back by :func:`load_contours`."""
from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

from torch_isc.images import contour_arrays, load_contours
from torch_isc.io.files import PathLike, atomic_write

__all__ = ["encode_contours", "write_contours", "load_contours"]


def encode_contours(result, fh: BinaryIO, mode: str = "tree") -> None:
    """The contours of ``result`` (``mode``: ``"tree"`` or ``"ccomp"``) as ``.npz`` into ``fh``."""
    np.savez(fh, **contour_arrays(result, mode))


def write_contours(path: PathLike, result, mode: str = "tree") -> Path:
    """:func:`encode_contours` into ``path`` (atomic write); :func:`load_contours` gives
    ``(contours, hierarchy)`` back as ``cv2.findContours`` returns them."""
    arrays = contour_arrays(result, mode)
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))
