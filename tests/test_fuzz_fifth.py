"""Fuzzing, fifth round (issue 18, robust21): one fast regression test per failure found, in
the style of ``tests/test_fuzz_fourth.py``.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
Arabic-Indic / full-width digits: ``--set tolerance=   test_non_ascii_digits_in_config,
٠.٠١`` and ``.xy`` rows read as numbers, ``max_level=  test_non_ascii_digits_in_point_files,
٣`` refused ("expected int"), ``--seed ３`` read        test_non_ascii_digits_in_options
empty option values: ``--out ''`` wrote into the       test_empty_option_values
working folder; ``--config ''`` "Is a directory"
a .npy with bytes after its data was read silently     test_npy_trailing_bytes
the --table temporary file stayed after SIGTERM or a   test_table_temporary_removed_when_close_fails,
failing last write                                     test_sigterm_is_an_interrupt
SIGTERM killed the run (no clean-up, no line)          test_sigterm_is_an_interrupt
ImplicitCurve(float32 mesh, float64 values): raw       test_implicit_curve_mixed_dtypes
``index_add_`` RuntimeError in measures
images: ``config={"max_level": 2}`` dropped the pixel  test_image_config_mapping,
settings (tolerance 0.004 of the diagonal);            test_image_inf_and_tiny_edges
``image_config(dict)`` AttributeError; Inf pixels read
as foreground; a 1x100 image in edges mode: kornia's
padding RuntimeError; ``sigma=inf`` OverflowError
YAML duplicate keys kept the last; ``tolerance: 1:30`` test_yaml_duplicate_keys,
read as 90; a key set flat and in its section; a 1 MiB test_yaml_base60_numbers,
list of numbers parsed for 37 s; ``max_level: 010``    test_key_set_twice, test_yaml_node_limit,
read as 8 (YAML 1.1 octal)                             test_yaml_octal_numbers
=====================================================  ==========================================
"""
from __future__ import annotations

import io
import math
import os
import signal
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_isc import ConfigError, ReconstructConfig, cli
from torch_isc.io.errors import PointFileError
from torch_isc.pipeline.config import MAX_CONFIG_NODES, load_config, parse_overrides, read_config_mapping


def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _circle_file(path: Path, n: int = 40) -> Path:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    np.savetxt(path, np.c_[np.cos(t), np.sin(t)])
    return path


