"""Fuzz round 14 (session 27): the defects found, each checked against the behaviour the standards
ask for (nothing silent, no library internals printed, stats in the caller's units).

- 7 or 8 points of a circle, or four specks of 3 points far apart: one small loop far from every
  point, ``converged`` with every point beyond the tolerance (no triangle held enough points to
  be tested): now ``unresolved``, not converged;
- the stats of a float32 item of scale 1e-300 gave tolerance 0 and ``max_error`` NaN (the frame's
  scale was cast to float32 first);
- float8 masks: a raw ``NotImplementedError`` from torch;
- ``--mode edges --spacing 2`` printed torch's beta warning for ``index_reduce_``, and
  ``find_contours(offset=(1e300, 0))`` numpy's overflow warning before its own error.
"""
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch

import torch_isc
from torch_isc import images


def _ring(n):
    t = np.linspace(0, 2 * np.pi, n + 1)[:-1]
    return np.stack([np.cos(t), np.sin(t)], 1)


@pytest.mark.parametrize("n", [7, 8])
def test_few_points_of_a_circle_are_not_converged_around_a_speck(n):
    r = torch_isc.reconstruct(torch.tensor(_ring(n)))
    s = r.stats[-1]
    # the case itself: every point beyond the tolerance of the curve it got
    assert s.points_beyond_tolerance == n
    assert not r.converged and r.limit == "unresolved"


def test_enough_points_of_a_circle_still_converge():
    r = torch_isc.reconstruct(torch.tensor(_ring(12)))
    assert r.converged and r.limit is None and r.num_closed == 1
    assert r.stats[-1].points_beyond_tolerance == 0


def test_four_specks_far_apart_are_not_one_converged_loop():
    c = np.array([[0, 0], [0, 100], [100, 0], [100, 100]], float)
    p = (c[:, None, :] + _ring(3)[None]).reshape(-1, 2)
    r = torch_isc.reconstruct(torch.tensor(p))
    assert r.stats[-1].points_beyond_tolerance == 12
    assert not r.converged and r.limit == "unresolved"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("scale", [1e-300, 1e-310])
def test_stats_keep_tiny_scales(dtype, scale):
    """The tolerance and noise of an item scaled by ``scale`` are ``scale`` times those of the
    unscaled item (they were 0, and ``max_error`` NaN, in float32 working precision)."""
    p = torch.tensor(_ring(8) * scale)
    cfg = torch_isc.ReconstructConfig().replace(dtype="float32" if dtype == torch.float32 else "float64")
    one = torch_isc.reconstruct(torch.tensor(_ring(8)), cfg).stats[-1]
    s = torch_isc.reconstruct(p, cfg).stats[-1]
    assert s.tolerance / scale == pytest.approx(one.tolerance, rel=1e-6)
    assert s.noise / scale == pytest.approx(one.noise, rel=1e-6)
    assert not np.isnan(s.max_error)


@pytest.mark.parametrize("dt", [torch.float8_e4m3fn, torch.float8_e5m2, torch.float8_e4m3fnuz])
def test_float8_masks_read_as_float(dt):
    m = np.zeros((10, 10), np.float32)
    m[2:7, 3:8] = 1
    ref, ref_h = images.find_contours(m)
    got, got_h = images.find_contours(torch.tensor(m).to(dt))
    assert len(got) == len(ref) == 1
    assert np.array_equal(got[0], ref[0]) and np.array_equal(got_h, ref_h)


def test_huge_offset_error_prints_no_numpy_warning():
    m = np.zeros((10, 10), np.uint8)
    m[2:7, 3:8] = 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(images.ImageError, match="beyond what float32 holds"):
            images.find_contours(m, offset=(1e300, 0))


def test_edges_with_spacing_print_nothing_of_torch(tmp_path):
    import cv2
    y, x = np.mgrid[:64, :64]
    cv2.imwrite(str(tmp_path / "disc.png"), (((x - 32) ** 2 + (y - 32) ** 2 < 400) * 255).astype(np.uint8))
    code = ("import sys, warnings; warnings.simplefilter('error'); from torch_isc.cli import main; "
            "sys.exit(main(sys.argv[1:]))")
    r = subprocess.run([sys.executable, "-c", code, "reconstruct", str(tmp_path / "disc.png"), "--out",
                        str(tmp_path / "o"), "--mode", "edges", "--spacing", "2", "--formats", "json"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Warning" not in r.stderr and "disc: 1 closed" in r.stdout + r.stderr
