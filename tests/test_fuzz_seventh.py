"""Fuzzing, seventh round (issue 18, the session-17 fuzzing report): one fast regression test per
failure found, in the style of ``tests/test_fuzz_sixth.py``.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
mask-mode curves (a band mesh): area 19 for a 100 px    test_band_curve_measures_count_the_holes,
square, its centre "outside", a hollow raster; the      test_band_curve_queries_and_raster,
same after an ``.npz`` round trip                       test_enclosed_survives_npz_and_checks
``grid_results([m, m, m], names=["a"])``: one result    test_mask_names_one_per_mask
a config field set after construction (max_level=-3):   test_config_changed_after_construction
``reconstruct`` returned None; 2.5 a TypeError
``rasterize`` with the default extent: gradients        test_rasterize_default_extent_gradients
ignoring the pixel grid's move with the vertices
``refit`` of an item without points moved its values    test_refit_item_without_points_kept
``refit`` with items -1, NaN floor, max_iter=-1, (N,3)  test_refit_and_point_gradient_arguments
points for ``attach_point_gradients``: silent
``ImplicitCurve.to(float16)``: values 0 or inf, no      test_curve_to_a_narrow_dtype
word; ``to(int64)`` accepted
``CHAIN_APPROX_SIMPLE`` int32 chains starting at        test_simple_int32_chains_are_cv2s
another point than cv2's (379 of 2,528)
float contours with repeated consecutive points         test_float_contours_no_repeated_points
``curvature(method="circle")``: NaN at coincident       test_circle_curvature_finite
zero-set points
``mask_to_points(spacing=1e-9)``: 1.5 TB asked; NaN     test_mask_spacing_bounded
a RuntimeError
a fractional ``offset`` with ``dtype=np.int32``: a      test_int32_offset_integers
collapsed chain
``--formats overlay.png`` on a point set: only a        test_overlay_for_points_is_said,
manifest, no word; ``contour_hierarchy`` of cv2's       test_hierarchy_of_cv2_contours,
(n, 1, 2) contours: IndexError; ``--set                 test_set_section_dot_key,
test.tolerance=...``: unknown key; a one-line JSON      test_one_line_of_words_is_named,
point file: "no data lines"; a read-only mask: a        test_read_only_mask_no_warning
torch UserWarning
--- second report ---
a file name that is not UTF-8 with ``--table``: the     test_non_utf8_file_name_written_with_table_and_svg
whole run lost (pyarrow); its SVG not written
an SVG title with control characters: not XML           test_svg_title_control_characters_well_formed
an integer Parquet manifest column: exit 134 about      test_parquet_manifest_of_numbers_always_exit_2
half the time, after the message
a manifest listing a folder: "done: 0 of 1 input(s)     test_manifest_folder_counts_its_inputs
ok, 1 failed" for 2 of 3
SVG (9 digits) and contours.npz (float32) merged the    test_far_offset_keeps_its_vertices_in_svg_and_contours
vertices of a small curve at a 1e7 offset
``--table res.csv`` got Parquet bytes; killed runs'     test_table_must_be_parquet_and_dead_temporaries_go
table temporaries piled up
a skipped mask's row: ``points_beyond_tolerance`` null  test_skipped_mask_row_matches_its_done_row
(0 when done)
``--mode edges --spacing 1000``: "no edges found        test_edges_coarse_spacing_is_named
... flat image?"
(an overlay wider than PNG allows, a region missing     tests/test_overlay_zoom.py
the image: the input's outputs lost)
--- third report (the new ``enclosed`` curves) ---
``inside`` / ``rasterize`` of a 512 px mask's curve:    test_band_curve_inside_every_pixel_of_a_noise_mask
minutes (a nearest-edge search per pixel); NaN points
inside
two pieces, the second all inside, or a plain piece     test_enclosed_refuses_mixed_regions
in an inside hole: accepted, areas wrong
an all-black mask's curve: IndexError on queries        test_all_black_mask_curve_queries
=====================================================  ==========================================
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

import torch_isc
from torch_isc import ImplicitCurve, ReconstructConfig, cli, hexagon_mesh, reconstruct, refit
from torch_isc.core.curve import InvalidValuesError
from torch_isc.core.render import rasterize
from torch_isc.images import ImageError, find_contours, grid_results, mask_to_points
from torch_isc.pipeline.config import ConfigError

cv2 = pytest.importorskip("cv2")
M = torch_isc.measures


def _shoelace(pl) -> float:
    p = pl["points"].double().numpy()
    return 0.5 * float((p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]).sum())


def _ring_with_island() -> np.ndarray:
    yy, xx = np.mgrid[:120, :120]
    d = np.hypot(xx - 60.3, yy - 59.6)
    m = (((d < 50) & (d > 26)) | (d < 12)).astype(np.uint8)
    m[3:9, 3:9] = 1                                   # a square by the corner
    return m


# ----------------------------------------------------------------------------- band curves
def test_band_curve_measures_count_the_holes():
    """The area of a mask-mode curve is the area its loops enclose (shoelace of the returned
    polylines, an independent route) and within the pixel count by a few crossings; the centroid
    is the mask's, by symmetry for a square and against pixel moments for the ring."""
    sq = np.zeros((12, 12), np.uint8)
    sq[1:11, 1:11] = 1
    r = grid_results([sq])[0]
    assert abs(float(M.area(r.curve)) - 100.0) < 0.5                   # was 19.06
    assert torch.allclose(M.centroid(r.curve), torch.tensor([[6.0, 6.0]], dtype=torch.float64), atol=1e-9)
    m = _ring_with_island()
    r = grid_results([m])[0]
    a = float(M.area(r.curve))
    assert abs(a - sum(_shoelace(p) for p in r.polylines)) < 1e-3
    assert abs(a - m.sum()) < 0.01 * m.sum()
    ys, xs = np.nonzero(m)
    want = torch.tensor([[xs.mean() + 0.5, ys.mean() + 0.5]], dtype=torch.float64)
    assert torch.allclose(M.centroid(r.curve), want, atol=0.05)
    # a batch: each item its own, the same as alone
    two = grid_results([sq, m])
    both = ImplicitCurve.cat([two[0].curve, two[1].curve])
    assert torch.allclose(M.area(both), torch.cat([M.area(two[0].curve), M.area(two[1].curve)]))


