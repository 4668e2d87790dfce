"""Point sets as ``.npy`` arrays of shape ``(N, 2)`` (any integer or float dtype, no pickles)."""
from __future__ import annotations

import io as _io
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from torch_isc._helpers import npy_header, one_line
from torch_isc.io.errors import PointFileError

__all__ = ["SUFFIXES", "MAGIC", "is_npy", "decode_points"]

SUFFIXES = (".npy",)
#: The first bytes of every ``.npy`` file: such a file is read as ``.npy`` whatever its suffix.
MAGIC = b"\x93NUMPY"


def is_npy(raw: bytes) -> bool:
    return raw.startswith(MAGIC)


def _check_header(p: Path, raw: bytes) -> None:
    """Check the declared shape, dtype and size against the bytes present, before numpy
    allocates anything: a 289-byte file may declare an array of a terabyte."""
    fp = _io.BytesIO(raw)
    try:
        shape, _, dtype = npy_header(fp)
    except Exception as e:  # corrupt or unknown headers
        raise PointFileError(f"{p}: unreadable .npy file ({one_line(e) or type(e).__name__})") from None
    if dtype.hasobject:
        raise PointFileError(f"{p}: unreadable .npy file (an object array: pickles are not read)")
    # by kind: numpy counts timedelta64 as an integer type, but durations are not coordinates
    if dtype.kind not in "iuf":
        raise PointFileError(f"{p}: expected a numeric (integer or float) array, got dtype {dtype}")
    if not all(type(n) is int for n in shape):      # (True, 2) passed numpy's header check
        raise PointFileError(f"{p}: unreadable .npy file (its header declares a shape of non-integers {tuple(shape)})")
    if any(int(n) < 0 for n in shape):
        raise PointFileError(f"{p}: unreadable .npy file (its header declares a negative shape {tuple(shape)})")
    if len(shape) != 2 or shape[1] != 2:
        raise PointFileError(f"{p}: expected an array of shape (N, 2), got shape {tuple(shape)}")
    need = int(shape[0]) * int(shape[1]) * int(dtype.itemsize)
    have = len(raw) - fp.tell()
    if need > have:
        raise PointFileError(f"{p}: unreadable .npy file (truncated: its header declares shape {tuple(shape)} of {dtype} "
                             f"({need} bytes), the file holds {have} bytes of data)")
    if need < have:      # np.load ignores them: a concatenation or a wrong header would be read silently
        raise PointFileError(f"{p}: unreadable .npy file ({have - need} bytes after the data its header declares: "
                             f"shape {tuple(shape)} of {dtype}, {need} bytes)")


def decode_points(p: Path, raw: bytes) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """``.npy`` bytes -> ``(points (N, 2) float64, None)`` (no line numbers); ``p`` names the
    file in messages.

    >>> b = _io.BytesIO(); np.save(b, np.zeros((3, 2), np.int32))
    >>> decode_points(Path("a.npy"), b.getvalue())[0].shape
    (3, 2)
    """
    if not is_npy(raw):
        raise PointFileError(f"{p}: not a valid .npy file (no NumPy header)")
    _check_header(p, raw)
    try:
        arr = np.load(_io.BytesIO(raw), allow_pickle=False)
    except (ValueError, EOFError, OSError) as e:
        # object arrays, truncated data and corrupt headers all end up here
        raise PointFileError(f"{p}: unreadable .npy file ({one_line(e) or type(e).__name__})") from None
    if not isinstance(arr, np.ndarray):  # pragma: no cover - np.load of a .npy gives an array
        raise PointFileError(f"{p}: not a .npy array")
    if arr.dtype.kind not in "iuf":
        raise PointFileError(f"{p}: expected a numeric (integer or float) array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise PointFileError(f"{p}: expected an array of shape (N, 2), got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0:
        raise PointFileError(f"{p}: no points (empty array)")
    with np.errstate(over="ignore"):
        out = arr.astype(np.float64)
    if arr.dtype.itemsize > 8 and np.isfinite(arr).all() and not np.isfinite(out).all():
        raise PointFileError(f"{p}: coordinates beyond the float64 range (its {arr.dtype} values overflow)")
    return out, None
