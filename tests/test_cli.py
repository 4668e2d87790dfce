"""The torch-isc command line (torch_isc.cli), end to end on tiny inputs.

These tests run the real reconstruction (``--set max_level=3`` keeps them fast). Only the
batch-retry test replaces ``reconstruct_batch`` with one that fails, to check that the items
are then retried one by one. Setting ``TORCH_ISC_FAKE_RECONSTRUCT=1`` runs the whole file
against a stand-in reconstruction (a circle fit), to work on the CLI without the core.
"""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import torch_isc
from torch_isc import cli
from torch_isc.core.curve import ImplicitCurve
from torch_isc.io import load_npz, read_points
from torch_isc.core.mesh import hexagon_mesh
from torch_isc.pipeline.result import ReconstructionResult
from torch_isc.pipeline.stats import LevelStats


def _listdir(d):
    """The outputs in ``d`` without the manifests (tested in test_robustness_fuzz)."""
    return [f for f in os.listdir(d) if not f.endswith(".manifest.json")]

REPO = Path(__file__).resolve().parents[1]
FAST = ["--set", "max_level=3"]
SUMMARY = re.compile(r"^(?P<stem>\S+): (?P<closed>\d+) closed, (?P<open>\d+) open, (?P<levels>\d+) levels, "
                     r"(converged|not converged \(.+\))(, \d+ point\(s\) beyond tolerance)?, \d+\.\d\d s$")


# ----------------------------------------------------------------------------- a stand-in reconstruction
def _fake_reconstruct(points, config=None, name=None):
    """One closed curve: the circle through the mean radius (only for TORCH_ISC_FAKE_RECONSTRUCT=1)."""
    config = config or torch_isc.ReconstructConfig()
    if points.dim() != 2 or points.shape[0] < 3:
        raise ValueError(f"need at least 3 points, got {points.shape[0]}")
    c = points.mean(0)
    r = (points - c).norm(dim=1).mean()
    mesh = hexagon_mesh(c[None], (2 * r)[None], 6)
    values = (mesh.verts - c).norm(dim=1) - r
    values = torch.where(values == 0, torch.full_like(values, 1e-9), values)
    stats = [LevelStats(level=0, triangles=int(mesh.faces.shape[0]), points=points.shape[0], delta1=0.0,
                        max_error=0.0, tolerance=0.0, noise=0.0, marked=0, points_beyond_tolerance=0)]
    return ReconstructionResult(ImplicitCurve(mesh, values), points, stats, config, True, None, name)


def _fake_batch(point_sets, config=None, names=None):
    names = names or [None] * len(point_sets)
    return [_fake_reconstruct(p, config, n) for p, n in zip(point_sets, names)]


@pytest.fixture(autouse=True)
def recon(monkeypatch):
    if os.environ.get("TORCH_ISC_FAKE_RECONSTRUCT") == "1":
        monkeypatch.setattr(torch_isc, "reconstruct", _fake_reconstruct, raising=False)
        monkeypatch.setattr(torch_isc, "reconstruct_batch", _fake_batch, raising=False)
    elif not hasattr(torch_isc, "reconstruct_batch"):
        pytest.fail("torch_isc.reconstruct_batch is missing (torch_isc/reconstruct.py not importable?)")


# ----------------------------------------------------------------------------- inputs
def _circle(n=120, r=1.0, c=(0.0, 0.0), seed=0):
    t = np.random.default_rng(seed).permutation(np.linspace(0, 2 * np.pi, n, endpoint=False))
    return np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], 1)


def _write_xy(path, pts):
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, pts, fmt="%.9f", header="x y", comments="")
    return path


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _summaries(out):
    return {m["stem"]: m for m in map(SUMMARY.match, out.splitlines()) if m}


def _error_lines(err):
    return [ln for ln in err.splitlines() if ln.startswith("torch-isc: error:")]