def test_band_curve_queries_and_raster():
    """``inside`` off the band mesh reads the mask; a rasterization at the pixel centres is the
    mask itself (was a hollow ring); ``__call__`` gives -inf in an inside hole."""
    m = _ring_with_island()
    c = grid_results([m])[0].curve
    rng = np.random.default_rng(0)
    q = rng.uniform(0, 120, (400, 2))
    cell = m[q[:, 1].astype(int), q[:, 0].astype(int)].astype(bool)
    centre = np.abs(q - (np.floor(q) + 0.5)).max(1) < 0.25          # well inside a pixel: its class
    got = c.inside(torch.as_tensor(q)).numpy()
    assert (got[centre] == cell[centre]).all()
    img = rasterize(c, 120, 120, 0.05, extent=[0, 0, 120, 120])[0] > 0.5
    assert (img.numpy() == m.astype(bool)).all()
    f = c(torch.tensor([[60.3, 59.6], [60.3, 20.0], [115.0, 115.0]], dtype=torch.float64))
    assert f[0] == -math.inf and f[1] == -math.inf and f[2] == math.inf
    local = torch_isc.core.render.soft_inside(c, torch.tensor([[60.3, 59.6]], dtype=torch.float64), 0.1, mode="local")
    assert float(local) == 1.0


def test_enclosed_survives_npz_and_checks(tmp_path):
    """``enclosed`` is saved and read back; a curve that cannot be one is refused."""
    from torch_isc.io import load_npz, save_npz
    m = _ring_with_island()
    c = grid_results([m])[0].curve
    save_npz(tmp_path / "r.npz", c)
    back, _ = load_npz(tmp_path / "r.npz")
    assert back.enclosed is not None and bool(back.enclosed.all())
    assert float(M.area(back)) == pytest.approx(float(M.area(c)), abs=1e-9)
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    with pytest.raises(InvalidValuesError, match="outermost boundary must be outside"):
        ImplicitCurve(hm, hm.verts.norm(dim=1) - 5.0, enclosed=True)   # all inside
    with pytest.raises(InvalidValuesError, match="boundary edge"):
        ImplicitCurve(hm, hm.verts[:, 0] + 0.1, enclosed=True)         # the boundary crosses the curve
    with pytest.raises(ValueError, match="enclosed"):
        ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5, enclosed=torch.ones(2, dtype=torch.bool))
    # the default is unchanged: off the mesh is outside
    c0 = ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5)
    assert c0.enclosed is None and not bool(c0.inside(torch.tensor([[3.0, 0.0]], dtype=torch.float64)))


