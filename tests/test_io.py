"""torch_isc.io: point files in, curves / JSON / SVG / PNG out."""
import json
import math
import os
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
import torch

from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.core.curve import ImplicitCurve
from torch_isc.io import (EXPORTERS, CurveFileError, PointFileError, atomic_write, export, json_dumps, load_npz,
                          read_points, render_png, save_npz, write_json, write_png, write_svg)
from torch_isc.core.mesh import MeshBatch, hexagon_mesh
from torch_isc.pipeline.result import ReconstructionResult
from torch_isc.pipeline.stats import LevelStats


# ----------------------------------------------------------------------------- helpers
def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def _circle_points(n=60, r=0.6, dtype=torch.float64):
    t = torch.linspace(0, 2 * math.pi, n + 1, dtype=dtype)[:-1]
    return torch.stack([r * torch.cos(t), r * torch.sin(t)], 1)


def _annulus_curve(dtype=torch.float64, resolution=6):
    """One item: two closed curves (radius 0.3 and 0.7) on a hexagon of radius 1."""
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=dtype), torch.ones(1, dtype=dtype), resolution)
    r = mesh.verts.norm(dim=1)
    values = (r - 0.3) * (0.7 - r) * -1.0 + 1e-3       # < 0 between the two circles
    return ImplicitCurve(mesh, values)


def _result(curve, points=None, name="item", open_chain=False):
    stats = [LevelStats(level=0, triangles=int(curve.mesh.faces.shape[0]), points=60, delta1=1e-5,
                        max_error=float("nan"), tolerance=0.004, noise=0.0, marked=0, points_beyond_tolerance=0,
                        seconds=0.123)]
    return ReconstructionResult(curve=curve, points=_circle_points() if points is None else points, stats=stats,
                                config=ReconstructConfig(), converged=True, limit=None, name=name)


def _line_curve():
    """A straight line x = 0.2 across the mesh: one open chain ending on the boundary."""
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 4)
    return ImplicitCurve(mesh, mesh.verts[:, 0] - 0.2 + 1e-3)


# ----------------------------------------------------------------------------- read_points: good input
def test_read_points_text_forms(tmp_path):
    p = _write(tmp_path, "a.xy", "# a comment\n\nx, y\n1, 2\n  3\t4   # trailing\n\n5,6\n-1e-3 +2.5E2\n")
    pts = read_points(p)
    assert pts.dtype == np.float64 and pts.shape == (4, 2) and pts.flags.c_contiguous
    np.testing.assert_array_equal(pts, [[1, 2], [3, 4], [5, 6], [-1e-3, 250.0]])


def test_read_points_crlf_and_few_points(tmp_path):
    p = tmp_path / "w.csv"
    p.write_bytes(b"\xef\xbb\xbfx,y\r\n0.5,1.5\r\n")        # BOM, Windows line ends, one point
    np.testing.assert_array_equal(read_points(p), [[0.5, 1.5]])   # < 3 points: not the reader's call


def test_read_points_npy(tmp_path):
    a = np.arange(10, dtype=np.int32).reshape(5, 2)
    np.save(tmp_path / "p.npy", a)
    out = read_points(tmp_path / "p.npy")
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, a)
    # the .npy magic decides, not the extension
    np.save(tmp_path / "q.npy", a.astype(np.float32))
    os.replace(tmp_path / "q.npy", tmp_path / "q.dat")
    np.testing.assert_array_equal(read_points(tmp_path / "q.dat"), a)


def test_read_points_shared_cases_format(tmp_path):
    # the public cases' format: a '# ...' header then 'x y' rows
    p = _write(tmp_path, "c.xy", "# circle_n0: 3 points\n0.99 -0.13\n-0.66 -0.74\n-0.03 0.99\n")
    assert read_points(p).shape == (3, 2)


# ----------------------------------------------------------------------------- read_points: bad input
@pytest.mark.parametrize("name,text,expect", [
    ("empty.xy", "", "no points"),
    ("comments.xy", "# only a comment\n\n   \n", "no points"),
    ("header.xy", "x y\n", "no points"),
    ("word.xy", "1 2\n3 4\nfoo 5\n", "line 3: non-numeric value 'foo'"),
    ("word2.xy", "1 2\n3 4\n5 6\nx y\n", "line 4: non-numeric value 'x'"),   # a header only on the first line
    ("cols3.xy", "# h\n1 2\n3 4 5\n", "line 3: expected 2 columns (x y), found 3"),
    ("cols1.xy", "1\n2\n", "line 1: expected 2 columns (x y), found 1"),
    ("allcols3.csv", "1,2,3\n4,5,6\n", "line 1: expected 2 columns (x y), found 3"),
    ("emptyfield.csv", "1,2\n3,,4\n", "line 2: empty field"),
    ("nan.xy", "1 2\nnan 3\n4 inf\n5 6\n", "2 point(s) have NaN or Inf coordinates (first at line 2)"),
])
def test_read_points_bad_text(tmp_path, name, text, expect):
    p = _write(tmp_path, name, text)
    with pytest.raises(PointFileError) as ei:
        read_points(p)
    msg = str(ei.value)
    assert "\n" not in msg
    assert msg.startswith(str(p) + ": ")
    assert expect in msg


