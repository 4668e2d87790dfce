"""Fuzzing, second round (issue 18's leftovers and a new round of hostile inputs): one fast
regression test each, in the style of ``tests/test_fuzz_inputs.py``. Every case gives a correct
answer or one line naming the input and the problem; the other inputs of the run are still
written.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
a circle of radius 1 at an offset of 1e15 (no curve:   test_circle_at_offset_1e15,
the collinearity slack was 8 rounding steps, more      test_too_few_rounding_steps_is_an_error
than the circle); below 8 steps across: an error
a ring plus one point 1e12 away (no curve: the box     test_far_outlier_dropped,
was the outlier's)                                     test_far_cluster_is_kept
a one-colour PNG whose alpha carries the shape (read   test_alpha_only_png
as empty: black x alpha)
int32 / int16 / float / 12-bit TIFF (divided by 2^31   test_pixel_types_read_by_their_range
- 1 or clipped: no edges, empty mask)
a JPEG cut short but closed with EOI, or with flipped  test_damaged_jpeg_is_an_error
bits (decoded silently, grey filled)
an animated PNG (first frame read silently)            test_animated_png_is_rejected
numpy arrays: reversed view (error), read-only (torch  test_api_array_layouts_and_types
warning), complex / bool / masked (silently cast)
numpy scalars as config values (refused)               test_config_numpy_scalars
UTF-16 text, quoted CSV fields (refused), 1_0 (read    test_text_encodings_quotes_and_underscores
as 10 on the slow path only)
.npz / .bin given by name ("byte 16 is not UTF-8")     test_binary_file_of_another_suffix
a 250-character input name (the whole run lost)        test_long_input_name
an output folder that is a file (FileExistsError)      test_out_dir_is_a_file
spike_rounds / snap_rounds unbounded (minutes)         test_every_numeric_key_is_bounded
far points with a sign oracle (kept)                   test_far_points_kept_with_a_sign_oracle
Ctrl-C during numpy's lazy import (lost: exit 0/1)     test_interrupt_early_in_the_entry
=====================================================  ==========================================
"""
from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
import torch

from torch_isc import PointSetError, cli, reconstruct
from torch_isc.images import ImageError
from torch_isc.images.read import decode_image


def _circle(n=200, r=1.0, c=(0.0, 0.0)):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[c[0] + r * np.cos(t), c[1] + r * np.sin(t)]


def _radius_error(res, center, r):
    """Largest distance of the curve's vertices from the circle (|p - c| - r), in float64."""
    worst = 0.0
    for pl in res.polylines:
        p = pl["points"].double() - torch.tensor(center, dtype=torch.float64)
        worst = max(worst, float((p.norm(dim=1) - r).abs().max()))
    return worst


def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# ============================================================================ offsets
def test_circle_at_offset_1e15():
    """float64 steps by 0.125 at 1e15: a circle of radius 1 there is 64 distinct points, a
    16-pixel circle. The same curve as the same rounded points near the origin, within one
    step of the true circle."""
    off = 1e15
    pts = torch.tensor(_circle(r=1.0) + off, dtype=torch.float64)
    res = reconstruct(pts, config={"max_level": 4})
    assert res.num_components == 1 and res.num_closed == 1 and res.limit is None
    assert _radius_error(res, (off, off), 1.0) <= 0.125
    near = reconstruct(pts - off, config={"max_level": 4})         # subtraction exact: same rounded set
    assert near.num_closed == 1
    a = torch.cat([p["points"] for p in res.polylines]).double() - off
    b = torch.cat([p["points"] for p in near.polylines]).double()
    assert a.shape == b.shape and float((a - b).abs().max()) <= 0.125 + 1e-9