def test_mask_names_one_per_mask():
    m = np.zeros((8, 8), np.uint8)
    m[2:6, 2:6] = 1
    with pytest.raises(ImageError, match="1 name"):
        grid_results([m, m, m], names=["a"])
    with pytest.raises(ImageError, match="1 name"):
        torch_isc.images.reconstruct_masks([m, m], names=["a"])
    assert [r.name for r in grid_results([m, m], names=["a", "b"])] == ["a", "b"]


# ----------------------------------------------------------------------------- config, autograd
def test_config_changed_after_construction():
    t = torch.linspace(0, 2 * math.pi, 61)[:-1]
    p = torch.stack([t.cos(), 0.6 * t.sin()], 1)
    for sec, key, val in (("limits", "max_level", -3), ("limits", "max_level", 2.5), ("test", "tolerance", math.nan),
                          ("run", "dtype", "float16"), ("mesh", "margin", -1.0)):
        cfg = ReconstructConfig()
        setattr(getattr(cfg, sec), key, val)
        with pytest.raises(ConfigError, match=f"'{key}'.*after the config was built"):
            reconstruct(p, config=cfg)
    for val in (None, {"tolerance": 0.1}, "test"):              # a whole section replaced (fuzz round 11)
        cfg = ReconstructConfig()
        cfg.test = val
        with pytest.raises(ConfigError, match=f"section 'test'.*got {type(val).__name__}.*after the config was built"):
            reconstruct(p, config=cfg)
    cfg = ReconstructConfig()
    cfg.limits.max_level = 3                                    # a valid change is used
    assert len(reconstruct(p, config=cfg).stats) <= 3


def test_rasterize_default_extent_gradients():
    """With the default extent (the mesh's box) the pixel grid moves with the vertices: the
    vertex gradient matches central differences (a generic mesh: no ties in the box)."""
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    v0 = hm.verts.norm(dim=1) - 0.5
    g = torch.Generator().manual_seed(0)
    x0 = hm.verts + 0.01 * torch.randn(hm.verts.shape, generator=g, dtype=torch.float64)

    def f(x):
        return rasterize(ImplicitCurve(hm.with_verts(x), v0, validate=False), 5, 5, 0.1).sum()

    x = x0.clone().requires_grad_()
    (grad,) = torch.autograd.grad(f(x), x)
    num = torch.zeros_like(x0)
    for i in range(x0.shape[0]):
        for j in range(2):
            e = torch.zeros_like(x0)
            e[i, j] = 1e-6
            num[i, j] = (f(x0 + e) - f(x0 - e)) / 2e-6
    assert (grad - num).abs().max() < 1e-6 * max(1.0, float(num.abs().max()))


def test_refit_item_without_points_kept():
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    c = ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5)
    assert torch.equal(refit(c, torch.zeros(0, 2, dtype=torch.float64)).values, c.values)
    off = torch.tensor([[5.0, 5.0], [6.0, 5.0]], dtype=torch.float64)           # all off the mesh
    assert torch.equal(refit(c, off).values, c.values)
    t = torch.arange(40, dtype=torch.float64) * (2 * math.pi / 40)
    pts = 0.55 * torch.stack([t.cos(), t.sin()], 1)
    two = refit(ImplicitCurve.cat([c, c]), pts, torch.zeros(40, dtype=torch.long))
    a = M.area(two)
    assert abs(float(a[0]) - math.pi * 0.55 ** 2) < 0.02 and float(a[1]) == pytest.approx(float(M.area(c)), abs=1e-12)