# ----------------------------------------------------------------------------- success
def test_one_input_all_formats(tmp_path, capsys):
    f = _write_xy(tmp_path / "in" / "circle.xy", _circle())
    out_dir = tmp_path / "out"
    code, out, err = _run(capsys, "reconstruct", f, "--out", out_dir, *FAST)
    assert code == 0, err
    assert sorted(_listdir(out_dir)) == ["circle.json", "circle.npz", "circle.png", "circle.svg"]
    s = _summaries(out)
    assert list(s) == ["circle"] and out.count("\n") == 1
    assert int(s["circle"]["closed"]) == 1 and int(s["circle"]["open"]) == 0
    d = json.loads((out_dir / "circle.json").read_text())
    assert d["num_components"] == 1 and d["polylines"][0]["closed"] is True
    assert {"polylines", "num_components", "bbox", "stats"} <= set(d)
    x0, y0, x1, y1 = d["bbox"]
    assert abs(x0 + 1) < 0.1 and abs(x1 - 1) < 0.1 and abs(y0 + 1) < 0.1 and abs(y1 - 1) < 0.1
    curve, meta = load_npz(out_dir / "circle.npz")
    assert curve.num_items == 1 and meta["name"] == "circle" and meta["config"]["limits"]["max_level"] == 3
    img = cv2.imread(str(out_dir / "circle.png"))
    assert img is not None and img.shape == (800, 800, 3)
    assert "Traceback" not in err and not _error_lines(err)


def test_many_inputs_in_batches_npy_and_seed(tmp_path, capsys):
    files = [_write_xy(tmp_path / f"c{i}.xy", _circle(100, r=1 + i, c=(i, -i), seed=i)) for i in range(2)]
    np.save(tmp_path / "c2.npy", _circle(100, r=0.5, seed=2))
    files.append(tmp_path / "c2.npy")
    code, out, err = _run(capsys, "reconstruct", *files, "--out", tmp_path / "o", "--batch-size", "2",
                          "--formats", "json,npz", "--seed", "5", *FAST)
    assert code == 0, err
    assert set(_summaries(out)) == {"c0", "c1", "c2"}
    assert "[0/3] batch 1: reconstructing 2 input(s)" in err            # progress on stderr
    assert "[2/3] batch 2: reconstructing 1 input(s)" in err
    assert sorted(_listdir(tmp_path / "o")) == ["c0.json", "c0.npz", "c1.json", "c1.npz", "c2.json", "c2.npz"]
    assert load_npz(tmp_path / "o" / "c1.npz")[1]["config"]["run"]["seed"] == 5
    for i, r in enumerate([1, 2, 0.5]):
        bbox = json.loads((tmp_path / "o" / f"c{i}.json").read_text())["bbox"]
        assert abs((bbox[2] - bbox[0]) - 2 * r) < 0.1 * r


def test_progress_bar_advances_per_input_within_a_batch(tmp_path, monkeypatch):
    """On a terminal the tqdm bar steps once per input as each one is final, also inside a batch
    of three (not once per batch)."""
    import io

    files = [_write_xy(tmp_path / f"c{i}.xy", _circle(60, r=1 + i, seed=i)) for i in range(3)]

    class Tty(io.StringIO):
        def isatty(self):
            return True

    err = Tty()
    monkeypatch.setattr(sys, "stderr", err)
    code = cli.main(["reconstruct", *map(str, files), "--out", str(tmp_path / "o"), "--batch-size", "3",
                     "--formats", "json", *FAST])
    monkeypatch.undo()
    assert code == 0
    steps = re.findall(r"(\d)/3", err.getvalue())
    assert {"1", "2", "3"} <= set(steps)


def test_same_input_same_json_bytes(tmp_path, capsys):
    f = _write_xy(tmp_path / "circle.xy", _circle())
    assert _run(capsys, "reconstruct", f, "--out", tmp_path / "a", "--formats", "json", *FAST)[0] == 0
    assert _run(capsys, "reconstruct", f, "--out", tmp_path / "b", "--formats", "json", *FAST)[0] == 0
    assert (tmp_path / "a" / "circle.json").read_bytes() == (tmp_path / "b" / "circle.json").read_bytes()


def test_duplicate_stems_are_disambiguated(tmp_path, capsys):
    a = _write_xy(tmp_path / "a" / "x.xy", _circle(seed=1))
    b = _write_xy(tmp_path / "b" / "x.xy", _circle(r=2, seed=2))
    code, out, err = _run(capsys, "reconstruct", a, b, "--out", tmp_path / "o", "--formats", "json", *FAST)
    assert code == 0, err
    # same stem and suffix: the stem, the suffix and a hash of the path, whatever the order
    import hashlib
    h = {p: hashlib.sha256(os.path.abspath(p).encode()).hexdigest()[:8] for p in (a, b)}
    names = {p: f"x_xy_{h[p]}" for p in (a, b)}
    assert sorted(_listdir(tmp_path / "o")) == sorted(f"{n}.json" for n in names.values())
    assert set(_summaries(out)) == set(names.values())
    assert names[b] in err and str(b) in err                          # said so
    w = json.loads((tmp_path / "o" / f"{names[b]}.json").read_text())["bbox"]
    assert w[2] - w[0] > 3                                            # the second input (radius 2)