@pytest.mark.parametrize("text", ["1,2\n3,4\n", ",1,2\n", "1,2,\n", "1;;2\n", "1, ,2\n", " ;1;2\n", "1,2 ,\n3,4",
                                  "1 2\n3 4", "1,2\r\n,3,4\r\n", "1;2\n3;4;", "1,\t;2\n", "a,b\n1,2\n"])
def test_empty_field_patterns_match_the_reference(text):
    """The two fast patterns find an empty field exactly where the one-pattern reference does."""
    import re
    from torch_isc.io.points_text import _EMPTY_FIELD
    ref = re.compile(r"^[ \t]*[,;]|[,;][ \t]*[,;]|[,;][ \t]*$", re.M)
    t = text.replace("\r\n", "\n")
    assert any(p.search(t) for p in _EMPTY_FIELD) == (ref.search(t) is not None)


def test_read_points_text_peak_memory(tmp_path):
    """A text file is parsed in chunks: the peak Python allocation stays within a few times the
    file (a StringIO of the whole text held four bytes a character: about 6x)."""
    import tracemalloc
    from torch_isc.io.points_text import decode_points
    a = np.random.default_rng(0).normal(size=(60_000, 2))
    p = tmp_path / "big.csv"
    np.savetxt(p, a, fmt="%.9f", delimiter=",")
    raw = p.read_bytes()
    tracemalloc.start()
    try:
        pts, _ = decode_points(p, raw)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_allclose(pts, a, atol=1e-9)
    assert peak < 3.5 * len(raw), (peak, len(raw))


def test_read_points_missing_and_dir(tmp_path):
    with pytest.raises(PointFileError, match="no such file"):
        read_points(tmp_path / "nope.xy")
    with pytest.raises(PointFileError, match="is a directory"):
        read_points(tmp_path)
    assert issubclass(PointFileError, ValueError)


def test_read_points_binary_text(tmp_path):
    p = tmp_path / "bin.xy"
    p.write_bytes(b"\xff\xfe\x00\x01garbage")
    with pytest.raises(PointFileError, match="not a text point file"):
        read_points(p)


@pytest.mark.parametrize("make,expect", [
    (lambda p: np.save(p, np.zeros((4, 3))), "expected an array of shape (N, 2), got shape (4, 3)"),
    (lambda p: np.save(p, np.zeros(8)), "got shape (8,)"),
    (lambda p: np.save(p, np.zeros((0, 2))), "no points"),
    (lambda p: np.save(p, np.zeros((3, 2), complex)), "expected a numeric (integer or float) array, got dtype complex128"),
    (lambda p: np.save(p, np.array([["a", "b"]])), "got dtype <U1"),
    (lambda p: np.save(p, np.array([[1, None]], object), allow_pickle=True), "unreadable .npy file"),
    (lambda p: np.save(p, np.array([[1.0, np.inf], [2, 3]])), "1 point(s) have NaN or Inf coordinates"),
])
def test_read_points_bad_npy(tmp_path, make, expect):
    p = tmp_path / "a.npy"
    make(p)
    with pytest.raises(PointFileError) as ei:
        read_points(p)
    assert expect in str(ei.value) and str(ei.value).startswith(str(p))
    assert "\n" not in str(ei.value)


def test_read_points_truncated_npy(tmp_path):
    p = tmp_path / "t.npy"
    np.save(p, np.zeros((100, 2)))
    p.write_bytes(p.read_bytes()[:-17])
    with pytest.raises(PointFileError, match="unreadable .npy file"):
        read_points(p)
    q = tmp_path / "fake.npy"
    q.write_text("1 2\n")
    with pytest.raises(PointFileError, match="not a valid .npy file"):
        read_points(q)


