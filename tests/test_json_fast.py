"""The JSON writer's fast paths (float matrices through one bulk format, plain number lists
through the C encoder) write the same bytes as the plain recursive encoder below: the writer
before them, plus the float matrix rule formatted value by value (a float32 number with 9
significant digits, an integral value as ``%.1f``, any other as repr)."""
import io
import json
import math
import random
from pathlib import Path

import numpy as np
import torch

from torch_isc.io import json as jn
from torch_isc.io.files import atomic_write


class _Num:
    """A float of a float matrix, formatted one by one (the rule of ``_Rows.text``)."""

    def __init__(self, v):
        self.v = v

    def __str__(self):
        v = self.v
        if v == math.floor(v) and abs(v) < 1e16:
            return "%.1f" % v
        if float(np.float32(v)) == v:
            return format(v, ".9g")
        return repr(v)


def _ref_matrix(obj):
    """A finite 2-D float matrix as rows of :class:`_Num`; None for anything else."""
    a = obj.detach().cpu().numpy() if isinstance(obj, torch.Tensor) else obj
    if not (isinstance(a, np.ndarray) and a.dtype.kind == "f" and a.ndim == 2 and a.size and np.isfinite(a).all()):
        return None
    return [[_Num(float(v)) for v in row] for row in a.astype(np.float64)]


def _ref_jsonable(obj):
    m = _ref_matrix(obj)
    if m is not None:
        return m
    if isinstance(obj, dict):
        return {str(k): _ref_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_ref_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return _ref_jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, np.ndarray):
        return _ref_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _ref_jsonable(obj.item())
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(type(obj))


def _ref_format(obj, indent=1, level=0):
    pad, inner = " " * (indent * level), " " * (indent * (level + 1))
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        return "{\n" + ",\n".join(f"{inner}{json.dumps(str(k))}: {_ref_format(v, indent, level + 1)}"
                                  for k, v in obj.items()) + "\n" + pad + "}"
    if isinstance(obj, list):
        if obj and all(isinstance(v, _Num) for v in obj):
            return "[" + ", ".join(map(str, obj)) + "]"
        if not obj or all(not isinstance(v, (list, dict)) for v in obj):
            return json.dumps(obj, separators=(", ", ": "), allow_nan=False)
        return "[\n" + ",\n".join(inner + _ref_format(v, indent, level + 1) for v in obj) + "\n" + pad + "]"
    return json.dumps(obj, separators=(", ", ": "), allow_nan=False)


def _ref_dumps(obj):
    return _ref_format(_ref_jsonable(obj)) + "\n"


def _mixed(rng):
    """A float64 matrix mixing float32 numbers, integral values and other floats (all formats)."""
    g = np.random.default_rng(rng.randint(0, 999))
    shape = (rng.randint(1, 5), rng.randint(1, 3))
    v = g.random(shape) * 10.0 ** rng.randint(-8, 8)
    kind = g.integers(0, 3, shape)
    v = np.where(kind == 0, v.astype(np.float32).astype(np.float64), np.where(kind == 1, np.rint(v), v))
    return v * g.choice([-1, 1], shape)


def _random(rng, depth=0):
    r = rng.random()
    if depth > 3 or r < 0.3:
        return rng.choice([0.5, 1, -3.25e-7, 1e300, float("nan"), float("inf"), True, None, "a], [b", 7,
                           np.float64(0.1), np.float32(0.5), 2 ** 70, -0.0, 1e16, 1e-5])
    if r < 0.55:
        return [_random(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    if r < 0.7:
        return [[rng.random() * 100, rng.choice([rng.random(), float("nan"), 1])] for _ in range(rng.randint(0, 5))]
    if r < 0.85:
        k = rng.randint(0, 3)
        return rng.choice([torch.rand(rng.randint(0, 3), k, dtype=rng.choice([torch.float32, torch.float64])),
                           np.random.default_rng(rng.randint(0, 99)).random((rng.randint(0, 3), 2)) * 10.0 ** rng.randint(-20, 20),
                           torch.tensor([[1, 2]]), np.array([[np.nan, 1.0]]), torch.rand(3), np.zeros((2, 0)),
                           _mixed(rng)])
    return {rng.choice(["a", "b", 3]): _random(rng, depth + 1) for _ in range(rng.randint(0, 3))}


def test_fast_paths_write_the_reference_bytes():
    rng = random.Random(0)
    for _ in range(3000):
        doc = {"x": _random(rng), "points": torch.rand(rng.randint(1, 6), 2, dtype=torch.float64) * 1e3}
        assert jn.json_dumps(doc) == _ref_dumps(doc)


def test_mask_result_json_bytes():
    from torch_isc import images
    yy, xx = np.mgrid[:40, :50] + 0.5
    m = ((xx - 20.3) ** 2 + (yy - 18.7) ** 2 < 121) & ~((xx - 20.3) ** 2 + (yy - 18.7) ** 2 < 16)
    r = images.grid_results([m])[0]
    fh = io.BytesIO()
    jn.encode_json(r, fh)
    assert fh.getvalue() == _ref_dumps(jn.result_json_dict(r)).encode()
    d = json.loads(fh.getvalue())
    assert d["num_components"] == 2
    # the curves are float32 numbers: written with 9 digits, they read back as the same float32
    for p, q in zip(d["polylines"], r.polylines):
        a, b = np.array(p["points"]), q["points"].numpy()
        assert np.array_equal(a.astype(np.float32), b.astype(np.float32))
        assert np.abs(a - b).max() < 1e-5 and float(np.float32(b[0, 0])) == b[0, 0]


def test_atomic_write_without_fsync(tmp_path):
    assert atomic_write(tmp_path / "a.txt", "hi", fsync=False).read_text() == "hi"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_float32_values_in_9_digits():
    # by hand: a float32 number's 17-digit repr becomes its 9 significant digits; a float64
    # value that is no float32 keeps its repr; integral values and short float32 ones read as before
    x = float(np.float32(113.24861))                      # 113.24861145019531
    doc = {"p": np.array([[x, 0.1], [22.5, -3.0], [float(np.float32(1e-6)), 2.0 ** 30]])}
    assert jn.json_dumps(doc) == ('{\n "p": [\n  [113.248611, 0.1],\n  [22.5, -3.0],\n'
                                  '  [9.99999997e-07, 1073741824.0]\n ]\n}\n')
    back = np.array(json.loads(jn.json_dumps(doc))["p"])
    assert np.array_equal(back.astype(np.float32), doc["p"].astype(np.float32))
    assert back[0, 1] == 0.1