# ----------------------------------------------------------------------------- skip / overwrite
def test_rerun_with_an_execution_setting_changed_skips_and_a_result_setting_redoes(tmp_path, capsys):
    """``run.cuda_graphs`` changes how a solve runs, not what it computes: outputs made with it
    on are finished for a rerun with it off; a setting of the result (the seed) redoes them."""
    f = _write_xy(tmp_path / "circle.xy", _circle())
    o = tmp_path / "o"
    args = ["reconstruct", f, "--out", o, "--formats", "json", *FAST]
    assert _run(capsys, *args)[0] == 0
    code, out, err = _run(capsys, *args, "--set", "cuda_graphs=false")
    assert code == 0 and "circle: skipped" in out, out
    code, out, err = _run(capsys, *args, "--set", "seed=3")
    assert code == 0 and "skipped" not in out


def test_rerun_skips_unless_overwrite(tmp_path, capsys):
    f = _write_xy(tmp_path / "circle.xy", _circle())
    o = tmp_path / "o"
    args = ["reconstruct", f, "--out", o, "--formats", "json,svg", *FAST]
    assert _run(capsys, *args)[0] == 0
    code, out, err = _run(capsys, *args)
    assert code == 0 and "circle: skipped" in out
    # a changed output no longer matches its manifest: the input runs again
    (o / "circle.json").write_text("marker")
    code, out, err = _run(capsys, *args)
    assert code == 0 and "skipped" not in out
    assert json.loads((o / "circle.json").read_text())["num_components"] >= 1
    # a missing output makes the input run again
    (o / "circle.svg").unlink()
    code, out, err = _run(capsys, *args)
    assert code == 0 and "skipped" not in out and (o / "circle.svg").exists()
    assert json.loads((o / "circle.json").read_text())["num_components"] >= 1
    (o / "circle.json").write_text("marker")
    code, out, err = _run(capsys, *args, "--overwrite")
    assert code == 0 and "skipped" not in out
    assert json.loads((o / "circle.json").read_text())["num_components"] >= 1
    assert sorted(_listdir(o)) == ["circle.json", "circle.svg"]    # no temporary files left


# ----------------------------------------------------------------------------- failures: exit 1
def test_bad_input_among_good_ones(tmp_path, capsys):
    g1 = _write_xy(tmp_path / "good1.xy", _circle(seed=1))
    bad = tmp_path / "bad.xy"
    bad.write_text("1 2\n3 4\nfoo 5\n")
    g2 = _write_xy(tmp_path / "good2.xy", _circle(r=3, seed=2))
    code, out, err = _run(capsys, "reconstruct", g1, bad, g2, "--out", tmp_path / "o", "--formats", "json,png", *FAST)
    assert code == 1
    assert sorted(_listdir(tmp_path / "o")) == ["good1.json", "good1.png", "good2.json", "good2.png"]
    errs = _error_lines(err)
    assert errs == [f"torch-isc: error: {bad}: line 3: non-numeric value 'foo'"]
    assert "Traceback" not in err
    assert set(_summaries(out)) == {"good1", "good2"}


def test_missing_file_and_too_few_points(tmp_path, capsys):
    g = _write_xy(tmp_path / "good.xy", _circle())
    few = _write_xy(tmp_path / "few.xy", _circle(2))                  # 2 points: the reconstruction refuses
    code, out, err = _run(capsys, "reconstruct", g, tmp_path / "nope.xy", few, "--out", tmp_path / "o",
                          "--formats", "json", *FAST)
    assert code == 1
    assert _listdir(tmp_path / "o") == ["good.json"]
    errs = _error_lines(err)
    assert len(errs) == 2 and "Traceback" not in err
    assert errs[0] == f"torch-isc: error: {tmp_path / 'nope.xy'}: no such file"
    assert errs[1].startswith(f"torch-isc: error: {few}: ")
    assert set(_summaries(out)) == {"good"}


