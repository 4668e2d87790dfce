"""Fuzzing, fourth round (issue 18, session 10): one fast regression test per failure found, in
the style of ``tests/test_fuzz_third.py``.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
YAML values PyYAML cannot construct (``2001-13-45``,   test_yaml_values_that_cannot_be_constructed
``!!float abc``, ``!!timestamp x``, a 5000-digit
integer): "internal error", exit 1, key unnamed
an integer beyond float64 for a float key (``tolerance test_huge_integer_for_a_float_key
= 10**400``): OverflowError, exit 1
an empty INPUT (``""``, an unset shell variable): the  test_empty_input_path
whole working folder was reconstructed
a rerun with fewer formats or another config left the  test_rerun_removes_the_previous_sets_other_files
previous set's other files beside the new set (a.npz
of config A beside a.json of config B)
a point file rewritten between its read and its hash: test_manifest_hashes_the_bytes_decoded
the manifest held the new hash beside outputs of the
old content (a later rerun skipped it)
a noise or checkerboard mask under the pixel limit:    test_mask_boundary_is_bounded,
hours of tracing, gigabytes (80 us a pixel edge)       test_boundary_length_hand_values
curve queries: point_item -1 meant the last curve;     test_query_points_and_items_are_checked
5, a float item or (N, 3) points raised torch errors
rasterize / soft_inside: tau NaN (NaN images), < 0     test_render_arguments_are_checked
(inverted), sizes -1 / 8.5, extent=[1.0] broadcast
deform(tol=nan) accepted any move of the boundary      test_deform_tolerance_and_safety_are_checked
curve .npz: float faces truncated, negative counts,    test_curve_file_dtypes_and_counts
integer vertices, complex values (torch errors later)
contours .npz: NaN / text points, float or             test_contours_file_is_checked
out-of-range hierarchy returned as they were
run_inputs(stems=["../x", ...]) wrote outside the    test_run_stems_stay_inside_the_output_folder
output folder; equal stems overwrote each other
=====================================================  ==========================================
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torch_isc import ConfigError, ReconstructConfig, cli
from torch_isc.pipeline.config import load_config, parse_overrides
from torch_isc.runner import ImageOptions, RunError, boundary_length, run_inputs

CONFIG = load_config(overrides={"max_level": 3})


def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _circle(n=60, r=1.0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[r * np.cos(t), r * np.sin(t)]


def _xy(path, pts):
    path = Path(path)
    np.savetxt(path, pts)
    return path


# ============================================================================ config values
@pytest.mark.parametrize("value,why", [("2001-13-45", "month must be in 1..12"), ("!!float abc", "could not convert"),
                                       ("!!timestamp x", "cannot be read"), ("1" + "0" * 5000, "4300 digits")])
def test_yaml_values_that_cannot_be_constructed(tmp_path, capsys, value, why):
    """A value PyYAML's constructors raise on is a ConfigError (exit 2, the --set named), in
    --set and in a config file."""
    with pytest.raises(ConfigError, match=why):
        parse_overrides([f"tolerance={value}"])
    code, out, err = _run(capsys, tmp_path / "none.xy", "--set", f"tolerance={value}", "--out", tmp_path / "o")
    assert code == 2 and err.startswith("torch-isc: error: --set 'tolerance=") and "cannot be read" in err, err
    assert len(err.splitlines()) == 1 and not (tmp_path / "o").exists()
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"tolerance: {value}\n")
    with pytest.raises(ConfigError, match=f"{cfg}: a YAML value cannot be read"):
        load_config(cfg)


@pytest.mark.parametrize("value", [10 ** 400, -10 ** 400])
def test_huge_integer_for_a_float_key(tmp_path, capsys, value):
    """An integer beyond the float64 range for a float key names the key (OverflowError before)."""
    with pytest.raises(ConfigError, match="config key 'tolerance': must be finite, got an integer of 401 digits"):
        ReconstructConfig().replace(tolerance=value)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"tolerance: {value}\n")
    code, out, err = _run(capsys, tmp_path / "none.xy", "--config", cfg, "--out", tmp_path / "o")
    assert code == 2 and "config key 'tolerance': must be finite" in err, err
    # integers within the float64 range are still read as floats
    assert ReconstructConfig().replace(tolerance=2 ** 1023).test.tolerance == 2.0 ** 1023


# ============================================================================ inputs and reruns
def test_empty_input_path(tmp_path, capsys, monkeypatch):
    """``""`` is a usage error, not the working folder (Path("") is "."): an unset variable in
    ``torch-isc reconstruct "$F"`` reconstructed every point file there."""
    _xy(tmp_path / "here.xy", _circle())
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(capsys, "", "--out", tmp_path / "o")
    assert code == 2 and err == "torch-isc: error: an empty path ('') given as an input\n"
    assert not (tmp_path / "o").exists() or not os.listdir(tmp_path / "o")
    with pytest.raises(RunError, match="empty path"):
        run_inputs([""], CONFIG, tmp_path / "o2")


def test_rerun_removes_the_previous_sets_other_files(tmp_path, capsys):
    """Run 1 writes json, npz and svg; run 2, with another config, only json: the old npz and
    svg (run 1's curve) are removed, so the folder holds one consistent set; a file the old
    manifest does not list (the user's) is kept."""
    src = _xy(tmp_path / "a.xy", _circle())
    out = tmp_path / "o"
    code, _, err = _run(capsys, src, "--out", out, "--formats", "json,npz,svg", "--set", "max_level=3")
    assert code == 0, err
    (out / "a.png").write_bytes(b"mine")
    code, _, err = _run(capsys, src, "--out", out, "--formats", "json", "--set", "max_level=2")
    assert code == 0, err
    assert sorted(os.listdir(out)) == ["a.json", "a.manifest.json", "a.png"]
    man = json.loads((out / "a.manifest.json").read_text())
    assert [f["name"] for f in man["files"]] == ["a.json"]
    # the same run again skips (the set is complete)
    code, o, err = _run(capsys, src, "--out", out, "--formats", "json", "--set", "max_level=2")
    assert code == 0 and "a: skipped" in o


def test_manifest_hashes_the_bytes_decoded(tmp_path, monkeypatch):
    """A point file rewritten between its read and its hash (another process): the manifest
    holds the hash of the bytes reconstructed, so a rerun sees the change and redoes it."""
    from torch_isc import runner

    src = _xy(tmp_path / "a.xy", _circle())
    first = src.read_bytes()
    real = runner.read_file_bytes

    def read_then_rewrite(path, *a, **k):
        data = real(path, *a, **k)
        if Path(path) == src:
            _xy(src, _circle(r=2.0))         # the file changes right after it was read
        return data

    monkeypatch.setattr(runner, "read_file_bytes", read_then_rewrite)
    rep = run_inputs([src], CONFIG, tmp_path / "o", formats=["json"])
    assert rep.records[0].status == "done"
    man = json.loads((tmp_path / "o" / "a.manifest.json").read_text())
    assert man["input"]["sha256"] == hashlib.sha256(first).hexdigest()
    monkeypatch.undo()
    rep = run_inputs([src], CONFIG, tmp_path / "o", formats=["json"])
    assert rep.records[0].status == "done"          # redone: the file on disk is the radius-2 circle
    pts = json.loads((tmp_path / "o" / "a.json").read_text())["polylines"][0]["points"]
    assert abs(np.linalg.norm(np.asarray(pts), axis=1).mean() - 2.0) < 0.05


# ============================================================================ bounded work on images
def test_boundary_length_hand_values():
    """Pixel edges between foreground and background, the frame counted where the foreground
    touches it."""
    assert boundary_length(torch.ones(1, 7, dtype=torch.bool)) == 2 * 7 + 2
    assert boundary_length(torch.tensor([[1, 0], [0, 1]], dtype=torch.bool)) == 8
    m = torch.zeros(6, 6, dtype=torch.bool)
    m[1:4, 2:5] = True                      # a 3x3 square inside: 12 edges
    assert boundary_length(m) == 12
    m[0, :] = True                          # a T: the top row (perimeter 14) on the square, 3 edges
    assert boundary_length(m) == 14 + 12 - 2 * 3        # shared (counted by neither any more)
    n = 20
    checker = torch.from_numpy(np.indices((n, n)).sum(0) % 2 == 1)
    assert boundary_length(checker) == 4 * (n * n // 2)       # every pixel edge of every foreground pixel


def test_mask_boundary_is_bounded(tmp_path, capsys):
    """A checkerboard mask beyond --max-boundary is one error line before any tracing; the disc
    beside it is written; --max-boundary 0 lifts the limit; ImageOptions checks the value."""
    n = 64
    cv2.imwrite(str(tmp_path / "checker.png"), ((np.indices((n, n)).sum(0) % 2) * 255).astype(np.uint8))
    yy, xx = np.mgrid[:40, :50]
    cv2.imwrite(str(tmp_path / "disc.png"), ((((xx - 24.5) ** 2 + (yy - 19.5) ** 2) < 144) * 255).astype(np.uint8))
    code, out, err = _run(capsys, tmp_path / "checker.png", tmp_path / "disc.png", "--out", tmp_path / "o",
                          "--max-boundary", 5000)
    assert code == 1 and "disc: 1 closed" in out
    assert f"{tmp_path / 'checker.png'}: mask boundary too long: 8192 pixel edges, more than the limit of 5000" in err
    assert sorted(os.listdir(tmp_path / "o")) == ["disc.contours.npz", "disc.json", "disc.manifest.json"]
    code, out, err = _run(capsys, tmp_path / "checker.png", "--out", tmp_path / "o", "--max-boundary", 0)
    assert code == 0 and "checker: 1923 closed" in out, err        # 31x31 + 31x31 inner holes + the outline
    code, out, err = _run(capsys, tmp_path / "disc.png", "--out", tmp_path / "o", "--max-boundary", -1)
    assert code == 2 and "--max-boundary must be >= 0" in err
    # edges mode: the limit counts edge points
    code, out, err = _run(capsys, tmp_path / "disc.png", "--mode", "edges", "--out", tmp_path / "o3",
                          "--max-boundary", 10)
    assert code == 1 and "too many edge points" in err
    for bad in (-1, 1.5, True, "10"):
        with pytest.raises(RunError, match="max_boundary"):
            ImageOptions(max_boundary=bad)


# ============================================================================ curve queries, rendering, deformation
def _disc_curve():
    from torch_isc import ImplicitCurve, hexagon_mesh

    m = hexagon_mesh(torch.zeros(2, 2, dtype=torch.float64), torch.ones(2), 3)
    return ImplicitCurve(m, m.verts.norm(dim=1) - torch.where(m.vert_item == 0, 0.5, 0.3).double())


def test_query_points_and_items_are_checked():
    """point_item of -1 meant the last curve (silently), 5 or a float raised torch's IndexError,
    (N, 3) points a broadcast error: now one PointSetError naming the argument. Valid queries
    give the hand values (distance to a circle of radius 0.5 / 0.3 from the centre)."""
    from torch_isc import PointSetError, measures

    c = _disc_curve()
    p = torch.zeros(2, 2, dtype=torch.float64)
    d = measures.point_curve_distance(c, p, torch.tensor([0, 1]))
    assert ((d - torch.tensor([0.5, 0.3], dtype=torch.float64)).abs() < 0.05).all()      # inscribed polygons
    for item, why in [(torch.tensor([0, -1]), r"in \[0, 2\), got -1"), (torch.tensor([0, 2]), r"in \[0, 2\), got 2"),
                      (torch.tensor([0.0, 1.0]), "integer"), (torch.tensor([0]), r"\(2,\)"), ([0, 1], "list")]:
        with pytest.raises(PointSetError, match=why):
            measures.point_curve_distance(c, p, item)
        with pytest.raises(PointSetError, match=why):
            c.inside(p, item)
    for bad in (torch.zeros(3, 3), torch.zeros(2), torch.zeros(2, 2, dtype=torch.complex64), [[0.0, 0.0]]):
        with pytest.raises(PointSetError, match="points: expected a real"):
            c.inside(bad, torch.zeros(len(bad), dtype=torch.long))
    # points or items on another device than the curve (meta stands in for a GPU here)
    with pytest.raises(PointSetError, match=r"points: on meta, the curve on cpu \(move them"):
        c.locate(torch.zeros(2, 2, dtype=torch.float64, device="meta"), torch.tensor([0, 1]))
    with pytest.raises(PointSetError, match="point_item: on meta, the curve on cpu"):
        c.inside(p, torch.tensor([0, 1], device="meta"))


def test_render_arguments_are_checked():
    """rasterize: a negative or fractional size raised torch errors; tau NaN gave NaN images,
    a negative tau the inverted occupancy; extent=[1.0] was broadcast to (1, 1, 1, 1)."""
    from torch_isc.render import rasterize, soft_inside

    c = _disc_curve()
    img = rasterize(c, np.int64(8), 8, tau=np.float32(0.01))     # numpy sizes and widths are numbers too
    assert img.shape == (2, 8, 8) and (img[0] > 0.5).sum() > (img[1] > 0.5).sum() > 0
    for h, w in ((-1, 8), (8.5, 8), (True, 8), ("8", 8)):
        with pytest.raises(ValueError, match="height must be an integer"):
            rasterize(c, h, w, tau=0.01)
    for tau in (0.0, -0.1, float("nan"), float("inf"), None):
        with pytest.raises(ValueError, match="tau must be a finite distance > 0"):
            rasterize(c, 4, 4, tau=tau)
        with pytest.raises(ValueError, match="tau must be a finite distance > 0"):
            soft_inside(c, torch.zeros(1, 2, dtype=torch.float64), tau, torch.zeros(1, dtype=torch.long))
    with pytest.raises(ValueError, match="extent must be 4 numbers"):
        rasterize(c, 4, 4, tau=0.01, extent=[1.0])


def test_deform_tolerance_and_safety_are_checked():
    """deform(tol=nan) accepted a move of the outer boundary (every comparison with NaN is
    False); a negative tol reported a corner moving when nothing moved."""
    from torch_isc.core.mesh import InvalidMeshError

    c = _disc_curve()
    v = c.mesh.verts.clone()
    v[c.mesh.is_corner_vert] += 0.1                          # the corners leave the boundary
    with pytest.raises(InvalidMeshError, match="corner"):
        c.deform(v, tol=1e-6)
    for tol in (float("nan"), -1.0, float("inf"), "1"):
        with pytest.raises(InvalidMeshError, match="tol must be a finite number >= 0"):
            c.deform(v, tol=tol)
    assert c.deform(c.mesh.verts.clone(), tol=0).mesh.verts.equal(c.mesh.verts)
    for safety in (0, 1.5, float("nan")):
        with pytest.raises(InvalidMeshError, match="safety must be in"):
            c.deform(v, clamp=True, safety=safety)


# ============================================================================ curve and contour files
def _saved_curve(tmp_path):
    from torch_isc import reconstruct
    from torch_isc.io import save_npz

    res = reconstruct(torch.from_numpy(_circle()), CONFIG)
    save_npz(tmp_path / "c.npz", res.curve, {"name": "c"})
    return dict(np.load(tmp_path / "c.npz"))


@pytest.mark.parametrize("case,why", [
    ("faces_float", "faces of dtype float32, expected integers"),          # truncated silently before
    ("negative_count", "verts_per_item holds a negative count"),           # RuntimeError in MeshBatch
    ("int_verts", "verts of dtype int64, expected floats"),                # RuntimeError in the measures
    ("complex_values", "values of dtype complex128, expected real numbers"),
    ("metadata_list", "metadata is a JSON list, not an object"),
])
def test_curve_file_dtypes_and_counts(tmp_path, case, why):
    from torch_isc.io import CurveFileError, load_npz

    z = _saved_curve(tmp_path)
    if case == "faces_float":
        z["faces"] = z["faces"].astype(np.float32)
    elif case == "negative_count":
        z["verts_per_item"] = np.array([-1, z["verts"].shape[0] + 1])
    elif case == "int_verts":
        z["verts"] = (z["verts"] * 100).astype(np.int64)
    elif case == "complex_values":
        z["values"] = z["values"].astype(complex)
    else:
        z["metadata"] = np.array("[1]")
    np.savez(tmp_path / "bad.npz", **z)
    with pytest.raises(CurveFileError, match=f"bad.npz: invalid curve \\({why}\\)"):
        load_npz(tmp_path / "bad.npz")
    curve, meta = load_npz(tmp_path / "c.npz")                   # the file as written still loads
    assert meta == {"name": "c"} and curve.num_items == 1


@pytest.mark.parametrize("case", ["nan_point", "text_points", "float_hierarchy", "hierarchy_out_of_range"])
def test_contours_file_is_checked(tmp_path, case):
    """A NaN point became a garbage int32 (rint of NaN), text points a numpy ValueError, a float
    or out-of-range hierarchy was returned as it was: now "inconsistent contours file"."""
    from torch_isc.images import ImageError, load_contours

    yy, xx = np.mgrid[:40, :50]
    r2 = (xx - 24.5) ** 2 + (yy - 19.5) ** 2
    cv2.imwrite(str(tmp_path / "ring.png"), (((r2 < 144) & (r2 >= 25)) * 255).astype(np.uint8))
    assert cli.main(["reconstruct", str(tmp_path / "ring.png"), "--out", str(tmp_path / "o")]) == 0
    z = dict(np.load(tmp_path / "o" / "ring.contours.npz"))
    contours, h = load_contours(tmp_path / "o" / "ring.contours.npz", dtype=np.int32)
    assert len(contours) == 2 and h.tolist() == [[[-1, -1, 1, -1], [-1, -1, -1, 0]]]     # outline, hole
    if case == "nan_point":
        z["points"][0, 0] = np.nan
    elif case == "text_points":
        z["points"] = z["points"].astype(str)
    elif case == "float_hierarchy":
        z["hierarchy"] = z["hierarchy"].astype(float)
    else:
        z["hierarchy"][0, 2] = 7
    np.savez(tmp_path / "bad.npz", **z)
    with pytest.raises(ImageError, match="bad.npz: inconsistent contours file"):
        load_contours(tmp_path / "bad.npz", dtype=np.int32)


def test_run_stems_stay_inside_the_output_folder(tmp_path):
    """run_inputs(stems=...) wrote "../x" beside the output folder and let two inputs share a
    stem (one set overwrote the other)."""
    a, b = _xy(tmp_path / "a.xy", _circle()), _xy(tmp_path / "b.xy", _circle(r=2.0))
    for stems in (["../x", "b"], ["a/b", "b"], ["", "b"], [".", "b"], ["x", "x"], [3, "b"]):
        with pytest.raises(RunError, match="stems: "):
            run_inputs([a, b], CONFIG, tmp_path / "o", formats=["json"], stems=stems)
    assert not (tmp_path / "x.json").exists()
    rep = run_inputs([a, b], CONFIG, tmp_path / "o", formats=["json"], stems=["p", "q"])
    assert [r.status for r in rep.records] == ["done", "done"]
    assert sorted(os.listdir(tmp_path / "o")) == ["p.json", "p.manifest.json", "q.json", "q.manifest.json"]