def test_refit_and_point_gradient_arguments():
    from torch_isc.core.points import PointSetError
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    c = ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5)
    pts = torch.zeros(40, 2, dtype=torch.float64)
    with pytest.raises(PointSetError, match="items must be in"):
        refit(ImplicitCurve.cat([c, c]), pts, torch.full((40,), -1))
    with pytest.raises(PointSetError, match="point_item"):
        refit(ImplicitCurve.cat([c, c]), pts, torch.zeros(40))
    with pytest.raises(PointSetError, match=r"\(N, 2\)"):
        refit(c, torch.zeros(5, 3, dtype=torch.float64))
    for kw, word in ((dict(floor=math.nan), "floor"), (dict(reg=math.nan), "reg"), (dict(rel_scale=0), "rel_scale"),
                     (dict(max_iter=-1), "max_iter"), (dict(max_iter=2.5), "max_iter")):
        with pytest.raises(ValueError, match=word):
            refit(c, pts, **kw)
    with pytest.raises(ValueError, match=r"point set 0: expected \(N, 2\)"):
        torch_isc.attach_point_gradients([c], [torch.zeros(6, 3, dtype=torch.float64, requires_grad=True)])


def test_curve_to_a_narrow_dtype():
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    for scale in (1e-9, 1e6):
        with pytest.raises(ValueError, match="float16 cannot hold"):
            ImplicitCurve(hm, (hm.verts.norm(dim=1) - 0.5) * scale).to(dtype=torch.float16)
    for dt in (torch.int64, torch.bool, "float16"):
        with pytest.raises(ValueError, match="real floating"):
            ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5).to(dtype=dt)
    c = ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5).to(dtype=torch.float16)
    assert c.values.dtype == torch.float16 and c.num_components().tolist() == [1]


def test_circle_curvature_finite():
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    v = hm.verts.norm(dim=1) - 0.5
    v[6] = -1e-100                                   # three coincident zero-set points
    k = M.curvature(ImplicitCurve(hm, v), method="circle")
    assert torch.isfinite(k).all()
    k_ref = M.curvature(ImplicitCurve(hm, hm.verts.norm(dim=1) - 0.5), method="circle")
    assert torch.isfinite(k_ref).all() and float(k_ref.mean()) > 0


# ----------------------------------------------------------------------------- contours
def _random_masks(n, seed=0):
    rng = np.random.default_rng(seed)
    out = [np.array([[1, 1], [1, 0]], np.uint8), np.ones((1, 5), np.uint8), np.ones((5, 1), np.uint8),
           np.ones((1, 1), np.uint8), np.eye(4, dtype=np.uint8)]
    for _ in range(n):
        h, w = rng.integers(1, 24, 2)
        out.append((rng.random((h, w)) < rng.uniform(0.1, 0.9)).astype(np.uint8))
    return out


def test_simple_int32_chains_are_cv2s():
    """CHAIN_APPROX_SIMPLE with int32: cv2's chains point for point, start included, and its
    hierarchy, in all four modes (a start point inside a straight run is dropped, as cv2 does)."""
    bad = []
    for i, m in enumerate(_random_masks(120)):
        for mode in (cv2.RETR_EXTERNAL, cv2.RETR_LIST, cv2.RETR_CCOMP, cv2.RETR_TREE):
            a, ha = cv2.findContours(m.copy(), mode, cv2.CHAIN_APPROX_SIMPLE)
            b, hb = find_contours(m, mode, cv2.CHAIN_APPROX_SIMPLE, dtype=np.int32)
            same = len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
            same &= (ha is None and hb is None) or np.array_equal(ha, hb)
            if not same:
                bad.append((i, mode))
    assert not bad


def test_float_contours_no_repeated_points():
    for m in _random_masks(60, seed=1):
        for c in find_contours(np.pad(m, 1))[0]:
            q = c.reshape(-1, 2)
            if len(q) > 1:
                assert not (q[1:] == q[:-1]).all(1).any()
                assert not (q[0] == q[-1]).all()


def test_int32_offset_integers():
    sq = np.zeros((6, 6), np.uint8)
    sq[1:4, 1:4] = 1
    with pytest.raises(ImageError, match="integers"):
        find_contours(sq, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE, offset=(0.5, 1.5), dtype=np.int32)
    a, _ = cv2.findContours(sq.copy(), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE, offset=(2, -1))
    b, _ = find_contours(sq, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE, offset=(2.0, -1), dtype=np.int32)
    assert np.array_equal(a[0], b[0])