def test_failing_batch_is_retried_item_by_item(tmp_path, capsys, monkeypatch):
    calls = {"batch": 0}

    def broken_batch(point_sets, config=None, names=None):
        calls["batch"] += 1
        raise RuntimeError("one item sank the batch")

    monkeypatch.setattr(torch_isc, "reconstruct_batch", broken_batch)
    files = [_write_xy(tmp_path / f"c{i}.xy", _circle(seed=i)) for i in range(3)]
    code, out, err = _run(capsys, "reconstruct", *files, "--out", tmp_path / "o", "--formats", "json", *FAST)
    assert code == 0, err
    assert calls["batch"] == 1
    assert sorted(_listdir(tmp_path / "o")) == ["c0.json", "c1.json", "c2.json"]


def test_internal_error_is_one_line(tmp_path, capsys, monkeypatch):
    def broken(points, config=None, name=None):
        raise RuntimeError("boom\nsecond line")

    monkeypatch.setattr(torch_isc, "reconstruct", broken)
    f = _write_xy(tmp_path / "c.xy", _circle())
    code, out, err = _run(capsys, "reconstruct", f, "--out", tmp_path / "o", "--formats", "json")
    assert code == 1
    assert _error_lines(err) == [f"torch-isc: error: {f}: reconstruction failed (RuntimeError: boom)"]
    assert "Traceback" not in err and _listdir(tmp_path / "o") == []


# ----------------------------------------------------------------------------- usage / config: exit 2
@pytest.mark.parametrize("extra,expect", [
    (["--set", "bogus_key=1"], "unknown config key 'bogus_key'"),
    (["--set", "max_level=abc"], "'max_level'"),
    (["--set", "max_level=0"], "'max_level'"),
    (["--set", "tolerance=-1.0"], "'tolerance'"),
    (["--set", "max_level"], "expected key=value"),
    (["--formats", "json,obj"], "unknown format 'obj'"),
    (["--batch-size", "0"], "--batch-size"),
])
def test_usage_errors_exit_2(tmp_path, capsys, extra, expect):
    f = _write_xy(tmp_path / "c.xy", _circle())
    code, out, err = _run(capsys, "reconstruct", f, "--out", tmp_path / "o", *extra)
    assert code == 2
    errs = _error_lines(err)
    assert len(errs) == 1 and expect in errs[0], err
    assert "Traceback" not in err and out == ""
    assert not (tmp_path / "o").exists() or _listdir(tmp_path / "o") == []


def test_config_file_errors_exit_2(tmp_path, capsys):
    f = _write_xy(tmp_path / "c.xy", _circle())
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("max_level: 3\nanneal_sweepz: 10\n")
    code, out, err = _run(capsys, "reconstruct", f, "--config", cfg, "--out", tmp_path / "o")
    assert code == 2 and "anneal_sweepz" in err and str(cfg) in err and "Traceback" not in err
    code, out, err = _run(capsys, "reconstruct", f, "--config", tmp_path / "none.yaml")
    assert code == 2 and "none.yaml" in err
    cfg.write_text("max_level: [3\n")
    assert _run(capsys, "reconstruct", f, "--config", cfg)[0] == 2
    # a good config file, then --set on top
    cfg.write_text("max_level: 9\nseed: 4\n")
    code, out, err = _run(capsys, "reconstruct", f, "--config", cfg, "--set", "max_level=2", "--out", tmp_path / "o",
                          "--formats", "npz")
    assert code == 0, err
    meta = load_npz(tmp_path / "o" / "c.npz")[1]
    assert meta["config"]["limits"]["max_level"] == 2 and meta["config"]["run"]["seed"] == 4


def test_argparse_and_output_folder_errors(tmp_path, capsys):
    assert _run(capsys, "reconstruct", "--out", tmp_path / "o")[0] == 2          # no INPUT
    code, out, err = _run(capsys, "frobnicate")
    assert code == 2 and "invalid choice" in err
    assert _run(capsys, "reconstruct", "x.xy", "--batch-size", "many")[0] == 2
    assert _run(capsys)[0] == 2
    blocker = tmp_path / "file"
    blocker.write_text("")
    f = _write_xy(tmp_path / "c.xy", _circle())
    code, out, err = _run(capsys, "reconstruct", f, "--out", blocker / "sub")
    assert code == 2 and "cannot create the output folder" in err and "Traceback" not in err
    code, out, err = _run(capsys, "--version")
    assert code == 0 and torch_isc.__version__ in out


