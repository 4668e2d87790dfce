"""The generated shapes of scripts/evaluate_synthetic.py: flattening, glyph nesting, new kinds."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import evaluate_synthetic as es  # noqa: E402


def test_bezier_matches_bernstein_form():
    p = np.array([[0.0, 0.0], [1.0, 2.0], [3.0, -1.0], [4.0, 0.5]])
    q = es._bezier(p, 5)
    t = np.arange(1, 6)[:, None] / 5
    ref = (1 - t) ** 3 * p[0] + 3 * (1 - t) ** 2 * t * p[1] + 3 * (1 - t) * t ** 2 * p[2] + t ** 3 * p[3]
    np.testing.assert_allclose(q, ref, atol=1e-12)


@pytest.mark.skipif(not es.fonts_available(), reason="no fontTools or DejaVu fonts")
def test_font_outlines_nest():
    f = es.fonts_available()[0]
    o = es.font_outlines("O", f)          # outer ring and counter, opposite orientations
    assert len(o) == 2
    assert es._signed_area(o[0]) * es._signed_area(o[1]) < 0
    outer, inner = sorted(o, key=lambda c: -abs(es._signed_area(c)))
    assert es._inside(inner[0], outer) and not es._inside(outer[0], inner)
    assert len(es.font_outlines("B", f)) == 3 and len(es.font_outlines("%", f)) == 5


@pytest.mark.parametrize("kind,n", [("rings3", 3), ("close2", 2), ("satellites", 7), ("squares3", 3),
                                    ("crescent", 1), ("dumbbell", 1), ("font", None)])
def test_new_kinds(kind, n):
    c = es.make_case(0, [kind], np.random.default_rng(3), noises=(0.0,))
    k = c["truth"]["n_components"]
    assert k == len(c["truth"]["curves"]) and (n is None or k == n)
    assert len(c["points"]) >= 7 * k
    if kind == "close2":                  # gap of three spacings between the circles
        m = len(c["points"]) // 2
        c0 = np.asarray(c["truth"]["curves"][0]).mean(0)
        c1 = np.asarray(c["truth"]["curves"][1]).mean(0)
        assert math.isclose(np.hypot(*(c1 - c0)) - 2.0, 3 * 2 * math.pi / m, rel_tol=1e-2)
