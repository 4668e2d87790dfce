"""The result as JSON: deterministic text (insertion order, shortest float repr, NaN/Inf as
``null``, one ``[x, y]`` per line) without wall times unless asked, so the same input gives a
byte-identical file.

Numbers of a float matrix (a polyline's points) that are float32 numbers, as the mask path's
curves are, are written with 9 significant digits (``%.9g``): exactly enough to read back the
same float32 (``np.float32(value)``), within 5e-9 relative as float64
(:func:`as_written` gives the values as read back). Other floats keep Python's repr."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, BinaryIO, Dict

import numpy as np
import torch

from torch_isc.io.files import PathLike, atomic_write

__all__ = ["jsonable", "json_dumps", "result_json_dict", "encode_json", "write_json", "as_written"]


def jsonable(obj: Any) -> Any:
    """Plain JSON types for tensors, numpy values, paths, dtypes; non-finite floats become None.

    >>> jsonable({"a": torch.tensor([1.5, float("nan")]), "p": Path("x")})
    {'a': [1.5, None], 'p': 'x'}
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if type(obj) is list and _plain_dump(obj) is not None:   # fast path: plain numbers already
            return obj
        return [jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (Path, torch.dtype, torch.device)):
        return str(obj)
    raise TypeError(f"cannot convert {type(obj).__name__} to JSON")


def _plain_dump(obj: list) -> Any:
    """The compact JSON text of ``obj`` when it holds only lists and JSON scalars other than
    strings (finite numbers, booleans, null): then :func:`jsonable` leaves it as it is and
    every part of the text is what the slow path would write; else None. One C-level
    ``json.dumps`` instead of a Python walk over every point of a polyline."""
    try:
        text = json.dumps(obj, separators=(", ", ": "), allow_nan=False)
    except (TypeError, ValueError):
        return None
    if '"' in text or "{" in text:
        return None
    return text


class _Rows:
    """A finite float matrix ready to print (float64 numpy ``(n, k)``, ``n, k >= 1``)."""
    __slots__ = ("a",)

    def __init__(self, a: np.ndarray):
        self.a = a

    def text(self, inner: str) -> str:
        """One ``[x, y, ...]`` per line, each line starting with ``inner``, from one C-level
        ``%`` format of the whole matrix (no Python loop over its values).

        A value that is exactly a float32 number (the mask path's curves are float32 data) is
        written with 9 significant digits, ``%.9g``: exactly enough to read back the same
        float32, and half the bytes and a third of the time of the 17 digits of its float64
        repr. Any other value is written as Python's repr (shortest round trip of the float64),
        an integral value below 1e16 as ``%.1f`` (``113.0``, as repr writes it)."""
        a = self.a
        n, k = a.shape
        with np.errstate(over="ignore"):          # beyond float32: inf, so not a float32 value
            f32 = a.astype(np.float32).astype(np.float64) == a
        integral = (a == np.rint(a)) & (np.abs(a) < 1e16)
        code = np.where(integral, 0, np.where(f32, 1, 2))
        fmts = ("%.1f", "%.9g", "%r")
        if bool((code == code.flat[0]).all()):      # one format for all: one template
            f = fmts[int(code.flat[0])]
            tmpl = (inner + "[" + ", ".join([f] * k) + "],\n") * n
        elif k == 2:                                  # points: one template per row
            rows = np.array([inner + "[" + fx + ", " + fy + "],\n" for fx in fmts for fy in fmts], dtype=object)
            tmpl = "".join(rows[code[:, 0] * 3 + code[:, 1]].tolist())
        else:
            parts = np.empty((n, 2 * k + 1), dtype=object)
            parts[:, 0] = inner + "["
            parts[:, 1:-1:2] = np.array(fmts, dtype=object)[code]
            parts[:, 2:-1:2] = ", "
            parts[:, -1] = "],\n"
            tmpl = "".join(parts.ravel().tolist())
        return (tmpl[:-2] % tuple(a.ravel().tolist()))


def as_written(a: np.ndarray) -> np.ndarray:
    """A float ``(n, k)`` matrix's values as its JSON text reads back (float64): a float32
    number is written with 9 significant digits (:meth:`_Rows.text`), so a table built from
    results matches one built from their JSON files value for value.

    >>> x = float(np.float32(0.1)); as_written(np.array([[x, 0.1]])).tolist() == [[0.100000001, 0.1]]
    True
    """
    r = _float_matrix(a)
    if r is None:
        return np.asarray(a, dtype=np.float64)
    return np.array(json.loads("[" + r.text("") + "]"), dtype=np.float64).reshape(r.a.shape)