# ----------------------------------------------------------------------------- the example
def test_example_data_is_reproducible(tmp_path):
    script = REPO / "torch_isc" / "data" / "make_example.py"
    subprocess.run([sys.executable, str(script), str(tmp_path / "n.xy")], check=True, capture_output=True)
    assert (tmp_path / "n.xy").read_bytes() == cli.EXAMPLE_PATH.read_bytes()
    pts = read_points(cli.EXAMPLE_PATH)
    assert 550 <= pts.shape[0] <= 650


def test_example_runs(tmp_path, capsys):
    code, out, err = _run(capsys, "reconstruct", "--example", "--out", tmp_path / "o", "--formats", "json",
                          "--set", "max_level=1")
    assert code == 0, err
    assert list(_summaries(out)) == ["nested"]
    assert _listdir(tmp_path / "o") == ["nested.json"]


@pytest.mark.slow
def test_example_reconstructs_four_nested_curves(tmp_path, capsys):
    code, out, err = _run(capsys, "reconstruct", "--example", "--out", tmp_path / "o", "--formats", "json")
    assert code == 0, err
    s = _summaries(out)["nested"]
    assert (int(s["closed"]), int(s["open"])) == (4, 0)


# ----------------------------------------------------------------------------- the entry point
def test_python_dash_m(tmp_path):
    f = _write_xy(tmp_path / "circle.xy", _circle())
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    if os.environ.get("TORCH_ISC_FAKE_RECONSTRUCT") == "1":
        pytest.skip("a subprocess cannot use the stand-in reconstruction")
    p = subprocess.run([sys.executable, "-m", "torch_isc", "reconstruct", str(f), "--out", str(tmp_path / "o"),
                        "--formats", "json", *FAST], capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    assert SUMMARY.match(p.stdout.strip()) and (tmp_path / "o" / "circle.json").exists()


# ----------------------------------------------------------------------------- images
def _disc_png(path, shape, c, r, value=255, hole=None):
    """A mask with a disc (pixel convention: a pixel is inside when its centre is)."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]] + 0.5
    d = np.hypot(xx - c[0], yy - c[1])
    m = np.where((d < r) & ((d >= hole) if hole else True), value, 0).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), m)
    return path


def test_image_folder_streams_with_bad_files(tmp_path, capsys):
    d = tmp_path / "in"
    _disc_png(d / "disc.png", (48, 56), (28.3, 23.6), 15.0)
    _disc_png(d / "ring.bmp", (60, 60), (30.0, 30.0), 22.0, hole=10.0)
    _write_xy(d / "pts.xy", _circle())
    (d / "fake.png").write_text("not an image")
    ok, buf = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (40, 40), dtype=np.uint8))
    (d / "trunc.png").write_bytes(buf.tobytes()[:150])
    assert cv2.imwrite(str(d / "black.png"), np.zeros((20, 20), np.uint8))
    assert cv2.imwrite(str(d / "white.tif"), np.full((16, 24), 255, np.uint8))
    (d / "notes.md").write_text("ignored: not a point or image file")
    o = tmp_path / "o"
    code, out, err = _run(capsys, "reconstruct", d, "--out", o, "--batch-size", "2",
                          "--formats", "json,npz,svg,png,contours.npz,overlay.png", *FAST)
    assert code == 1 and "Traceback" not in err
    errs = _error_lines(err)
    assert sorted(errs) == sorted([
        f"torch-isc: error: {d / 'fake.png'}: not a readable image (unknown format, truncated or corrupt)",
        f"torch-isc: error: {d / 'trunc.png'}: not a readable image (unknown format, truncated or corrupt)"])
    # an all-black mask is a mask without borders (cv2.findContours: no contour), not a failure
    assert f"torch-isc: note: {d / 'black.png'}: empty mask (no pixel above threshold 0.5, all black): no curve" \
        in err.splitlines()
    s = _summaries(out)
    assert {k: (int(v["closed"]), int(v["open"])) for k, v in s.items()} == {
        "disc": (1, 0), "ring": (2, 0), "pts": (1, 0), "white": (1, 0), "black": (0, 0)}
    assert json.loads((o / "black.json").read_text())["polylines"] == []
    files = set(_listdir(o))
    for stem in ("disc", "ring", "white", "black"):
        assert {f"{stem}.{f}" for f in ("json", "npz", "svg", "png", "contours.npz", "overlay.png")} <= files
    assert "pts.overlay.png" not in files                                # the overlay needs an image
    assert "batch 1" in err and "%" in err                               # progress with a bar
    # pixel coordinates: the disc's curve is within a pixel of the analytic circle
    pl = json.loads((o / "disc.json").read_text())["polylines"][0]["points"]
    rad = np.hypot(*(np.array(pl) - (28.3, 23.6)).T)
    assert np.abs(rad - 15.0).max() < 1.0
    ov = cv2.imread(str(o / "disc.overlay.png"))
    assert ov.shape == (48, 56, 3) and (ov[:, :, 1] > ov[:, :, 2] + 50).any()       # green curve drawn
    from torch_isc.images import load_contours
    c, h = load_contours(o / "ring.contours.npz")
    assert len(c) == 2 and sorted(h[0, :, 3].tolist()) == [-1, 0]
    # a rerun of the same command skips everything that was written, and fails again on the bad
    # ones only; asking for other formats redoes the inputs (a manifest names its formats)
    code, out, err = _run(capsys, "reconstruct", d, "--out", o, "--batch-size", "2",
                          "--formats", "json,npz,svg,png,contours.npz,overlay.png", *FAST)
    assert code == 1 and out.count("skipped") == 5 and len(_error_lines(err)) == 2
    code, out, err = _run(capsys, "reconstruct", d, "--out", o, "--batch-size", "2", *FAST)
    assert code == 1 and out.count("skipped") == 0 and len(_error_lines(err)) == 2


def test_image_modes_and_threshold(tmp_path, capsys):
    g = np.full((50, 50), 60, np.uint8)
    yy, xx = np.mgrid[0:50, 0:50] + 0.5
    g[np.hypot(xx - 25.0, yy - 25.0) < 14.0] = 200
    g[np.hypot(xx - 25.0, yy - 25.0) < 6.0] = 120            # three gray levels: 60, 120, 200
    f = tmp_path / "gray.png"
    assert cv2.imwrite(str(f), g)
    o = tmp_path / "o"
    # mask mode, default threshold 0.5: only the 200 level is foreground -> a ring
    code, out, err = _run(capsys, "reconstruct", f, "--out", o, "--formats", "json", *FAST)
    assert code == 0, err
    assert int(_summaries(out)["gray"]["closed"]) == 2
    # a lower threshold takes the 120 level in too -> a disc
    code, out, err = _run(capsys, "reconstruct", f, "--out", o, "--formats", "json", "--threshold", "0.3",
                          "--overwrite", *FAST)
    assert code == 0, err
    assert int(_summaries(out)["gray"]["closed"]) == 1
    # edges mode: Canny edges of the two steps -> two circles
    code, out, err = _run(capsys, "reconstruct", f, "--out", o, "--formats", "json,overlay.png", "--mode", "edges",
                          "--overwrite", *FAST)
    assert code == 0, err
    assert (int(_summaries(out)["gray"]["closed"]), int(_summaries(out)["gray"]["open"])) == (2, 0)
    assert (o / "gray.overlay.png").exists()
    for bad, expect in ((["--threshold", "2"], "--threshold"), (["--canny", "0.3"], "--canny"),
                        (["--mode", "blobs"], "invalid choice")):
        code, out, err = _run(capsys, "reconstruct", f, "--out", o, *bad)
        assert code == 2 and expect in err and "Traceback" not in err
    (tmp_path / "empty").mkdir()
    code, out, err = _run(capsys, "reconstruct", tmp_path / "empty", "--out", tmp_path / "o2")
    assert code == 2 and "folder has no point or image file" in err and "Traceback" not in err


def test_progress_bar_on_a_terminal_only(tmp_path, capsys, monkeypatch):
    """tqdm: one bar per run on stderr when it is a terminal, advanced per input; the summary
    lines still reach stdout; off a terminal no bar, the batch notes instead."""
    import io

    files = [_write_xy(tmp_path / f"c{i}.xy", _circle(60, seed=i)) for i in range(3)]

    class Tty(io.StringIO):
        def isatty(self):
            return True

    err = Tty()
    monkeypatch.setattr(sys, "stderr", err)
    code = cli.main(["reconstruct", *map(str, files), "--out", str(tmp_path / "o"), "--batch-size", "2",
                 "--formats", "json", *FAST])
    monkeypatch.undo()
    out = capsys.readouterr().out
    assert code == 0 and set(_summaries(out)) == {"c0", "c1", "c2"}
    text = err.getvalue()
    assert "3/3" in text and "input" in text and "batch 1:" not in text
