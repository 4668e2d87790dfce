"""The result as JSON: deterministic text (insertion order, shortest float repr, NaN/Inf as
``null``, one ``[x, y]`` per line) without wall times unless asked, so the same input gives a
byte-identical file."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, BinaryIO, Dict

import numpy as np
import torch

from torch_isc.io.files import PathLike, atomic_write

__all__ = ["jsonable", "json_dumps", "result_json_dict", "encode_json", "write_json"]


def jsonable(obj: Any) -> Any:
    """Plain JSON types for tensors, numpy values, paths, dtypes; non-finite floats become None.

    >>> jsonable({"a": torch.tensor([1.5, float("nan")]), "p": Path("x")})
    {'a': [1.5, None], 'p': 'x'}
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if _float_pairs(obj):            # fast path: a polyline's points, already plain floats
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


def _float_pairs(obj: Any) -> bool:
    """``obj`` is a non-empty list of ``[x, y]`` lists of finite Python floats (written as is)."""
    if not (type(obj) is list and obj and type(obj[0]) is list):
        return False
    return all(type(p) is list and len(p) == 2 and type(p[0]) is float and type(p[1]) is float
               and math.isfinite(p[0]) and math.isfinite(p[1]) for p in obj)


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
        if _float_pairs(obj):
            return "[\n" + ",\n".join(f"{inner}[{p[0]!r}, {p[1]!r}]" for p in obj) + "\n" + pad + "]"
        if not obj or all(not isinstance(v, (list, dict)) for v in obj):
            return _compact(obj)
        items = [inner + _format_json(v, indent, level + 1) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return _compact(obj)


def json_dumps(obj: Any, indent: int = 1) -> str:
    """Deterministic JSON text: insertion order kept, floats as Python's shortest round-trip
    repr, NaN/Inf written as ``null``, one ``[x, y]`` per line, trailing newline.

    >>> print(json_dumps({"points": [[0.5, 1], [2, float("inf")]]}), end="")
    {
     "points": [
      [0.5, 1],
      [2, null]
     ]
    }
    """
    return _format_json(jsonable(obj), indent) + "\n"


def result_json_dict(result, timings: bool = False) -> Dict[str, Any]:
    """``result.to_json_dict()`` without the per-level ``seconds`` unless ``timings``: wall
    times differ from run to run, and without them the same input gives a byte-identical file."""
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
