"""Fuzzing, third round (issue 18's last leftovers and a round on the newest features): one fast
regression test each, in the style of ``tests/test_fuzz_more.py``. The time budget inside a
level has its own file (``tests/test_budget.py``).

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
a .gif or .webp input (refused: "a binary .gif file,   test_gif_and_webp_are_read,
neither a point file nor an image read here")          test_gif_webp_headers_checked_before_decoding
an animated GIF / WebP (first frame would be read      test_animated_gif_and_webp_are_rejected
silently)
an interrupt cleared by native code during the         test_interrupt_cleared_by_native_code_is_seen
imports (rare: status 0, the run went on)
find_contours: mode/method/connectivity/batch_pixels   test_find_contours_odd_arguments
raised builtin errors, epsilon=1e308 cv2.error, an
offset of 1e308 inf contours
blob_max_points=1e6 (over 40 s, gigabytes)             test_blob_max_points_is_bounded
=====================================================  ==========================================
"""
from __future__ import annotations

import io
import struct

import cv2
import numpy as np
import pytest

from torch_isc import cli
from torch_isc.images import ImageError
from torch_isc.images.read import decode_image, image_header, read_image

Image = pytest.importorskip("PIL.Image")


def _run(capsys, *argv):
    code = cli.main(["reconstruct"] + [str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _disc(h=40, w=50):
    yy, xx = np.mgrid[:h, :w]
    return (((xx - 24.5) ** 2 + (yy - 19.5) ** 2) < 12 ** 2).astype(np.uint8) * 255


def _encoded(a, fmt, **kw):
    b = io.BytesIO()
    Image.fromarray(a).save(b, fmt, **kw)
    return b.getvalue()


@pytest.mark.parametrize("fmt,kw", [("GIF", {}), ("WEBP", {"lossless": True}), ("WEBP", {"quality": 95})])
def test_gif_and_webp_are_read(tmp_path, capsys, fmt, kw):
    """A disc mask as GIF, lossless and lossy WebP reads as the same pixels as the PNG (lossy:
    within a few grey levels), and the CLI reconstructs it (one closed curve)."""
    a = _disc()
    data = _encoded(a, fmt, **kw)
    suffix = "." + fmt.lower()
    head = image_header(data)
    assert (head.format, head.width, head.height, head.pages) == (fmt.lower(), 50, 40, 1)
    g = decode_image(data, "x" + suffix)
    if kw.get("quality"):
        assert np.abs(g - a / 255.0).max() < 0.2 and ((g > 0.5) == (a > 127)).mean() > 0.99
    else:
        assert np.array_equal(g, a / np.float32(255.0))
    (tmp_path / ("m" + suffix)).write_bytes(data)
    assert np.array_equal(read_image(tmp_path / ("m" + suffix)), g)
    code, out, err = _run(capsys, tmp_path / ("m" + suffix), "--out", tmp_path / "o", "--formats", "json")
    assert code == 0 and "m: 1 closed, 0 open" in out, err
    # read_points of such a file says what it is
    from torch_isc.io import PointFileError, read_points
    with pytest.raises(PointFileError, match=rf"m\{suffix}: an image \({suffix}\), not a point file"):
        read_points(tmp_path / ("m" + suffix))


def test_animated_gif_and_webp_are_rejected():
    """Two frames: refused like an animated PNG or a multi-page TIFF (OpenCV decodes the first
    frame alone, silently)."""
    frames = [Image.fromarray(_disc()), Image.fromarray(255 - _disc())]
    for fmt, name in (("GIF", "GIF"), ("WEBP", "WebP")):
        b = io.BytesIO()
        frames[0].save(b, fmt, save_all=True, append_images=frames[1:])
        assert image_header(b.getvalue()).pages == 2
        with pytest.raises(ImageError, match=rf"^a: animated {name} \(2 frames\): only single images are read"):
            decode_image(b.getvalue(), "a")
        assert cv2.imdecode(np.frombuffer(b.getvalue(), np.uint8), cv2.IMREAD_UNCHANGED) is not None


def test_gif_webp_headers_checked_before_decoding():
    """A 30-byte GIF and a 30-byte WebP declaring 60000x60000 pixels are "too large" from the
    header, before any decoding; a GIF's frames are counted past extension blocks."""
    gif = b"GIF89a" + struct.pack("<HH", 60000, 60000) + b"\x00\x00\x00" + b",\x00\x00\x00\x00\x01\x00\x01\x00\x00\x02\x02D\x01\x00;"
    vp8x = (b"RIFF" + struct.pack("<I", 22) + b"WEBPVP8X" + struct.pack("<I", 10) + b"\x00\x00\x00\x00"
            + (59999).to_bytes(3, "little") + (59999).to_bytes(3, "little"))
    for data, fmt in ((gif, "gif"), (vp8x, "webp")):
        h = image_header(data)
        assert (h.format, h.width, h.height) == (fmt, 60000, 60000)
        with pytest.raises(ImageError, match=r"^big: image too large: 60000x60000 pixels \(3600 megapixels\)"):
            decode_image(data, "big")
    # comment and graphic-control extensions before the frame, then two frames: 2 counted
    ext = b"!\xfe\x03abc\x00" + b"!\xf9\x04\x00\x00\x00\x00\x00"
    frame = b",\x00\x00\x00\x00\x01\x00\x01\x00\x00\x02\x02D\x01\x00"
    two = b"GIF89a\x01\x00\x01\x00\x80\x00\x00" + b"\x00" * 6 + ext + frame + ext + frame + b";"
    assert image_header(two).pages == 2
    assert image_header(two[:-len(frame + b";") - len(ext)] + b";").pages == 1


def test_interrupt_cleared_by_native_code_is_seen(monkeypatch, capsys):
    """An interrupt whose KeyboardInterrupt native code catches and clears (as torch's C++ does
    for a lazy numpy import; seen once under load in the timed test of test_robustness_fuzz:
    status 0, the run completed) still ends the command with status 130 and one line: the
    entry's handler records it."""
    import os
    import signal
    import torch_isc.cli as tc
    import torch_isc.entry as entry

    def run_with_cleared_interrupt():
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):            # the handler runs at the next bytecode check
                pass
        except KeyboardInterrupt:
            pass                             # what a C++ caller's error clearing does
        return 0
    monkeypatch.setattr(tc, "main", run_with_cleared_interrupt)
    assert entry.main() == 130
    assert capsys.readouterr().err == "torch-isc: interrupted\n"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler      # restored
    monkeypatch.setattr(tc, "main", lambda: 0)
    assert entry.main() == 0                                                   # the flag was reset


def test_find_contours_odd_arguments():
    """A fresh round on ``find_contours``: bad modes, methods, connectivities and batch sizes raised
    builtin ValueError/TypeError (now :class:`ImageError`, still a ValueError, naming the
    argument); ``epsilon=1e308`` raised OpenCV's "Epsilon not valid" (now: the same polygon as any
    epsilon beyond the contour, here 1e6); an offset of 1e308 gave inf float32 contours (now
    refused)."""
    from torch_isc.images.contours import find_contours, find_contours_batch
    m = np.zeros((20, 30), np.uint8)
    m[5:15, 5:20] = 1
    for kw, what in (({"mode": -1}, "retrieval mode -1"), ({"mode": "x"}, "retrieval mode 'x'"),
                     ({"method": 0}, "approximation method 0"), ({"connectivity": 6}, "connectivity must be 8 or 4"),
                     ({"connectivity": "8"}, "connectivity must be 8 or 4"),
                     ({"offset": (1e308, 0.0)}, r"offset \(1e\+308, 0.0\): contour coordinates beyond what float32"),
                     ({"offset": (3e9, 0), "dtype": np.int32}, "beyond what int32")):
        with pytest.raises(ImageError, match=what):
            find_contours(m, **kw)
    for bp in ("a", float("nan"), -1, True):
        with pytest.raises(ImageError, match="batch_pixels must be an integer >= 0"):
            find_contours_batch([m, m], batch_pixels=bp)
    assert len(find_contours_batch([m, m], batch_pixels=0)) == 2          # one mask per solve
    huge = find_contours(m, 3, 2, epsilon=1e308)[0]
    ref = find_contours(m, 3, 2, epsilon=1e6)[0]
    assert len(huge) == 1 and np.array_equal(huge[0], ref[0])
    # the contour of a 10x15 rectangle collapses to 2 points (Douglas-Peucker's end points)
    assert 1 <= len(huge[0]) <= 2


def test_blob_max_points_is_bounded():
    """``blob_max_points=1000000`` built a nearest-neighbour table of a million columns per point
    (over 40 s and gigabytes on a 320-point set); the blob rule is for small clusters: at most
    1000 points."""
    from torch_isc import ReconstructConfig
    from torch_isc.pipeline.config import ConfigError
    with pytest.raises(ConfigError, match="config key 'blob_max_points'"):
        ReconstructConfig().replace(blob_max_points=1_000_000)
    ReconstructConfig().replace(blob_max_points=1000)
