"""Failures found by fuzzing the inputs (``/tmp`` harnesses: hostile files, configs, API
arguments, reruns), one fast regression test each. Every case gives a correct answer or one
line naming the input and the problem; the other inputs of the run are still written; exit
status 0 ok, 1 some inputs failed, 2 usage or config.

====  ==================================================  =========================================
item  case (what happened before)                          tests
====  ==================================================  =========================================
1     a FIFO as input / config / manifest (hung forever)   test_fifo_*
1     /dev/zero as input or manifest (filled the memory)   test_character_device_*
2     an output would overwrite an input (m.png in --out   test_output_never_overwrites_an_input*
      with --formats png: the mask destroyed, a rerun
      then read the drawing as its input)
3     binary / fake Parquet / int-column manifests         test_bad_manifests_are_one_line
      (tracebacks)
3     --table a folder or an input (traceback after all    test_bad_table_is_a_usage_error
      the work / an input overwritten)
4     point sets and names as generators (TypeError,       test_api_sequences
      IndexError), names as a str (silently split)
4     a newline in a name (two-line message)               test_api_name_with_newline
4     an oracle not callable, raising, answering None      test_api_bad_oracles
      (TypeError, ZeroDivisionError, RuntimeError)
====  ==================================================  =========================================
"""
from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torch_isc import PointSetError, cli, reconstruct, reconstruct_batch
from torch_isc.dataset import read_manifest
from torch_isc.io import PointFileError, read_points
from torch_isc.pipeline.config import ConfigError, read_config_mapping
from torch_isc.pipeline.signs import SignOracleError
from torch_isc.runner import RunError

FAST = ["--set", "max_level=3", "--formats", "json"]
fifo_only = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs os.mkfifo")


