"""Measure the reconstruction on many generated point sets with known curves, and on the public
cases turned by other angles: a broader sample than the 24 public cases, for judging a change.

Run from the repository root:

    .venv/bin/python scripts/evaluate_synthetic.py                      # 280 shapes, seed 0
    .venv/bin/python scripts/evaluate_synthetic.py --count 840 --seed 1 --set coverage_test=false
    .venv/bin/python scripts/evaluate_synthetic.py --kinds gapcircle,outliers --count 120
    .venv/bin/python scripts/evaluate_synthetic.py --rotations 8 --count 0   # public cases, 8 angles
    .venv/bin/python scripts/evaluate_synthetic.py --peers                   # + NN-crust, concave hull
    .venv/bin/python scripts/evaluate_synthetic.py --suite broad --peers     # issue 13's families, 192 shapes
    .venv/bin/python scripts/evaluate_synthetic.py --suite sparse            # curves of few points, 72 scenes

Generated shapes (``--kinds``, taken in turn; noise levels 0, 0.25, 0.5, 1% of the truth's
diagonal in turn over each round of kinds; every shape with a random rotation, 80-600 points
per curve, spaced evenly in arclength with a random phase):

- circle, ellipse (axis ratio 0.25-0.7), flower (r = 1 + a cos kt, a 0.15-0.35, k 3-6),
  squircle (|x|^p + |y|^p = 1, p 3-6);
- two: circles of radius 1 and 0.8 with a gap of 0.1-0.6 between them;
- annulus (inner radius 0.4-0.75), nested3 (radii 1, 0.7, 0.35);
- gapcircle, gapflower: one or two arcs of 0.15-0.5 rad with no samples (the truth is closed);
- outliers: an ellipse plus 3-24 points uniform over its box widened by 10% of the diagonal;
- glyph: a character of ``--glyphs`` (default: with holes or without, no dots) drawn by OpenCV's Hershey stroke fonts
  with strokes 40-70 px wide at 1024 px, outlines from ``cv2.findContours`` (outer boundaries and
  holes, simplified to 1 px), 240-1800 points in all.

Further kinds (``--suite broad`` runs them at noise 0, 0.5, 1, 2% with ``--noises``):

- font: a character of ``--font-glyphs`` (letters, digits, & @ % # $ ...; no glyph with a detached
  dot) in one of ten DejaVu TrueType fonts (sans, serif, mono, math; bold, condensed), outlines
  read with fontTools and flattened here (12 points per Bezier segment); outer contours and
  holes, their nesting checked against their orientation; 240-1800 points in all. Without
  fontTools or the font files: Hershey glyphs instead (a notice says so);
- rings3: three concentric circles with gaps of 9-11 noise widths at 1% noise;
- close2: two unit circles 3 sample spacings apart (80-600 points each);
- satellites: a unit circle and six circles of radius 0.12-0.18 at distance 1.5, 7-9 points each;
- squares3: three concentric squares (half-sizes 1, 0.7, 0.4);
- crescent: a unit disc minus a disc of radius 0.8-0.9 shifted by 0.3-0.45 (two sharp tips);
- dumbbell: two unit discs 1.2 apart joined by a neck of half-width 0.12-0.2.

Sparse kinds (``--suite sparse`` runs them at noise 0, 0.25, 0.5%): every curve of few points, so
that curvature, not noise, fills each point's neighbourhood:

- ringgrid: 2x2 to 6x6 unit circles of 10-24 points each, 2.5-5 sample spacings apart;
- scatter: 4-12 circles of radius 0.3-1 at random, 10-24 points on a circle of radius 0.65 (the
  same spacing on all), 3-8 spacings apart;
- sparsefont: a font glyph (as ``font``) of 90-200 points in all.

A kind of no suite (``--kinds clutter``), the failure mode of ``fitconnect/Monitor0.txt``:

- clutter: an ellipse (axis ratio 0.4-0.9) with a patch of uniform 2D scatter straddling it: an
  elliptic patch 0.08-0.2 of the diagonal along the curve and 0.025-0.06 across it, centred up to
  half its width off the curve, holding 1-3 times the points the curve has along that length;
  in half the cases the curve's own samples under the patch are taken away. The truth is the
  ellipse alone.

Cells of the tables: right topology / cases, median Hausdorff and median Chamfer (% of the
truth's diagonal).

The public cases (``--rotations K``) are turned about the origin by K angles spread over
(0, 60) degrees (the hexagonal initial mesh repeats every 60 degrees), truth included: the
public table at 0 degrees is one draw of the mesh's alignment with shapes that are themselves
axis-aligned. Scoring is :func:`torch_isc.metrics.score_case` (the cases' rule: one-to-one
match within 10% Hausdorff). All sets go through ONE ``reconstruct_batch`` call. A measuring
tool: it exits 0 whatever the scores.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = Path(__file__).resolve().parent
for _p in (str(REPO), str(SCRIPTS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import torch_isc  # noqa: E402
from _common import (Curve, add_run_args, arclength_samples, ellipse, flower, resolve_dir,  # noqa: E402
                     run_main, setup_run)
from torch_isc import metrics  # noqa: E402

KINDS = ("circle", "ellipse", "flower", "two", "annulus", "squircle", "nested3", "gapcircle", "gapflower",
         "outliers", "glyph")           # the default (record_outputs' synthetic suite draws these)
ALL_KINDS = KINDS + ("font", "rings3", "close2", "satellites", "squares3", "crescent", "dumbbell", "ringgrid",
                     "scatter", "sparsefont", "clutter")
GLYPHS = "ABDOPQRabdegopq04689CGSUVXZ235"
NOISES = (0.0, 0.25, 0.5, 1.0)          # % of the truth's diagonal
# issue 13's families: font glyphs weighted 4 of 12 (several fonts, letters, digits, symbols),
# close and nested curves, small components of few points, sharp corners and tips, a neck, gaps,
# outliers; 192 shapes = per noise level 16 glyphs and 4 of each other family
BROAD_KINDS = ("font", "rings3", "close2", "satellites", "font", "squares3", "crescent", "dumbbell",
               "font", "gapcircle", "outliers", "font")
# sparsely sampled scenes: every curve of few points (10-24 to a small circle), so that the item's
# own curvature, not the noise, dominates each neighbourhood
SPARSE_KINDS = ("ringgrid", "scatter", "sparsefont")
SUITES = {"broad": dict(kinds=",".join(BROAD_KINDS), noises="0,0.5,1,2", count=192),
          "sparse": dict(kinds=",".join(SPARSE_KINDS), noises="0,0.25,0.5", count=72)}


def squircle(p: float) -> Curve:
    def fn(t):
        c, s = np.cos(t), np.sin(t)
        return np.stack([np.sign(c) * np.abs(c) ** (2 / p), np.sign(s) * np.abs(s) ** (2 / p)], 1)
    return fn


def polyline_curve(poly: np.ndarray) -> Curve:
    """The closed polyline ``poly (n, 2)`` as a curve of ``t in [0, 2 pi]`` (by arclength)."""
    q = np.concatenate([poly, poly[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*(q[1:] - q[:-1]).T))])

    def fn(t):
        u = np.asarray(t) / (2 * math.pi) * s[-1]
        return np.stack([np.interp(u, s, q[:, 0]), np.interp(u, s, q[:, 1])], 1)
    return fn


def glyph_outlines(ch: str, font: int, thickness: int) -> List[np.ndarray]:
    """The outlines of ``ch`` drawn by OpenCV's stroke font (outer boundaries and holes), as
    closed polylines in a unit-height frame (y up), from a 1024 px rendering."""
    import cv2
    size = 1024
    img = np.zeros((size, size), np.uint8)
    scale = 18.0
    (w, h), _ = cv2.getTextSize(ch, font, scale, thickness)
    cv2.putText(img, ch, ((size - w) // 2, (size + h) // 2), font, scale, 255, thickness, cv2.LINE_AA)
    contours, _ = cv2.findContours((img > 127).astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in contours:
        if cv2.contourArea(c) < 400:                  # specks of the anti-aliasing
            continue
        c = cv2.approxPolyDP(c, 1.0, True)[:, 0, :].astype(np.float64)
        out.append(np.stack([c[:, 0], size - c[:, 1]], 1) / size)
    return out


# ----------------------------------------------------------------------------- TrueType glyphs
FONT_DIR = Path("/usr/share/fonts/truetype/dejavu")
FONT_FILES = ("DejaVuSans.ttf", "DejaVuSerif.ttf", "DejaVuSansMono.ttf", "DejaVuMathTeXGyre.ttf",
              "DejaVuSans-Bold.ttf", "DejaVuSerif-Bold.ttf", "DejaVuSansMono-Bold.ttf",
              "DejaVuSansCondensed.ttf", "DejaVuSerifCondensed.ttf", "DejaVuSansCondensed-Bold.ttf")
# counters, thin strokes, sharp inner corners, several components (% and the like); no glyph
# with a detached dot or accent (i j ? ! ; :), which would be a speck of a few points
FONT_GLYPHS = "&@%#$8B0469ABDOPQRagbdegopqs2357GKMSWXkwy"
_FONTS: Dict[str, Any] = {}


def fonts_available() -> List[str]:
    """The DejaVu font files of :data:`FONT_FILES` that exist here and that fontTools reads."""
    try:
        import fontTools.ttLib  # noqa: F401
    except ImportError:
        return []
    return [f for f in FONT_FILES if (FONT_DIR / f).is_file()]


def _bezier(p: np.ndarray, n: int) -> np.ndarray:
    """``n`` points of the Bezier curve with control points ``p (k, 2)`` at t = 1/n .. 1
    (de Casteljau; the start point is the previous segment's end)."""
    t = np.arange(1, n + 1)[:, None, None] / n
    q = np.broadcast_to(p, (n,) + p.shape).copy()
    while q.shape[1] > 1:
        q = (1 - t) * q[:, :-1] + t * q[:, 1:]
    return q[:, 0]


def _outline_pen():
    """A fontTools pen that flattens the outline: lines kept, every quadratic or cubic segment
    sampled at 12 points (BasePen splits TrueType's implied on-curve points for us)."""
    from fontTools.pens.basePen import BasePen

    class Pen(BasePen):
        def __init__(self):
            super().__init__(None)
            self.contours: List[np.ndarray] = []
            self._cur: List[np.ndarray] = []

        def _moveTo(self, pt):
            self._cur = [np.asarray([pt], np.float64)]

        def _lineTo(self, pt):
            self._cur.append(np.asarray([pt], np.float64))

        def _curveToOne(self, p1, p2, p3):
            self._cur.append(_bezier(np.asarray([self._getCurrentPoint(), p1, p2, p3], np.float64), 12))

        def _qCurveToOne(self, p1, p2):
            self._cur.append(_bezier(np.asarray([self._getCurrentPoint(), p1, p2], np.float64), 12))

        def _closePath(self):
            c = np.concatenate(self._cur)
            if len(c) > 1 and np.allclose(c[0], c[-1]):
                c = c[:-1]
            if len(c) >= 3:
                self.contours.append(c)
            self._cur = []

        _endPath = _closePath

    return Pen()


def _signed_area(c: np.ndarray) -> float:
    x, y = c[:, 0], c[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _inside(p: np.ndarray, poly: np.ndarray) -> bool:
    """Even-odd test of the point ``p`` against the closed polygon ``poly``."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = (y > p[1]) != (yn > p[1])
    xs = x + (p[1] - y) * (xn - x) / np.where(yn == y, 1.0, yn - y)
    return bool(np.sum(cross & (p[0] < xs)) % 2)


def font_outlines(ch: str, font_file: str) -> Optional[List[np.ndarray]]:
    """The contours of ``ch`` in ``font_file`` (closed polylines, em units scaled to 1), or
    None when the font lacks the glyph or its contours are not properly nested: every contour's
    depth (how many contours enclose it) must match its orientation (TrueType: outer contours
    clockwise, holes anticlockwise), else the truth would not be a set of disjoint curves."""
    from fontTools.ttLib import TTFont
    if font_file not in _FONTS:
        _FONTS[font_file] = TTFont(str(FONT_DIR / font_file))
    font = _FONTS[font_file]
    name = font.getBestCmap().get(ord(ch))
    if name is None:
        return None
    pen = _outline_pen()
    font.getGlyphSet()[name].draw(pen)
    em = float(font["head"].unitsPerEm)
    cs = [c / em for c in pen.contours if abs(_signed_area(c)) > 1e-4 * em * em]
    if not cs:
        return None
    for i, c in enumerate(cs):
        depth = sum(_inside(c[0], d) for j, d in enumerate(cs) if j != i)
        if (depth % 2 == 0) != (_signed_area(c) < 0):
            return None
    return cs


def make_case(i: int, kinds: Sequence[str], rng: np.random.Generator, glyphs: str = GLYPHS,
              noises: Sequence[float] = NOISES, font_glyphs: str = FONT_GLYPHS,
              points: Optional[int] = None) -> Dict[str, Any]:
    """Case ``i``: kind ``kinds[i % len(kinds)]``; ``points``: the samples on its curves in all
    (before gaps and outliers), instead of the random count (kinds with their own counts keep them)."""
    kind = kinds[i % len(kinds)]
    noise = noises[(i // len(kinds)) % len(noises)]
    extra: Dict[str, Any] = {}
    counts: Optional[List[int]] = None
    if kind == "circle":
        fns = [ellipse(1, 1)]
    elif kind == "ellipse":
        fns = [ellipse(1, rng.uniform(0.25, 0.7))]
    elif kind in ("flower", "gapflower"):
        fns = [flower(rng.uniform(0.15, 0.35), int(rng.integers(3, 7)))]
    elif kind == "two":
        g = rng.uniform(0.1, 0.6)
        fns = [ellipse(1, 1, -1 - g / 2), ellipse(0.8, 0.8, 0.8 + g / 2)]
    elif kind == "annulus":
        r = rng.uniform(0.4, 0.75)
        fns = [ellipse(1, 1), ellipse(r, r)]
    elif kind == "squircle":
        fns = [squircle(rng.uniform(3, 6))]
    elif kind == "nested3":
        fns = [ellipse(1, 1), ellipse(0.7, 0.7), ellipse(0.35, 0.35)]
    elif kind in ("gapcircle", "outliers"):
        fns = [ellipse(1, rng.uniform(0.6, 1.0))]
    elif kind == "clutter":
        fns = [ellipse(1, rng.uniform(0.4, 0.9))]
    elif kind == "glyph":
        import cv2
        ch = glyphs[int(rng.integers(len(glyphs)))]
        font = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX)[int(rng.integers(2))]
        fns = [polyline_curve(c) for c in glyph_outlines(ch, font, int(rng.integers(40, 70)))]
    elif kind == "font":
        fonts = fonts_available()
        cs = None
        while cs is None:
            ch = font_glyphs[int(rng.integers(len(font_glyphs)))]
            if fonts:
                ff = fonts[int(rng.integers(len(fonts)))]
                cs = font_outlines(ch, ff)
                extra = dict(glyph=ch, font=ff)
            else:                                      # no DejaVu / fontTools: Hershey instead
                import cv2
                hf = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX)[int(rng.integers(2))]
                cs = glyph_outlines(ch, hf, int(rng.integers(40, 70))) or None
                extra = dict(glyph=ch, font=f"hershey{hf}")
        fns = [polyline_curve(c) for c in cs]
    elif kind == "rings3":
        # gaps of 9-11 noise widths at 1% noise (1% of the diagonal 2 sqrt 2)
        g = rng.uniform(9, 11) * 0.01 * 2 * math.sqrt(2)
        fns = [ellipse(1, 1), ellipse(1 - g, 1 - g), ellipse(1 - 2 * g, 1 - 2 * g)]
    elif kind == "close2":
        m = int(rng.uniform(80, 600))                 # points per circle; gap = 3 spacings
        h = 2 * math.pi / m
        fns = [ellipse(1, 1, -1 - 1.5 * h), ellipse(1, 1, 1 + 1.5 * h)]
        counts = [m, m]
    elif kind == "satellites":
        rs = rng.uniform(0.12, 0.18)
        a0 = rng.uniform(0, 2 * math.pi)
        cen = [(1.5 * math.cos(a0 + k * math.pi / 3), 1.5 * math.sin(a0 + k * math.pi / 3)) for k in range(6)]
        fns = [ellipse(1, 1)] + [ellipse(rs, rs, cx, cy) for cx, cy in cen]
        counts = [int(rng.uniform(80, 600))] + [int(rng.integers(7, 10)) for _ in cen]
    elif kind == "squares3":
        sq = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
        fns = [polyline_curve(sq * r) for r in (1.0, 0.7, 0.4)]
    elif kind == "crescent":
        from shapely.geometry import Point
        d, r2 = rng.uniform(0.3, 0.45), rng.uniform(0.8, 0.9)
        poly = Point(0, 0).buffer(1.0, quad_segs=256).difference(Point(d, 0).buffer(r2, quad_segs=256))
        fns = [polyline_curve(np.asarray(poly.exterior.coords)[:-1])]
    elif kind == "dumbbell":
        from shapely.geometry import Point, box
        w = rng.uniform(0.12, 0.2)                    # half-width of the neck (discs of radius 1)
        poly = Point(-1.6, 0).buffer(1.0, quad_segs=256).union(Point(1.6, 0).buffer(1.0, quad_segs=256)).union(
            box(-1.6, -w, 1.6, w))
        fns = [polyline_curve(np.asarray(poly.exterior.coords)[:-1])]
    elif kind == "ringgrid":
        g, m = int(rng.integers(2, 7)), int(rng.integers(10, 25))          # g x g unit circles, m points each
        pitch = 2 + rng.uniform(2.5, 5.0) * 2 * math.pi / m                # gaps of 2.5-5 spacings
        fns = [ellipse(1, 1, i * pitch, j * pitch) for i in range(g) for j in range(g)]
        counts = [m] * len(fns)
    elif kind == "scatter":
        # 4-12 circles of radius 0.3-1, 10-24 points each at one spacing, 3-8 spacings apart
        h = 2 * math.pi * 0.65 / int(rng.integers(10, 25))
        cs: List[Tuple[float, float, float]] = []
        want = int(rng.integers(4, 13))
        for _ in range(400):
            if len(cs) == want:
                break
            r = rng.uniform(0.3, 1.0)
            x, y = rng.uniform(-4, 4, 2)
            if all(math.hypot(x - a, y - b) > r + c + rng.uniform(3, 8) * h for a, b, c in cs):
                cs.append((x, y, r))
        fns = [ellipse(r, r, x, y) for x, y, r in cs]
        counts = [max(6, int(round(2 * math.pi * r / h))) for _, _, r in cs]
    elif kind == "sparsefont":
        glyph = make_case(i, ("font",), rng, glyphs, (0.0,), font_glyphs)
        extra = {k: glyph[k] for k in ("glyph", "font") if k in glyph}
        fns = [polyline_curve(np.asarray(c)) for c in glyph["truth"]["curves"]]
        points = int(rng.integers(90, 200))          # its own count, as the kinds with counts
    else:
        raise ValueError(f"unknown kind {kind!r} (known: {', '.join(ALL_KINDS)})")
    lengths = [arclength_samples(f, 8, 0.0)[1] for f in fns]
    if counts is None:
        n = int(rng.uniform(80, 600)) * (len(fns) if kind not in ("glyph", "font") else 3)
        n = n if points is None else points
        counts = [max(12, int(round(n * ln / sum(lengths)))) for ln in lengths]
    pts = np.concatenate([arclength_samples(f, c, rng.uniform())[0] for f, c in zip(fns, counts)])
    truth = [arclength_samples(f, 1000, 0.0)[0] for f in fns]
    allt = np.concatenate(truth)
    lo, hi = allt.min(0), allt.max(0)
    diag = float(np.hypot(*(hi - lo)))
    pts = pts + rng.normal(0.0, noise / 100 * diag, pts.shape)
    if kind.startswith("gap"):
        a0 = rng.uniform(-math.pi, math.pi)
        for k in range(int(rng.integers(1, 3))):
            width = rng.uniform(0.15, 0.5)
            ang = np.arctan2(pts[:, 1], pts[:, 0])
            off = np.angle(np.exp(1j * (ang - (a0 + math.pi * k))))
            pts = pts[np.abs(off) > width / 2]
    if kind == "outliers":
        m = int(rng.integers(3, 25))
        pts = np.concatenate([pts, rng.uniform(lo - 0.1 * diag, hi + 0.1 * diag, (m, 2))])
    if kind == "clutter":
        pts = _add_clutter(pts, truth[0], counts[0] / lengths[0], diag, rng)
    a = rng.uniform(0, 2 * math.pi)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return dict(name=f"{kind}_{i}", kind=kind, noise=f"n{noise:g}", points=pts @ R.T, **extra,
                truth={"curves": [(c @ R.T).tolist() for c in truth], "n_components": len(fns)})


def _add_clutter(pts: np.ndarray, curve: np.ndarray, density: float, diag: float,
                 rng: np.random.Generator) -> np.ndarray:
    """``pts`` with a patch of uniform 2D scatter about a random point of ``curve`` (dense
    samples of the truth), along its tangent: see the module's ``clutter`` kind. ``density``:
    the curve's samples per unit length."""
    k = int(rng.integers(len(curve)))
    t = curve[(k + 5) % len(curve)] - curve[k - 5]
    t = t / np.linalg.norm(t)
    nrm = np.array([-t[1], t[0]])
    a, b = rng.uniform(0.08, 0.2) * diag, rng.uniform(0.025, 0.06) * diag
    c0 = curve[k] + nrm * rng.uniform(-0.5, 0.5) * b
    m = int(density * 2 * a * rng.uniform(1.0, 3.0))
    r, th = np.sqrt(rng.uniform(0, 1, m)), rng.uniform(0, 2 * math.pi, m)
    patch = c0 + (a * r * np.cos(th))[:, None] * t + (b * r * np.sin(th))[:, None] * nrm
    if rng.uniform() < 0.5:                    # the curve's own samples under the patch taken away
        d = pts - c0
        pts = pts[(d @ t / a) ** 2 + (d @ nrm / b) ** 2 >= 1]
    return np.concatenate([pts, patch])


def rotated_public(cases_dir: Path, k: int) -> List[Dict[str, Any]]:
    import evaluate_cases as ev
    base = ev.load_cases(cases_dir, None)
    out = []
    for j in range(k):
        deg = 60.0 * (j + 0.5) / k
        th = math.radians(deg)
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        for c in base:
            truth = dict(c["truth"], curves=[(np.asarray(cv) @ R.T).tolist() for cv in c["truth"]["curves"]])
            shape = c["name"].rsplit("_n", 1)[0]
            out.append(dict(name=f"{c['name']}@{deg:.1f}", kind=f"public {shape}", noise=c["noise"],
                            points=np.asarray(c["points"]) @ R.T, truth=truth))
    return out


def score(cases: List[Dict[str, Any]], polylines: List[Any]) -> List[Dict[str, Any]]:
    return [metrics.score_case(pl, c["truth"]) for c, pl in zip(cases, polylines)]


#: the failure types of :func:`failure_type`, in the order the misses table lists them
FAILURES = ("extra loop", "merged or missing", "open chain", "off by more than 10%")


def failure_type(s: Dict[str, Any]) -> str:
    """Why a case scored wrong, from its :func:`metrics.score_case` dict: ``"right"``; an open
    chain; more closed curves than the truth (a stroke cut in two, a speck, a loop at a corner:
    "extra loop"); fewer (two curves merged, a counter filled, a small component missed:
    "merged or missing"); or as many as the truth but one of them not matched within 10% of the
    diagonal (a tip or a stroke cut off, a curve drawn elsewhere)."""
    if s["topology_ok"]:
        return "right"
    if s["n_open"] > 0:
        return "open chain"
    if s["n_closed"] > s["n_truth"]:
        return "extra loop"
    if s["n_closed"] < s["n_truth"]:
        return "merged or missing"
    return "off by more than 10%"


def print_misses(cases, scores) -> None:
    """The wrong cases counted by kind, noise level and :func:`failure_type`."""
    kinds = list(dict.fromkeys(c["kind"] for c in cases))
    noises = sorted({c["noise"] for c in cases}, key=lambda s: float(s[1:]))
    print("## misses by failure type\n")
    print("cells: extra loop / merged or missing / open chain / off by more than 10% (cases)\n")
    print("| kind | " + " | ".join(f"noise {n[1:]}%" for n in noises) + " |")
    print("|---|" + "---:|" * len(noises))
    for k in kinds + [None]:
        cells = []
        for n in noises:
            ft = [failure_type(s) for c, s in zip(cases, scores) if (k is None or c["kind"] == k) and c["noise"] == n]
            cells.append("/".join(str(ft.count(f)) for f in FAILURES) if ft else "")
        print(f"| {'**all**' if k is None else k} | " + " | ".join(cells) + " |")
    print()


def _cell(rows) -> str:
    """``right/n H C``: the right-topology count, median Hausdorff and median Chamfer (% of the
    truth's diagonal) of the scores ``rows``."""
    if not rows:
        return ""
    ok = sum(bool(s["topology_ok"]) for s in rows)
    h = 100 * statistics.median(s["hausdorff"] for s in rows)
    c = 100 * statistics.median(s["chamfer"] for s in rows)
    return f"{ok}/{len(rows)} {h:.2f} {c:.2f}"


def print_summary(title: str, cases, scores, seconds: float) -> Tuple[int, int]:
    kinds = list(dict.fromkeys(c["kind"] for c in cases))
    noises = sorted({c["noise"] for c in cases}, key=lambda s: float(s[1:]))
    print(f"## {title}\n")
    print("cells: right topology / cases, median Hausdorff %, median Chamfer % (of the truth's diagonal)\n")
    print("| kind | " + " | ".join(f"noise {n[1:]}%" for n in noises) + " | all |")
    print("|---|" + "---:|" * (len(noises) + 1))
    for k in kinds + [None]:
        sel = [(c, s) for c, s in zip(cases, scores) if k is None or c["kind"] == k]
        cells = [_cell([s for c, s in sel if c["noise"] == n]) for n in noises] + [_cell([s for _, s in sel])]
        label = "**all**" if k is None else k
        print(f"| {label} | " + " | ".join(cells) + " |")
    ok = [bool(s["topology_ok"]) for s in scores]
    print(f"\ntopology right: {sum(ok)} of {len(ok)}; {seconds:.2f} s\n")
    return sum(ok), len(ok)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", choices=sorted(SUITES), default=None,
                    help="a preset of --kinds, --noises and --count (broad: the families of issue 13 at "
                         "noise 0, 0.5, 1, 2%%); explicit options override it")
    ap.add_argument("--count", type=int, default=None, help="generated shapes (default 280)")
    ap.add_argument("--seed", type=int, default=0, help="generator seed (default 0)")
    ap.add_argument("--kinds", default=None, help=f"comma list, taken in turn (default: {','.join(KINDS)}; "
                                                  f"all: {','.join(ALL_KINDS)})")
    ap.add_argument("--noises", default=None, help="comma list of noise levels, %% of the truth's diagonal, taken "
                                                   "in turn over each round of kinds (default 0,0.25,0.5,1)")
    ap.add_argument("--font-glyphs", default=FONT_GLYPHS, help="characters of the font kind (default " + FONT_GLYPHS.replace("%", "%%") + ")")
    ap.add_argument("--glyphs", default=GLYPHS, help=f"characters of the glyph kind (default {GLYPHS})")
    ap.add_argument("--rotations", type=int, default=0, help="also the public cases turned by K angles (default 0)")
    ap.add_argument("--cases", default=None, help="public cases folder (default: ../shared/cases)")
    ap.add_argument("--peers", action="store_true", help="also score NN-crust and shapely.concave_hull")
    ap.add_argument("--json", default=None, help="write every case's name and score here")
    ap.add_argument("--only-noise", type=float, default=None, metavar="PCT",
                    help="keep only the generated shapes at this noise level (the same shapes as in the full run)")
    ap.add_argument("--misses", action="store_true", help="also count the wrong cases by failure type "
                                                          "(extra loop, merged or missing, open chain, off by >10%%)")
    add_run_args(ap, "set")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    config = setup_run(args)
    suite = SUITES.get(args.suite, {})
    kinds = [k.strip() for k in (args.kinds or suite.get("kinds") or ",".join(KINDS)).split(",") if k.strip()]
    noises = tuple(float(x) for x in (args.noises or suite.get("noises") or ",".join(map(str, NOISES))).split(","))
    count = args.count if args.count is not None else suite.get("count", 280)
    unknown = [k for k in kinds if k not in ALL_KINDS]
    if unknown:
        print(f"--kinds: unknown {', '.join(unknown)} (known: {', '.join(ALL_KINDS)})", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    if "font" in kinds and not fonts_available():
        print(f"font kind: no fontTools or no DejaVu fonts in {FONT_DIR}; Hershey glyphs instead", file=sys.stderr)
    cases = [make_case(i, kinds, rng, args.glyphs, noises, args.font_glyphs) for i in range(count)]
    if args.rotations > 0:
        cases += rotated_public(resolve_dir(args.cases, REPO / ".." / "shared" / "cases"), args.rotations)
    if args.only_noise is not None:
        cases = [c for c in cases if c["noise"] == f"n{args.only_noise:g}"]
    if args.filter:
        cases = [c for c in cases if args.filter in c["name"]]
    if not cases:
        print("no set to reconstruct", file=sys.stderr)
        return 2
    print(f"{len(cases)} point set(s): {count} generated (seed {args.seed}{', suite ' + args.suite if args.suite else ''}), public cases at "
          f"{args.rotations} angle(s); config overrides: {' '.join(args.set) or 'none'}\n")
    sets = [torch.as_tensor(c["points"], dtype=torch.float64, device=args.device) for c in cases]
    t0 = time.perf_counter()
    if args.one_by_one:
        results = [torch_isc.reconstruct_batch([s], config)[0] for s in sets]
    else:
        results = torch_isc.reconstruct_batch(sets, config)
    seconds = time.perf_counter() - t0
    scores = score(cases, [r.polylines for r in results])
    print_summary("torch_isc", cases, scores, seconds)
    # how far the results' own convergence flag can be trusted: its limits against the scores
    flags: Dict[Tuple[str, str], int] = {}
    for r, s in zip(results, scores):
        key = (r.limit or "converged", "right" if s["topology_ok"] else "wrong")
        flags[key] = flags.get(key, 0) + 1
    print("limit (converged = none), right / wrong topology: "
          + "; ".join(f"{lim} {flags.get((lim, 'right'), 0)} / {flags.get((lim, 'wrong'), 0)}"
                      for lim in sorted({k[0] for k in flags})) + "\n")
    if args.misses:
        print_misses(cases, scores)
    if args.peers:
        import evaluate_cases as ev
        for name, fn in ev.PEERS.items():
            try:
                t1 = time.perf_counter()
                pls = [fn(np.asarray(c["points"])) for c in cases]
            except ImportError as e:
                print(f"{name}: skipped ({e})\n")
                continue
            print_summary(name, cases, score(cases, pls), time.perf_counter() - t1)
    if args.json:
        rows = [dict(name=c["name"], kind=c["kind"], noise=c["noise"], glyph=c.get("glyph"), font=c.get("font"), topology_ok=bool(s["topology_ok"]),
                     hausdorff=float(s["hausdorff"]), chamfer=float(s["chamfer"]), n_closed=int(s["n_closed"]),
                     n_open=int(s["n_open"]), n_truth=int(s["n_truth"]), failure=failure_type(s), limit=r.limit)
                for c, s, r in zip(cases, scores, results)]
        torch_isc.io.atomic_write(args.json, json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    run_main(main)