def test_too_few_rounding_steps_is_an_error():
    """Radius 0.2 at 1e15: its diagonal spans 0.71, 3.2 steps of eps x 1e15 (the points are 16
    grid nodes): a one-line PointSetError naming the set, not a curve made of rounding. A
    float32 set at 1e7 (step 1) likewise; integers have no rounding (a 3-point triangle far
    out is fine)."""
    with pytest.raises(PointSetError, match=r"^ring: the points span 0\.707 at coordinates of magnitude 1e\+15, "
                                            r"only 3\.2 rounding steps of float64 there \(at least 8 needed\)"):
        reconstruct(torch.tensor(_circle(r=0.2) + 1e15, dtype=torch.float64), name="ring")
    with pytest.raises(PointSetError, match="rounding steps of float32"):
        reconstruct(torch.tensor(_circle(r=1.0) + 1e7, dtype=torch.float32))
    tri = torch.tensor([[0, 0], [1, 0], [0, 1]], dtype=torch.int64) + 10 ** 15
    assert reconstruct(tri).limit in (None, "no_curve", "max_level")
    # int64 beyond 2^53 is rounded by the float64 packing (steps of 1024 at 2^62): the same rule
    ring = torch.tensor(np.round(_circle(r=1000.0))).long() + 2 ** 62
    with pytest.raises(PointSetError, match="only 2.8 rounding steps of float64 there"):
        reconstruct(ring)
    assert reconstruct(ring - 2 ** 62 + 2 ** 52, config={"max_level": 2}).num_closed == 1
    # a long line at that offset is collinear (no curve), not an error
    x = torch.linspace(0, 1000, 300, dtype=torch.float64)
    line = torch.stack([x + 1e15, 0.5 * x + 1e15], 1)
    assert reconstruct(line).limit == "no_curve"


# ============================================================================ far outliers
@pytest.mark.parametrize("far", [(1e12, 1e12), (40.0, 12.0), (-3e5, 7.0)])
@pytest.mark.parametrize("k", [1, 3])
def test_far_outlier_dropped(far, k):
    """A ring of 200 points plus k points far away (16 median distances from the median
    centre or more): they are left out, counted in ``far_outliers`` (JSON stats too), and the
    curve is the ring's, the same as without them."""
    ring = _circle()
    extra = np.asarray(far) + 0.01 * np.arange(k)[:, None]
    res = reconstruct(torch.tensor(np.vstack([ring, extra])), config={"max_level": 4})
    assert res.far_outliers == k and res.to_json_dict()["stats"]["far_outliers"] == k
    assert res.num_closed == 1 and _radius_error(res, (0.0, 0.0), 1.0) < 0.01
    assert res.points.shape[0] == 200 + k                     # the caller's points, as given
    alone = reconstruct(torch.tensor(ring), config={"max_level": 4})
    assert alone.far_outliers == 0
    a = torch.cat([p["points"] for p in res.polylines])
    b = torch.cat([p["points"] for p in alone.polylines])
    assert a.shape == b.shape and float((a - b).abs().max()) < 1e-9


def test_far_cluster_is_kept():
    """Real data far away is kept: a second ring with 30% of the points, 40 radii off, is not
    an outlier (too many points to be one); a moderate outlier (3 radii) is kept too."""
    from torch_isc.core.points import prepare_points
    two = np.vstack([_circle(140), _circle(60, 1.0, (40.0, 0.0))])
    near = np.vstack([_circle(), [[3.0, 0.0]]])
    pb = prepare_points([torch.tensor(two), torch.tensor(near)])
    assert pb.far_outliers == [0, 0] and pb.counts.tolist() == [200, 201]
    # an item's drop does not depend on its batch
    far = torch.tensor(np.vstack([_circle(), [[1e12, 1e12]]]))
    alone, mixed = prepare_points([far]), prepare_points([torch.tensor(two), far, torch.tensor(near)])
    assert alone.far_outliers == [1] and mixed.far_outliers == [0, 1, 0]
    assert torch.equal(alone.points, mixed.points[200:400]) and torch.equal(alone.source, mixed.source[200:400])


