"""Issue 6, "Bad input, failures and determinism", for point inputs, the API, configs and the CLI.

The sections follow the issue's list. Cases already tested elsewhere are not repeated here; the
table says where each one lives (image inputs are covered with the image code).

====  =============================================  ===========================================
item  case                                           tests
====  =============================================  ===========================================
1     empty file                                     test_io::test_read_points_bad_text[empty],
                                                     here: test_cli_bad_point_files
1     1, 2 or 3 points                               test_reconstruct::test_point_set_errors,
                                                     test_cli::test_missing_file_and_too_few_points,
                                                     here: test_cli_bad_point_files,
                                                     test_three_points_give_no_curve
1     NaN or Inf coordinates                         test_reconstruct::test_point_set_errors,
                                                     test_io::test_read_points_bad_text[nan],
                                                     here: test_cli_bad_point_files
1     duplicate points                               here: test_many_copies_of_one_point,
                                                     test_duplicated_noisy_points
1     all points identical                           test_reconstruct::test_point_set_errors,
                                                     here: test_cli_bad_point_files
1     all points collinear                           here: test_collinear_points_give_no_curve
1     offset 1e7 (spread 1), scaled by 1e-6          test_reconstruct::test_large_offset_*,
                                                     here: test_offset_1e7_and_scale_1e-6,
                                                     test_cli_offset_1e7
1     1,000,000 points                               here: test_million_points (slow)
1     non-numeric text, wrong column counts,         test_io::test_read_points_bad_text / _bad_npy,
      .npy of the wrong shape or dtype               here: test_cli_bad_point_files
1     config: unknown key, wrong type, negative      test_config (API), test_cli (--set),
      tolerance, max level of 0                      here: test_cli_bad_config_file
2     a failing input never stops the others         test_cli::test_bad_input_among_good_ones,
                                                     test_cli::test_failing_batch_is_retried_*,
                                                     here: test_cli_bad_point_files,
                                                     test_cli_unreconstructable_input_in_a_batch
2     atomic writes, no half-written file            test_io::test_atomic_write_failure_*,
                                                     here: test_atomic_write_interrupted_new_file,
                                                     test_cli_interrupted_run_then_rerun
2     rerun skips finished outputs (--overwrite)     test_cli::test_rerun_skips_unless_overwrite,
                                                     here: test_cli_interrupted_run_then_rerun
3     translation / scale invariance                 test_reconstruct::test_translation_scale_*,
                                                     here: test_property_translation_scale
3     rotation by multiples of 90 degrees            here: test_property_rot90
3     same seed, byte-identical JSON                 test_cli::test_same_input_same_json_bytes,
                                                     here: test_json_bytes_identical_across_processes
3     float64 and float32 agree on the topology      test_reconstruct::test_float64_same_topology,
                                                     here: test_property_float32_float64_topology
4     max-level and max-triangle caps in the stats   test_reconstruct::test_level_and_triangle_limits,
                                                     here: test_triangle_cap_bounds_a_pathological_input,
                                                     test_level_cap_reports_unmet_tolerance
====  =============================================  ===========================================

Truths are analytic (star-shaped curves r(t) = 1 + sum a_k cos(k t + p_k), straight segments);
distances come from :func:`torch_isc.metrics.hausdorff`.
"""
from __future__ import annotations

import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_isc import ReconstructConfig, cli, reconstruct
from torch_isc.io import EXPORTERS, Exporter, atomic_write, json_dumps, result_json_dict
from torch_isc.metrics import bbox_diagonal, hausdorff


def _listdir(d):
    """The outputs in ``d`` without the manifests (tested in test_robustness_fuzz)."""
    return [f for f in os.listdir(d) if not f.endswith(".manifest.json")]

