"""Helpers shared by images, io, the runner and the CLI. This module imports nothing from
torch_isc, so every layer may use it without an import cycle."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

__all__ = ["one_line", "import_cv2", "read_file_bytes", "decode_text"]


def one_line(msg: object, default: str = "") -> str:
    """The first line of ``str(msg)`` stripped, or ``default`` when it is empty.

    >>> one_line(ValueError("bad\\nmore")), one_line(KeyError(), "KeyError")
    ('bad', 'KeyError')
    """
    lines = str(msg).strip().splitlines()
    return lines[0] if lines else default


def import_cv2():
    """OpenCV, imported on first use: only image input and PNG output need it."""
    import cv2

    return cv2


def read_file_bytes(path: Union[str, os.PathLike], error: type, what: str) -> bytes:
    """The bytes of ``path``, or ``error`` with one line naming the file (missing, a folder,
    unreadable); ``what`` names the expected kind of file (e.g. ``"a point file"``)."""
    p = Path(path)
    try:
        return p.read_bytes()
    except FileNotFoundError:
        raise error(f"{p}: no such file") from None
    except IsADirectoryError:
        raise error(f"{p}: is a directory, not {what}") from None
    except OSError as e:
        raise error(f"{p}: cannot read ({e.strerror or e})") from None


def decode_text(raw: bytes, label: str, what: str, error: type) -> str:
    """``raw`` as UTF-8 text (a BOM allowed), or ``error`` saying ``"<label>: not a <what>"``
    and why (a byte that is not UTF-8, NUL bytes: a binary file)."""
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{label}: not a {what} (byte {e.start} is not UTF-8)") from None
    if "\x00" in text:
        raise error(f"{label}: not a {what} (contains NUL bytes)")
    return text
