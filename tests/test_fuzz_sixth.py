"""Fuzzing, sixth round (issue 18, the session-15 fuzzing report): one fast regression test per
failure found, in the style of ``tests/test_fuzz_fifth.py``.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
``'d/**/*.xy'`` over a folder with a link to ``.``:     test_glob_walks_each_real_folder_once
each file once per level (82 inputs for 2); two such
links: 2^depth paths, the run hung
a FIFO or a dangling link in an input folder was       test_folder_fifo_and_dangling_link_fail_alone
skipped without a word
``a.xy`` with ``a.manifest.xy``, ``m.png`` with         test_output_names_never_shared,
``m.contours.xy``: one input's JSON overwrote the       test_cli_dotted_stems_keep_their_own_outputs
other's manifest or contours, exit 0
a point set given twice with a 1e-9 jitter: the        test_near_repeats_are_one_point,
spacings collapsed to the jitter, two loops or         test_set_given_twice_with_a_jitter
``converged`` with ``max_error`` inf
``find_contours(min_area=10**400)``, ``threshold=      test_huge_numbers_in_image_arguments
2**70``, ``read_image(max_pixels='x')``, ``rasterize``
of 2**40 rows: builtin TypeError / OverflowError or
an allocation
float8 points: a raw RuntimeError (no promotion)       test_float8_points
``reconstruct_batch`` of one (N, 2) tensor: "point     test_batch_of_one_array_is_named
set 0: expected (N, 2), got (2,)"
``--device hpu``: "internal error"                     test_device_without_backend_is_a_usage_error
``--sigma 1e-300``: kornia's "sigma must be positive,  test_sigma_below_float32
got tensor(...)" for every image
a timedelta64 ``.npy`` read as numbers; a negative     test_npy_durations_and_negative_shapes
shape in a header: "-48 bytes"
=====================================================  ==========================================
"""
from __future__ import annotations

import glob
import io
import os
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_isc
from torch_isc import cli
from torch_isc.core.points import NEAR_REPEAT, PointSetError, merge_near_repeats
from torch_isc.dataset import glob_files
from torch_isc.images import ImageError, find_contours, read_image
from torch_isc.runner import unique_stems


def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _circle(n: int = 40, r: float = 1.0) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[r * np.cos(t), r * np.sin(t)]


# ------------------------------------------------------------------ inputs
def test_glob_walks_each_real_folder_once(tmp_path, monkeypatch):
    """Against ``glob.glob`` on the same tree without the links (an independent route): the
    same files, each once, and no hang with two links to ``.`` (2^depth paths before)."""
    d = tmp_path / "d"
    (d / "sub").mkdir(parents=True)
    (d / ".hidden").mkdir()
    for f in ("a.xy", "sub/b.xy", ".hidden/h.xy", "sub/.c.xy", "sub/n.png"):
        (d / f).write_text("0 0\n")
    monkeypatch.chdir(tmp_path)
    ref = sorted(h for h in glob.glob("d/**/*.xy", recursive=True) if os.path.isfile(h))
    assert ref == ["d/a.xy", "d/sub/b.xy"]
    assert glob_files("d/**/*.xy") == ref
    assert glob_files(str(d) + "/**/.*.xy") == sorted(glob.glob(str(d) + "/**/.*.xy", recursive=True))
    (d / "loop1").symlink_to(".")
    (d / "sub" / "loop2").symlink_to("..")
    assert glob_files("d/**/*.xy") == ref
    # a link to a folder outside the pattern's root is followed, once
    other = tmp_path / "other"
    other.mkdir()
    (other / "o.xy").write_text("0 0\n")
    (d / "link").symlink_to(other)
    (other / "back").symlink_to(d)
    assert glob_files("d/**/*.xy") == sorted(ref + ["d/link/o.xy"])