REPO = Path(__file__).resolve().parents[1]
FAST = ["--set", "max_level=3"]
PROPERTY = settings(max_examples=6, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ============================================================================ data
def star(n, harmonics=((3, 0.2, 0.0),), centre=(0.0, 0.0), size=1.0, seed=0, uniform=False):
    """``n`` samples of r(t) = 1 + sum a cos(k t + p) (float64, sorted by t) and the dense truth.

    Returns ``(points (n, 2), truth (4000, 2), largest gap between consecutive samples)``."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False) if uniform else np.sort(rng.uniform(0, 2 * np.pi, n))

    def at(tt):
        r = 1 + sum(a * np.cos(k * tt + p) for k, a, p in harmonics)
        return np.stack([centre[0] + size * r * np.cos(tt), centre[1] + size * r * np.sin(tt)], 1)

    pts = at(t)
    gap = float(np.linalg.norm(pts - np.roll(pts, -1, 0), axis=1).max())
    return torch.from_numpy(pts), at(np.linspace(0, 2 * np.pi, 4000, endpoint=False)), gap


def circle(n, r=1.0):
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    return torch.stack([r * t.cos(), r * t.sin()], 1)


def ncomp(res):
    return res.num_closed, res.num_open


def mapped(res, fn):
    """The result's polylines with ``fn`` applied to their points (float64)."""
    return [{"closed": p["closed"], "points": fn(p["points"].double())} for p in res.polylines]


def rot90(p, k):
    """Rotate ``(n, 2)`` points by ``k`` quarter turns counter-clockwise (exact in floating point)."""
    for _ in range(k % 4):
        p = torch.stack([-p[:, 1], p[:, 0]], 1)
    return p


# ---------------------------------------------------------------------------- CLI helpers
def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _error_lines(err):
    return [ln for ln in err.splitlines() if ln.startswith("torch-isc: error:")]


def _write_xy(path, pts, fmt="%.17g"):
    np.savetxt(path, np.asarray(pts), fmt=fmt)
    return path


# ============================================================================ 1. inputs
BAD_FILES = {
    # name: (writer, fragment of the one-line message)
    "empty.xy": (lambda p: p.write_text(""), "no points"),
    "comments.xy": (lambda p: p.write_text("# nothing\n\n"), "no points"),
    "one.xy": (lambda p: p.write_text("1 2\n"), "needs at least 3 distinct points, got 1"),
    "two.xy": (lambda p: p.write_text("1 2\n3 4\n"), "needs at least 3 distinct points, got 2"),
    "identical.xy": (lambda p: p.write_text("1.5 2.5\n" * 50), "needs at least 3 distinct points, got 1"),
    "nan.xy": (lambda p: p.write_text("0 0\n1 nan\n2 2\n3 1\n"), "NaN or Inf coordinates (first at line 2)"),
    "inf.csv": (lambda p: p.write_text("x,y\n0,0\n1,2\n-inf,3\n3,1\n"), "NaN or Inf coordinates (first at line 4)"),
    "text.xy": (lambda p: p.write_text("1 2\n3 4\nfoo 5\n"), "line 3: non-numeric value 'foo'"),
    "cols3.xy": (lambda p: p.write_text("1 2 3\n4 5 6\n7 8 9\n"), "line 1: expected 2 columns (x y), found 3"),
    "cols1.xy": (lambda p: p.write_text("1 2\n3 4\n5\n"), "line 3: expected 2 columns (x y), found 1"),
    "shape.npy": (lambda p: np.save(p, np.zeros((5, 3))), "expected an array of shape (N, 2), got shape (5, 3)"),
    "shape3d.npy": (lambda p: np.save(p, np.zeros((5, 2, 1))), "got shape (5, 2, 1)"),
    "flat.npy": (lambda p: np.save(p, np.zeros(10)), "got shape (10,)"),
    "strings.npy": (lambda p: np.save(p, np.array([["a", "b"]] * 3)), "expected a numeric (integer or float) array"),
    "complex.npy": (lambda p: np.save(p, np.zeros((4, 2), complex)), "got dtype complex128"),
    "bool.npy": (lambda p: np.save(p, np.zeros((4, 2), bool)), "got dtype bool"),
    "nan.npy": (lambda p: np.save(p, np.array([[0, 0], [1, np.nan], [2, 2], [3, 1.0]])), "NaN or Inf"),
    "identical.npy": (lambda p: np.save(p, np.ones((9, 2), np.float32)), "needs at least 3 distinct points"),
}


def test_cli_bad_point_files(tmp_path, capsys):
    """Every bad file gives exactly one error line naming it, the good inputs around them are
    written, nothing is written for a bad one, and the exit status is 1."""
    good = [_write_xy(tmp_path / "good_a.xy", circle(100)), _write_xy(tmp_path / "good_b.xy", 3 * circle(90))]
    bad = []
    for name, (make, _) in BAD_FILES.items():
        make(tmp_path / name)
        bad.append(tmp_path / name)
    inputs = [good[0], *bad, good[1]]
    code, out, err = _run(capsys, "reconstruct", *inputs, "--out", tmp_path / "o", "--formats", "json", *FAST)
    assert code == 1
    assert "Traceback" not in err
    errs = _error_lines(err)
    assert len(errs) == len(bad), err
    for path, (name, (_, fragment)) in zip(bad, BAD_FILES.items()):
        line = [e for e in errs if e.startswith(f"torch-isc: error: {path}: ")]
        assert len(line) == 1, (name, errs)
        assert fragment in line[0], (name, line[0])
    assert sorted(_listdir(tmp_path / "o")) == ["good_a.json", "good_b.json"]
    assert f"done: 2 of {len(inputs)} input(s) ok, {len(bad)} failed" in err
    assert [ln.split(":")[0] for ln in out.splitlines()] == ["good_a", "good_b"]


def test_cli_point_set_error_names_the_file_once(tmp_path, capsys):
    f = tmp_path / "one.xy"
    f.write_text("1 2\n")
    code, _out, err = _run(capsys, "reconstruct", f, "--out", tmp_path / "o", "--formats", "json")
    assert code == 1
    assert _error_lines(err) == [f"torch-isc: error: {f}: needs at least 3 distinct points, got 1"]


def test_three_points_give_no_curve():
    """Three points (a triangle) hold no line-like evidence: the result has no curve, says so
    (``limit == "no_curve"``, not converged) and its implicit function is outside everywhere."""
    res = reconstruct([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])
    assert ncomp(res) == (0, 0) and res.polylines == []
    assert res.converged is False and res.limit == "no_curve"
    assert bool((res.curve.values > 0).all())
    assert not bool(res.curve.inside(torch.tensor([[1.0, 1.0]], dtype=res.curve.mesh.dtype)).any())
    d = res.to_json_dict()
    assert d["num_components"] == 0 and d["stats"]["limit"] == "no_curve"


def _collinear_inputs():
    x = torch.linspace(0.0, 1.0, 300, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    u = torch.rand(200, generator=g, dtype=torch.float64)
    return {
        "axis, 300 even": torch.stack([x, torch.zeros_like(x)], 1),
        "vertical, 30 random": torch.stack([torch.full((30,), 2.0, dtype=torch.float64), u[:30]], 1),
        "diagonal, 200 random": torch.stack([3.0 * u - 1.0, -0.5 * (3.0 * u - 1.0) + 7.0], 1),
        "diagonal, offset 1e7": torch.stack([u + 1e7, 2.0 * u - 3e6], 1),
        "float32 diagonal": torch.stack([u, 0.25 * u], 1).float(),
        "integers": torch.stack([torch.arange(0, 50), 3 * torch.arange(0, 50) + 1], 1),
        "1000 even + repeats": torch.cat([torch.stack([x, 2 * x], 1)] * 3),
    }


@pytest.mark.parametrize("name", list(_collinear_inputs()))
def test_collinear_points_give_no_curve(name):
    """Documented behaviour: points that all lie on one straight line (an open segment) enclose no
    region, and an implicit curve is closed (or ends on the mesh boundary), so there is no curve
    to return. ``reconstruct`` returns a result with no polyline, ``converged=False`` and
    ``limit="no_curve"`` (the same answer as for three points), after level 0 only; the CLI
    writes its outputs (0 components) and prints ``not converged (no_curve)``. "On one line" is
    judged in float64 up to the rounding of the input's own dtype, so a float32 or an offset
    input counts as collinear too. Points *near* a line (noise) are not collinear: they are
    reconstructed like any other data, as closed curves around them."""
    pts = _collinear_inputs()[name]
    res = reconstruct(pts)
    assert ncomp(res) == (0, 0)
    assert res.converged is False and res.limit == "no_curve"
    assert len(res.stats) == 1
    assert bool((res.curve.values > 0).all())
    assert torch.equal(res.points, pts)


def test_many_copies_of_one_point():
    """A curve plus 1000 copies of one point (on the curve, or inside it): the curve is still
    reconstructed (one closed loop close to the true circle)."""
    base = circle(200)
    truth = [(circle(4000), True)]
    for extra in (base[7:8], torch.tensor([[0.3, 0.2]], dtype=torch.float64)):
        pts = torch.cat([base[:100], extra.repeat(1000, 1), base[100:]])
        res = reconstruct(pts)
        assert ncomp(res) == (1, 0)
        assert hausdorff(res.polylines, truth) < 0.01 * 2.0
        # every point counted, or every distinct point once (when repeats are merged)
        distinct = torch.unique(pts, dim=0).shape[0]
        assert res.stats[0].points in (pts.shape[0], distinct)


def test_duplicated_noisy_points():
    """Every point of a noisy circle given 5 times: the same curve as the points given once
    (a point set is a set). Without merging repeats this gave 10-19 loops."""
    g = torch.Generator().manual_seed(0)
    pts = circle(300) + 0.02 * torch.randn(300, 2, generator=g, dtype=torch.float64)
    once = reconstruct(pts)
    assert ncomp(once) == (1, 0)
    five = reconstruct(torch.cat([pts] * 5))
    assert ncomp(five) == (1, 0)
    assert hausdorff(five.polylines, once.polylines) < 1e-6 * bbox_diagonal(pts)


def test_offset_1e7_and_scale_1e6():
    """Spread 1 at an offset of 1e7, the same scaled by 1e-6, and both: the same curve,
    transformed, as the unshifted input (default float32 working dtype; the input is float64
    and the normalization runs in float64)."""
    pts, truth, _ = star(240, ((3, 0.15, 0.3), (5, 0.05, 1.0)), size=0.35, seed=3)   # spread ~1
    diag = bbox_diagonal(pts)
    base = reconstruct(pts)
    assert ncomp(base) == (1, 0)
    assert hausdorff(base.polylines, [(truth, True)]) < 0.01 * diag
    off = torch.tensor([1e7, -1e7], dtype=torch.float64)
    for fwd, back in [(lambda p: p + off, lambda p: p - off),
                      (lambda p: p * 1e-6, lambda p: p / 1e-6),
                      (lambda p: (p + off) * 1e-6, lambda p: p / 1e-6 - off)]:
        res = reconstruct(fwd(pts))
        assert ncomp(res) == ncomp(base)
        assert [s.triangles for s in res.stats] == [s.triangles for s in base.stats]
        # At 1e7 the float64 input itself is rounded to ~2e-9 of its spread; the fit is not
        # unique within its dead zone (one tolerance each side of the data), and the loop's
        # values (a fixed number of L-BFGS steps) carry such perturbations up by ~1e5, so the
        # band stage's refit may settle on the other side of the data: 0.97 tolerances here,
        # 0.36-1.63 on 3 of 10 such stars (band_solver newton alike; 1 of 10, 2.8, with the
        # noise estimate of session 23). Both curves stay within the tolerance of the data, so
        # within about two of each other
        tol = base.stats[-1].tolerance
        assert hausdorff(mapped(res, back), base.polylines) < 2.0 * tol
        assert hausdorff(mapped(res, back), [(truth, True)]) < 0.01 * diag


def test_cli_offset_1e7(tmp_path, capsys):
    """The same through files: text written with 17 digits, curve read back from the JSON."""
    pts, _, _ = star(200, size=0.35, seed=4)
    off = np.array([1e7, 1e7])
    _write_xy(tmp_path / "a.xy", pts.numpy())
    _write_xy(tmp_path / "b.xy", pts.numpy() + off)
    code, _out, err = _run(capsys, "reconstruct", tmp_path / "a.xy", tmp_path / "b.xy", "--out", tmp_path / "o",
                          "--formats", "json", *FAST)
    assert code == 0, err
    a = json.loads((tmp_path / "o" / "a.json").read_text())
    b = json.loads((tmp_path / "o" / "b.json").read_text())
    assert a["num_components"] == b["num_components"] == 1
    pa = [(np.array(p["points"]), p["closed"]) for p in a["polylines"]]
    pb = [(np.array(p["points"]) - off, p["closed"]) for p in b["polylines"]]
    assert hausdorff(pb, pa) < 0.25 * a["stats"]["levels"][-1]["tolerance"]      # see test_offset_1e7_...
    assert b["bbox"][0] > 1e7 - 1 and b["bbox"][2] < 1e7 + 1


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="dense noisy data: 1 closed curve now (3 before, 40 at first), but not "
                   "converged: the max test still finds points about 6 noise levels off the curve in a few triangles "
                   "of the band and refines them into vertex clumps until max_level (open problem, see README)")
def test_million_points_dense_noisy_ellipse():
    """1,000,000 points about an ellipse with noise 0.002 (0.09% of the diagonal): a line fit
    on 8 neighbours reads the spacing, not the noise, and the largest of thousands of
    deviations in a triangle exceeds 3 sigma. Before the multi-scale noise estimate, the
    sqrt(2 ln n) allowance of the max test and the noise floor of the edge weights this gave
    40 loops at max_level."""
    n = 1_000_000
    g = torch.Generator().manual_seed(0)
    t = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    pts = (torch.stack([t.cos(), 0.6 * t.sin()], 1) + 0.002 * torch.randn(n, 2, generator=g, dtype=torch.float64))
    res = reconstruct(pts.float())
    assert ncomp(res) == (1, 0) and res.converged
    tt = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    truth = [(np.stack([np.cos(tt), 0.6 * np.sin(tt)], 1), True)]
    assert hausdorff(res.polylines, truth) < 0.01 * bbox_diagonal(pts)


@pytest.mark.slow
def test_million_points():
    """1,000,000 noisy samples of one closed curve through the API: one loop, accurate.
    Measured on the 2-core dev box (OMP_NUM_THREADS=1): about 40 s, peak RSS about 1 GiB
    (the noise estimate works in blocks)."""
    n = 1_000_000
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, n)
    r = 1 + 0.2 * np.cos(3 * t)
    pts = torch.from_numpy(np.stack([r * np.cos(t), r * np.sin(t)], 1) + 0.002 * rng.standard_normal((n, 2)))
    tt = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    rr = 1 + 0.2 * np.cos(3 * tt)
    truth = [(np.stack([rr * np.cos(tt), rr * np.sin(tt)], 1), True)]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    res = reconstruct(pts)
    seconds = time.perf_counter() - t0
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20      # ru_maxrss is KiB on Linux
    print(f"1e6 points: {seconds:.1f} s, peak RSS {peak_gib:.2f} GiB (before: {rss0 / 2 ** 20:.2f} GiB)")
    assert ncomp(res) == (1, 0) and res.converged
    assert hausdorff(res.polylines, truth) < 0.01 * bbox_diagonal(pts)
    assert res.stats[-1].points == n
    assert peak_gib < 6.0
    assert seconds < 900


