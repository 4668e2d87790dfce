"""Issue 18: inputs that crashed a whole run, unbounded work, lost or mixed results, silent wrong
answers and unclear messages. Every case gives a correct answer or one line naming the input
and the problem (the API: an exception of the library's own types), the other inputs of a run
are still written, and the exit status is the documented one (0 ok, 1 some inputs failed, 2
usage or config). Sizes are small: a .npy header stands for a huge array, a PNG header for a
decompression bomb.

====  ==================================================  =========================================
item  case                                                tests
====  ==================================================  =========================================
1     .npy header declaring 1.46 TiB among good inputs    test_huge_npy_header_*
1     folder without read permission                      test_unlistable_folder_*
1     --mode edges on 1x1, 1x2, 1x100 images              test_edges_mode_tiny_images
1     --config of random bytes                            test_config_file_bounds
1     decompression bomb, 50000x50000 PNG, --max-pixels   test_image_pixel_limit_*
2     billion-laughs YAML, big config, aliases in --set   test_config_file_bounds
2     max_triangles bounds the initial mesh               test_initial_mesh_checked_against_max_triangles
2     per-batch time bound (limits.max_seconds)           test_max_seconds_stops_items
3     names / sign_oracles of the wrong length            test_names_and_oracles_length
3     a.xy and a.npy in one run; a.npy later alone        test_stems_*, test_manifest_*
3     --overwrite failing while exporting; disk full      test_failed_export_leaves_no_complete_set
4     scale 1e-300 .. 1e300; overflow                     test_extreme_scales, test_too_large_*
4     tolerance below the working precision               test_tolerance_floor
5     seed >= 2**63, empty_weight 1e308, other bounds     test_config_upper_bounds
6     newline in a file name                              test_newline_in_file_name
6     dict config, meta and sparse tensors                test_api_boundary_types
6     multi-page TIFF, EXIF orientation                   test_multipage_tiff, test_exif_orientation
6     out of memory / unexpected errors while reading     test_read_errors_are_isolated
====  ==================================================  =========================================
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import struct
import time
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import torch_isc
from torch_isc import ConfigError, PointSetError, ReconstructConfig, cli, reconstruct, reconstruct_batch
from torch_isc.images import ImageError
from torch_isc.images.read import decode_image, image_header
from torch_isc.io import EXPORTERS, Exporter, PointFileError, export, load_npz, read_points
from torch_isc.pipeline.config import load_config, parse_overrides
from torch_isc.runner import ImageOptions, expand_inputs, manifest_path, run_inputs, unique_stems

FAST = ["--set", "max_level=3"]
CONFIG = load_config(overrides={"max_level": 3})


def _circle(n=80, r=1.0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[r * np.cos(t), r * np.sin(t)]


def _xy(path, pts):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, pts)
    return path


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _errors(err):
    return [ln for ln in err.splitlines() if ln.startswith("torch-isc: error:")]


def _outputs(d):
    return sorted(f for f in os.listdir(d) if not f.endswith(".manifest.json"))


def _npy_header_only(shape, descr="<f8", data=160):
    b = io.BytesIO()
    np.lib.format.write_array_header_1_0(b, {"descr": descr, "fortran_order": False, "shape": shape})
    return b.getvalue() + b"\0" * data


def _png_header_only(w, h):
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 1, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 1000)) + chunk(b"IEND", b""))


# ============================================================================ 1. crashes
def test_huge_npy_header_is_rejected_before_allocating(tmp_path):
    p = tmp_path / "huge.npy"
    p.write_bytes(_npy_header_only((100_000_000_000, 2)))
    assert p.stat().st_size < 300
    with pytest.raises(PointFileError) as ei:
        read_points(p)
    msg = str(ei.value)
    assert msg.startswith(str(p)) and "(100000000000, 2)" in msg and "1600000000000 bytes" in msg and "\n" not in msg
    p.write_bytes(_npy_header_only((10 ** 12, 3)))               # wrong shape: said before any allocation
    with pytest.raises(PointFileError, match=r"expected an array of shape \(N, 2\)"):
        read_points(p)


def test_huge_npy_header_among_good_inputs_cli(tmp_path, capsys):
    g1, g2 = _xy(tmp_path / "g1.xy", _circle()), _xy(tmp_path / "g2.xy", _circle(r=2))
    (tmp_path / "huge.npy").write_bytes(_npy_header_only((100_000_000_000, 2)))
    code, out, err = _run(capsys, "reconstruct", g1, tmp_path / "huge.npy", g2, "--out", tmp_path / "o",
                          "--formats", "json", *FAST)
    assert code == 1 and "Traceback" not in err
    assert len(_errors(err)) == 1 and "huge.npy" in _errors(err)[0]
    assert _outputs(tmp_path / "o") == ["g1.json", "g2.json"]


def test_unlistable_folder_is_one_failed_input(tmp_path, capsys, monkeypatch):
    """Run as root, permissions do not stop a listing: the PermissionError is simulated."""
    locked = tmp_path / "locked"
    locked.mkdir()
    _xy(locked / "inside.xy", _circle())
    good = _xy(tmp_path / "good.xy", _circle())
    real = Path.iterdir

    def iterdir(self):
        if self == locked:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(Path, "iterdir", iterdir)
    errors = {}
    assert expand_inputs([locked, good], errors) == [str(locked), str(good)]
    assert errors[str(locked)] == f"{locked}: cannot list the folder (Permission denied)"
    code, out, err = _run(capsys, "reconstruct", locked, good, "--out", tmp_path / "o", "--formats", "json", *FAST)
    assert code == 1 and "Traceback" not in err
    assert _errors(err) == [f"torch-isc: error: {locked}: cannot list the folder (Permission denied)"]
    assert _outputs(tmp_path / "o") == ["good.json"]


def test_edges_mode_tiny_images(tmp_path, capsys):
    d = tmp_path / "in"
    d.mkdir()
    for h, w in ((1, 1), (1, 2), (1, 100)):
        cv2.imwrite(str(d / f"tiny{h}x{w}.png"), np.full((h, w), 255, np.uint8))
    g = np.zeros((40, 40), np.uint8)
    cv2.circle(g, (20, 20), 10, 255, -1)
    cv2.imwrite(str(d / "disc.png"), g)
    code, out, err = _run(capsys, "reconstruct", d, "--mode", "edges", "--out", tmp_path / "o", "--formats", "json",
                          *FAST)
    assert code == 1 and "Traceback" not in err and "Padding" not in err
    lines = _errors(err)
    assert len(lines) == 3 and all("image too small for edges mode" in ln for ln in lines)
    assert "disc.json" in _outputs(tmp_path / "o")


def test_config_file_bounds(tmp_path, capsys):
    ex = ["reconstruct", "--example", "--out", tmp_path / "o", "--formats", "json"]
    rnd = tmp_path / "random.yaml"
    rnd.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    laughs = tmp_path / "laughs.yaml"
    laughs.write_text('a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
                      + "".join(f"{k}: &{k} [{','.join(['*' + p] * 9)}]\n" for p, k in zip("abcdefg", "bcdefgh"))
                      + "tolerance: [" + ",".join(["*h"] * 9) + "]\n")
    assert laughs.stat().st_size < 1000
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (1 << 20) + "\nmax_level: 2\n")
    for f, expect in ((rnd, "not a YAML text file"), (laughs, "YAML aliases"), (big, "larger than")):
        t0 = time.perf_counter()
        code, out, err = _run(capsys, *ex, "--config", f)
        assert code == 2 and "Traceback" not in err and time.perf_counter() - t0 < 5
        assert len(err.strip().splitlines()) == 1 and expect in err and str(f) in err
    with pytest.raises(ConfigError, match="aliases"):
        parse_overrides(["tolerance=[&a [1, 2], *a]"])
    # a wrong type's message never holds the repr of a large value
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as ei:
        load_config(overrides={"tolerance": [[0] * 1000] * 10000})
    assert time.perf_counter() - t0 < 1 and len(str(ei.value)) < 200 and "tolerance" in str(ei.value)


def test_image_pixel_limit_from_the_header(tmp_path, capsys):
    for w, h in ((32000, 32000), (50000, 50000)):
        data = _png_header_only(w, h)
        assert len(data) < 2000 and image_header(data).width == w
        with pytest.raises(ImageError) as ei:
            decode_image(data, "bomb.png")
        assert str(ei.value).startswith("bomb.png: image too large") and f"{w}x{h}" in str(ei.value)
    (tmp_path / "bomb.png").write_bytes(_png_header_only(32000, 32000))
    g = np.zeros((40, 40), np.uint8)
    cv2.circle(g, (20, 20), 10, 255, -1)
    cv2.imwrite(str(tmp_path / "disc.png"), g)
    args = ["reconstruct", tmp_path / "bomb.png", tmp_path / "disc.png", "--out", tmp_path / "o", "--formats",
            "json", *FAST]
    code, out, err = _run(capsys, *args)
    assert code == 1 and len(_errors(err)) == 1 and "image too large: 32000x32000" in err
    assert "disc.json" in _outputs(tmp_path / "o")
    # --max-pixels: a lower limit rejects the 40x40 disc too; 0 removes the limit
    code, out, err = _run(capsys, "reconstruct", tmp_path / "disc.png", "--out", tmp_path / "o2", "--max-pixels",
                          "1000", *FAST)
    assert code == 1 and "40x40 pixels" in err
    with pytest.raises(ImageError):        # and a limit of None lets a header through to the decoder
        decode_image(_png_header_only(32000, 32000)[:-20], "cut.png", max_pixels=None)


# ============================================================================ 2. bounded work
def test_initial_mesh_checked_against_max_triangles(tmp_path, capsys):
    with pytest.raises(ConfigError, match="'initial_resolution'.*540000 triangles"):
        ReconstructConfig().replace(initial_resolution=300)
    with pytest.raises(ConfigError, match="initial_resolution"):
        ReconstructConfig().replace(initial_resolution=1500)
    assert ReconstructConfig().replace(initial_mesh="square", initial_resolution=300).mesh.initial_resolution == 300
    with pytest.raises(ConfigError, match="initial_resolution"):
        ReconstructConfig().replace(initial_mesh="square", initial_resolution=317)   # 2 * 317**2 > 200000
    cfg = ReconstructConfig()
    cfg.mesh.initial_resolution = 1500                # changed after it was built: checked by the call too
    with pytest.raises(ConfigError, match="initial_resolution"):
        reconstruct(_circle(), cfg)
    code, out, err = _run(capsys, "reconstruct", "--example", "--out", tmp_path / "o", "--set",
                          "initial_resolution=1500")
    assert code == 2 and "initial_resolution" in err and not (tmp_path / "o").exists()


def test_max_seconds_stops_items():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1000, 2, generator=g, dtype=torch.float64)
    cfg = ReconstructConfig().replace(max_level=100, tolerance=0.0001, noise_factor=0.0, min_split_size=0.0,
                                      min_points_split=0, max_seconds=1e-6)
    t0 = time.perf_counter()
    r = reconstruct(pts, cfg)
    assert time.perf_counter() - t0 < 10
    assert r.limit == "max_seconds" and not r.converged and len(r.stats) == 1
    assert json.loads(json.dumps(r.to_json_dict()))["stats"]["limit"] == "max_seconds"
    # an item that converges before the bound is not marked
    r = reconstruct(_circle(200), ReconstructConfig().replace(max_seconds=1e6))
    assert r.limit is None and r.converged


# ============================================================================ 3. lost or mixed results
def test_names_and_oracles_length():
    a, b, c = _circle(), _circle(r=2), _circle(r=3)
    for names in (["first"], []):
        with pytest.raises(PointSetError, match="name"):
            reconstruct_batch([a, b, c], names=names)
    with pytest.raises(PointSetError, match="sign_oracles"):
        reconstruct_batch([a, b, c], sign_oracles=[lambda p: p[:, 0] > 0])


def test_stems_do_not_depend_on_input_order():
    a = ["d/a.xy", "d/a.npy", "e/a.xy", "b.csv"]
    names = unique_stems(a)
    assert names[1] == "a_npy" and names[3] == "b"
    assert names[0].startswith("a_xy_") and names[2].startswith("a_xy_") and names[0] != names[2]
    assert unique_stems(a[::-1]) == names[::-1]
    first = unique_stems(["x.xy", "x.xy"])[0]              # the same path twice: the repeat gets _2
    assert unique_stems(["x.xy", "x.xy"]) == [first, first + "_2"]


def test_manifest_ties_outputs_to_input_and_config(tmp_path, capsys):
    d = tmp_path / "in"
    _xy(d / "a.xy", _circle())
    np.save(d / "a.npy", _circle(r=2))
    o = tmp_path / "o"
    code, out, err = _run(capsys, "reconstruct", d / "a.npy", d / "a.xy", "--out", o, "--formats", "json,svg", *FAST)
    assert code == 0 and _outputs(o) == ["a_npy.json", "a_npy.svg", "a_xy.json", "a_xy.svg"]
    m = json.loads(manifest_path(o, "a_npy").read_text())
    assert m["input"]["sha256"] == hashlib.sha256((d / "a.npy").read_bytes()).hexdigest()
    assert m["formats"] == ["json", "svg"] and [f["name"] for f in m["files"]] == ["a_npy.json", "a_npy.svg"]
    assert all(f["sha256"] == hashlib.sha256((o / f["name"]).read_bytes()).hexdigest() for f in m["files"])
    # a.xy alone writes 'a'; a.npy alone afterwards is a different input: never skipped, and its
    # set is not replaced without --overwrite (fuzz 13: that lost a.xy's finished work silently)
    code, out, err = _run(capsys, "reconstruct", d / "a.xy", "--out", o, "--formats", "json", *FAST)
    assert code == 0 and "skipped" not in out
    code, out, err = _run(capsys, "reconstruct", d / "a.npy", "--out", o, "--formats", "json", *FAST)
    assert code != 0 and "skipped" not in out and "made from another input" in err
    code, out, err = _run(capsys, "reconstruct", d / "a.npy", "--out", o, "--formats", "json", "--overwrite", *FAST)
    assert code == 0 and "skipped" not in out
    w = json.loads((o / "a.json").read_text())["bbox"]
    assert w[2] - w[0] > 3                                    # a.npy's curve (radius 2)
    code, out, err = _run(capsys, "reconstruct", d / "a.npy", "--out", o, "--formats", "json", *FAST)
    assert "a: skipped" in out
    # another config: redone
    code, out, err = _run(capsys, "reconstruct", d / "a.npy", "--out", o, "--formats", "json", "--set", "max_level=2")
    assert code == 0 and "skipped" not in out


@pytest.mark.parametrize("failure", [RuntimeError("exporter bug"), OSError(28, "No space left on device")])
def test_failed_export_leaves_no_complete_set(tmp_path, capsys, monkeypatch, failure):
    f = _xy(tmp_path / "c.xy", _circle())
    o = tmp_path / "o"
    args = ["reconstruct", f, "--out", o, "--formats", "json,npz,svg", *FAST]
    assert _run(capsys, *args)[0] == 0
    real = EXPORTERS["svg"]

    def broken(result, fh, context):
        raise failure

    monkeypatch.setitem(EXPORTERS, "svg", Exporter(broken))
    code, out, err = _run(capsys, *args, "--overwrite")
    assert code == 1 and len(_errors(err)) == 1 and "c.xy" in err
    assert not manifest_path(o, "c").exists()
    assert not (o / "c.json").exists() and not (o / "c.npz").exists()      # this attempt's files removed
    monkeypatch.setitem(EXPORTERS, "svg", real)
    code, out, err = _run(capsys, *args)
    assert code == 0 and "skipped" not in out and _outputs(o) == ["c.json", "c.npz", "c.svg"]
    assert "c: skipped" in _run(capsys, *args)[1]


# ============================================================================ 4. scale, precision
@pytest.mark.parametrize("scale", [1e-300, 1e-170, 1e154, 1e300, 1e307])
def test_extreme_scales(tmp_path, scale):
    c = torch.as_tensor(_circle(100)) + torch.tensor([0.3, -0.2], dtype=torch.float64)
    ref = reconstruct(c)
    r = reconstruct(c * scale, name="x")
    assert (r.num_closed, r.num_open, r.limit) == (ref.num_closed, ref.num_open, ref.limit) == (1, 0, None)
    assert torch.isfinite(r.curve.mesh.verts).all() and torch.isfinite(r.curve.values).all()
    dev = (r.polylines[0]["points"] / scale - ref.polylines[0]["points"]).abs().max().item()
    assert dev < 1e-3                     # a few ulps of normalization may move a refinement decision (below tolerance)
    export(r, tmp_path / "x", ["json", "npz", "svg", "png"])
    curve, meta = load_npz(tmp_path / "x.npz")
    assert torch.equal(curve.mesh.verts, r.curve.mesh.verts)
    assert json.loads((tmp_path / "x.json").read_text())["num_components"] == 1


def test_too_large_coordinates_raise_point_set_error():
    c = torch.as_tensor(_circle(60))
    for s in (1e308, 1.7e308):
        with pytest.raises(PointSetError, match="^big: coordinates too large"):
            reconstruct(c * s, name="big")
    with pytest.raises(PointSetError, match="^f32: coordinates too large.*float32"):
        reconstruct((c * 1e38).float(), name="f32")


def test_tolerance_floor():
    c = torch.as_tensor(_circle(100))
    with pytest.warns(RuntimeWarning, match="circle: tolerance below what float32 resolves"):
        r = reconstruct(c, ReconstructConfig().replace(tolerance=1e-12), name="circle")
    assert r.num_closed == 1 and math.isfinite(r.stats[-1].max_error)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                 # float64 resolves 1e-12: no warning
        assert reconstruct(c, ReconstructConfig().replace(tolerance=1e-12, dtype="float64")).num_closed == 1


# ============================================================================ 5. config bounds
@pytest.mark.parametrize("key,value", [("seed", 2 ** 64 - 1), ("seed", 2 ** 63), ("empty_weight", 1e308),
                                       ("anneal_replicas", 10 ** 9), ("lbfgs_iterations", 10 ** 12),
                                       ("max_level", -1), ("max_triangles", 2 ** 70)])
def test_config_upper_bounds(tmp_path, capsys, key, value):
    with pytest.raises(ConfigError, match=f"config key '{key}'"):
        load_config(overrides={key: value})
    code, out, err = _run(capsys, "reconstruct", "--example", "--out", tmp_path / "o", "--set", f"{key}={value}")
    assert code == 2 and f"'{key}'" in err and len(err.strip().splitlines()) == 1
    assert load_config(overrides={"seed": 2 ** 63 - 1}).run.seed == 2 ** 63 - 1


# ============================================================================ 6. messages and types
def test_newline_in_file_name(tmp_path, capsys):
    bad = _xy(tmp_path / "new\nline.xy", _circle()[:2])
    good = _xy(tmp_path / "good.xy", _circle())
    code, out, err = _run(capsys, "reconstruct", bad, good, "--out", tmp_path / "o", "--formats", "json", *FAST)
    assert code == 1
    lines = _errors(err)
    assert len(lines) == 1 and "new\\nline.xy: needs at least 3 distinct points" in lines[0]


def test_api_boundary_types():
    c = _circle()
    assert reconstruct(c, config={"max_level": 2}).config.limits.max_level == 2
    with pytest.raises(ConfigError, match="unknown config key"):
        reconstruct(c, config={"max_levels": 2})
    with pytest.raises(ConfigError, match="expected a ReconstructConfig"):
        reconstruct(c, config=3)
    with pytest.raises(PointSetError, match="meta"):
        reconstruct(torch.empty(10, 2, device="meta"))
    with pytest.raises(PointSetError, match="dense"):
        reconstruct(torch.as_tensor(c).to_sparse())


def test_multipage_tiff(tmp_path, capsys):
    a = np.zeros((20, 30), np.uint8)
    a[5:15, 5:20] = 255
    ok, buf = cv2.imencodemulti(".tiff", [a, a, a])
    assert ok and image_header(buf.tobytes()).pages == 3
    (tmp_path / "multi.tif").write_bytes(buf.tobytes())
    with pytest.raises(ImageError, match=r"multi.tif: multi-page TIFF \(3 pages\)"):
        torch_isc.images.read_image(tmp_path / "multi.tif")


@pytest.mark.parametrize("fmt", ["JPEG", "PNG", "TIFF"])
def test_exif_orientation(fmt):
    from PIL import Image

    img = cv2.GaussianBlur((np.random.default_rng(0).random((24, 40)) * 255).astype(np.uint8), (5, 5), 2)
    for o in range(1, 9):
        b = io.BytesIO()
        ex = Image.Exif()
        ex[274] = o
        Image.fromarray(img).save(b, fmt, exif=ex.tobytes(), **({"quality": 95} if fmt == "JPEG" else {}))
        data = b.getvalue()
        mine = decode_image(data)
        viewer = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
        assert mine.shape == viewer.shape == ((24, 40) if o <= 4 else (40, 24))
        assert np.abs(mine - viewer).max() < 1e-6


def test_read_errors_are_isolated(tmp_path, monkeypatch):
    from torch_isc.io import registry

    g1, bad, g2 = _xy(tmp_path / "g1.xy", _circle()), _xy(tmp_path / "bad.xy", _circle()), _xy(tmp_path / "g2.xy", _circle())
    real = registry.read_points

    def load(path):
        if Path(path).name == "bad.xy":
            raise MemoryError()
        return real(path)

    monkeypatch.setitem(registry.LOADERS, ".xy", registry.Loader("points", load))
    rep = run_inputs([g1, bad, g2], CONFIG, tmp_path / "o", formats=["json"])
    assert [r.status for r in rep.records] == ["done", "failed", "done"]
    assert rep.records[1].error == f"{bad}: out of memory while reading it"


def test_interrupt_while_the_libraries_load_is_quiet(tmp_path):
    """Ctrl-C during the first second (torch still importing) ends with status 130 and one
    line, no traceback; the entry module itself imports no torch."""
    import signal
    import subprocess
    import sys
    import time
    code = "import sys, torch_isc.entry; print('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "False"
    # the interrupt is timed from inside the child, 0.2 s after the entry starts (torch takes a
    # second or more to import): a signal sent 0.2 s after the process starts could land, on a
    # loaded machine, in Python's own start-up (site's .pth hooks), before any code of ours runs
    child = ("import os, signal, sys, threading, torch_isc.entry as e\n"
             "sys.argv = ['torch-isc', 'reconstruct', '--example', '--out', sys.argv[1]]\n"
             "threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
             "sys.exit(e.main())\n")
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", child, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 130 and "Traceback" not in p.stderr and "interrupted" in p.stderr, p.stderr[-500:]
    assert time.perf_counter() - t0 < 60