# ------------------------------------------------------------------ non-ASCII digits
@pytest.mark.parametrize("value", ["٠.٠١", "０.０１", "۰.۰۱"])
def test_non_ascii_digits_in_config(tmp_path, capsys, value):
    # Python's float("٠.٠١") is 0.01; YAML keeps it a string and int keys refused it: now refused everywhere
    with pytest.raises(ConfigError, match=r"'tolerance'.*non-ASCII digit"):
        load_config(None, parse_overrides([f"tolerance={value}"]))
    with pytest.raises(ConfigError, match=r"'max_level'.*non-ASCII digit"):
        ReconstructConfig().replace(max_level="٣")
    f = tmp_path / "c.yaml"
    f.write_text(f"tolerance: {value}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"c\.yaml: config key 'tolerance'.*non-ASCII digit"):
        load_config(f)
    code, out, err = _run(capsys, _circle_file(tmp_path / "a.xy"), "--out", tmp_path / "o", "--set",
                          f"tolerance={value}")
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and "non-ASCII digit" in err
    assert ReconstructConfig().replace(tolerance="0.01").test.tolerance == 0.01      # ASCII text still read


def test_non_ascii_digits_in_point_files(tmp_path):
    from torch_isc.io import points_text

    for text, line in (("١ ٢\n3 4\n5 6\n", 1), ("1,2\n3,4\n５,6\n", 3), ("x y\n1 2\n3 4\n5 ٦\n", 4)):
        with pytest.raises(PointFileError, match=rf"a\.xy: line {line}: non-ASCII digit"):
            points_text.decode_points(Path("a.xy"), text.encode())
    # non-ASCII letters in a header or a comment are fine
    pts, _ = points_text.decode_points(Path("a.xy"), "x é\n1 2 # ٣\n3 4\n".encode())
    assert pts.tolist() == [[1.0, 2.0], [3.0, 4.0]]


def test_non_ascii_digits_in_options(tmp_path, capsys):
    f = _circle_file(tmp_path / "a.xy")
    for opt in (["--seed", "３"], ["--batch-size", "٣"], ["--sigma", "１"], ["--canny", "٠.١,٠.٢"]):
        code, out, err = _run(capsys, f, "--out", tmp_path / "o", *opt)
        assert code == 2 and out == "" and "Traceback" not in err, opt
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


# ------------------------------------------------------------------ empty option values
def test_empty_option_values(tmp_path, capsys, monkeypatch):
    f = _circle_file(tmp_path / "a.xy")
    monkeypatch.chdir(tmp_path)
    for argv, msg in (([f, "--out", ""], "--out: empty value"), ([f, "--config", ""], "--config: empty value"),
                      ([f, "--table", " "], "--table: empty value"), ([f, "--set", "tolerance="], "empty value"),
                      ([f, "--set", "=0.1"], "empty key"), ([f, "--manifest-column", ""], "empty value")):
        code, out, err = _run(capsys, *argv)
        assert code == 2 and out == "", argv
        assert len(err.strip().splitlines()) == 1 and msg in err, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.xy"]      # nothing written into the working folder


# ------------------------------------------------------------------ .npy trailing bytes
def test_npy_trailing_bytes(tmp_path, capsys):
    from torch_isc._helpers import load_npz_arrays
    from torch_isc.io import npy

    b = io.BytesIO()
    np.save(b, np.zeros((3, 2)))
    raw = b.getvalue()
    assert npy.decode_points(Path("a.npy"), raw)[0].shape == (3, 2)
    with pytest.raises(PointFileError, match=r"a\.npy: .*8 bytes after the data"):
        npy.decode_points(Path("a.npy"), raw + b"garbage!")
    # in a run: the bad file fails alone, the good one is written
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    good = io.BytesIO()
    np.save(good, np.c_[np.cos(t), np.sin(t)])
    (tmp_path / "good.npy").write_bytes(good.getvalue())
    (tmp_path / "bad.npy").write_bytes(good.getvalue() + good.getvalue())       # two arrays concatenated
    code, out, err = _run(capsys, tmp_path / "good.npy", tmp_path / "bad.npy", "--out", tmp_path / "o",
                          "--formats", "json", "--set", "max_level=2")
    assert code == 1 and "good:" in out and (tmp_path / "o" / "good.json").exists()
    assert err.count("error:") == 1 and "bad.npy" in err and "bytes after the data" in err
    # an .npz member likewise
    z = tmp_path / "m.npz"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("verts.npy", raw + b"xx")
    with pytest.raises(ValueError, match=r"member verts\.npy has 2 bytes after"):
        load_npz_arrays(z, ValueError)


# ------------------------------------------------------------------ table and SIGTERM
def test_table_temporary_removed_when_close_fails(tmp_path):
    pytest.importorskip("pyarrow")
    from torch_isc.dataset import TABLE_SCHEMA, _TableSink

    sink = _TableSink(tmp_path / "t.parquet", rows=10)
    assert sink.tmp.exists()
    sink.add(TABLE_SCHEMA().empty_table())

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    sink.writer.write_table = boom
    sink.buf = [TABLE_SCHEMA().empty_table()]
    from torch_isc.runner import RunError
    with pytest.raises(RunError, match=r"t\.parquet: cannot be written \(No space left on device\)"):
        sink.close(True)                   # one line naming the table (it was a raw OSError)
    assert sorted(p.name for p in tmp_path.iterdir()) == []          # neither the table nor its temporary
    sink = _TableSink(tmp_path / "t.parquet", rows=10)
    sink.close(False)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_sigterm_is_an_interrupt(monkeypatch, capsys):
    """SIGTERM under the torch-isc entry raises like SIGINT (same clean-up), ends with one line
    and status 143; the handler is removed afterwards."""
    from torch_isc import entry

    def run_and_get_killed(argv=None):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)                  # the handler raises before this ends
        return 0

    monkeypatch.setattr(cli, "main", run_and_get_killed)
    before = signal.getsignal(signal.SIGTERM)
    if before != signal.SIG_DFL:
        pytest.skip("a SIGTERM handler is already installed")
    t0 = time.perf_counter()
    assert entry.main() == 143
    assert time.perf_counter() - t0 < 4
    assert capsys.readouterr().err == "torch-isc: terminated\n"
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    # and the CLI maps the exception the same way
    assert entry.stop_status(entry.Terminated()) == ("terminated", 143)
    assert entry.stop_status(KeyboardInterrupt()) == ("interrupted", 130)