# ---------------------------------------------------------------------------- configs
@pytest.mark.parametrize("text,fragment", [
    ("max_level: 3\nanneal_sweepz: 10\n", "unknown config key 'anneal_sweepz'"),
    ("max_level: three\n", "config key 'max_level': expected int, got str 'three'"),
    ("max_level: 2.5\n", "config key 'max_level': expected int"),
    ("tolerance: [0.1]\n", "config key 'tolerance': expected float"),
    ("dtype: 64\n", "config key 'dtype': expected str"),
    ("tolerance: -0.01\n", "config key 'tolerance': must be > 0, got -0.01"),
    ("tolerance: .nan\n", "config key 'tolerance': must be finite"),
    ("max_level: 0\n", "config key 'max_level': must be > 0, got 0"),
    ("max_triangles: 0\n", "config key 'max_triangles': must be > 0"),
    ("- 1\n- 2\n", "expected a mapping of keys to values"),
])
def test_cli_bad_config_file(tmp_path, capsys, text, fragment):
    """A config file error: exit 2, one line naming the file and the key, nothing reconstructed.
    ``max_level: 0`` is rejected (max_level is the last *subdivision* level; 0 would keep the
    96-triangle initial mesh and never test a refinement)."""
    f = _write_xy(tmp_path / "c.xy", circle(60))
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    code, out, err = _run(capsys, "reconstruct", f, "--config", cfg, "--out", tmp_path / "o")
    assert code == 2
    errs = _error_lines(err)
    assert len(errs) == 1 and errs[0].startswith(f"torch-isc: error: {cfg}: ") and fragment in errs[0], err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and out == ""
    assert not (tmp_path / "o").exists() or _listdir(tmp_path / "o") == []


