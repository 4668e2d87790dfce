"""Fuzzing round 12: what a report-only pass over the point-file loaders, the dataset runner and
its CLI found (each test fails on the commit before its fix)."""
from __future__ import annotations

import io

import cv2
import numpy as np
import pytest

from torch_isc import load_config
from torch_isc.cli import main
from torch_isc.io import PointFileError, read_points
from torch_isc.runner import RunError, expand_inputs, run_inputs

pa = pytest.importorskip("pyarrow")

CONFIG = load_config(overrides={"max_level": 3})


def _ring(path, r=1.0, n=90):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    np.savetxt(path, np.stack([r * np.cos(t), r * np.sin(t)], 1))


def _disc(path):
    m = np.zeros((30, 30), np.uint8)
    cv2.circle(m, (14, 14), 8, 255, -1)
    cv2.imwrite(str(path), m)


def test_a_rerun_does_not_read_its_own_outputs_as_inputs(tmp_path, capsys):
    # --out inside a globbed tree: every rerun read the previous drawings as masks (7 -> 22 -> 57
    # files), renamed the real inputs' stems and never resumed
    d = tmp_path / "in"
    d.mkdir()
    _disc(d / "m0.png")
    _ring(d / "p00.xy")
    args = ["reconstruct", str(d / "**" / "*.png"), str(d / "p00.xy"), "--out", str(d / "out"),
            "--formats", "json,png", "--set", "max_level=3"]
    assert main(args) == 0
    first = sorted(p.name for p in (d / "out").iterdir())
    assert main(args) == 0
    assert sorted(p.name for p in (d / "out").iterdir()) == first
    assert capsys.readouterr().out.count("skipped, outputs exist") == 2
    assert "m0.json" in first and "p00.png" in first


def test_the_output_folder_given_as_an_input_folder_is_refused(tmp_path, capsys):
    # --out equal to the input folder: the second run read p00.png (the drawing of p00.xy) as a
    # mask ("154 closed") and renamed the real input p00_xy
    _ring(tmp_path / "p00.xy")
    assert main(["reconstruct", str(tmp_path), "--out", str(tmp_path), "--formats", "json,png"]) == 2
    assert "is the output folder" in capsys.readouterr().err
    with pytest.raises(RunError, match="is the output folder"):
        expand_inputs([tmp_path], out_dir=tmp_path / ".")
    assert list(tmp_path.iterdir()) == [tmp_path / "p00.xy"]            # nothing written


def test_a_folder_in_a_manifest_stands_for_its_files_and_an_empty_one_fails_alone(tmp_path):
    # every input of the folder's batch failed: "3 stem(s) given for 10 input(s)"; an empty
    # folder failed them all too
    from torch_isc.dataset import reconstruct_dataset
    ds = tmp_path / "ds"
    ds.mkdir()
    _ring(ds / "p00.xy")
    _ring(ds / "p01.xy", r=2)
    (tmp_path / "empty").mkdir()
    (tmp_path / "q").mkdir()
    _ring(tmp_path / "q" / "p09.xy", r=3)
    man = tmp_path / "list.txt"
    man.write_text("ds\nempty\nq/p09.xy\n")
    rep = reconstruct_dataset([], tmp_path / "out", CONFIG, manifest=man, formats=["json"])
    status = [(r.stem, r.status) for r in rep.records]
    assert status == [("p00", "done"), ("p01", "done"), ("empty", "failed"), ("p09", "done")]
    assert "folder has no point or image file" in rep.records[2].error


@pytest.mark.parametrize("table", [False, True])
def test_a_manifest_line_is_read_once_with_or_without_a_table(tmp_path, capsys, table):
    # "p0[12].xy" in a manifest: "no such file" without --table, a glob of two files with it
    for k in range(3):
        _ring(tmp_path / f"p0{k}.xy", r=1 + k)
    man = tmp_path / "list.txt"
    man.write_text("p00.xy\np0[12].xy\n")
    args = ["reconstruct", "--manifest", str(man), "--out", str(tmp_path / "o"), "--formats", "json",
            "--set", "max_level=3"] + (["--table", str(tmp_path / "t.parquet")] if table else [])
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "p0[12].xy: no such file" in err and "1 of 2 input(s) ok" in err
    assert sorted(p.name for p in (tmp_path / "o").glob("*.json")) == ["p00.json", "p00.manifest.json"]


@pytest.mark.parametrize("row", ["1D2 2D-2", "0x1p0 0x1p1", "10% 20%", "1.0O 2.0O"])
def test_a_malformed_first_row_is_refused_not_dropped_as_a_header(tmp_path, row):
    # no token parsed as a float, so the row was blanked as a header: 3 points of 4, no word
    f = tmp_path / "a.xy"
    f.write_text(f"{row}\n0 0\n1 0\n0 1\n")
    with pytest.raises(PointFileError, match=r"a\.xy: line 1: non-numeric value"):
        read_points(f)
    f.write_text("x_coord, Y\n0 0\n1 0\n0 1\n")                    # a header of names still is one
    assert read_points(f).shape == (3, 2)


def test_a_batch_size_beyond_the_bound_or_with_an_underscore_is_refused(tmp_path, capsys):
    # 2**63 with --table: a raw OverflowError from Arrow ("internal error", exit 1); 4_0 read as 40
    for b in ("9223372036854775808", "4_0"):
        assert main(["reconstruct", "--example", "--out", str(tmp_path), "--batch-size", b,
                     "--table", str(tmp_path / "t.parquet")]) == 2
    err = capsys.readouterr().err
    assert "--batch-size must be in [1, 2147483648]" in err and "'4_0' (no _ in numbers)" in err
    with pytest.raises(RunError, match=r"batch size must be an integer in \[1, 2147483648\]"):
        run_inputs([], CONFIG, tmp_path, batch_size=2 ** 63)