def test_folder_fifo_and_dangling_link_fail_alone(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    np.savetxt(src / "a.xy", _circle())
    os.mkfifo(src / "f.xy")
    (src / "d.xy").symlink_to("nowhere.xy")
    code, out, err = _run(capsys, src, "--out", tmp_path / "o", "--formats", "json")
    assert code == 1
    assert (tmp_path / "o" / "a.json").is_file()
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert any("f.xy: not a regular file (a FIFO)" in ln for ln in lines), err
    assert any("d.xy: a dangling symbolic link (to 'nowhere.xy')" in ln for ln in lines), err
    assert "1 of 3 input(s) ok, 2 failed" in err


# ------------------------------------------------------------------ output names
FORMATS = ("json", "npz", "svg", "png", "contours.npz", "overlay.png", "manifest.json")


@pytest.mark.parametrize("sources", [
    ["a.xy", "a.manifest.xy", "m.png", "m.contours.xy"],
    ["x/a.b.c.xy", "a.b.xy", "a.xy", "y/a.xy", "a.b.png"],
    ["m.overlay.xy", "m.png", "m.xy"],
])
def test_output_names_never_shared(sources):
    """Every file name any format could give: disjoint between inputs, whatever their order."""
    names = unique_stems(sources)
    files = [{f"{s}.{f}" for f in FORMATS} for s in names]
    for i in range(len(files)):
        for j in range(i + 1, len(files)):
            assert not files[i] & files[j], (sources[i], sources[j], files[i] & files[j])
    back = unique_stems(sources[::-1])[::-1]
    assert back == names
    # an input without such a neighbour keeps its plain stem
    assert unique_stems(["a.manifest.xy", "b.xy"]) == ["a.manifest", "b"]


def test_cli_dotted_stems_keep_their_own_outputs(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    np.savetxt(src / "a.xy", _circle())
    np.savetxt(src / "a.manifest.xy", _circle(30, 3.0))
    out = tmp_path / "o"
    code, _, err = _run(capsys, src, "--out", out, "--formats", "json")
    assert code == 0, err
    assert "would share file names" in err
    man = __import__("json").loads((out / "a.manifest.json").read_text())
    assert "formats" in man and "polylines" not in man          # a's manifest, not the other's curve
    other = [p for p in out.glob("a.manifest_*.json") if not p.name.endswith(".manifest.json")]
    assert len(other) == 1
    code, so, err = _run(capsys, src, "--out", out, "--formats", "json")
    assert code == 0 and (so + err).count("skipped") == 2, so + err


# ------------------------------------------------------------------ near repeats
def _naive_cells(norm, item, radius, shift):
    """The first point of each (item, cell) of the grid offset by ``shift`` cells, by dict."""
    seen, keep = set(), []
    for i, (p, b) in enumerate(zip(norm.tolist(), item.tolist())):
        key = (b, int(np.floor(p[0] / radius + shift[0])), int(np.floor(p[1] / radius + shift[1])))
        if key not in seen:
            seen.add(key)
            keep.append(i)
    return keep


def test_near_repeats_are_one_point():
    """Against a per-point dict of grid cells (four grids, half a cell apart in x, y or both):
    the same points kept; every pair far below the radius merges, even across cell
    boundaries; points a few radii apart never merge, so a dense scan is thinned, not
    collapsed."""
    g = torch.Generator().manual_seed(0)
    base = torch.rand(300, 2, generator=g, dtype=torch.float64) - 0.5
    pts = torch.cat([base, base + 1e-3 * NEAR_REPEAT * torch.randn(300, 2, generator=g, dtype=torch.float64),
                     base[:50] + 3.0 * NEAR_REPEAT])
    # pairs across a cell's side, across a corner of the first grid, and across a corner of the others
    e = 1e-9 * NEAR_REPEAT
    edge = torch.tensor([[3 * NEAR_REPEAT - e, 0.1], [3 * NEAR_REPEAT + e, 0.1],
                         [-7 * NEAR_REPEAT - e, -5 * NEAR_REPEAT - e], [-7 * NEAR_REPEAT + e, -5 * NEAR_REPEAT + e],
                         [-6.5 * NEAR_REPEAT - e, 0.5 * NEAR_REPEAT + e], [-6.5 * NEAR_REPEAT + e, 0.5 * NEAR_REPEAT - e]],
                        dtype=torch.float64)
    pts = torch.cat([pts, edge])
    item = torch.zeros(pts.shape[0], dtype=torch.long)
    item[300:] = 0
    counts = torch.tensor([pts.shape[0]])
    norm, it, cnt, src = merge_near_repeats(pts, item, counts, torch.arange(pts.shape[0]), 1, ["s"])
    want = list(range(pts.shape[0]))
    for shift in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        want = [want[k] for k in _naive_cells(pts[want], item[want], NEAR_REPEAT, shift)]
    assert src.tolist() == want
    assert cnt.tolist() == [len(want)] == [300 + 50 + 3]
    assert torch.equal(norm, pts[want])
    # nothing to merge: the same tensors back
    n2, _, c2, s2 = merge_near_repeats(base, item[:300], torch.tensor([300]), torch.arange(300), 1, ["s"])
    assert n2 is base and c2.tolist() == [300]
    # all but two points within the radius of one of them
    tri = torch.tensor([[-0.5, 0.0], [0.5, 0.0], [0.5, 1e-9]], dtype=torch.float64)
    with pytest.raises(PointSetError, match="s: needs at least 3 distinct points, got 2"):
        merge_near_repeats(tri, torch.zeros(3, dtype=torch.long), torch.tensor([3]), torch.arange(3), 1, ["s"])


@pytest.mark.parametrize("jitter", [1e-9, 1e-7])
def test_set_given_twice_with_a_jitter(jitter):
    """A quarter arc given twice, the copy jittered far below the tolerance: the arc's own
    points (the copy merged) and one loop, not two loops or ``converged`` with points at an
    infinite distance. (The frame still moves by the jitter; how far the curve follows such a
    move is the stability question of ``tests/test_stability.py``.)"""
    t = np.linspace(0, np.pi / 2, 100)
    arc = np.c_[np.cos(t), np.sin(t)]
    rng = np.random.default_rng(0)
    twice = np.concatenate([arc, arc + jitter * rng.standard_normal(arc.shape)])
    from torch_isc.core.points import prepare_points

    pb = prepare_points([torch.tensor(twice)])
    assert pb.counts.tolist() == [100] and pb.source.tolist() == list(range(100))
    alone, both = torch_isc.reconstruct(arc), torch_isc.reconstruct(twice)
    assert both.num_components == alone.num_components == 1
    assert both.converged and np.isfinite(both.stats[-1].max_error)


# ------------------------------------------------------------------ API arguments
def test_huge_numbers_in_image_arguments():
    m = np.zeros((20, 20), np.uint8)
    m[5:15, 5:15] = 1
    for kw in ({"min_area": 10 ** 400}, {"epsilon": 10 ** 400}, {"min_area": -2 ** 70}):
        with pytest.raises(ImageError, match=f"{next(iter(kw))} must be a finite number >= 0"):
            find_contours(m, "tree", "simple", **kw)
    with pytest.raises(ImageError, match="threshold must be a finite number or None"):
        find_contours(m, "tree", "none", threshold=10 ** 400)
    # beyond the pixel type's range: every pixel on one side, as for any threshold there
    assert len(find_contours(m, "tree", "none", threshold=2 ** 70)[0]) == 0
    assert len(find_contours(m, "tree", "none", threshold=-2 ** 70)[0]) == 1
    assert len(find_contours(m, "tree", "none", threshold=2 ** 70 * 1.0 - 2 ** 70 + 0.5)[0]) == 1
    with pytest.raises(ImageError, match="max_pixels must be None or an integer >= 0"):
        read_image(Path(__file__), max_pixels="x")
    from torch_isc.core.render import MAX_RASTER_PIXELS, rasterize
    r = torch_isc.reconstruct(_circle())
    with pytest.raises(ValueError, match=f"about 10\\^12 x 3 x 1: more than {MAX_RASTER_PIXELS} pixels"):
        rasterize(r.curve, 2 ** 40, 3, 0.01)


def test_float8_points():
    p = torch.tensor(_circle(60, 3.0), dtype=torch.float32)
    for dt in (torch.float8_e4m3fn, torch.float8_e5m2):
        q = p.to(dt)
        a, b = torch_isc.reconstruct(q), torch_isc.reconstruct(q.float())
        assert a.num_components == b.num_components == 1
        assert torch.equal(a.curve.mesh.verts, b.curve.mesh.verts) and torch.equal(a.curve.values, b.curve.values)


def test_batch_of_one_array_is_named():
    with pytest.raises(PointSetError, match=r"point_sets: one \(50, 2\) array, not a sequence of point sets"):
        torch_isc.reconstruct_batch(torch.randn(50, 2))
    assert len(torch_isc.reconstruct_batch(torch.tensor(np.stack([_circle(), 2 * _circle()])))) == 2


# ------------------------------------------------------------------ CLI options and files
def test_device_without_backend_is_a_usage_error(tmp_path, capsys):
    f = tmp_path / "a.xy"
    np.savetxt(f, _circle())
    code, _, err = _run(capsys, f, "--out", tmp_path / "o", "--device", "hpu")
    assert code == 2 and err.startswith("torch-isc: error: --device hpu:") and "internal" not in err
    assert len(err.strip().splitlines()) == 1


def test_sigma_below_float32(tmp_path, capsys):
    import cv2
    from torch_isc.images import edge_points

    im = np.zeros((32, 32), np.uint8)
    im[8:24, 8:24] = 255
    f = tmp_path / "s.png"
    cv2.imwrite(str(f), im)
    code, _, err = _run(capsys, f, "--out", tmp_path / "o", "--mode", "edges", "--sigma", "1e-300")
    assert code == 2 and "--sigma must be in [0.001, 1000]" in err
    with pytest.raises(ImageError, match="sigma must be at least 0.001 pixels"):
        edge_points([im / 255.0], sigma=1e-300)
    assert edge_points([im / 255.0], sigma=1e-3)[0].shape[0] > 0


def test_npy_durations_and_negative_shapes(tmp_path, capsys):
    td = tmp_path / "td.npy"
    np.save(td, np.array([[1, 2], [3, 4], [5, 1]], dtype="m8[s]"))
    raw = io.BytesIO()
    np.save(raw, np.zeros((3, 2)))
    neg = tmp_path / "neg.npy"
    neg.write_bytes(raw.getvalue().replace(b"(3, 2)", b"(-3, 2)"))
    good = tmp_path / "good.npy"
    np.save(good, _circle())
    code, _, err = _run(capsys, td, neg, good, "--out", tmp_path / "o", "--formats", "json")
    assert code == 1 and (tmp_path / "o" / "good.json").is_file()
    assert "td.npy: expected a numeric (integer or float) array, got dtype timedelta64[s]" in err
    assert "neg.npy: unreadable .npy file (its header declares a negative shape (-3, 2))" in err


# ------------------------------------------------------------------ the seventh round (a second report)
def test_table_never_overwrites_config_manifest_or_outputs(tmp_path, capsys, monkeypatch):
    pytest.importorskip("pyarrow")
    monkeypatch.chdir(tmp_path)
    np.savetxt("a.xy", _circle())
    Path("cfg.yaml").write_text("max_level: 8\n")
    Path("l.txt").write_text("a.xy\n")
    cases = [(["a.xy", "--config", "cfg.yaml", "--table", "cfg.yaml"], "is the --config file"),
             (["--manifest", "l.txt", "--table", "l.txt"], "is a manifest of the run"),
             (["a.xy", "--formats", "json", "--table", "o/a.json"], "is an output file of the run (a.json)"),
             (["a.xy", "--formats", "json", "--table", "o/a.manifest.json"], "is an output file of the run")]
    for argv, msg in cases:
        code, _, err = _run(capsys, *argv, "--out", "o")
        assert code == 2 and msg in err and len(err.strip().splitlines()) == 1, err
    assert Path("cfg.yaml").read_text() == "max_level: 8\n" and Path("l.txt").read_text() == "a.xy\n"
    code, _, err = _run(capsys, "a.xy", "--formats", "json", "--out", "o", "--table", "o/t.parquet")
    assert code == 0 and Path("o/t.parquet").is_file() and Path("o/a.json").is_file()


def _ring_grid(k, per_ring, r=0.1):
    t = np.linspace(0, 2 * np.pi, per_ring, endpoint=False)
    ring = np.c_[r * np.cos(t), r * np.sin(t)]
    return np.concatenate([ring + [x, y] for x in range(k) for y in range(k)])


def _rings_found(r, k):
    centres = np.array([(x, y) for x in range(k) for y in range(k)], float)
    loops = [np.asarray(p["points"], float) for p in r.polylines]
    return sum(any(np.abs(np.hypot(*(q - c).T) - 0.1).max() < 0.05 for q in loops) for c in centres)


def test_a_grid_of_eight_point_rings():
    """100 rings of 8 points, 0.1 across and 1 apart, counted against each ring's own centre (an
    independent route). Session 23 found none (eight neighbours span a whole ring, read as noise
    of 80% of its radius) and said ``unresolved``; four neighbours read the noise, and the
    enclosure rule no longer rings the middle of four rings with their points. One such ring
    alone is resolved and converges."""
    r = torch_isc.reconstruct(_ring_grid(10, 8))
    assert _rings_found(r, 10) >= 92
    ok = torch_isc.reconstruct(_ring_grid(1, 16))
    assert ok.converged and ok.limit is None and ok.num_closed == 1


@pytest.mark.xfail(strict=True, reason="known: the corner rings of the grid merge in pairs and the result says converged")
def test_unresolved_components_do_not_converge():
    """The rings the grid loses (its four corner pairs, each joined into one loop) must not come
    with a converged result: nothing flags a loop that wraps two rings yet."""
    r = torch_isc.reconstruct(_ring_grid(10, 8))
    assert _rings_found(r, 10) == 100 or not r.converged


@pytest.mark.parametrize("scale", [1e-100, 1e30, 1e150])
def test_point_gradients_follow_the_scale(scale):
    """d(area)/d(points) of a circle scaled by s is s times that of the unit circle (area is
    homogeneous of degree 2): 4e35 times too small at 1e30 before, and an IndexError at 1e-200."""
    from torch_isc.core import measures

    base = torch.tensor(_circle(60), requires_grad=True)
    g1, = torch.autograd.grad(measures.area(torch_isc.reconstruct(base).curve).sum(), base)
    p = torch.tensor(_circle(60) * scale, requires_grad=True)
    gs, = torch.autograd.grad(measures.area(torch_isc.reconstruct(p).curve).sum(), p)
    assert torch.allclose(gs / scale, g1, rtol=1e-6, atol=1e-9 * float(g1.abs().max()))
    tiny = torch.tensor(_circle(60) * 1e-200, requires_grad=True)
    assert torch_isc.reconstruct(tiny).num_components == 1


def test_resource_bounds_of_the_second_report(tmp_path, capsys):
    from torch_isc import ConfigError, ReconstructConfig
    from torch_isc.core.mesh import hexagon_mesh
    from torch_isc.images.grid import trace_masks
    from torch_isc.runner import ImageOptions, RunError

    im = np.zeros((16, 16), np.uint8)
    im[4:12, 4:12] = 255
    import cv2
    cv2.imwrite(str(tmp_path / "m.png"), im)
    code, _, err = _run(capsys, tmp_path / "m.png", "--out", tmp_path / "o", "--no-oracle", "--spacing", "1e-3")
    assert code == 2 and "--spacing must be 0 (no resampling) or in [0.01, 1e6]" in err
    with pytest.raises(RunError, match="spacing must be 0"):
        ImageOptions(spacing=1e-4)
    with pytest.raises(ImageError, match="smooth must be an integer in \\[0, 10000\\]"):
        trace_masks([torch.tensor(im > 0)], smooth=10 ** 9)
    assert len(trace_masks([im > 0]).polylines) == 1                      # numpy masks are read
    with pytest.raises(ConfigError, match="max_triangles"):
        ReconstructConfig().replace(max_triangles=100_000_000)
    with pytest.raises(ValueError, match="6000000000000 triangles"):
        hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 10 ** 6)


def test_api_arguments_of_the_second_report(tmp_path):
    from torch_isc import ReconstructConfig
    from torch_isc.core.curve import InvalidValuesError
    from torch_isc.core.mesh import InvalidMeshError, MeshBatch
    from torch_isc.core.render import rasterize
    from torch_isc.runner import RunError, run_arguments, run_inputs

    r = torch_isc.reconstruct(_circle())
    with pytest.raises(InvalidValuesError, match="magnitudes must be a"):
        r.curve.rescale(0.5)
    with pytest.raises(ImageError, match="expected a path .* got bytes"):
        read_image(b"x.png")
    with pytest.raises(RunError, match="out_dir: expected a folder path"):
        run_inputs(["a.xy"], ReconstructConfig(), None)
    with pytest.raises(RunError, match="formats: no output format"):
        run_inputs(["a.xy"], ReconstructConfig(), tmp_path, formats=())
    # one order for one set of formats, repeats dropped: a rerun with "svg,json" skips
    assert run_arguments(["a"], "svg,json,svg", ["contours.npz", "json"], 1)[1:] == (["json", "svg"],
                                                                                      ["json", "contours.npz"])
    with pytest.raises(ValueError, match="extent must be finite"):
        rasterize(r.curve, 4, 4, 0.01, extent=[float("nan"), 0, 1, 1])
    with pytest.raises(ValueError, match="xmin < xmax"):
        rasterize(r.curve, 4, 4, 0.01, extent=[1, 0, 0, 1])
    v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(InvalidMeshError, match="integer vertex indices"):
        MeshBatch(v, torch.tensor([[0.0, 1.0, 2.0]]), torch.tensor([3]), torch.tensor([1]))
    with pytest.raises(InvalidMeshError, match="negative count"):
        MeshBatch(torch.cat([v, v]), torch.tensor([[0, 1, 2]]), torch.tensor([9, -3]), torch.tensor([1, 0]))


def test_rerun_with_formats_reordered_skips(tmp_path, capsys):
    f = tmp_path / "a.xy"
    np.savetxt(f, _circle())
    code, _, _ = _run(capsys, f, "--out", tmp_path / "o", "--formats", "json,svg")
    assert code == 0
    code, out, err = _run(capsys, f, "--out", tmp_path / "o", "--formats", "svg,json,json")
    assert code == 0 and "skipped" in out + err
