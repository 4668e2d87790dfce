"""Inputs and outputs: point files in, curves / JSON / SVG / PNG out.

Reading: :func:`read_points` accepts text (``x y`` or ``x,y`` rows, ``#`` comments, blank
lines, one optional header line of words) and ``.npy`` arrays of shape ``(N, 2)``. Every
problem raises :class:`PointFileError` with one line naming the file and the problem.

Writing: every writer goes through :func:`atomic_write` (a temporary file in the destination
folder, then ``os.replace``), so an interrupted run never leaves a half-written output: a file
either has its old content or its complete new content.

Exporters work on a :class:`~torch_isc.pipeline.result.ReconstructionResult` and are registered in
:data:`EXPORTERS` by format name, the way trimesh registers its exporters; :func:`export` writes
several formats next to each other.

This module uses numpy and OpenCV only (no matplotlib) and is not imported by the core.
"""
from __future__ import annotations

import io as _io
import json
import math
import os
import re
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Tuple, Union

import numpy as np
import torch

from torch_isc.core.curve import ImplicitCurve, InvalidValuesError
from torch_isc.core.mesh import InvalidMeshError, MeshBatch

__all__ = [
    "PointFileError", "CurveFileError", "read_file_bytes", "read_points", "atomic_write", "save_npz", "load_npz",
    "json_dumps", "write_json", "write_npz", "write_svg", "render_png", "write_png",
    "write_contours", "EXPORTERS", "export",
]

PathLike = Union[str, os.PathLike]

#: Version of the ``.npz`` layout written by :func:`save_npz`.
NPZ_FORMAT = 1


class PointFileError(ValueError):
    """A point file that cannot be read; the message is one line naming the file."""


class CurveFileError(ValueError):
    """A curve ``.npz`` file that cannot be loaded; the message is one line naming the file."""


# =============================================================================== reading
_NPY_MAGIC = b"\x93NUMPY"
_FIELD_SPLIT = re.compile(r"\s*,\s*|\s+")


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _one_line(msg: object) -> str:
    s = str(msg).strip().splitlines()
    return s[0] if s else ""


def read_file_bytes(path: PathLike, error: type, what: str) -> bytes:
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


def read_points(path: PathLike) -> np.ndarray:
    """Read a point set.

    Args:
        path: a text file of ``x y`` rows (whitespace- or comma-separated; ``#`` starts a
            comment; blank lines are skipped; the first data line may be a header of
            non-numeric words such as ``x,y``), or a ``.npy`` file holding a numeric
            ``(N, 2)`` array. A file that starts with the ``.npy`` magic is read as ``.npy``
            whatever its extension.

    Returns:
        points: ``(N, 2)`` float64, C-contiguous. ``N`` may be 1 or 2: whether that is enough
        is for the reconstruction to decide.

    Raises:
        PointFileError: missing or unreadable file, no points, non-numeric text (with the line
            number), a row without exactly 2 columns (with the line number and the count), a
            ``.npy`` of the wrong shape or dtype or truncated, NaN/Inf coordinates (with the count).
    """
    p = Path(path)
    raw = read_file_bytes(p, PointFileError, "a point file")
    if raw.startswith(_NPY_MAGIC) or p.suffix.lower() == ".npy":
        pts = _read_npy(p, raw)
        rows: Optional[np.ndarray] = None
    else:
        pts, rows = _read_text(p, raw)
    bad = ~np.isfinite(pts)
    if bad.any():
        nbad = int(bad.any(1).sum())
        first = int(np.flatnonzero(bad.any(1))[0])
        where = f"line {int(rows[first])}" if rows is not None else f"array row {first}"
        raise PointFileError(f"{p}: {nbad} point(s) have NaN or Inf coordinates (first at {where})")
    return np.ascontiguousarray(pts, dtype=np.float64)


