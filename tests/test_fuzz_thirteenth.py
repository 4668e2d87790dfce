"""Fuzz round 13: the defects found, each checked against the behaviour the standards ask for
(one-line errors naming the input, bounded work, nothing silent)."""
import json
import math
import os
import subprocess
import sys

import pytest
import torch

import torch_isc
from torch_isc import ImplicitCurve, hexagon_mesh
from torch_isc.core.curve import InvalidValuesError, crossed_triangles
from torch_isc.core.mesh import InvalidMeshError
from torch_isc.pipeline.knobs import ConfigError


def _curve(res=3):
    m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), res)
    return ImplicitCurve(m, m.verts.norm(dim=1) - 0.5)


@pytest.mark.parametrize("ratio", [float("nan"), float("inf"), 0.0, -1.0, True, "2", 1e308, 2e6])
def test_flip_simple_refuses_a_bad_ratio(ratio):
    # NaN / inf / 0 made NaN, inf or zero nodal values; -1 reported flips that did not happen
    with pytest.raises(InvalidValuesError, match="flip_simple: ratio"):
        _curve().flip_simple(ratio=ratio)


@pytest.mark.parametrize("cand", [torch.ones(37), torch.tensor([True, False]), [True] * 37])
def test_flip_simple_refuses_bad_candidates(cand):
    with pytest.raises(InvalidValuesError, match=r"flip_simple: candidates must be a \(37,\) bool tensor"):
        _curve().flip_simple(candidates=cand)


def test_flip_simple_still_takes_a_learned_ratio():
    c = _curve()
    r = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    g, flipped = c.flip_simple(ratio=r)
    g.values.sum().backward()
    # d/dr of sum(-r f_v) over the flipped vertices: minus their values' sum
    assert r.grad.item() == pytest.approx(-c.values[flipped].sum().item())
    assert int(flipped.sum()) > 0


@pytest.mark.parametrize("rings", [-1, float("nan"), 1.5, "3", True])
def test_refine_band_refuses_bad_rings(rings):
    with pytest.raises(InvalidMeshError, match="refine_band: rings must be an integer >= 0"):
        _curve().refine_band(rings)


def test_refine_band_rings_are_bounded_by_the_mesh():
    # one pass per ring took hours for 10**9; past the mesh's diameter nothing changes
    c = _curve()
    a, b = crossed_triangles(c.mesh, c.values, 100), crossed_triangles(c.mesh, c.values, 10 ** 9)
    assert torch.equal(a, b) and bool(a.all())
    ref = crossed_triangles(c.mesh, c.values, 0)
    nb = c.mesh.face_neighbors
    for _ in range(2):                     # by hand: two rings of edge neighbours
        ref = ref | (ref[nb.clamp_min(0)] & (nb >= 0)).any(1)
    assert torch.equal(crossed_triangles(c.mesh, c.values, 2), ref)


@pytest.mark.parametrize("text, key", [("tolerance: 1_000\n", "tolerance"), ("seed: 1_0\n", "seed"),
                                       ("tolerance: .00_4\n", "tolerance"), ("coverage_test: on\n", "coverage_test"),
                                       ("coverage_test: Yes\n", "coverage_test")])
def test_config_files_refuse_underscores_and_yaml11_booleans(tmp_path, text, key):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=f"config key '{key}'") as ei:
        torch_isc.load_config(p)
    assert "\n" not in str(ei.value)


def test_config_values_refuse_underscores_on_every_path():
    with pytest.raises(ConfigError, match="no _ in numbers"):
        torch_isc.ReconstructConfig().replace(tolerance="1_0")
    from torch_isc.pipeline.config import parse_overrides
    with pytest.raises(ConfigError, match="no _ in numbers"):
        torch_isc.load_config(None, parse_overrides(["seed=1_0"]))
    ok = torch_isc.load_config(None, parse_overrides(["seed=10", "coverage_test=false", "tolerance=0.008"]))
    assert (ok.run.seed, ok.test.coverage_test, ok.test.tolerance) == (10, False, 0.008)


@pytest.mark.parametrize("key, shown", [("tol\nerance", r"tol\nerance"), ("x\x1b[2J", r"x\x1b[2J"),
                                        ("tolerance\x00", r"tolerance\x00")])
def test_unknown_keys_are_shown_with_control_characters_escaped(key, shown):
    from torch_isc.pipeline.config import from_dict
    with pytest.raises(ConfigError) as ei:
        from_dict({key: 1})
    msg = str(ei.value)
    assert shown in msg and msg.isprintable(), msg
    with pytest.raises(ConfigError) as ei:
        from_dict({"test": {key: 1}})
    assert shown in str(ei.value) and str(ei.value).isprintable()


def test_atomic_write_to_a_folder_names_the_folder(tmp_path):
    from torch_isc.io import atomic_write, save_npz
    d = tmp_path / "adir"
    d.mkdir()
    with pytest.raises(IsADirectoryError) as ei:
        save_npz(d, _curve())
    assert ei.value.filename == str(d) and ".tmp" not in str(ei.value)
    with pytest.raises(IsADirectoryError):
        atomic_write(d, b"x")
    assert os.listdir(d) == []                                   # no temporary left


def _ring_file(path, r, n=40):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(f"{r * math.cos(2 * math.pi * k / n):.6f} {math.sin(2 * math.pi * k / n):.6f}"
                              for k in range(n)) + "\n")