# ============================================================================ 2. nothing lost
def test_cli_unreconstructable_input_in_a_batch(tmp_path, capsys):
    """An input that reads fine but cannot be reconstructed (all points identical), in the same
    batch as good ones: the batch is retried item by item and the good ones are written."""
    a = _write_xy(tmp_path / "a.xy", circle(80))
    same = _write_xy(tmp_path / "same.xy", np.ones((20, 2)))
    b = _write_xy(tmp_path / "b.xy", 2 * circle(80))
    code, _out, err = _run(capsys, "reconstruct", a, same, b, "--out", tmp_path / "o", "--formats", "json",
                          "--batch-size", "3", *FAST)
    assert code == 1
    errs = _error_lines(err)
    assert len(errs) == 1 and errs[0].startswith(f"torch-isc: error: {same}: ") and "3 distinct" in errs[0]
    assert sorted(_listdir(tmp_path / "o")) == ["a.json", "b.json"]


def test_atomic_write_interrupted_new_file(tmp_path):
    """Interrupted (KeyboardInterrupt, a BaseException) half way through a new file: neither the
    target nor a temporary file is left."""
    target = tmp_path / "new.json"

    def writer(fh):
        fh.write(b'{"polylines": [')
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, writer)
    assert _listdir(tmp_path) == []
    atomic_write(target, b"{}")
    assert target.read_bytes() == b"{}" and _listdir(tmp_path) == ["new.json"]