# ----------------------------------------------------------------------------- atomic writes
def test_atomic_write_bytes_and_writer(tmp_path):
    p = tmp_path / "f.bin"
    atomic_write(p, b"abc")
    assert p.read_bytes() == b"abc"
    atomic_write(p, lambda fh: fh.write(b"xyz"))
    assert p.read_bytes() == b"xyz"
    assert sorted(os.listdir(tmp_path)) == ["f.bin"]
    umask = os.umask(0)
    os.umask(umask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~umask          # the usual mode, not mkstemp's 0600


def test_atomic_write_failure_leaves_old_file_and_no_temp(tmp_path):
    p = tmp_path / "f.txt"
    p.write_text("old")

    def broken(fh):
        fh.write(b"half")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        atomic_write(p, broken)
    assert p.read_text() == "old"
    assert os.listdir(tmp_path) == ["f.txt"]


def test_writers_leave_no_temp_files(tmp_path):
    res = _result(_annulus_curve())
    written = export(res, tmp_path / "r", ["json", "npz", "svg", "png"])
    assert [w.name for w in written] == ["r.json", "r.npz", "r.svg", "r.png"]
    assert sorted(os.listdir(tmp_path)) == ["r.json", "r.npz", "r.png", "r.svg"]


def test_export_unknown_format(tmp_path):
    with pytest.raises(ValueError, match="unknown output format 'obj'"):
        export(_result(_annulus_curve()), tmp_path / "r", ["json", "obj"])
    assert os.listdir(tmp_path) == []
    assert set(EXPORTERS) == {"json", "npz", "svg", "png", "contours.npz", "geojson", "overlay.png"}


# ----------------------------------------------------------------------------- npz
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_npz_round_trip_bit_exact(tmp_path, dtype):
    g = torch.Generator().manual_seed(0)
    mesh = hexagon_mesh(torch.tensor([[0.0, 0.0], [5.0, -1.0]], dtype=dtype),
                        torch.tensor([1.0, 2.5], dtype=dtype), 3)
    # random-looking values with full mantissas, none zero
    values = (torch.rand(mesh.verts.shape[0], generator=g, dtype=dtype) - 0.5) * math.pi
    values = torch.where(values == 0, torch.ones_like(values), values)
    # perturb vertices too, so bits beyond the lattice are exercised (keeping orientation)
    verts = mesh.verts + 1e-3 * torch.rand(mesh.verts.shape, generator=g, dtype=dtype)
    curve = ImplicitCurve(mesh.with_verts(verts), values)
    meta = {"name": "two", "n": 2, "x": [1.5, float("nan")], "t": torch.tensor([1, 2])}
    save_npz(tmp_path / "c.npz", curve, meta)
    back, m = load_npz(tmp_path / "c.npz")
    assert back.num_items == 2
    for a, b in [(back.mesh.verts, curve.mesh.verts), (back.mesh.faces, curve.mesh.faces),
                 (back.values, curve.values), (back.mesh.verts_per_item, curve.mesh.verts_per_item),
                 (back.mesh.faces_per_item, curve.mesh.faces_per_item)]:
        assert a.dtype == b.dtype
        assert torch.equal(a, b)
    assert m == {"name": "two", "n": 2, "x": [1.5, None], "t": [1, 2]}
    # no pickles inside
    with np.load(tmp_path / "c.npz", allow_pickle=False) as z:
        assert {"verts", "faces", "values", "verts_per_item", "faces_per_item", "metadata"} <= set(z.files)
    assert os.listdir(tmp_path) == ["c.npz"]


def test_npz_bfloat16_and_errors(tmp_path):
    mesh = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 2).to(dtype=torch.bfloat16)
    curve = ImplicitCurve(mesh, (mesh.verts.norm(dim=1) - 0.5).to(torch.bfloat16) + 0.01, validate=False)
    save_npz(tmp_path / "b.npz", curve)
    back, meta = load_npz(tmp_path / "b.npz", validate=False)
    assert back.values.dtype == torch.bfloat16 and torch.equal(back.values, curve.values) and meta == {}
    with pytest.raises(CurveFileError, match="no such file"):
        load_npz(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(CurveFileError, match="junk.npz"):
        load_npz(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(CurveFileError, match="not a torch_isc curve file"):
        load_npz(tmp_path / "other.npz")


# ----------------------------------------------------------------------------- JSON
def test_json_schema_and_determinism(tmp_path):
    res = _result(_annulus_curve())
    write_json(tmp_path / "a.json", res)
    text = (tmp_path / "a.json").read_text()
    d = json.loads(text)
    assert list(d)[:3] == ["polylines", "num_components", "bbox"] and "stats" in d
    assert isinstance(d["num_components"], int) and d["num_components"] == 2 == len(d["polylines"])
    for pl in d["polylines"]:
        assert set(pl) == {"closed", "points"}
        assert pl["closed"] is True
        assert all(isinstance(p, list) and len(p) == 2 and all(isinstance(c, float) for c in p) for p in pl["points"])
    assert len(d["bbox"]) == 4 and all(isinstance(v, float) for v in d["bbox"])
    xmin, ymin, xmax, ymax = d["bbox"]
    assert xmin < xmax and ymin < ymax and abs(xmax - 0.7) < 0.05
    assert d["stats"]["levels"][0]["max_error"] is None          # NaN written as null (valid JSON)
    assert "seconds" not in d["stats"]["levels"][0]              # wall time left out: reproducible file
    # same result -> byte-identical file; a fresh result of the same curve too
    write_json(tmp_path / "b.json", _result(_annulus_curve()))
    assert (tmp_path / "b.json").read_bytes() == text.encode()
    write_json(tmp_path / "c.json", res, timings=True)
    assert json.loads((tmp_path / "c.json").read_text())["stats"]["levels"][0]["seconds"] == 0.123


def test_json_dumps_layout():
    s = json_dumps({"a": [[1.0, 2.0], [3.0, 4.5]], "b": {"c": float("inf")}, "e": []})
    assert s.endswith("\n")
    assert json.loads(s) == {"a": [[1.0, 2.0], [3.0, 4.5]], "b": {"c": None}, "e": []}
    assert "[1.0, 2.0]" in s             # one point per line


# ----------------------------------------------------------------------------- SVG
def test_svg_is_xml_with_closed_and_open_paths(tmp_path):
    write_svg(tmp_path / "a.svg", _result(_annulus_curve(), name="a <&> b"))
    root = ET.fromstring((tmp_path / "a.svg").read_bytes())
    ns = {"s": "http://www.w3.org/2000/svg"}
    assert root.tag.endswith("svg")
    vb = [float(v) for v in root.get("viewBox").split()]
    assert vb[2] > 1.4 and vb[3] > 1.4                        # the bbox (1.4 wide) plus a margin
    paths = root.findall(".//s:path", ns)
    closed = [p for p in paths if p.get("class") == "closed"]
    assert len(closed) == 1 and closed[0].get("fill-rule") == "evenodd"
    assert closed[0].get("d").count("M ") == 2 and closed[0].get("d").count("Z") == 2
    assert root.find("s:g", ns).get("transform") == "scale(1,-1)"

    write_svg(tmp_path / "b.svg", _result(_line_curve()))
    root = ET.fromstring((tmp_path / "b.svg").read_bytes())
    opened = [p for p in root.findall(".//s:path", ns) if p.get("class") == "open"]
    assert len(opened) == 1 and opened[0].get("fill") == "none" and "Z" not in opened[0].get("d")
    # path data are the data coordinates (y not flipped in the numbers)
    xs = [float(xy.split(",")[0]) for xy in opened[0].get("d").replace("M ", "").split(" L ")]
    assert max(abs(x - 0.2) for x in xs) < 0.01


def test_svg_empty_result(tmp_path):
    mesh = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 2)
    res = _result(ImplicitCurve(mesh, torch.ones(mesh.verts.shape[0])), points=torch.zeros(1, 2))
    write_svg(tmp_path / "e.svg", res)
    ET.fromstring((tmp_path / "e.svg").read_bytes())


# ----------------------------------------------------------------------------- PNG
def test_png_written_and_readable(tmp_path):
    res = _result(_annulus_curve())
    write_png(tmp_path / "a.png", res)
    img = cv2.imread(str(tmp_path / "a.png"))
    assert img is not None and img.shape == (800, 800, 3)
    # the colours are there: green curve, black points, blue and red vertex dots
    b, g, r = (img[..., i].astype(int) for i in range(3))
    assert ((g > 120) & (r < 60) & (b < 60)).sum() > 100                 # green
    assert ((b > 150) & (r < 60) & (g < 100)).sum() > 10                 # blue (inside)
    assert ((r > 150) & (b < 60) & (g < 60)).sum() > 10                  # red (outside)
    assert ((r < 40) & (g < 40) & (b < 40)).sum() > 10                   # black points


def test_png_y_up_open_chain_and_options(tmp_path):
    # a single point at the top of the mesh must land in the upper half of the image
    curve = _line_curve()
    render_png(tmp_path / "p.png", curve, torch.tensor([[0.0, 0.8]]), size=200, draw_mesh=False, draw_signs=False)
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img.shape == (200, 200, 3)
    black = np.argwhere(img.max(2) < 40)
    assert len(black) and black[:, 0].mean() < 100
    orange = (img[..., 2] > 200) & (img[..., 1] > 100) & (img[..., 1] < 180) & (img[..., 0] < 60)
    cols = np.argwhere(orange)[:, 1]
    assert len(cols) > 20 and abs(cols.mean() - (100 + 0.2 * (200 - 8) / 2)) < 8   # x = 0.2 is right of centre
    with pytest.raises(ValueError, match="one curve"):
        two = ImplicitCurve(MeshBatch.cat([curve.mesh, curve.mesh]), torch.cat([curve.values, curve.values]))
        render_png(tmp_path / "x.png", two)
    assert sorted(os.listdir(tmp_path)) == ["p.png"]