# ------------------------------------------------------------------ ImplicitCurve dtypes
def test_implicit_curve_mixed_dtypes():
    from torch_isc import ImplicitCurve, hexagon_mesh, measures
    from torch_isc.core.curve import InvalidValuesError

    ref_m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 3)
    ref = measures.area(ImplicitCurve(ref_m, ref_m.verts.norm(dim=1) - 0.55)).item()
    for md, vd, want in ((torch.float32, torch.float64, torch.float64), (torch.float64, torch.float32, torch.float64),
                         (torch.float32, torch.float16, torch.float32)):
        m = hexagon_mesh(torch.zeros(1, 2, dtype=md), torch.ones(1), 3)
        v = (ref_m.verts.norm(dim=1) - 0.55).to(vd).requires_grad_()
        c = ImplicitCurve(m, v)
        assert c.values.dtype == c.mesh.verts.dtype == want
        a = measures.area(c)
        assert a.dtype == want and abs(a.item() - ref) < 2e-3 * ref
        a.sum().backward()             # the gradient reaches the caller's tensor
        assert v.grad is not None and v.grad.dtype == vd
    m = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 3)
    signs = torch.where(m.verts.norm(dim=1) < 0.55, -1, 1)           # integer signs: the mesh's dtype
    assert ImplicitCurve(m, signs).values.dtype == torch.float32
    with pytest.raises(InvalidValuesError, match="real numbers"):
        ImplicitCurve(m, signs > 0)


# ------------------------------------------------------------------ images
def test_image_config_mapping():
    from torch_isc import images

    m = np.zeros((32, 32), np.float32)
    m[8:24, 8:24] = 1
    assert images.image_config({"max_level": 2}).test.tolerance == 0.5
    assert images.image_config({"tolerance": 0.3}).test.tolerance == 0.3         # a key given is kept
    r = images.reconstruct_masks([m], config={"max_level": 2})[0]
    assert (r.config.test.tolerance, r.config.test.tolerance_mode, r.config.limits.max_level) == (0.5, "absolute", 2)
    r = images.reconstruct_edges([m], config={"max_level": 2})[0]
    assert (r.config.test.tolerance, r.config.limits.max_level) == (0.5, 2)
    with pytest.raises(ConfigError):
        images.image_config([1])
    with pytest.raises(ConfigError, match="mode"):
        images.image_config(mode="canny")


def test_image_inf_and_tiny_edges():
    from torch_isc import images

    m = np.zeros((32, 32), np.float32)
    m[8:24, 8:24] = 1
    bad = m.copy()
    bad[0, 0] = np.inf
    with pytest.raises(images.ImageError, match="mask 0: has Inf values"):
        images.reconstruct_masks([bad])
    with pytest.raises(images.ImageError, match="image 0: has Inf values"):
        images.edge_points([bad])
    for shape in ((1, 1), (1, 100), (2, 50)):
        with pytest.raises(images.ImageError, match=r"image 0: .*too small for Canny.*at least 3x3"):
            images.edge_points([np.ones(shape, np.float32), m])
    assert images.edge_points([np.eye(3, dtype=np.float32)])[0].shape[1] == 2        # 3x3 is enough at sigma 1
    for kw in ({"sigma": math.inf}, {"sigma": math.nan}, {"sigma": 0.0}, {"spacing": math.inf},
               {"low_threshold": math.nan}, {"kernel_size": 4}):
        with pytest.raises(images.ImageError):
            images.edge_points([m], **kw)