def _circle(n=60, r=1.0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[r * np.cos(t), r * np.sin(t)]


def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _errors(err):
    return [ln for ln in err.splitlines() if ln.startswith("torch-isc: error:")]


def _sha(p):
    return hashlib.sha256(Path(p).read_bytes()).hexdigest()


def _bounded(fn, seconds=60):
    """Run ``fn`` in a thread; fail (instead of hanging the suite) when it does not return."""
    box = {}

    def target():
        try:
            box["r"] = fn()
        except BaseException as e:      # re-raised in the caller
            box["e"] = e

    th = threading.Thread(target=target, daemon=True)
    th.start()
    th.join(seconds)
    assert not th.is_alive(), "blocked"
    if "e" in box:
        raise box["e"]
    return box["r"]


# ============================================================================ 1. special files
@fifo_only
def test_fifo_input_config_manifest(tmp_path, capsys):
    np.savetxt(tmp_path / "ring.xy", _circle())
    fifo = tmp_path / "pipe.xy"
    os.mkfifo(fifo)
    with pytest.raises(PointFileError, match=r"pipe.xy: not a regular file \(a FIFO\)"):
        _bounded(lambda: read_points(fifo))
    code, out, err = _bounded(lambda: _run(capsys, tmp_path / "ring.xy", fifo, "--out", tmp_path / "o", *FAST))
    assert code == 1 and _errors(err) == [f"torch-isc: error: {fifo}: not a regular file (a FIFO), not a point file"]
    assert (tmp_path / "o" / "ring.json").exists()
    # a FIFO named like an input's manifest (the skip check hashes) does not block either
    code, out, err = _bounded(lambda: _run(capsys, tmp_path / "ring.xy", "--out", tmp_path / "o", *FAST))
    assert code == 0 and "skipped" in out
    with pytest.raises(ConfigError, match="not a regular file"):
        _bounded(lambda: read_config_mapping(fifo))
    with pytest.raises(RunError, match="not a regular file"):
        _bounded(lambda: read_manifest(fifo))
    code, out, err = _bounded(lambda: _run(capsys, "--manifest", fifo, "--out", tmp_path / "o", *FAST))
    assert code == 2 and len(_errors(err)) == 1 and "Traceback" not in err


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
def test_character_device_input_and_manifest(tmp_path, capsys):
    np.savetxt(tmp_path / "ring.xy", _circle())
    code, out, err = _bounded(lambda: _run(capsys, "/dev/zero", tmp_path / "ring.xy", "--out", tmp_path / "o", *FAST))
    assert code == 1 and _errors(err) == ["torch-isc: error: /dev/zero: not a regular file (a character device), "
                                          "not a point file"]
    assert (tmp_path / "o" / "ring.json").exists()
    code, out, err = _bounded(lambda: _run(capsys, "--manifest", "/dev/zero", "--out", tmp_path / "o", *FAST))
    assert code == 2 and _errors(err) == ["torch-isc: error: /dev/zero: not a regular file (a character device), "
                                          "not a manifest"]


def test_file_size_limit(tmp_path):
    from torch_isc._helpers import read_file_bytes
    p = tmp_path / "a.xy"
    p.write_bytes(b"1 2\n" * 10)
    assert read_file_bytes(p, PointFileError, "a point file", limit=40) == b"1 2\n" * 10
    with pytest.raises(PointFileError, match=r"a.xy: file larger than 39 bytes \(40 bytes\)"):
        read_file_bytes(p, PointFileError, "a point file", limit=39)


# ============================================================================ 2. outputs never overwrite inputs
def _mask_png(path):
    m = np.zeros((40, 40), np.uint8)
    cv2.circle(m, (20, 20), 10, 255, -1)
    cv2.imwrite(str(path), m)
    return path


@pytest.mark.parametrize("table", [False, True])
def test_output_never_overwrites_an_input(tmp_path, capsys, table):
    out = tmp_path / "o"
    out.mkdir()
    m = _mask_png(out / "m.png")
    before = _sha(m)
    np.savetxt(tmp_path / "ring.xy", _circle())
    extra = ["--table", tmp_path / "t.parquet", "--batch-size", "1"] if table else []
    code, stdout, err = _run(capsys, m, tmp_path / "ring.xy", "--out", out, "--formats", "json,png",
                             "--set", "max_level=3", *extra)
    assert code == 1 and _sha(m) == before            # the mask is intact
    assert _errors(err) == [f"torch-isc: error: {m}: its output {out / 'm.png'} would overwrite the input itself; "
                            f"choose another output folder or format"]
    assert (out / "ring.png").exists() and not (out / "m.json").exists()
    # a rerun gives the same answer (before, it read the drawing as its input)
    code2, _, err2 = _run(capsys, m, tmp_path / "ring.xy", "--out", out, "--formats", "json,png", "--set",
                          "max_level=3", *extra)
    assert code2 == 1 and _errors(err2) == _errors(err) and _sha(m) == before


def test_output_never_overwrites_another_input(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    np.savetxt(out / "a.xy", _circle())
    np.savetxt(out / "a.xy.json", _circle(r=2))       # stem "a.xy": its json output is this very file
    before = _sha(out / "a.xy.json")
    code, _, err = _run(capsys, out / "a.xy.json", "--out", out, *FAST)
    assert code == 1 and _sha(out / "a.xy.json") == before
    assert len(_errors(err)) == 1 and "would overwrite the input itself" in err
    # beside a.xy the stem "a.xy" is a's followed by a dot: renamed, so both are written
    code, _, err = _run(capsys, out / "a.xy", out / "a.xy.json", "--out", out, *FAST)
    assert code == 0 and _sha(out / "a.xy.json") == before and "would share file names" in err
    assert (out / "a.json").exists() and len(list(out.glob("a.xy_*.json"))) == 2     # its json and manifest


# ============================================================================ 3. manifests and table
def test_bad_manifests_are_one_line(tmp_path, capsys):
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    np.savetxt(tmp_path / "ring.xy", _circle())
    np.save(tmp_path / "bin.npy", _circle())
    (tmp_path / "bin.txt").write_bytes((tmp_path / "bin.npy").read_bytes())
    (tmp_path / "bin.csv").write_bytes((tmp_path / "bin.npy").read_bytes())
    (tmp_path / "fake.parquet").write_bytes((tmp_path / "bin.npy").read_bytes())
    pq.write_table(pa.table({"path": [1, 2]}), tmp_path / "ints.parquet")
    cases = {"bin.txt": "not a text manifest (byte 0 is not UTF-8)", "bin.csv": "not a CSV manifest (byte 0 is not UTF-8)",
             "fake.parquet": "not a readable Parquet manifest", "ints.parquet": "manifest column 'path' holds int64, not paths"}
    for name, msg in cases.items():
        with pytest.raises(RunError, match=msg.replace("(", r"\(").replace(")", r"\)")):
            read_manifest(tmp_path / name)
        code, out, err = _run(capsys, "--manifest", tmp_path / name, "--out", tmp_path / "o", *FAST)
        assert code == 2 and _errors(err) == [f"torch-isc: error: {tmp_path / name}: " + read_err(tmp_path / name)]
    # a .parquet given as an input is a manifest too
    code, out, err = _run(capsys, tmp_path / "fake.parquet", "--out", tmp_path / "o", *FAST)
    assert code == 2 and len(_errors(err)) == 1 and "Traceback" not in err
    # good ones still work: a dictionary-encoded column; a null entry is named, not skipped (fuzz 13)
    pq.write_table(pa.table({"path": pa.array(["ring.xy", "b.xy"]).dictionary_encode()}), tmp_path / "ok.parquet")
    assert read_manifest(tmp_path / "ok.parquet") == [str(tmp_path / "ring.xy"), str(tmp_path / "b.xy")]
    pq.write_table(pa.table({"path": pa.array(["ring.xy", None]).dictionary_encode()}), tmp_path / "null.parquet")
    with pytest.raises(RunError, match="row 2 of manifest column 'path' is null"):
        read_manifest(tmp_path / "null.parquet")


def read_err(p):
    try:
        read_manifest(p)
    except RunError as e:
        return str(e).split(": ", 1)[1]
    raise AssertionError("no error")


def test_bad_table_is_a_usage_error(tmp_path, capsys):
    pytest.importorskip("pyarrow")
    np.savetxt(tmp_path / "ring.xy", _circle())
    (tmp_path / "tdir").mkdir()
    code, out, err = _run(capsys, tmp_path / "ring.xy", "--out", tmp_path / "o", "--table", tmp_path / "tdir", *FAST)
    assert code == 2 and _errors(err) == [f"torch-isc: error: table {tmp_path / 'tdir'}: is a folder, not a file"]
    before = _sha(tmp_path / "ring.xy")
    code, out, err = _run(capsys, tmp_path / "ring.xy", "--out", tmp_path / "o", "--table", tmp_path / "ring.xy", *FAST)
    assert code == 2 and "is an input of the run" in err and _sha(tmp_path / "ring.xy") == before
    assert not (tmp_path / "o" / "ring.json").exists()          # checked before any work


# ============================================================================ 4. API arguments
def test_api_sequences():
    a, b = torch.tensor(_circle(), dtype=torch.float32), torch.tensor(_circle(r=2), dtype=torch.float32)
    cfg = {"max_level": 3}
    ref = reconstruct_batch([a, b], cfg, names=["a", "b"])
    got = reconstruct_batch((p for p in (a, b)), cfg, names=(n for n in "ab"))
    assert [r.name for r in got] == ["a", "b"]
    for r, g in zip(ref, got):
        assert torch.equal(r.curve.values, g.curve.values)
    with pytest.raises(PointSetError, match="names: expected a sequence, got str"):
        reconstruct_batch([a, b], cfg, names="ab")
    with pytest.raises(PointSetError, match="point_sets: expected a sequence, got int"):
        reconstruct_batch(3, cfg)


def test_api_name_with_newline():
    with pytest.raises(PointSetError) as ei:
        reconstruct_batch([torch.zeros(1, 2)], names=["b\nc"])
    assert str(ei.value) == "b\\nc: needs at least 3 distinct points, got 1"
    with pytest.raises(PointSetError) as ei:
        reconstruct(torch.zeros(1, 2), name="x" * 1000)
    assert len(str(ei.value)) < 300


def test_api_bad_oracles():
    pts = torch.tensor(_circle(), dtype=torch.float32)
    with pytest.raises(PointSetError, match=r"sign_oracles\[0\]: expected a callable or None, got int"):
        reconstruct_batch([pts], sign_oracles=[3])
    with pytest.raises(SignOracleError, match="item 0: sign oracle raised ZeroDivisionError: division by zero") as ei:
        reconstruct(pts, sign_oracle=lambda p: 1 / 0)
    assert isinstance(ei.value.__cause__, ZeroDivisionError)           # the user's error is kept
    with pytest.raises(SignOracleError, match="item 0: sign oracle returned NoneType, not an array of booleans"):
        reconstruct(pts, sign_oracle=lambda p: None)
    with pytest.raises(SignOracleError, match="sign oracle raised KeyError"):
        reconstruct_batch([pts], sign_oracles=lambda p, item: {}[0])
    # a numpy answer is fine: the inside of the unit circle
    res = reconstruct(pts, {"max_level": 3}, sign_oracle=lambda p: (p.norm(dim=1) < 1).numpy())
    assert res.num_closed == 1


# ============================================================================ 5. options at the boundary
def test_image_options_checked_at_the_boundary(tmp_path, capsys):
    from torch_isc.runner import ImageOptions

    for kw, key in (({"spacing": float("inf")}, "spacing"), ({"spacing": float("nan")}, "spacing"),
                    ({"mode": "x"}, "mode"), ({"threshold": 1.5}, "threshold"), ({"canny": (0.2, 0.1)}, "canny"),
                    ({"canny": (0.1, float("inf"))}, "canny"), ({"sigma": 0}, "sigma"), ({"zoom": 0}, "zoom"),
                    ({"connectivity": 6}, "connectivity"), ({"max_pixels": -1}, "max_pixels"),
                    ({"region": (0, 0, 1)}, "region"), ({"use_oracle": "no"}, "use_oracle")):
        with pytest.raises(RunError, match=f"image options: {key} "):
            ImageOptions(**kw)
    ImageOptions(spacing=0, threshold=0.0, canny=(0.1, 0.9), max_pixels=None, connectivity=4, zoom=64)
    m = _mask_png(tmp_path / "m.png")
    for argv, msg in ((["--mode", "edges", "--spacing", "inf"], "--spacing must be 0 (no resampling) or in [0.01, 1e6] pixels, got inf"),
                      (["--canny", "0.1,inf"], "--canny: expected 0 < LOW < HIGH, got '0.1,inf'"),
                      (["--device", "meta"], "--device meta: a meta device holds no values"),
                      (["--cpus-per-actor", "nan"], "--cpus-per-actor must be > 0 and below 1e6, got nan")):
        code, out, err = _run(capsys, m, "--out", tmp_path / "o", *argv)
        assert code == 2 and _errors(err) == [f"torch-isc: error: {msg}"], err


def test_internal_error_is_one_line(tmp_path, capsys, monkeypatch):
    import torch_isc.runner

    np.savetxt(tmp_path / "ring.xy", _circle())

    def boom(*a, **k):
        raise KeyError("surprise")

    monkeypatch.setattr(cli, "run_inputs", boom)
    code, out, err = _run(capsys, tmp_path / "ring.xy", "--out", tmp_path / "o")
    assert code == 1 and err.splitlines() == ["torch-isc: error: internal error (KeyError: 'surprise'); "
                                              "--debug shows the traceback"]
    with pytest.raises(KeyError):
        _run(capsys, tmp_path / "ring.xy", "--out", tmp_path / "o", "--debug")


# ============================================================================ 6. far ends of float64
@pytest.mark.parametrize("k", [1.0, 1e300, -1e300, 1e-300, 1e-320])
def test_nesting_at_extreme_magnitudes(k):
    import warnings
    from torch_isc.core.nesting import polygons_with_holes, signed_area

    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    c = np.c_[np.cos(t), np.sin(t)]
    outer, hole = c * k, (0.5 * c)[::-1] * k
    with warnings.catch_warnings():
        warnings.simplefilter("error")            # no overflow warning on stderr
        assert signed_area(outer) > 0 and signed_area(hole) < 0       # the sign survives overflow/underflow
        got = polygons_with_holes([outer, hole])
    assert got == [(0, [1])]                       # one exterior (0) with its hole (1)


# ============================================================================ 7. curve and contour files
def _zip(members):
    import io
    import zipfile

    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED) as z:
        for k, v in members.items():
            z.writestr(k, v)
    return b.getvalue()


def _npy_bytes(a=None, header_shape=None):
    import io

    b = io.BytesIO()
    if header_shape is not None:        # a header alone, declaring a huge array
        np.lib.format.write_array_header_1_0(b, {"descr": "<f8", "fortran_order": False, "shape": header_shape})
        return b.getvalue() + b"\0" * 64
    np.save(b, a)
    return b.getvalue()


def test_contours_and_curve_files_fail_in_one_line(tmp_path):
    from torch_isc.images import ImageError
    from torch_isc.io import CurveFileError, load_contours, load_npz

    good = {"points.npy": _npy_bytes(np.zeros((4, 2), np.float32)), "counts.npy": _npy_bytes(np.array([4])),
            "hierarchy.npy": _npy_bytes(np.array([[-1, -1, -1, -1]], np.int32))}
    (tmp_path / "ok.npz").write_bytes(_zip(good))
    c, h = load_contours(tmp_path / "ok.npz")
    assert len(c) == 1 and c[0].shape == (4, 1, 2) and h.shape == (1, 1, 4)
    bad = {"empty": b"", "text": b"hello", "npy": _npy_bytes(np.zeros(3)),
           "no_points": _zip({k: v for k, v in good.items() if k != "points.npy"}),
           "counts_lie": _zip({**good, "counts.npy": _npy_bytes(np.array([7]))}),
           "huge_header": _zip({**good, "points.npy": _npy_bytes(header_shape=(10 ** 12, 2))})}
    for name, data in bad.items():
        p = tmp_path / f"{name}.npz"
        p.write_bytes(data)
        with pytest.raises(ImageError) as ei:           # before: EOFError, pickle ValueError, KeyError, MemoryError
            load_contours(p)
        assert str(ei.value).startswith(f"{p}: ") and "\n" not in str(ei.value)
        with pytest.raises(CurveFileError) as ei:
            load_npz(p)
        assert str(ei.value).startswith(f"{p}: ") and "\n" not in str(ei.value)
    with pytest.raises(ImageError, match="truncated"):
        load_contours(tmp_path / "huge_header.npz")


def test_npz_decompressed_size_is_bounded(tmp_path):
    from torch_isc._helpers import load_npz_arrays

    p = tmp_path / "bomb.npz"
    p.write_bytes(_zip({"a.npy": _npy_bytes(np.zeros(1_000_000))}))        # 8 MB of zeros in ~8 KB
    assert p.stat().st_size < 100_000
    assert load_npz_arrays(p, ValueError)["a"].shape == (1_000_000,)
    with pytest.raises(ValueError, match="decompress to 8000128 bytes, more than 1000000"):
        load_npz_arrays(p, ValueError, limit=1_000_000)


# ============================================================================ 8. text separators
def test_semicolon_separated_rows(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("x;y\n1.5;2.5\n-3 ; 4e1\n")       # before: the first row taken for a header, then line 3 refused
    assert read_points(p).tolist() == [[1.5, 2.5], [-3.0, 40.0]]
    p.write_text("1,5;2,5\n")                     # decimal commas: four fields, refused with the line
    with pytest.raises(PointFileError, match="line 1: expected 2 columns"):
        read_points(p)
    p.write_text("1;;2\n")
    with pytest.raises(PointFileError, match="line 1: empty field"):
        read_points(p)


# ============================================================================ 9. run arguments
def test_run_arguments(tmp_path):
    from torch_isc.dataset import reconstruct_dataset
    from torch_isc.runner import ImageOptions, run_inputs

    np.savetxt(tmp_path / "ring.xy", _circle())
    # one path is one input (before: its characters were the inputs, each "no such file")
    rep = run_inputs(str(tmp_path / "ring.xy"), {"max_level": 3}, tmp_path / "o", formats="json",
                     batch_size=np.int64(2))
    assert [(r.stem, r.status) for r in rep.records] == [("ring", "done")]
    assert sorted(os.listdir(tmp_path / "o")) == ["ring.json", "ring.manifest.json"]
    for kw, msg in (({"batch_size": 1.5}, r"batch size must be an integer in \[1, 2147483648\], got 1.5"),
                    ({"batch_size": True}, r"batch size must be an integer in \[1, 2147483648\], got True"),
                    ({"device": "meta"}, "device meta: a meta device holds no values"),
                    ({"image_options": {}}, "image_options: expected an ImageOptions, got dict"),
                    ({"formats": [1]}, "formats: expected format names")):
        with pytest.raises(RunError, match=msg):
            run_inputs([tmp_path / "ring.xy"], None, tmp_path / "o", **kw)
    with pytest.raises(ConfigError, match="got int"):
        run_inputs([tmp_path / "ring.xy"], 5, tmp_path / "o")
    if __import__("importlib").util.find_spec("pyarrow") is not None:
        rep = reconstruct_dataset(tmp_path / "ring.xy", tmp_path / "o", {"max_level": 3}, formats="json")
        assert rep.counts == {"done": 0, "skipped": 1, "failed": 0}
        with pytest.raises(RunError, match="table_rows must be an integer >= 1, got 0"):
            reconstruct_dataset([tmp_path / "ring.xy"], tmp_path / "o", table=tmp_path / "t.parquet", table_rows=0)


# ============================================================================ 10. find_contours arguments
def test_find_contours_arguments():
    from torch_isc.images import ImageError, find_contours

    m = np.zeros((20, 20), np.uint8)
    m[5:15, 5:15] = 1
    ref, _ = find_contours(m)
    # unsigned types torch cannot compare, big-endian: the same square (before: NotImplementedError)
    for a in (m.astype(np.uint16) * 60000, m.astype(np.uint32) * 4_000_000_000, m.astype(np.uint64) * (2 ** 64 - 1),
              m.astype(">u2"), torch.from_numpy(m.astype(np.int32)).to(torch.uint16)):
        got, _ = find_contours(a)
        assert len(got) == 1 and np.array_equal(got[0], ref[0])
    bad = {"NaN values": lambda: find_contours(np.where(m, np.nan, 0.0)),          # before: silently no contour
           "got dtype object": lambda: find_contours(np.array([[None, 1]])),       # before: TypeError
           "got dtype complex64": lambda: find_contours(m.astype(np.complex64)),
           "offset must be": lambda: find_contours(m, offset=(np.nan, 0)),          # before: NaN contours
           "smooth must be an integer in": lambda: find_contours(m, smooth=10 ** 12),   # before: never ended
           "min_area must be": lambda: find_contours(m, min_area=float("nan")),
           "threshold must be a finite number": lambda: find_contours(m, threshold=float("nan")),
           "dtype must be": lambda: find_contours(m, dtype=np.complex64)}
    for msg, call in bad.items():
        with pytest.raises(ImageError, match=msg):
            call()
