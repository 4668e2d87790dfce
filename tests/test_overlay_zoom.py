"""overlay.png at a zoom and over a region (``--zoom``, ``--region``): shapes, where the curve
lands in the zoomed frame, clipping, errors, and the CLI plumbing."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from torch_isc import cli
from torch_isc.io import render_overlay
from torch_isc.io.overlay import overlay_region


def _square(x0, y0, x1, y1):
    return {"polylines": [{"closed": True, "points": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]}]}


def test_zoom_and_region_shape_and_curve_position():
    img = np.zeros((20, 30), np.uint8)
    out = render_overlay(img, _square(4.25, 5.5, 10.75, 15.0), scale=8, region=(2, 3, 12, 8))
    assert out.shape == (5 * 8, 10 * 8, 3)
    g = out[:, :, 1].astype(int)
    # the edge y = 5.5 lies (5.5 - 3) * 8 = 20 output pixels down: drawn across rows 19 and 20
    col = (7 - 2) * 8
    assert g[19:21, col].max() > 100 and g[:17, col].max() == 0 and g[23:, col].max() == 0
    # the edge x = 4.25 lies (4.25 - 2) * 8 = 18 output pixels right, below y = 5.5
    row = 30
    assert g[row, 17:19].max() > 100 and g[row, :15].max() == 0 and g[row, 21:60].max() == 0
    # the vertex (4.25, 5.5) is marked at zoom >= 8 (yellow: red and green)
    assert out[19:21, 17:19, 2].max() > 100


def test_zoom_one_without_region_is_the_plain_overlay():
    img = (np.arange(12 * 16).reshape(12, 16) % 7 * 30).astype(np.uint8)
    sq = _square(2.3, 3.1, 9.7, 8.2)
    a = render_overlay(img, sq)
    assert np.array_equal(a, render_overlay(img, sq, scale=1, region=(0, 0, 16, 12)))
    assert np.array_equal(a, render_overlay(img, sq, region=(-5, -5, 100, 100)))      # clipped to the image
    z = render_overlay(img, {"polylines": []}, scale=3)
    assert np.array_equal(z[::3, ::3, 0], img) and np.array_equal(z[2::3, 2::3, 0], img)


def test_region_errors():
    assert overlay_region((10, 20), None) == (0, 0, 20, 10)
    assert overlay_region((10, 20), (5, -3, 30, 4)) == (5, 0, 20, 4)
    # a region that misses this image shows all of it (a folder of images of several sizes: the
    # small ones failed, their json and contours lost with the overlay)
    assert overlay_region((10, 20), (25, 0, 30, 5)) == (0, 0, 20, 10)
    with pytest.raises(ValueError, match="x0 < x1"):
        overlay_region((10, 20), (5, 0, 5, 5))
    with pytest.raises(ValueError, match="zoom"):
        render_overlay(np.zeros((4, 4)), {"polylines": []}, scale=0)
    with pytest.raises(ValueError, match="larger than"):
        render_overlay(np.zeros((4000, 4000), np.uint8), {"polylines": []}, scale=64)
    # under the pixel count, but a row wider than PNG allows (libpng failed with several lines)
    with pytest.raises(ValueError, match="more than PNG allows"):
        render_overlay(np.zeros((1, 20000), np.uint8), {"polylines": []}, scale=64)


def _disc(path, h=40, w=50, c=(24.3, 18.7), r=11.2):
    yy, xx = np.mgrid[:h, :w] + 0.5
    cv2.imwrite(str(path), (((xx - c[0]) ** 2 + (yy - c[1]) ** 2 < r * r) * 255).astype(np.uint8))
    return path


def test_cli_zoom_region(tmp_path, capsys):
    f = _disc(tmp_path / "disc.png")
    o = tmp_path / "o"
    assert cli.main(["reconstruct", str(f), "--out", str(o), "--zoom", "6", "--region", "10,5,30,20"]) == 0
    ov = cv2.imread(str(o / "disc.overlay.png"))
    assert ov.shape == (15 * 6, 20 * 6, 3)
    assert ov[:, :, 1].max() > 150 and (ov[:, :, 1] > ov[:, :, 2] + 50).any()      # the green curve is drawn
    man = json.loads((o / "disc.manifest.json").read_text())
    assert man["formats"] == ["json", "contours.npz", "overlay.png"]              # the zoom asks for the overlay
    # another view is another output set: redone, not skipped
    capsys.readouterr()
    assert cli.main(["reconstruct", str(f), "--out", str(o), "--zoom", "2"]) == 0
    assert "skipped" not in capsys.readouterr().out
    assert cv2.imread(str(o / "disc.overlay.png")).shape == (80, 100, 3)
    assert cli.main(["reconstruct", str(f), "--out", str(o), "--zoom", "2"]) == 0
    assert "skipped" in capsys.readouterr().out


@pytest.mark.parametrize("args, msg", [(["--zoom", "0"], "--zoom"), (["--zoom", "65"], "--zoom"),
                                       (["--region", "1,2,3"], "--region"), (["--region", "5,0,2,4"], "--region"),
                                       (["--region", "a,b,c,d"], "--region")])
def test_cli_zoom_region_usage_errors(tmp_path, capsys, args, msg):
    f = _disc(tmp_path / "disc.png")
    assert cli.main(["reconstruct", str(f), "--out", str(tmp_path / "o"), *args]) == 2
    assert msg in capsys.readouterr().err


def test_cli_region_outside_an_image_shows_it_whole(tmp_path, capsys):
    """A region that misses an image (here the only one; in a folder, the small ones) no longer
    fails its output set: the overlay shows the whole image, the json and contours are written."""
    f = _disc(tmp_path / "disc.png")
    o = tmp_path / "o"
    assert cli.main(["reconstruct", str(f), "--out", str(o), "--region", "100,100,120,120"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert cv2.imread(str(o / "disc.overlay.png")).shape[:2] == (40, 50)
    assert (o / "disc.json").exists() and (o / "disc.contours.npz").exists()