def _read_npy(p: Path, raw: bytes) -> np.ndarray:
    if not raw.startswith(_NPY_MAGIC):
        raise PointFileError(f"{p}: not a valid .npy file (no NumPy header)")
    try:
        arr = np.load(_io.BytesIO(raw), allow_pickle=False)
    except (ValueError, EOFError, OSError) as e:
        # object arrays, truncated data and corrupt headers all end up here
        raise PointFileError(f"{p}: unreadable .npy file ({_one_line(e) or type(e).__name__})") from None
    if not isinstance(arr, np.ndarray):  # pragma: no cover - np.load of a .npy gives an array
        raise PointFileError(f"{p}: not a .npy array")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise PointFileError(f"{p}: expected a numeric (integer or float) array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise PointFileError(f"{p}: expected an array of shape (N, 2), got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0:
        raise PointFileError(f"{p}: no points (empty array)")
    return arr.astype(np.float64)


_COMMENT = re.compile(r"#[^\n]*")
_FIRST_LINE = re.compile(r"^[ \t\f\v]*(\S[^\n]*)$", re.M)
_EMPTY_FIELD = re.compile(r"^[ \t]*,|,[ \t]*,|,[ \t]*$", re.M)


def _read_text(p: Path, raw: bytes) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Text rows -> ``(points (N, 2), line numbers (N,) or None)``.

    Fast path: comments are cut and the header blanked with regexes over the whole text, then
    numpy parses all rows at once (blank lines skipped). Only when that fails, or when a row
    number is needed for a message, are the lines walked one by one."""
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise PointFileError(f"{p}: not a text point file (byte {e.start} is not UTF-8)") from None
    if "\x00" in text:
        raise PointFileError(f"{p}: not a text point file (contains NUL bytes)")
    text = _COMMENT.sub("", text.replace("\r\n", "\n").replace("\r", "\n"))
    first = _FIRST_LINE.search(text)
    if first is None:
        raise PointFileError(f"{p}: no points (the file has no data lines)")
    toks = _FIELD_SPLIT.split(first.group(1).strip())
    if all(tok and not _is_number(tok) for tok in toks):
        # a header line of words: blank it, keeping the line count for messages
        text = text[:first.start(1)] + text[first.end(1):]
    pts: Optional[np.ndarray] = None
    if _EMPTY_FIELD.search(text) is None:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")          # "input contained no data"
                pts = np.loadtxt(_io.StringIO(text.replace(",", " ")), dtype=np.float64, ndmin=2, comments=None)
        except ValueError:
            pts = None
    if pts is not None and pts.size == 0:
        raise PointFileError(f"{p}: no points (the file has no data lines)")
    if pts is None or pts.shape[1] != 2 or not np.isfinite(pts).all():
        return _parse_lines(p, text)
    return pts, None


def _parse_lines(p: Path, text: str) -> Tuple[np.ndarray, np.ndarray]:
    """The slow path: parse row by row, raising at the first bad line (1-based numbers)."""
    rows: List[Tuple[float, float]] = []
    line_no: List[int] = []
    for i, line in enumerate(text.split("\n")):
        s = line.strip()
        if not s:
            continue
        toks = _FIELD_SPLIT.split(s)
        for tok in toks:
            if tok == "":
                raise PointFileError(f"{p}: line {i + 1}: empty field")
            if not _is_number(tok):
                shown = tok if len(tok) <= 20 else tok[:17] + "..."
                raise PointFileError(f"{p}: line {i + 1}: non-numeric value {shown!r}")
        if len(toks) != 2:
            raise PointFileError(f"{p}: line {i + 1}: expected 2 columns (x y), found {len(toks)}")
        rows.append((float(toks[0]), float(toks[1])))
        line_no.append(i + 1)
    if not rows:
        raise PointFileError(f"{p}: no points (the file has no data lines)")
    return np.asarray(rows, dtype=np.float64), np.asarray(line_no, dtype=np.int64)


# =============================================================================== writing
_UMASK: Optional[int] = None


def _file_mode() -> int:
    global _UMASK
    if _UMASK is None:
        _UMASK = os.umask(0)
        os.umask(_UMASK)
    return 0o666 & ~_UMASK


def atomic_write(path: PathLike, data: Union[bytes, bytearray, str, Callable[[Any], None]]) -> Path:
    """Write ``path`` atomically.

    ``data`` is the content (``bytes``, or ``str`` written as UTF-8) or a function called with an
    open binary file object that writes the content. It goes to a temporary file in the
    destination folder (same file system), which is flushed, synced and then moved over
    ``path`` with ``os.replace``; on any error the temporary file is removed and the error is
    re-raised, and ``path`` is left as it was. The destination folder must exist.

    Returns:
        ``path`` as a :class:`Path`.
    """
    dest = Path(path)
    folder = dest.parent if str(dest.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            if callable(data):
                data(fh)
            elif isinstance(data, str):
                fh.write(data.encode("utf-8"))
            else:
                fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _file_mode())        # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, dest)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return dest


# ------------------------------------------------------------------------------- npz
def _to_numpy(t: torch.Tensor) -> Tuple[np.ndarray, str]:
    """Tensor -> numpy array and torch dtype name; bfloat16 (no numpy dtype) keeps its raw bits."""
    t = t.detach().cpu().contiguous()
    name = str(t.dtype).replace("torch.", "")
    if t.dtype == torch.bfloat16:
        return t.view(torch.int16).numpy(), name
    return t.numpy(), name


def _from_numpy(a: np.ndarray, name: str) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(a))
    if name == "bfloat16":
        return t.view(torch.bfloat16)
    return t


def _jsonable(obj: Any) -> Any:
    """Plain JSON types for tensors, numpy values, paths, dtypes; non-finite floats become None."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return _jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (Path, torch.dtype, torch.device)):
        return str(obj)
    raise TypeError(f"cannot convert {type(obj).__name__} to JSON")


def save_npz(path: PathLike, curve: ImplicitCurve, metadata: Optional[Dict[str, Any]] = None) -> Path:
    """Save a curve batch losslessly (atomic write, compressed ``.npz``).

    Arrays: ``verts (V, 2)``, ``faces (T, 3)`` (global indices), ``values (V,)``,
    ``verts_per_item (B,)``, ``faces_per_item (B,)``, each in its own dtype, plus ``dtypes`` (the
    torch dtype names), ``format`` and ``metadata`` (a JSON string; tensors and numpy values
    become lists, NaN/Inf become null). No pickles: the file loads with ``allow_pickle=False``.
    """
    m = curve.mesh
    arrays: Dict[str, np.ndarray] = {}
    dtypes: Dict[str, str] = {}
    for key, t in (("verts", m.verts), ("faces", m.faces), ("values", curve.values),
                   ("verts_per_item", m.verts_per_item), ("faces_per_item", m.faces_per_item)):
        arrays[key], dtypes[key] = _to_numpy(t)
    arrays["dtypes"] = np.array(json.dumps(dtypes, sort_keys=True))
    arrays["format"] = np.array(NPZ_FORMAT, dtype=np.int64)
    arrays["metadata"] = np.array(json.dumps(_jsonable(metadata or {}), sort_keys=True))
    return atomic_write(path, lambda fh: np.savez_compressed(fh, **arrays))


def load_npz(path: PathLike, device: Union[str, torch.device, None] = None,
             validate: bool = True) -> Tuple[ImplicitCurve, Dict[str, Any]]:
    """Load a file written by :func:`save_npz`.

    Returns:
        ``(curve, metadata)``: the :class:`ImplicitCurve` batch, bit-exact, dtypes as saved (on
        ``device``, default CPU), and the metadata dict.

    Raises:
        CurveFileError: missing, unreadable or inconsistent file (one line naming the file).
    """
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            missing = [k for k in ("verts", "faces", "values", "verts_per_item", "faces_per_item", "dtypes")
                       if k not in z.files]
            if missing:
                raise CurveFileError(f"{p}: not a torch_isc curve file (no '{missing[0]}' array)")
            fmt = int(z["format"]) if "format" in z.files else NPZ_FORMAT
            if fmt > NPZ_FORMAT:
                raise CurveFileError(f"{p}: curve file format {fmt} is newer than this version reads ({NPZ_FORMAT})")
            dtypes = json.loads(str(z["dtypes"]))
            t = {k: _from_numpy(z[k], dtypes.get(k, "")) for k in
                 ("verts", "faces", "values", "verts_per_item", "faces_per_item")}
            meta = json.loads(str(z["metadata"])) if "metadata" in z.files else {}
    except CurveFileError:
        raise
    except FileNotFoundError:
        raise CurveFileError(f"{p}: no such file") from None
    except OSError as e:
        raise CurveFileError(f"{p}: cannot read ({e.strerror or _one_line(e)})") from None
    except Exception as e:  # zipfile.BadZipFile, ValueError, KeyError, json errors from a corrupt file
        raise CurveFileError(f"{p}: unreadable curve file ({type(e).__name__}: {_one_line(e)})") from None
    try:
        if device is not None:
            t = {k: v.to(device) for k, v in t.items()}
        mesh = MeshBatch(t["verts"], t["faces"], t["verts_per_item"], t["faces_per_item"])
        curve = ImplicitCurve(mesh, t["values"], validate=validate)
    except (InvalidMeshError, InvalidValuesError) as e:
        raise CurveFileError(f"{p}: invalid curve ({_one_line(e)})") from None
    return curve, meta


# ------------------------------------------------------------------------------- JSON
def _compact(obj: Any) -> str:
    return json.dumps(obj, separators=(", ", ": "), allow_nan=False)


def _format_json(obj: Any, indent: int, level: int = 0) -> str:
    """Indented JSON in which lists of scalars (e.g. one ``[x, y]``) stay on one line."""
    pad, inner = " " * (indent * level), " " * (indent * (level + 1))
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_format_json(v, indent, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list):
        if not obj or all(not isinstance(v, (list, dict)) for v in obj):
            return _compact(obj)
        items = [inner + _format_json(v, indent, level + 1) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return _compact(obj)


def json_dumps(obj: Any, indent: int = 1) -> str:
    """Deterministic JSON text: insertion order kept, floats as Python's shortest round-trip
    repr, NaN/Inf written as ``null``, one ``[x, y]`` per line, trailing newline."""
    return _format_json(_jsonable(obj), indent) + "\n"


def result_json_dict(result, timings: bool = False) -> Dict[str, Any]:
    """``result.to_json_dict()`` without the per-level ``seconds`` unless ``timings``: wall
    times differ from run to run, and without them the same input gives a byte-identical file."""
    d = result.to_json_dict()
    if not timings and isinstance(d.get("stats"), dict) and isinstance(d["stats"].get("levels"), list):
        d["stats"] = dict(d["stats"])
        d["stats"]["levels"] = [{k: v for k, v in lv.items() if k not in ("seconds", "stage_seconds")} if isinstance(lv, dict) else lv
                                for lv in d["stats"]["levels"]]
    return d


def write_json(path: PathLike, result, timings: bool = False) -> Path:
    """Write ``result.to_json_dict()``: ``{"polylines": [{"closed": bool, "points": [[x, y], ...]}],
    "num_components": int, "bbox": [xmin, ymin, xmax, ymax], "stats": {...}}`` in the caller's
    coordinates. Per-level wall times are left out unless ``timings`` (see :func:`result_json_dict`)."""
    return atomic_write(path, json_dumps(result_json_dict(result, timings)))


def write_npz(path: PathLike, result) -> Path:
    """Save ``result.curve`` with :func:`save_npz`; the metadata holds the name, convergence,
    limit, counts, config and per-level stats."""
    meta = {
        "name": result.name,
        "converged": bool(result.converged),
        "limit": result.limit,
        "num_closed": result.num_closed,
        "num_open": result.num_open,
        "config": result.config.to_dict(),
        "stats": [lv.to_dict() for lv in result.stats],
    }
    return save_npz(path, result.curve, meta)


# ------------------------------------------------------------------------------- SVG
def _fmt_xy(pts: np.ndarray) -> List[str]:
    return [f"{x:.9g},{y:.9g}" for x, y in pts.tolist()]


def _padded_bbox(bbox: Iterable[float], margin: float) -> Tuple[float, float, float, float]:
    x0, y0, x1, y1 = (float(v) for v in bbox)
    w, h = x1 - x0, y1 - y0
    size = max(w, h)
    if not math.isfinite(size) or size <= 0:
        size = max(abs(x0), abs(y0), abs(x1), abs(y1), 1.0)
    m = margin * size
    return x0 - m, y0 - m, x1 + m, y1 + m


def write_svg(path: PathLike, result, margin: float = 0.05, width: int = 800, y_down: bool = False) -> Path:
    """Write the zero set as SVG.

    Closed polylines together form one ``<path>`` with ``fill-rule="evenodd"`` (a hole inside an
    outer curve stays unfilled, an island inside a hole is filled again); open chains are
    stroked, unfilled paths. The viewBox is the polylines' bbox plus ``margin`` (a fraction of the
    larger side).

    The y axis is as in the data: path coordinates are the caller's ``(x, y)`` unchanged, and
    a ``transform="scale(1,-1)"`` on the group flips the drawing so y points up on screen (SVG's
    own y axis points down). Reading the path data back gives the data coordinates.
    """
    pls = [(bool(pl["closed"]), pl["points"].detach().double().cpu().numpy()) for pl in result.polylines]
    x0, y0, x1, y1 = _padded_bbox(result.bbox(), margin)
    w, h = x1 - x0, y1 - y0
    height = max(1, int(round(width * h / w)))
    stroke = "vector-effect=\"non-scaling-stroke\""
    closed_d = " ".join("M " + " L ".join(_fmt_xy(p)) + " Z" for c, p in pls if c and len(p))
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{width}" height="{height}" '
        f'viewBox="{x0:.9g} {(y0 if y_down else -y1):.9g} {w:.9g} {h:.9g}">',
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
    return atomic_write(path, "\n".join(out))


def _xml_escape(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


# ------------------------------------------------------------------------------- PNG
# BGR colours (OpenCV)
_GREY = (205, 205, 205)
_BLUE = (220, 60, 0)
_RED = (0, 0, 220)
_BLACK = (0, 0, 0)
_GREEN = (0, 160, 0)
_ORANGE = (0, 140, 255)
_SHIFT = 4  # sub-pixel bits for OpenCV drawing


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


def render_png(path: PathLike, curve: ImplicitCurve, points: Optional[torch.Tensor] = None, size: int = 800,
               draw_mesh: bool = True, draw_signs: bool = True, y_down: bool = False) -> Path:
    """Render one curve to a ``size x size`` PNG with OpenCV (atomic write).

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
    size = int(size)
    if size < 16:
        raise ValueError(f"size must be >= 16 pixels, got {size}")
    c = curve.detach()
    verts = c.mesh.verts.double().cpu().numpy()
    x0, y0, x1, y1 = c.mesh.item_bbox()[0].double().cpu().tolist()
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
        cv2 = _cv2()
        cv2.polylines(img, list(segs), False, _GREY, lw, cv2.LINE_AA, _SHIFT)
    if draw_signs:
        r = max(1, int(round(size / 300)))
        vals = c.values.cpu().numpy()
        px = to_px(verts)
        _stamp(img, px[vals < 0], r, _BLUE)
        _stamp(img, px[vals > 0], r, _RED)
    pl = c.zero_set()
    if len(pl):
        cv2 = _cv2()
        lines = [fixed(to_px(q.double().cpu().numpy())) for q in pl.polyline_list()]
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
        _stamp(img, to_px(pts), max(1, int(size // 800)), _BLACK)
    ok, buf = _cv2().imencode(".png", img)
    if not ok:  # pragma: no cover
        raise OSError(f"{path}: PNG encoding failed")
    return atomic_write(path, buf.tobytes())


def _cv2():
    import cv2  # imported lazily: only PNG output needs OpenCV

    return cv2


def write_png(path: PathLike, result, size: int = 800, y_down: bool = False) -> Path:
    """:func:`render_png` of ``result.curve`` with ``result.points``."""
    return render_png(path, result.curve, result.points, size=size, y_down=y_down)


def write_contours(path: PathLike, result, mode: str = "tree") -> Path:
    """The closed curves as OpenCV contours with their ``RETR_TREE`` hierarchy, in OpenCV's
    pixel coordinates (:func:`torch_isc.images.write_contours`; read back with
    :func:`torch_isc.images.load_contours`)."""
    from torch_isc.images import write_contours as _write

    return _write(path, result, mode)


# ------------------------------------------------------------------------------- registry
#: Format name -> ``writer(path, result)``; :func:`export` writes ``<stem>.<format>``.
EXPORTERS: Dict[str, Callable[..., Path]] = {
    "json": write_json,
    "npz": write_npz,
    "svg": write_svg,
    "png": write_png,
    "contours.npz": write_contours,
}

#: Writers that draw in a plane and take ``y_down`` (image coordinates, y pointing down).
_Y_DOWN = {"svg", "png"}


def export(result, path_stem: PathLike, formats: Iterable[str] = ("json", "npz", "svg", "png"),
           y_down: bool = False) -> List[Path]:
    """Write ``result`` as ``<path_stem>.<fmt>`` for every format (each write atomic).

    ``y_down``: the coordinates are image pixels (y pointing down): SVG and PNG are drawn
    without flipping y, so they look like the image.

    Returns:
        the written paths, in the order of ``formats``.

    Raises:
        ValueError: an unknown format (before anything is written). OSError from the writes.
    """
    formats = list(formats)
    unknown = [f for f in formats if f not in EXPORTERS]
    if unknown:
        raise ValueError(f"unknown output format '{unknown[0]}' (known: {', '.join(EXPORTERS)})")
    stem = os.fspath(path_stem)
    return [EXPORTERS[f](Path(f"{stem}.{f}"), result, **({"y_down": True} if y_down and f in _Y_DOWN else {}))
            for f in formats]