def test_a_later_run_does_not_replace_another_input_s_set(tmp_path, capsys):
    # d1/a.xy then d2/a.xy (another file, the same stem) into one folder: the second run replaced
    # the first's complete set without a word; now it fails alone, named, until --overwrite
    from torch_isc import cli
    a1, a2, out = tmp_path / "d1" / "a.xy", tmp_path / "d2" / "a.xy", tmp_path / "o"
    _ring_file(a1, 1.0)
    _ring_file(a2, 0.5)
    args = ["--out", str(out), "--formats", "json", "--set", "max_level=3"]
    assert cli.main(["reconstruct", str(a1), *args]) == 0
    first = (out / "a.json").read_bytes()
    code = cli.main(["reconstruct", str(a2), *args])
    err = capsys.readouterr().err
    assert code != 0 and "was made from another input" in err and str(a1) in err
    assert (out / "a.json").read_bytes() == first
    assert json.loads((out / "a.manifest.json").read_text())["input"]["path"] == str(a1)
    # the same input with new content is redone, as before
    _ring_file(a1, 2.0)
    assert cli.main(["reconstruct", str(a1), *args]) == 0
    assert (out / "a.json").read_bytes() != first
    # with --overwrite the other input takes the stem
    assert cli.main(["reconstruct", str(a2), *args, "--overwrite"]) == 0
    assert json.loads((out / "a.manifest.json").read_text())["input"]["path"] == str(a2)
    # the owner gone (moved or deleted): its set is no longer anyone's, a new input may take it
    a2.unlink()
    _ring_file(tmp_path / "d3" / "a.xy", 0.7)
    assert cli.main(["reconstruct", str(tmp_path / "d3" / "a.xy"), *args]) == 0


def test_a_large_offset_in_float32_contours_warns():
    # offset 1e8: float32 holds every 8th pixel there, the contour collapsed onto 3 columns silently
    import warnings
    cv2 = pytest.importorskip("cv2")
    import numpy as np
    from torch_isc.images import find_contours
    m = np.zeros((20, 30), np.uint8)
    cv2.circle(m, (15, 10), 6, 255, -1)
    with pytest.warns(UserWarning, match=r"steps of 8 px"):
        find_contours(m, 3, 1, (1e8, 0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c, _ = find_contours(m, 3, 1, (1e5, 0))                    # steps of 1/128 px: no warning
        c0, _ = find_contours(m, 3, 1)
        assert np.abs(c[0].astype(np.float64) - (c0[0].astype(np.float64) + [1e5, 0])).max() < 1 / 64
        find_contours(m, 3, 1, (10 ** 8, 0), dtype=np.int32)        # whole pixels: exact
    from torch_isc.images.contours import cast_coordinates
    with pytest.warns(UserWarning, match="sub-pixel detail lost"):
        cast_coordinates(np.array([[3e7 + 0.25, 1.0]]), np.float32, "to_cv_contours")


@pytest.mark.parametrize("text, expect", [
    ("path,path\na.xy,b.xy\n", "2 columns named 'path'"),          # DictReader kept the last: a.xy dropped
    ("path,x\na.xy,1\n,2\n", "line 3: manifest column 'path' is empty"),
    ("x,path\n1\n", "line 2: manifest column 'path' is missing"),
])
def test_csv_manifests_drop_nothing_silently(tmp_path, text, expect):
    from torch_isc.dataset import read_manifest
    from torch_isc.runner import RunError
    p = tmp_path / "m.csv"
    p.write_text(text)
    with pytest.raises(RunError, match=expect):
        read_manifest(p)
    p.write_text("path,x\na.xy,1\n\n  b.xy ,\n")                 # a blank line skipped; fields stripped
    assert read_manifest(p) == [str(tmp_path / "a.xy"), str(tmp_path / "b.xy")]


def test_parquet_manifests_drop_nothing_silently(tmp_path):
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq
    from torch_isc.dataset import read_manifest
    from torch_isc.runner import RunError
    p = tmp_path / "m.parquet"
    for values, expect in ((["a.xy", None, "b.xy"], "row 2 .* is null"), (["a.xy", "  "], "row 2 .* is empty")):
        pq.write_table(pa.table({"path": values}), p)
        with pytest.raises(RunError, match=expect):
            read_manifest(p)
    pq.write_table(pa.table({"path": ["a.xy", " b.xy "]}), p)          # stripped, as the CSV reader does
    assert read_manifest(p) == [str(tmp_path / "a.xy"), str(tmp_path / "b.xy")]


@pytest.mark.parametrize("row", ["1 2\x0c3 4", "1 2\u20283 4", "1 2\x0b3 4"])
def test_a_row_with_a_form_feed_stays_one_row(tmp_path, row):
    # the chunked parser splits at "\n" only (splitlines broke such a row into two points)
    from torch_isc.io import PointFileError, read_points
    p = tmp_path / "f.xy"
    p.write_text(row + "\n5 6\n", encoding="utf-8")
    with pytest.raises(PointFileError, match="line 1: expected 2 columns"):
        read_points(p)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_grid_of_small_rings_keeps_every_ring(seed):
    # D2: 36 clean rings of 16 points, 3.4 spacings apart. Eight neighbours span half a ring,
    # whose curvature read as noise of 12% of the radius; the tolerance (3 noise widths) then
    # let one loop wrap whole rows of rings, 18 or 20 loops, "converged"
    def ring(cx, cy, r=0.3, n=16):
        t = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
        return torch.stack([r * t.cos() + cx, r * t.sin() + cy], 1)
    pts = torch.cat([ring(i, j) for i in range(6) for j in range(6)])
    r = torch_isc.reconstruct(pts, config={"seed": seed})
    assert r.converged and r.num_closed == 36
    # every loop is one ring: its vertices within 0.1 of one centre's circle
    for pl in r.polylines:
        v = pl["points"].detach()
        c = v.mean(0).round()
        assert float(((v - c).norm(dim=1) - 0.3).abs().max()) < 0.1