def _float_matrix(obj: Any) -> Any:
    """A floating ``(n, k)`` tensor or array (``n, k >= 1``, all finite) as :class:`_Rows`
    (printed by one format of the whole matrix, see :meth:`_Rows.text`); None for anything else."""
    if isinstance(obj, torch.Tensor):
        if not (obj.dtype.is_floating_point and obj.dim() == 2 and obj.shape[0] > 0 and obj.shape[1] > 0):
            return None
        a = obj.detach().cpu().double().numpy()
    elif isinstance(obj, np.ndarray):
        if not (obj.dtype.kind == "f" and obj.ndim == 2 and obj.shape[0] > 0 and obj.shape[1] > 0):
            return None
        a = obj.astype(np.float64, copy=False)
    else:
        return None
    if not np.isfinite(a).all():
        return None
    return _Rows(a)


def _prepare(obj: Any) -> Any:
    """:func:`jsonable`, but floating matrices become :class:`_Rows` (printed as is)."""
    rows = _float_matrix(obj)
    if rows is not None:
        return rows
    if isinstance(obj, dict):
        return {str(k): _prepare(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if type(obj) is list and _plain_dump(obj) is not None:
            return obj
        return [_prepare(v) for v in obj]
    return jsonable(obj)


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
    if type(obj) is _Rows:
        return "[\n" + obj.text(inner) + "\n" + pad + "]"
    if isinstance(obj, list):
        if obj and type(obj[0]) is list and all(type(v) is list for v in obj):
            # a list of flat lists of numbers (a polyline's points): one per line, from one dump
            text = _plain_dump(obj)
            if text is not None and text.count("[") == len(obj) + 1:
                return "[\n" + inner + text[1:-1].replace("], [", "],\n" + inner + "[") + "\n" + pad + "]"
        if not obj or all(not isinstance(v, (list, dict, _Rows)) for v in obj):
            return _compact(obj)
        items = [inner + _format_json(v, indent, level + 1) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return _compact(obj)


def json_dumps(obj: Any, indent: int = 1) -> str:
    """Deterministic JSON text: insertion order kept, floats as Python's shortest round-trip
    repr (float32 numbers in a float matrix: 9 significant digits, see the module docstring),
    NaN/Inf written as ``null``, one ``[x, y]`` per line, trailing newline.

    >>> print(json_dumps({"points": [[0.5, 1], [2, float("inf")]]}), end="")
    {
     "points": [
      [0.5, 1],
      [2, null]
     ]
    }
    """
    return _format_json(_prepare(obj), indent) + "\n"


def result_json_dict(result, timings: bool = False) -> Dict[str, Any]:
    """``result.to_json_dict()`` without the per-level ``seconds`` unless ``timings``: wall
    times differ from run to run, and without them the same input gives a byte-identical file."""
    try:
        d = result.to_json_dict(arrays=True)        # points as arrays: printed without a Python list
    except TypeError:
        d = result.to_json_dict()
    if not timings and isinstance(d.get("stats"), dict) and isinstance(d["stats"].get("levels"), list):
        d["stats"] = dict(d["stats"])
        d["stats"]["levels"] = [{k: v for k, v in lv.items() if k not in ("seconds", "stage_seconds")} if isinstance(lv, dict) else lv
                                for lv in d["stats"]["levels"]]
    return d


def encode_json(result, fh: BinaryIO, timings: bool = False) -> None:
    """Write ``result.to_json_dict()`` as UTF-8 into ``fh``: ``{"polylines": [{"closed": bool,
    "points": [[x, y], ...]}], "num_components": int, "bbox": [xmin, ymin, xmax, ymax],
    "stats": {...}}`` in the caller's coordinates (see :func:`result_json_dict`)."""
    fh.write(json_dumps(result_json_dict(result, timings)).encode("utf-8"))


def write_json(path: PathLike, result, timings: bool = False) -> Path:
    """:func:`encode_json` into ``path`` (atomic write)."""
    return atomic_write(path, lambda fh: encode_json(result, fh, timings))
