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
                                    ("crescent", 1), ("dumbbell", 1), ("font", None), ("clutter", 1)])
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


def _ring(cx, r, n=64):
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.stack([cx + r * np.cos(t), r * np.sin(t)], 1)


@pytest.mark.parametrize("recon,expected", [
    ([(0.0, 1.0), (3.0, 1.0)], "right"),
    ([(0.0, 1.0), (3.0, 1.0), (6.0, 0.3)], "extra loop"),            # a speck beside the two
    ([(1.5, 2.6)], "merged or missing"),                            # one curve round both
    ([(0.0, 1.0), (3.0, 1.6)], "off by more than 10%"),             # as many, one drawn elsewhere
])
def test_failure_type_of_scored_cases(recon, expected):
    from torch_isc import metrics
    truth = {"curves": [_ring(0.0, 1.0).tolist(), _ring(3.0, 1.0).tolist()], "n_components": 2}
    pls = [{"points": _ring(cx, r), "closed": True} for cx, r in recon]
    assert es.failure_type(metrics.score_case(pls, truth)) == expected


def test_failure_type_open_chain_first():
    # an open chain is named before the counts (it also makes the closed count short)
    s = dict(topology_ok=False, n_open=1, n_closed=1, n_truth=2)
    assert es.failure_type(s) == "open chain"
    assert es.failure_type(dict(s, n_open=0, n_closed=3)) == "extra loop"


def test_print_misses_counts_by_type(capsys):
    cases = [dict(kind="a", noise="n1")] * 3 + [dict(kind="b", noise="n0")]
    ok = dict(topology_ok=True, n_open=0, n_closed=1, n_truth=1)
    scores = [dict(ok, topology_ok=False, n_closed=2), dict(ok, topology_ok=False, n_closed=2), ok,
              dict(ok, topology_ok=False, n_closed=0)]
    es.print_misses(cases, scores)
    rows = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[2:-1]]
            for ln in capsys.readouterr().out.splitlines() if ln.startswith("| ") and "kind" not in ln}
    assert rows["a"] == ["", "2/0/0/0"] and rows["b"] == ["0/1/0/0", ""]
    assert rows["**all**"] == ["0/1/0/0", "2/0/0/0"]


def test_clutter_adds_a_patch_of_scatter_off_the_curve():
    """The clutter kind: the truth is one ellipse, and a share of the points (the patch) lies
    off it by more than any noise-free sample does, all of them near one place of the curve."""
    for seed in range(4):
        c = es.make_case(0, ["clutter"], np.random.default_rng(seed), noises=(0.0,))
        P, T = np.asarray(c["points"]), np.asarray(c["truth"]["curves"][0])
        d = np.sqrt(((P[:, None, :] - T[None, :, :]) ** 2).sum(-1)).min(1)
        diag = float(np.hypot(*(T.max(0) - T.min(0))))
        off = P[d > 5e-3 * diag]                  # beyond half the truth samples' spacing
        assert len(off) >= 0.05 * len(P)
        # the patch is at most 0.2 of the diagonal long: its points are near each other
        assert float(np.hypot(*(off.max(0) - off.min(0)))) <= 0.45 * diag