# ------------------------------------------------------------------ YAML
def test_yaml_duplicate_keys(tmp_path, capsys):
    f = tmp_path / "c.yaml"
    f.write_text("max_level: 3\ntolerance: 0.01\ntolerance: 0.02\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: line 3: duplicate key 'tolerance'"):
        load_config(f)
    f.write_text("test:\n  tolerance: 0.01\n  tolerance: 0.02\n")
    with pytest.raises(ConfigError, match="line 3: duplicate key 'tolerance'"):
        load_config(f)
    with pytest.raises(ConfigError, match=r"--set .*duplicate key 'tolerance'"):
        parse_overrides(["test={tolerance: 1, tolerance: 2}"])
    code, out, err = _run(capsys, _circle_file(tmp_path / "a.xy"), "--out", tmp_path / "o", "--config", f)
    assert code == 2 and out == "" and "duplicate key" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("value", ["1:30", "-1:30", "1:30:00", "1:30.5", "+190:20:30.15"])
def test_yaml_base60_numbers(tmp_path, capsys, value):
    f = tmp_path / "c.yaml"
    f.write_text(f"tolerance: {value}\n")
    with pytest.raises(ConfigError, match=r"config key 'tolerance': .*base-60"):
        load_config(f)
    with pytest.raises(ConfigError, match=r"config key 'max_level': .*base-60"):
        load_config(None, parse_overrides([f"max_level={value}"]))
    code, out, err = _run(capsys, _circle_file(tmp_path / "a.xy"), "--out", tmp_path / "o", "--set", f"tolerance={value}")
    assert code == 2 and "'tolerance'" in err and "base-60" in err and len(err.strip().splitlines()) == 1
    # other numbers still read as before
    assert load_config(None, parse_overrides(["tolerance=0.01", "max_level=12"])).limits.max_level == 12
    assert load_config(None, parse_overrides(["tolerance=1e-3"])).test.tolerance == 1e-3


def test_key_set_twice(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("tolerance: 0.01\ntest:\n  tolerance: 0.02\n")
    with pytest.raises(ConfigError, match=r"'tolerance' is set twice \(as a flat key and as 'test.tolerance'\)"):
        load_config(f)
    with pytest.raises(ConfigError, match="set twice"):
        ReconstructConfig().replace(max_level=3, limits={"max_level": 4})


def test_yaml_node_limit(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("tolerance: [" + "1," * (3 * MAX_CONFIG_NODES) + "1]\n")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=f"more than {MAX_CONFIG_NODES} YAML values"):
        read_config_mapping(f)
    assert time.perf_counter() - t0 < 5          # parsing stops at the limit (the whole list: ~2 s)
    # the documented defaults are far below it
    root = Path(__file__).resolve().parents[1]
    assert read_config_mapping(root / "configs" / "default.yaml")


def test_yaml_octal_numbers(tmp_path):
    # YAML 1.1 (PyYAML) reads 010 as 8, YAML 1.2 and most tools as 10: refused, the key named
    f = tmp_path / "c.yaml"
    f.write_text("max_level: 010\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: config key 'max_level': '010' has a leading zero"):
        load_config(f)
    with pytest.raises(ConfigError, match=r"'seed': '-07' has a leading zero"):
        load_config(None, parse_overrides(["seed=-07"]))
    assert load_config(None, parse_overrides(["max_level=10", "seed=0", "tolerance=0.05"])).limits.max_level == 10


def test_set_errors_name_the_set_not_the_file(tmp_path, capsys):
    # the file was named for a bad --set value: "ok.yaml: config key 'tolerance': must be > 0"
    f = tmp_path / "ok.yaml"
    f.write_text("tolerance: 0.01\n")
    code, out, err = _run(capsys, _circle_file(tmp_path / "a.xy"), "--out", tmp_path / "o", "--config", f,
                          "--set", "tolerance=-1")
    assert code == 2 and err.startswith("torch-isc: error: --set: config key 'tolerance'") and "ok.yaml" not in err
    with pytest.raises(ConfigError, match=r"^overrides: config key 'max_level'"):
        load_config(f, {"max_level": 0}, "overrides")
