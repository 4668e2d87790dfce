"""The zero set as SVG: closed curves filled even-odd, open chains stroked."""
from __future__ import annotations

import math
from pathlib import Path
from typing import BinaryIO, Iterable, List, Tuple

import numpy as np

from torch_isc._helpers import printable
from torch_isc.io.files import PathLike, atomic_write

__all__ = ["svg_text", "encode_svg", "write_svg"]


def _fmt_xy(pts: np.ndarray) -> List[str]:
    # the shortest text that reads back as the same float64 (9 digits merged the vertices of a
    # curve 1e-2 across at an offset of 1e7)
    return [f"{x!r},{y!r}" for x, y in pts.tolist()]


def _padded_bbox(bbox: Iterable[float], margin: float) -> Tuple[float, float, float, float]:
    x0, y0, x1, y1 = (float(v) for v in bbox)
    w, h = x1 - x0, y1 - y0
    size = max(w, h)
    if not math.isfinite(size) or size <= 0:
        size = max(abs(x0), abs(y0), abs(x1), abs(y1), 1.0)
    m = margin * size
    return x0 - m, y0 - m, x1 + m, y1 + m


def _xml_escape(s: str) -> str:
    # control characters (not allowed in XML 1.0) and the lone surrogates of a non-UTF-8 file name
    # (not encodable) written as backslash escapes first
    s = printable(s)
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def svg_text(result, margin: float = 0.05, width: int = 800, y_down: bool = False) -> str:
    """The SVG document of ``result``'s zero set.

    Closed polylines together form one ``<path>`` with ``fill-rule="evenodd"`` (a hole inside an
    outer curve stays unfilled, an island inside a hole is filled again); open chains are
    stroked, unfilled paths. The viewBox is the polylines' bbox plus ``margin`` (a fraction of the
    larger side).

    The y axis is as in the data: path coordinates are the caller's ``(x, y)`` unchanged, and
    a ``transform="scale(1,-1)"`` on the group flips the drawing so y points up on screen (SVG's
    own y axis points down); ``y_down`` (image pixels) leaves it unflipped. Reading the path
    data back gives the data coordinates.
    """
    pls = [(bool(pl["closed"]), pl["points"].detach().double().cpu().numpy()) for pl in result.polylines]
    x0, y0, x1, y1 = _padded_bbox(result.bbox(), margin)
    w, h = x1 - x0, y1 - y0
    height = max(1, min(1 << 20, int(round(width * (h / w)))))      # h / w first: width * h can overflow
    stroke = "vector-effect=\"non-scaling-stroke\""
    closed_d = " ".join("M " + " L ".join(_fmt_xy(p)) + " Z" for c, p in pls if c and len(p))
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{width}" height="{height}" '
        f'viewBox="{x0!r} {(y0 if y_down else -y1)!r} {w!r} {h!r}">',
        f"<title>{_xml_escape(result.name or 'torch_isc reconstruction')}</title>",
        '<g>' if y_down else '<g transform="scale(1,-1)">',
    ]
    if closed_d:
        out.append(f'<path class="closed" d="{closed_d}" fill="#8fd18f" fill-opacity="0.5" fill-rule="evenodd" '
                   f'stroke="#008a00" stroke-width="1.5" stroke-linejoin="round" {stroke}/>')
    for c, p in pls:
        if not c and len(p):
            out.append(f'<path class="open" d="M {" L ".join(_fmt_xy(p))}" fill="none" stroke="#ff8c00" '
                       f'stroke-width="1.5" stroke-linejoin="round" stroke-linecap="round" {stroke}/>')
    out += ["</g>", "</svg>", ""]
    return "\n".join(out)


def encode_svg(result, fh: BinaryIO, margin: float = 0.05, width: int = 800, y_down: bool = False) -> None:
    """:func:`svg_text` as UTF-8 into ``fh``."""
    fh.write(svg_text(result, margin, width, y_down).encode("utf-8"))


def write_svg(path: PathLike, result, margin: float = 0.05, width: int = 800, y_down: bool = False) -> Path:
    """:func:`svg_text` into ``path`` (atomic write)."""
    return atomic_write(path, svg_text(result, margin, width, y_down))