def test_cli_interrupted_run_then_rerun(tmp_path, capsys, monkeypatch):
    """An interrupt while the second format of the first input is written: exit 130, the first
    format is complete, the interrupted one is absent, no temporary file. The same command
    again (no --overwrite) redoes that input (its outputs are incomplete) and the other; a third
    run skips both."""
    a = _write_xy(tmp_path / "a.xy", circle(80))
    b = _write_xy(tmp_path / "b.xy", 2 * circle(80))
    o = tmp_path / "o"
    real_svg = EXPORTERS["svg"]

    def half(result, fh, context):
        fh.write(b"<?xml version=")
        raise KeyboardInterrupt

    monkeypatch.setitem(EXPORTERS, "svg", Exporter(half))
    args = ["reconstruct", a, b, "--out", o, "--formats", "json,svg", "--batch-size", "1", *FAST]
    code, out, err = _run(capsys, *args)
    assert code == 130 and "interrupted" in err and "Traceback" not in err
    assert _listdir(o) == ["a.json"]
    assert json.loads((o / "a.json").read_text())["num_components"] == 1
    monkeypatch.setitem(EXPORTERS, "svg", real_svg)
    code, out, err = _run(capsys, *args)
    assert code == 0, err
    assert "skipped" not in out
    assert sorted(_listdir(o)) == ["a.json", "a.svg", "b.json", "b.svg"]
    code, out, err = _run(capsys, *args)
    assert code == 0 and out.count("skipped, outputs exist") == 2