# ============================================================================ images
def test_alpha_only_png(tmp_path, capsys):
    """Rule: when the colour is the same wherever alpha > 0 (a one-colour icon), the image is
    its alpha channel (opaque reads as white); otherwise alpha multiplies the gray value (a
    transparent background reads as black), as before. RGBA with black colour, gray+alpha
    (PNG LA), and the CLI's mask: the disc's curve."""
    Image = pytest.importorskip("PIL.Image")
    a = np.zeros((48, 48), np.uint8)
    cv2.circle(a, (24, 24), 14, 255, -1)
    rgba = np.zeros((48, 48, 4), np.uint8)
    rgba[..., 3] = a
    rgba[a == 0, :3] = 255                               # hidden colour under alpha 0 does not count
    cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
    Image.fromarray(np.stack([np.zeros_like(a), a], 2), "LA").save(tmp_path / "la.png")
    for name in ("rgba.png", "la.png"):
        g = decode_image((tmp_path / name).read_bytes(), name)
        assert np.array_equal(g, a / np.float32(255)), name
    # two colours: composited on black (the black half vanishes, the white half stays)
    two = rgba.copy()
    two[:, 24:, :3] = 255
    two[:, :24, :3] = 0
    g = decode_image(cv2.imencode(".png", two)[1].tobytes())
    assert g[24, 30] == 1.0 and g[24, 18] == 0.0
    code, out, err = _run(capsys, tmp_path / "rgba.png", tmp_path / "la.png", "--out", tmp_path / "o",
                          "--formats", "json")
    assert code == 0 and out.count("1 closed, 0 open") == 2, (out, err)


@pytest.mark.parametrize("dtype,top", [(np.int32, 1000), (np.int16, -1000), (np.float32, 1000.0),
                                       (np.float32, -1.0), (np.uint16, 4095), (np.int8, 100), (np.uint32, 7)])
def test_pixel_types_read_by_their_range(tmp_path, capsys, dtype, top):
    """int32/int16/int8/uint32 TIFFs and floats beyond [0, 1] read by their own range (min to
    max: the disc is 1 and the background 0, or the reverse for a negative ``top``), 12-bit data
    in uint16 by its bit depth; before, int32 was divided by 2^31 - 1 and floats clipped, so
    ``--mode edges`` found no edges and masks were empty. The CLI's edges mode finds the disc."""
    disc = np.zeros((48, 48), np.float32)
    cv2.circle(disc, (24, 24), 14, 1.0, -1)
    img = (disc * top).astype(dtype)
    p = tmp_path / "im.tiff"
    assert cv2.imwrite(str(p), img)
    assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED).dtype == np.dtype(dtype)
    g = decode_image(p.read_bytes(), p)
    want = disc if top > 0 else 1.0 - disc
    assert np.abs(g - want).max() < 1e-6
    code, out, err = _run(capsys, p, "--mode", "edges", "--out", tmp_path / "o", "--formats", "json")
    assert code == 0 and "1 closed" in out, (out, err)


def test_uint8_and_full_uint16_unchanged():
    """The common types keep their full-scale rule: uint8 by 255, 16-bit data using 16 bits by
    65535, a 0/1 label image stays two-level."""
    a = np.array([[0, 128, 255]], np.uint8)
    assert np.array_equal(decode_image(cv2.imencode(".png", a)[1].tobytes()), a / np.float32(255))
    b = np.array([[0, 40000, 65535]], np.uint16)
    assert np.allclose(decode_image(cv2.imencode(".png", b)[1].tobytes()), b / 65535.0)
    c = np.array([[0, 1, 1]], np.uint16)
    assert np.allclose(decode_image(cv2.imencode(".png", c)[1].tobytes()), c / 255.0)