def test_mask_spacing_bounded():
    from torch_isc.images.masks import MAX_RESAMPLED, resample_closed
    m = np.zeros((5, 5), np.uint8)
    m[1:4, 1:4] = 1
    for sp in (1e-9, 1e-7, math.nan, math.inf):
        with pytest.raises(ImageError, match="spacing"):
            mask_to_points([m], spacing=sp)
    assert mask_to_points([m], spacing=-1)[0].shape[0] == mask_to_points([m], spacing=0)[0].shape[0] > 0
    with pytest.raises(ValueError, match=f"more than {MAX_RESAMPLED}"):
        resample_closed(torch.tensor([[0.0, 0], [4, 0], [4, 4]]), torch.tensor([3]), 1e-9)


def test_hierarchy_of_cv2_contours():
    from torch_isc.images.contours import contour_hierarchy
    m = np.zeros((12, 12), np.uint8)
    m[1:11, 1:11] = 1
    m[3:8, 3:8] = 0
    m[4:6, 4:6] = 1
    c, h = cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
    assert contour_hierarchy(list(c), "tree").tolist() == h[0].tolist()
    with pytest.raises(ValueError, match=r"polys\[0\]"):
        contour_hierarchy([np.zeros((3, 3))])


def test_read_only_mask_no_warning():
    m = np.zeros((6, 6), np.uint8)
    m[1:4, 1:4] = 1
    m.setflags(write=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(find_contours(m)[0]) == 1


# ----------------------------------------------------------------------------- CLI
def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _circle_file(path):
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    np.savetxt(path, np.c_[np.cos(t), np.sin(t)])
    return path


def test_overlay_for_points_is_said(tmp_path, capsys):
    f = _circle_file(tmp_path / "c.xy")
    code, out, err = _run(capsys, f, "--out", tmp_path / "o", "--formats", "overlay.png")
    assert code == 0 and "overlay.png needs an image: point-set inputs get only the manifest" in err
    code, out, err = _run(capsys, f, "--out", tmp_path / "o2", "--formats", "overlay.png,json")
    assert code == 0 and "point-set inputs get json" in err and (tmp_path / "o2" / "c.json").exists()


def test_set_section_dot_key(tmp_path, capsys):
    from torch_isc.pipeline.config import from_dict, parse_overrides
    d = parse_overrides(["test.tolerance=0.01", "test.noise_factor=2", "max_level=4"])
    cfg = from_dict(d)
    assert cfg.test.tolerance == 0.01 and cfg.test.noise_factor == 2.0 and cfg.limits.max_level == 4
    f = _circle_file(tmp_path / "c.xy")
    code, _, err = _run(capsys, f, "--out", tmp_path / "o", "--set", "test.tolx=1")
    assert code == 2 and "unknown config key 'test.tolx'" in err
    code, _, err = _run(capsys, f, "--out", tmp_path / "o", "--set", "test.tolerance=0.01", "--set", "tolerance=0.02")
    assert code == 2 and "set twice" in err
    code, _, _ = _run(capsys, f, "--out", tmp_path / "o", "--set", "limits.max_level=3")
    assert code == 0


def test_one_line_of_words_is_named(tmp_path, capsys):
    f = tmp_path / "j.xy"
    f.write_text("[[0,0],[1,0],[0,1]]\n")
    code, _, err = _run(capsys, f, "--out", tmp_path / "o")
    assert code == 1 and "its one line '[[0,0],[1,0],[0,1]]' is not numbers" in err


# ----------------------------------------------------------------------------- second report
def test_non_utf8_file_name_written_with_table_and_svg(tmp_path, capsys):
    """A file name that is not UTF-8 (byte 0xff) beside a normal one, with ``--table``: before,
    pyarrow raised and the whole run was lost (nothing written), and the SVG writer failed."""
    import os
    import pyarrow.parquet as pq
    d = tmp_path / "d"
    d.mkdir()
    t = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    pts = np.c_[np.cos(t), np.sin(t)]
    bad = os.path.join(os.fsencode(str(d)), b"bad\xffbyte.xy")
    with open(bad, "wb") as fh:
        np.savetxt(fh, pts)
    np.savetxt(d / "ok.xy", pts)
    code, _, err = _run(capsys, d, "--out", tmp_path / "o", "--table", tmp_path / "o" / "t.parquet")
    assert code == 0, err
    names = sorted(p.name for p in (tmp_path / "o").iterdir())
    assert sum(n.endswith(".svg") for n in names) == 2 and sum(n.endswith(".manifest.json") for n in names) == 2
    rows = pq.read_table(tmp_path / "o" / "t.parquet", columns=["source", "status"]).to_pylist()
    assert [r["status"] for r in rows] == ["done", "done"] and any("\\udcff" in r["source"] for r in rows)


def test_svg_title_control_characters_well_formed():
    import xml.etree.ElementTree as ET
    from torch_isc.io.svg import svg_text
    t = torch.linspace(0, 2 * math.pi, 41)[:-1]
    r = reconstruct(torch.stack([t.cos(), t.sin()], 1).double())
    r.name = "a\x01b\x1bc\udcffd<e>"
    root = ET.fromstring(svg_text(r))
    title = root.find("{http://www.w3.org/2000/svg}title").text
    assert title == "a\\x01b\\x1bc\\udcffd<e>"


def test_parquet_manifest_of_numbers_always_exit_2(tmp_path):
    """A manifest column of integers: the one-line usage error and exit 2 every time (the read
    that started Arrow's threads made about half the runs abort with 134 after the message)."""
    import subprocess
    import sys
    import pyarrow as pa
    import pyarrow.parquet as pq
    pq.write_table(pa.table({"path": [1, 2]}), tmp_path / "ints.parquet")
    for _ in range(3):
        p = subprocess.run([sys.executable, "-m", "torch_isc", "reconstruct", "--manifest", str(tmp_path / "ints.parquet"),
                            "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120,
                           env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
        assert p.returncode == 2 and "holds int64, not paths" in p.stderr and "terminate" not in p.stderr


def test_manifest_folder_counts_its_inputs(tmp_path, capsys):
    d = tmp_path / "mf" / "d"
    d.mkdir(parents=True)
    _circle_file(d / "a.xy")
    _circle_file(d / "c.xy")
    (d / "b.xy").write_text("1 2\n")
    (tmp_path / "mf" / "list.txt").write_text("d\n")
    code, _, err = _run(capsys, "--manifest", tmp_path / "mf" / "list.txt", "--out", tmp_path / "o")
    assert code == 1 and "done: 2 of 3 input(s) ok, 1 failed" in err


def test_far_offset_keeps_its_vertices_in_svg_and_contours(tmp_path, capsys):
    """A curve 1e-2 across at an offset of 1e7: the SVG (9 digits) kept 6 distinct vertices and
    the contours file (float32) 2, of the JSON's 54."""
    import json
    import re
    from torch_isc.images import load_contours
    t = np.linspace(0, 6.283, 200, endpoint=False)
    f = tmp_path / "off.xy"
    np.savetxt(f, np.c_[1e7 + 1e-2 * np.cos(t), -3e6 + 1e-2 * np.sin(t)], fmt="%.12f")
    code, _, _ = _run(capsys, f, "--out", tmp_path / "o", "--formats", "json,svg,contours.npz")
    assert code == 0
    pts = np.asarray(json.loads((tmp_path / "o" / "off.json").read_text())["polylines"][0]["points"])
    n = len(np.unique(pts, axis=0))
    d = re.search(r'class="closed" d="([^"]+)"', (tmp_path / "o" / "off.svg").read_text()).group(1)
    xy = np.array([[float(a) for a in m.split(",")] for m in re.findall(r"[-0-9.e+]+,[-0-9.e+]+", d)])
    assert len(np.unique(xy, axis=0)) == n and np.allclose(np.unique(xy, axis=0), np.unique(pts, axis=0), atol=0, rtol=0)
    c, _ = load_contours(tmp_path / "o" / "off.contours.npz", dtype=np.float64)
    assert len(np.unique(c[0].reshape(-1, 2), axis=0)) == n


def test_table_must_be_parquet_and_dead_temporaries_go(tmp_path, capsys):
    f = _circle_file(tmp_path / "c.xy")
    code, _, err = _run(capsys, f, "--out", tmp_path / "o", "--table", tmp_path / "res.csv")
    assert code == 2 and "name it .parquet or .pq" in err and not (tmp_path / "res.csv").exists()
    stale = tmp_path / "o" / ".t.parquet.999999999.tmp"          # a pid no process has
    (tmp_path / "o").mkdir(exist_ok=True)
    stale.write_bytes(b"x")
    code, _, _ = _run(capsys, f, "--out", tmp_path / "o", "--table", tmp_path / "o" / "t.parquet")
    assert code == 0 and not stale.exists() and (tmp_path / "o" / "t.parquet").exists()


def test_skipped_mask_row_matches_its_done_row(tmp_path, capsys):
    import pyarrow.parquet as pq
    yy, xx = np.mgrid[:64, :64]
    cv2.imwrite(str(tmp_path / "disc.png"), ((np.hypot(xx - 32, yy - 32) < 20) * 255).astype(np.uint8))
    cols = ["num_closed", "converged", "limit", "points_beyond_tolerance"]
    rows = []
    for name in ("t1", "t2"):
        assert _run(capsys, tmp_path / "disc.png", "--out", tmp_path / "o", "--table", tmp_path / f"{name}.parquet")[0] == 0
        rows.append(pq.read_table(tmp_path / f"{name}.parquet", columns=["status"] + cols).to_pylist()[0])
    assert [r["status"] for r in rows] == ["done", "skipped"]
    assert {k: rows[0][k] for k in cols} == {k: rows[1][k] for k in cols}


def test_edges_coarse_spacing_is_named(tmp_path, capsys):
    yy, xx = np.mgrid[:64, :64]
    cv2.imwrite(str(tmp_path / "disc.png"), ((np.hypot(xx - 32, yy - 32) < 20) * 255).astype(np.uint8))
    code, _, err = _run(capsys, tmp_path / "disc.png", "--out", tmp_path / "o", "--mode", "edges", "--spacing", "1000")
    assert code == 1 and "--spacing 1000" in err and "too coarse" in err


# ----------------------------------------------------------------------------- third report (enclosed)
def test_band_curve_inside_every_pixel_of_a_noise_mask():
    """Holes signed by the parity of the inside loops, edges bucketed in bands: every pixel
    centre of a 128 px noise mask (thousands of loops) reads its class (the nearest-edge search
    this replaced took 17 s here, minutes at 256 px)."""
    rng = np.random.default_rng(0)
    m = (rng.random((128, 128)) < 0.5).astype(np.uint8)
    c = grid_results([m])[0].curve
    yy, xx = np.mgrid[:128, :128]
    q = torch.as_tensor(np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], 1))
    assert (c.inside(q).numpy().reshape(128, 128) == m.astype(bool)).all()
    assert bool(c(torch.tensor([[math.nan, math.nan]], dtype=torch.float64))[0] == math.inf)   # NaN: outside


def test_enclosed_refuses_mixed_regions():
    """A second, all-inside piece beside the first (its outer boundary inside), and a plain
    piece inside an inside hole: regions off the mesh bounded by loops of both signs."""
    from torch_isc.core.mesh import MeshBatch
    hm = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    n = hm.verts.shape[0]
    v = torch.cat([hm.verts, hm.verts + torch.tensor([5.0, 0.0], dtype=torch.float64)])
    f = torch.cat([hm.faces, hm.faces + n])
    two = MeshBatch(v, f, torch.tensor([2 * n]), torch.tensor([f.shape[0]]))
    vals = torch.cat([hm.verts.norm(dim=1) - 0.5, -torch.ones(n, dtype=torch.float64)])
    with pytest.raises(InvalidValuesError, match="a hole must take one sign"):
        ImplicitCurve(two, vals, enclosed=True)
    # a ring of inside pixels with an outside island in its hole passes (a band mesh)
    m = np.zeros((20, 20), np.uint8)
    m[2:18, 2:18] = 1
    m[6:14, 6:14] = 0
    m[9:11, 9:11] = 1
    c = grid_results([m])[0].curve
    ImplicitCurve(c.mesh, c.values, enclosed=True)
    assert abs(float(M.area(c)) - m.sum()) < 0.05 * m.sum()


def test_all_black_mask_curve_queries():
    c = grid_results([np.zeros((6, 9), np.uint8)])[0].curve
    q = torch.tensor([[1.0, 1.0]], dtype=torch.float64)
    assert not bool(c.inside(q)[0]) and float(c(q)[0]) == math.inf
    assert float(rasterize(c, 4, 4, 0.1, extent=[0, 0, 9, 6]).sum()) == 0.0 and float(M.area(c)[0]) == 0.0