# ============================================================================ 3. invariance, determinism
@st.composite
def shapes(draw):
    """Random closed curves: one star, two disjoint stars, or a star inside a smaller copy of it
    (an annulus). Returns ``(points float64, truth [(dense, True)], gap, n_components)``."""
    kind = draw(st.sampled_from(["one", "two", "nested"]))
    nh = draw(st.integers(1, 3))
    ks = draw(st.lists(st.integers(2, 5), min_size=nh, max_size=nh, unique=True))
    harm = tuple((k, draw(st.floats(0.02, 0.24 / nh)), draw(st.floats(0.0, 2 * math.pi))) for k in ks)
    n = draw(st.integers(150, 300))
    seed = draw(st.integers(0, 2 ** 31 - 1))
    parts = [star(n, harm, seed=seed)]
    if kind == "two":
        parts.append(star(n * 4 // 5, harm, centre=(3.2, 0.6), size=0.8, seed=seed + 1))
    elif kind == "nested":
        parts.append(star(n // 2, harm, size=0.45, seed=seed + 1))
    pts = torch.cat([p for p, _, _ in parts])
    return pts, [(torch.from_numpy(tr), True) for _, tr, _ in parts], max(g for _, _, g in parts), len(parts)


@PROPERTY
@given(shape=shapes(), log_scale=st.floats(-3.0, 3.0), offset=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)))
def test_property_translation_scale(shape, log_scale, offset):
    """Translating and scaling give the same curve, transformed, with the same refinement.
    Coordinates are normalized in float64 before the cast to the working dtype, so the
    normalized points agree up to float64 rounding (~1e-16 x offset / spread); usually the cast
    absorbs that and the curves agree to ~1e-15 of the diagonal, but where a coordinate rounds
    to the next float32 the fit amplifies it (see test_offset_1e7_and_scale_1e6): the bound is a
    quarter of the tolerance."""
    pts, _truth, _, _n_true = shape
    s = 10.0 ** log_scale
    off = torch.tensor(offset, dtype=torch.float64)
    base = reconstruct(pts)
    res = reconstruct(pts * s + off)
    assert ncomp(res) == ncomp(base)
    assert [x.triangles for x in res.stats] == [x.triangles for x in base.stats]
    h = hausdorff(mapped(res, lambda p: (p - off) / s), base.polylines)
    assert h < 0.25 * base.stats[-1].tolerance, h / bbox_diagonal(pts)


@PROPERTY
@given(shape=shapes(), k=st.integers(1, 3))
def test_property_rot90(shape, k):
    """Rotating by k quarter turns gives the same number of components and the same curve up to
    the rotation and the tolerance. It is not bit-identical (the hexagonal initial mesh is not
    symmetric under a quarter turn, and the annealing streams are keyed by vertex index), so the
    two results are two valid reconstructions: each passes every data point within the
    effective tolerance delta, and between two consecutive samples (at most ``gap`` apart) a
    curve can only be pinned to the chord's neighbourhood, hence H <= 2 delta + gap. Measured:
    3e-3..1e-2 of the diagonal for quarter turns, ~1e-4 for a half turn (the hexagon is
    symmetric under it)."""
    pts, _truth, gap, n_true = shape
    diag = bbox_diagonal(pts)
    base = reconstruct(pts)
    assert ncomp(base) == (n_true, 0), "the unrotated shape itself is reconstructed wrongly"
    res = reconstruct(rot90(pts, k))
    assert ncomp(res) == ncomp(base)
    delta = max(base.stats[-1].tolerance, res.stats[-1].tolerance)
    h = hausdorff(mapped(res, lambda p: rot90(p, 4 - k)), base.polylines)
    assert h <= 2 * delta + gap, (h / diag, delta / diag, gap / diag)


@settings(max_examples=4, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(shape=shapes())
def test_property_float32_float64_topology(shape):
    """A float64 run (float64 input and working dtype) and a float32 run agree on the topology,
    and it is the true one."""
    pts, _truth, _gap, n_true = shape
    r32 = reconstruct(pts.float())
    r64 = reconstruct(pts, ReconstructConfig().replace(dtype="float64"))
    assert r32.curve.values.dtype == torch.float32 and r64.curve.values.dtype == torch.float64
    assert ncomp(r32) == ncomp(r64) == (n_true, 0)


def test_json_bytes_identical_across_processes(tmp_path, capsys):
    """The same input and seed give a byte-identical JSON in this process and in a fresh one
    with another hash seed (nothing may depend on set/dict hashing or on earlier runs)."""
    pts, _, _ = star(150, ((2, 0.1, 0.5), (4, 0.05, 0.0)), seed=9)
    f = _write_xy(tmp_path / "s.xy", pts.numpy())
    args = ["reconstruct", str(f), "--formats", "json", "--seed", "7", *FAST]
    assert _run(capsys, *args, "--out", tmp_path / "a")[0] == 0
    env = {**os.environ, "PYTHONHASHSEED": "12345", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.run([sys.executable, "-m", "torch_isc", *args, "--out", str(tmp_path / "b")],
                       check=False, capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    a, b = (tmp_path / "a" / "s.json").read_bytes(), (tmp_path / "b" / "s.json").read_bytes()
    assert a == b
    # and the API gives the same text as the file
    res = reconstruct(torch.from_numpy(np.loadtxt(f)), ReconstructConfig().replace(max_level=3, seed=7), name="s")
    assert json_dumps(result_json_dict(res)).encode() == a


# ============================================================================ 4. resource limits
def test_triangle_cap_bounds_a_pathological_input():
    """Uniform noise (no curve at all, 20,000 points) with a small triangle cap: the mesh never
    exceeds the cap, and the result says it stopped there without meeting the tolerance."""
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(20_000, 2, generator=g, dtype=torch.float64)
    for cap in (400, 1500):
        res = reconstruct(pts, ReconstructConfig().replace(max_triangles=cap, max_level=50))
        assert all(s.triangles <= cap for s in res.stats)
        assert res.curve.mesh.faces.shape[0] <= cap
        assert res.converged is False and res.limit in ("max_triangles", "no_curve")
        if res.limit == "max_triangles":
            assert res.stats[-1].marked > 0
        d = res.to_json_dict()["stats"]
        assert d["converged"] is False and d["limit"] == res.limit


def test_level_cap_reports_unmet_tolerance():
    """Stopped by max_level: not converged, limit "max_level", and the last level's stats show
    the error above the tolerance (the JSON carries both)."""
    pts, _truth, _ = star(300, ((5, 0.2, 0.0),), seed=1)
    full = reconstruct(pts)
    assert full.converged and len(full.stats) >= 3
    assert full.stats[-1].max_error <= full.stats[-1].tolerance
    res = reconstruct(pts, ReconstructConfig().replace(max_level=1))
    assert len(res.stats) == 2
    assert res.converged is False and res.limit == "max_level"
    last = res.stats[-1]
    assert last.marked > 0 and last.max_error > last.tolerance
    stats = json.loads(json_dumps(result_json_dict(res)))["stats"]
    assert stats["limit"] == "max_level" and stats["converged"] is False
    assert stats["levels"][-1]["max_error"] > stats["levels"][-1]["tolerance"]


def test_foreign_manifest_nested_or_huge_is_redone(tmp_path, capsys):
    """A ``<stem>.manifest.json`` in the output folder that is deeply nested JSON (json raises
    RecursionError) or larger than any manifest (sparse, 2 GB) is not a finished output set:
    the input is redone and the run exits 0, the other input written too; with --overwrite the
    same. Before, the nested one stopped the whole run with an internal error."""
    a = _write_xy(tmp_path / "a.xy", circle(80))
    b = _write_xy(tmp_path / "b.xy", 2 * circle(80))
    for content in ("[" * 3000 + "]" * 3000, None):
        o = tmp_path / ("o_nested" if content else "o_huge")
        o.mkdir()
        man = o / "a.manifest.json"
        if content:
            man.write_text(content)
        else:
            with open(man, "wb") as fh:
                fh.truncate(2 << 30)
        for extra in ([], ["--overwrite"]):
            code, out, err = _run(capsys, "reconstruct", a, b, "--out", o, *FAST, *extra)
            assert code == 0, err
            assert "internal error" not in err and "Traceback" not in err
            assert json.loads((o / "a.json").read_text())["num_components"] == 1
            assert (o / "b.json").exists()