def test_damaged_jpeg_is_an_error(tmp_path, capfd):
    """libjpeg fills a damaged JPEG in grey and only warns on stderr: a file cut in half and
    closed with EOI (the bytes OpenCV decodes without an error), or with bits flipped in its
    scan, is "truncated or corrupt" in one line; the good file decodes; libpng's own error
    lines do not leak to stderr."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur((rng.random((120, 160)) * 255).astype(np.uint8), (9, 9), 3)
    good = cv2.imencode(".jpg", img)[1].tobytes()
    assert decode_image(good, "g.jpg").shape == (120, 160)
    cut = good[:len(good) // 2] + b"\xff\xd9"
    flipped = bytearray(good)
    for k in range(5):
        flipped[len(good) // 2 + 37 * k] ^= 0x5A
    for data in (cut, bytes(flipped)):
        with pytest.raises(ImageError, match=r"^d\.jpg: truncated or corrupt JPEG \(libjpeg: Corrupt JPEG data"):
            decode_image(data, "d.jpg")
    png = cv2.imencode(".png", img)[1].tobytes()
    with pytest.raises(ImageError, match="not a readable image"):
        decode_image(png[:len(png) // 2], "h.png")
    assert capfd.readouterr().err == ""
    (tmp_path / "cut.jpg").write_bytes(cut)
    m = np.zeros((40, 40), np.uint8)
    cv2.circle(m, (20, 20), 10, 255, -1)
    cv2.imwrite(str(tmp_path / "ok.png"), m)
    code = cli.main(["reconstruct", str(tmp_path / "cut.jpg"), str(tmp_path / "ok.png"), "--out", str(tmp_path / "o"),
                     "--formats", "json"])
    err = capfd.readouterr().err
    assert code == 1 and (tmp_path / "o" / "ok.json").exists()
    assert [ln for ln in err.splitlines() if "error" in ln] == [
        f"torch-isc: error: {tmp_path / 'cut.jpg'}: truncated or corrupt JPEG (libjpeg: Corrupt JPEG data: "
        f"premature end of data segment)"]


def test_animated_png_is_rejected(tmp_path):
    """An APNG (acTL chunk) read as its first frame silently; now refused like a multi-page
    TIFF, from the header."""
    Image = pytest.importorskip("PIL.Image")
    from torch_isc.images.read import image_header
    frames = [Image.fromarray(np.full((8, 8), v, np.uint8)) for v in (0, 128, 255)]
    b = io.BytesIO()
    frames[0].save(b, "PNG", save_all=True, append_images=frames[1:])
    assert image_header(b.getvalue()).pages == 3
    with pytest.raises(ImageError, match=r"^a\.png: animated PNG \(3 frames\): only single images are read"):
        decode_image(b.getvalue(), "a.png")
    assert image_header(cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes()).pages == 1


# ============================================================================ API arguments
def test_api_array_layouts_and_types():
    """numpy arrays as users hold them: a reversed view (negative strides: "not an array of
    numbers" before), read-only memory (a torch warning before), are read as they are; complex
    and bool arrays are refused like the same tensors (complex lost its imaginary part with a
    numpy warning, bool became 0/1); a masked array with masked values is refused (its hidden
    values were used)."""
    import warnings
    ring = _circle(60)
    ref = reconstruct(torch.tensor(ring), config={"max_level": 2})
    ro = ring.copy()
    ro.setflags(write=False)
    for arr in (ring[::-1].copy()[::-1], ro):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            r = reconstruct(arr, config={"max_level": 2})
        assert torch.equal(r.curve.values, ref.curve.values)
    assert reconstruct(ring[::-1], config={"max_level": 2}).num_closed == 1
    for bad, what in ((ring.astype(complex), "complex128"), (ring > 0, "bool")):
        with pytest.raises(PointSetError, match=rf"^point set 0: expected real coordinates, got dtype {what}$"):
            reconstruct(bad)
    masked = np.ma.masked_array(ring, mask=np.zeros_like(ring, bool))
    assert reconstruct(masked, config={"max_level": 2}).num_closed == 1
    masked[3, 0] = np.ma.masked
    with pytest.raises(PointSetError, match=r"^point set 0: a masked array with 1 masked value\(s\)"):
        reconstruct(masked)


def test_config_numpy_scalars():
    """A parameter sweep's numpy scalars (np.int64, np.float32, np.bool_) are accepted as their
    Python values (before: "expected int, got int64"); arrays and torch tensors still are not."""
    from torch_isc.pipeline.config import ConfigError, from_dict
    c = from_dict({"max_level": np.int64(3), "tolerance": np.float64(0.01), "coverage_test": np.bool_(False)})
    assert (c.limits.max_level, c.test.tolerance, c.test.coverage_test) == (3, 0.01, False)
    assert type(c.limits.max_level) is int and type(c.test.coverage_test) is bool
    assert c == from_dict({"max_level": 3, "tolerance": 0.01, "coverage_test": False})
    for bad in ({"max_level": np.array([1, 2])}, {"max_level": torch.tensor(2)}, {"max_level": np.bool_(True)}):
        with pytest.raises(ConfigError, match="config key 'max_level': expected int"):
            from_dict(bad)


# ============================================================================ text point files
def test_text_encodings_quotes_and_underscores(tmp_path):
    """UTF-16 (with its BOM, as Windows tools write) is read ("byte 0 is not UTF-8" before);
    quoted fields ``"1.5","2"`` are read ("non-numeric" before); ``1_000`` is refused on both
    paths (Python's float read it as 1000 on the row-by-row path only)."""
    from torch_isc.io import PointFileError, read_points
    rows = "x,y\n1.5,2\n3,4.25\n-1,0\n"
    for name, data in (("u16le.xy", rows.encode("utf-16")), ("u16be.xy", b"\xfe\xff" + rows.encode("utf-16-be")),
                       ("u32.xy", rows.encode("utf-32")), ("quoted.csv", rows.replace("1.5,2", '"1.5","2"').encode())):
        (tmp_path / name).write_bytes(data)
        assert read_points(tmp_path / name).tolist() == [[1.5, 2.0], [3.0, 4.25], [-1.0, 0.0]], name
    (tmp_path / "us.xy").write_text("1 2\n3 4\nnan 1_0\n")
    with pytest.raises(PointFileError, match=r"us\.xy: line 3: non-numeric value '1_0'"):
        read_points(tmp_path / "us.xy")


def test_binary_file_of_another_suffix(tmp_path, capsys):
    """An .npz, a .gif given by name: one line saying what is read ("byte 16 is not UTF-8"
    before); a text file of any suffix is still read as text."""
    from torch_isc.io import PointFileError, read_points
    np.savez(tmp_path / "p.npz", points=_circle(10))
    (tmp_path / "a.bin").write_bytes(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;")
    (tmp_path / "pts.dat").write_text("1 2\n3 4\n5 7\n")
    for name, what in (("p.npz", "a .npz archive"), ("a.bin", "a binary .bin file")):
        with pytest.raises(PointFileError, match=rf"^{tmp_path / name}: {what}, neither a point file"):
            read_points(tmp_path / name)
    # .gif and .webp are images now (tests/test_fuzz_third.py): read_points says so
    (tmp_path / "a.gif").write_bytes(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;")
    with pytest.raises(PointFileError, match=r"a\.gif: an image \(\.gif\), not a point file"):
        read_points(tmp_path / "a.gif")
    assert read_points(tmp_path / "pts.dat").shape == (3, 2)


# ============================================================================ runs
def test_long_input_name(tmp_path, capsys):
    """A 250-character file name: its outputs (``<stem>.manifest.json`` and the temporary
    ``.<name>.XXXXXXXX.tmp``) overflowed the 255-byte file name and the whole run stopped with an
    internal error, the other input unwritten. Now the stem is cut to 200 bytes plus 8 hex
    digits of its hash, noted on stderr; a rerun skips it."""
    long_name = "é" * 125 + ".xy"                     # 250 bytes of UTF-8 + 3
    for name in (long_name, "ok.xy"):
        np.savetxt(tmp_path / name, _circle(60))
    code, out, err = _run(capsys, tmp_path / long_name, tmp_path / "ok.xy", "--out", tmp_path / "o",
                          "--formats", "json", "--set", "max_level=2")
    assert code == 0 and out.count("1 closed") == 2, (out, err)
    assert "name too long for an output file" in err
    names = sorted(p.name for p in (tmp_path / "o").iterdir())
    assert len(names) == 4 and "ok.json" in names
    long_json = [n for n in names if n.endswith(".json") and not n.endswith("manifest.json") and n != "ok.json"][0]
    assert len(long_json.encode()) <= 205 and long_json.startswith("é" * 95)
    code, out, err = _run(capsys, tmp_path / long_name, "--out", tmp_path / "o", "--formats", "json",
                          "--set", "max_level=2")
    assert code == 0 and "skipped" in out


def test_out_dir_is_a_file(tmp_path):
    """``run_inputs``/``reconstruct_dataset`` with an output folder that is a file: a RunError
    naming it (a FileExistsError traceback before), nothing written."""
    from torch_isc.dataset import reconstruct_dataset
    from torch_isc.runner import RunError, run_inputs
    np.savetxt(tmp_path / "a.xy", _circle(60))
    for call in (lambda: run_inputs([tmp_path / "a.xy"], None, tmp_path / "a.xy", formats=["json"]),
                 lambda: reconstruct_dataset([tmp_path / "a.xy"], tmp_path / "a.xy", formats=["json"])):
        with pytest.raises(RunError, match=rf"^{tmp_path / 'a.xy'}: cannot create the output folder \(File exists\)"):
            call()


def test_every_numeric_key_is_bounded():
    """Every integer and float key has an upper bound (its own ``le``/``lt`` or
    ``UPPER_BOUNDS``), except ``tolerance`` (clamped to ``TOLERANCE_CEILING`` diagonals): with
    none, ``spike_rounds=1000000`` ran for minutes. A new key without one fails here."""
    import dataclasses
    from torch_isc.pipeline.config import UPPER_BOUNDS, ConfigError, ReconstructConfig, from_dict
    cfg, loose = ReconstructConfig(), []
    for sec in dataclasses.fields(cfg):
        for f in dataclasses.fields(getattr(cfg, sec.name)):
            v = getattr(getattr(cfg, sec.name), f.name)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and f.name not in UPPER_BOUNDS \
                    and f.metadata.get("le") is None and f.metadata.get("lt") is None:
                loose.append(f.name)
    assert loose == ["tolerance"]
    for key in ("spike_rounds", "snap_rounds"):
        with pytest.raises(ConfigError, match=rf"config key '{key}': must be <= 1000, got 1000000"):
            from_dict({key: 10 ** 6})


def test_far_points_kept_with_a_sign_oracle():
    """With a sign oracle (masks) the far points stay: the oracle says a far speck is real."""
    ring = np.vstack([_circle(), [[60.0, 0.0], [60.5, 0.0], [60.0, 0.5]]])
    inside = lambda p: (p.norm(dim=1) < 1) | ((p - torch.tensor([60.2, 0.2], dtype=p.dtype)).norm(dim=1) < 0.3)
    res = reconstruct(torch.tensor(ring), config={"max_level": 3}, sign_oracle=inside)
    assert res.far_outliers == 0 and res.stats[0].points == 203


@pytest.mark.parametrize("delay", [0.05, 0.15, 0.4])
def test_interrupt_early_in_the_entry(tmp_path, delay):
    """Ctrl-C at several instants of the libraries' loading: always status 130 and one line.
    Before, one landing in numpy's import (done lazily by torch's C++, which clears the error)
    was lost: the run went on with numpy half-imported and failed, or finished with status 0."""
    import subprocess
    import sys
    child = ("import os, signal, sys, threading, torch_isc.entry as e\n"
             "sys.argv = ['torch-isc', 'reconstruct', '--example', '--out', sys.argv[1], '--set', 'max_level=1']\n"
             f"threading.Timer({delay}, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
             "sys.exit(e.main())\n")
    p = subprocess.run([sys.executable, "-c", child, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 130 and "Traceback" not in p.stderr, p.stderr[-500:]
    assert [ln for ln in p.stderr.splitlines() if "[" not in ln] == ["torch-isc: interrupted"]
