"""A curve drawn with OpenCV as PNG: data points, mesh, vertex signs and the zero set."""
from __future__ import annotations

import math
import operator
from pathlib import Path
from typing import BinaryIO, Optional, Tuple

import numpy as np
import torch

from torch_isc._helpers import import_cv2
from torch_isc.core.curve import ImplicitCurve
from torch_isc.io.files import PathLike, atomic_write

__all__ = ["png_bytes", "render_curve", "render_png", "encode_png", "write_png"]

# BGR colours (OpenCV)
_GREY = (205, 205, 205)
_BLUE = (220, 60, 0)
_RED = (0, 0, 220)
_BLACK = (0, 0, 0)
_GREEN = (0, 160, 0)
_ORANGE = (0, 140, 255)
_SHIFT = 4  # sub-pixel bits for OpenCV drawing


def png_bytes(img: np.ndarray, name: object = "image") -> bytes:
    """An ``(H, W)`` or ``(H, W, 3)`` uint8 (BGR) image encoded as PNG; ``name`` labels errors."""
    ok, buf = import_cv2().imencode(".png", img)
    if not ok:  # pragma: no cover
        raise OSError(f"{name}: PNG encoding failed")
    return buf.tobytes()


def _stamp(img: np.ndarray, xy: np.ndarray, radius: int, colour: Tuple[int, int, int]) -> None:
    """Draw filled discs at pixel centres ``xy (P, 2)`` (float) by stamping a disc of offsets:
    one numpy assignment per offset, not per point."""
    if xy.shape[0] == 0:
        return
    H, W = img.shape[:2]
    c = np.rint(xy).astype(np.int64)
    r = int(radius)
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = (dx * dx + dy * dy) <= r * r + (r if r > 1 else 0)   # r = 1: a 5-pixel plus, small next to curves
    for ox, oy in zip(dx[disc].tolist(), dy[disc].tolist()):
        x, y = c[:, 0] + ox, c[:, 1] + oy
        ok = (x >= 0) & (x < W) & (y >= 0) & (y < H)
        img[y[ok], x[ok]] = colour


def _unit(verts: torch.Tensor) -> float:
    """A power of 2 within a factor 2 of the largest finite coordinate magnitude (1 if none)."""
    a = verts.detach().double().abs()
    a = a[torch.isfinite(a)]
    m = float(a.max()) if a.numel() else 0.0
    return math.ldexp(1.0, math.frexp(m)[1]) if m > 0 else 1.0


#: the largest PNG side :func:`render_curve` draws (16384^2 x 3 bytes: 805 MB)
MAX_RENDER_SIZE = 16384


def render_curve(curve: ImplicitCurve, points: Optional[torch.Tensor] = None, size: int = 800,
                 draw_mesh: bool = True, draw_signs: bool = True, y_down: bool = False) -> np.ndarray:
    """Draw one curve: a ``(size, size, 3)`` uint8 BGR image.

    Args:
        curve: :class:`ImplicitCurve`, a batch of one.
        points: ``(N, 2)`` data points (black), or ``None``.
        size: image width and height in pixels.
        draw_mesh: light grey mesh edges.
        draw_signs: vertex dots, blue where ``f < 0`` (inside), red where ``f > 0`` (outside).

    Closed curves are green, open chains orange. The item's mesh bbox is fitted into the image
    (aspect kept, centred, a small margin) and y points up (image rows are flipped), or down
    with ``y_down`` (image pixel coordinates).
    """
    if curve.num_items != 1:
        raise ValueError(f"render_png draws one curve, got a batch of {curve.num_items}")
    try:
        n = operator.index(size)
    except TypeError:
        n = -1
    if isinstance(size, bool) or not 16 <= n <= MAX_RENDER_SIZE:
        raise ValueError(f"size must be an integer of 16 to {MAX_RENDER_SIZE} pixels, got {size!r:.40}")
    size = n
    cv2 = import_cv2()
    c = curve.detach()
    # work in units of a power of 2 near the largest coordinate: exact, and no spans or
    # products that overflow (or underflow) float64 at extreme magnitudes
    unit = _unit(c.mesh.verts)
    verts = c.mesh.verts.double().cpu().numpy() / unit
    x0, y0, x1, y1 = (v / unit for v in c.mesh.item_bbox()[0].double().cpu().tolist())
    span = max(x1 - x0, y1 - y0)
    if not math.isfinite(span) or span <= 0:
        span = 1.0
    pad = max(4.0, 0.02 * size)
    scale = (size - 2 * pad) / span
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)

    def to_px(xy: np.ndarray) -> np.ndarray:
        # y up: image rows grow downwards, so the data y is negated
        sy = scale if y_down else -scale
        return np.stack([(xy[:, 0] - cx) * scale + 0.5 * size, 0.5 * size + (xy[:, 1] - cy) * sy], 1)

    def fixed(px: np.ndarray) -> np.ndarray:
        return np.rint(px * (1 << _SHIFT)).astype(np.int32)

    img = np.full((size, size, 3), 255, np.uint8)
    lw = max(1, int(round(size / 800)))
    if draw_mesh and c.mesh.faces.shape[0]:
        e = c.mesh.edges.cpu().numpy()
        segs = fixed(to_px(verts[e.reshape(-1)])).reshape(-1, 2, 2)
        cv2.polylines(img, list(segs), False, _GREY, lw, cv2.LINE_AA, _SHIFT)
    if draw_signs:
        r = max(1, int(round(size / 300)))
        vals = c.values.cpu().numpy()
        px = to_px(verts)
        _stamp(img, px[vals < 0], r, _BLUE)
        _stamp(img, px[vals > 0], r, _RED)
    pl = c.zero_set()
    if len(pl):
        lines = [fixed(to_px(q.double().cpu().numpy() / unit)) for q in pl.polyline_list()]
        closed = pl.closed.cpu().tolist()
        lw2 = max(2, int(round(size / 400)))
        cl = [q for q, k in zip(lines, closed) if k]
        op = [q for q, k in zip(lines, closed) if not k]
        if cl:
            cv2.polylines(img, cl, True, _GREEN, lw2, cv2.LINE_AA, _SHIFT)
        if op:
            cv2.polylines(img, op, False, _ORANGE, lw2, cv2.LINE_AA, _SHIFT)
    if points is not None:
        pts = torch.as_tensor(points).detach().double().cpu().numpy().reshape(-1, 2)
        _stamp(img, to_px(pts / unit), max(1, int(size // 800)), _BLACK)
    return img


def render_png(path: PathLike, curve: ImplicitCurve, points: Optional[torch.Tensor] = None, size: int = 800,
               draw_mesh: bool = True, draw_signs: bool = True, y_down: bool = False) -> Path:
    """:func:`render_curve` written as PNG to ``path`` (atomic write)."""
    img = render_curve(curve, points, size, draw_mesh, draw_signs, y_down)
    return atomic_write(path, png_bytes(img, path))


def encode_png(result, fh: BinaryIO, size: int = 800, y_down: bool = False) -> None:
    """:func:`render_curve` of ``result.curve`` with ``result.points``, as PNG into ``fh``."""
    fh.write(png_bytes(render_curve(result.curve, result.points, size=size, y_down=y_down), result.name))


def write_png(path: PathLike, result, size: int = 800, y_down: bool = False) -> Path:
    """:func:`encode_png` into ``path`` (atomic write)."""
    return atomic_write(path, png_bytes(render_curve(result.curve, result.points, size=size, y_down=y_down), path))