def _npy_with_header(path, header: str, data: bytes = b""):
    h = header.encode("latin1")
    h += b" " * ((64 - (10 + len(h) + 1) % 64) % 64) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + len(h).to_bytes(2, "little") + h + data)


def test_an_npy_shape_of_booleans_is_a_point_file_error(tmp_path):
    # np.load raised a raw TypeError ("an integer is required") past the header check
    f = tmp_path / "b.npy"
    _npy_with_header(f, "{'descr': '<f8', 'fortran_order': False, 'shape': (True, 2), }", bytes(16))
    with pytest.raises(PointFileError, match=r"b\.npy: unreadable \.npy file \(its header declares a shape of non-integers"):
        read_points(f)


def test_longdouble_values_beyond_float64_are_named(tmp_path):
    if np.finfo(np.longdouble).max <= np.finfo(np.float64).max:
        pytest.skip("longdouble is float64 here")
    f = tmp_path / "ld.npy"
    buf = io.BytesIO()
    np.save(buf, np.array([[1, 2], [3, 4], [5, 6]], np.longdouble) * np.longdouble(10) ** 4000)
    f.write_bytes(buf.getvalue())
    with pytest.raises(PointFileError, match=r"ld\.npy: coordinates beyond the float64 range"):
        read_points(f)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_values_whose_differences_overflow_are_refused(dtype):
    # +-0.9 x the largest float: f_i - f_j overflowed, every crossing sat on a vertex and the
    # area came out 0.577 for 0.6495, the length 0, with finite gradients
    import torch
    from torch_isc import ImplicitCurve, InvalidValuesError, hexagon_mesh
    from torch_isc.core.measures import area, length
    dt = getattr(torch, dtype)
    m = hexagon_mesh(torch.zeros(1, 2, dtype=dt), torch.ones(1, dtype=dt), 3)
    sgn = torch.sign(m.verts.norm(dim=1) - 0.5)
    unit = ImplicitCurve(m, sgn)
    top = torch.finfo(dt).max
    ok = ImplicitCurve(m, sgn * (top / 4))                 # the largest accepted: the same curve
    assert torch.equal(area(ok), area(unit)) and torch.equal(length(ok), length(unit))
    # hand: the crossings are the midpoints between the rings 1/3 and 2/3, the regular hexagon of
    # circumradius 1/2: 3 sqrt(3) / 8
    assert float(area(unit)) == pytest.approx(3 * 3 ** 0.5 / 8, rel=1e-6)
    with pytest.raises(InvalidValuesError, match=r"value\(s\) beyond .*a quarter of the largest " + dtype):
        ImplicitCurve(m, sgn * (0.9 * top))


def test_stems_equal_up_to_case_or_normalization_clash():
    # Ring.xy and ring.xy kept the stems Ring and ring: one set of files on a case-insensitive
    # volume (macOS, Windows), redone by every rerun
    import unicodedata
    from torch_isc.runner import unique_stems
    a, b, c = unique_stems(["d1/Ring.xy", "d2/ring.xy", "d3/other.xy"])
    assert a.startswith("Ring_xy_") and b.startswith("ring_xy_") and a.lower() != b.lower() and c == "other"
    nfc, nfd = (unicodedata.normalize(f, "caf\u00e9") for f in ("NFC", "NFD"))
    s1, s2 = unique_stems([f"d1/{nfc}.xy", f"d2/{nfd}.xy"])
    assert unicodedata.normalize("NFC", s1).casefold() != unicodedata.normalize("NFC", s2).casefold()


def test_a_table_that_cannot_be_written_is_one_line(tmp_path, monkeypatch, capsys):
    # a full disk while writing the --table: "internal error (OSError ...)", exit 1
    import errno
    import pyarrow.parquet as pq
    _ring(tmp_path / "a.xy")

    def full(self, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(pq.ParquetWriter, "write_table", full)
    table = tmp_path / "t.parquet"
    assert main(["reconstruct", str(tmp_path / "a.xy"), "--out", str(tmp_path / "o"), "--table", str(table),
                 "--set", "max_level=3"]) == 2
    err = capsys.readouterr().err
    assert f"table {table}: cannot be written (No space left on device)" in err and "internal error" not in err
    assert not table.exists() and not list(tmp_path.glob(".t.parquet*"))        # no table, no temporary
    assert (tmp_path / "o" / "a.json").exists()                                  # the input's outputs stay


@pytest.mark.parametrize("dtype, big", [("float32", 1e25), ("float64", 1e200)])
def test_a_huge_step_is_clamped_to_the_same_move(dtype, big):
    # deform(clamp=True) returned t = 0 beyond 1e19 (float32) or 1e154 (float64): a^2 t overflowed
    import torch
    from torch_isc import ImplicitCurve, hexagon_mesh
    dt = getattr(torch, dtype)
    m = hexagon_mesh(torch.zeros(1, 2, dtype=dt), torch.ones(1, dtype=dt), 3)
    c = ImplicitCurve(m, m.verts.norm(dim=1) - 0.5)
    d = torch.randn(m.verts.shape[0], 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    moved, t1 = c.deform((m.verts.double() + d).to(dt), clamp=True)
    far, tb = c.deform((m.verts.double() + d * big).to(dt), clamp=True)
    assert 0 < float(t1) < 1 and float(tb) * big == pytest.approx(float(t1), rel=1e-3)
    assert bool((far.mesh.signed_areas() > 0).all())
    assert torch.allclose(far.mesh.verts, moved.mesh.verts, rtol=1e-3, atol=1e-4)
