"""Measure the reconstruction on many generated point sets with known curves, and on the public
cases turned by other angles: a broader sample than the 24 public cases, for judging a change.

Run from the repository root:

    .venv/bin/python scripts/evaluate_synthetic.py                      # 280 shapes, seed 0
    .venv/bin/python scripts/evaluate_synthetic.py --count 840 --seed 1 --set coverage_test=false
    .venv/bin/python scripts/evaluate_synthetic.py --kinds gapcircle,outliers --count 120
    .venv/bin/python scripts/evaluate_synthetic.py --rotations 8 --count 0   # public cases, 8 angles
    .venv/bin/python scripts/evaluate_synthetic.py --peers                   # + NN-crust, concave hull

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
         "outliers", "glyph")
GLYPHS = "ABDOPQRabdegopq04689CGSUVXZ235"
NOISES = (0.0, 0.25, 0.5, 1.0)          # % of the truth's diagonal


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


def make_case(i: int, kinds: Sequence[str], rng: np.random.Generator, glyphs: str = GLYPHS,
              points: Optional[int] = None) -> Dict[str, Any]:
    """Case ``i``: kind ``kinds[i % len(kinds)]``; ``points``: the samples on its curves in all
    (before gaps and outliers), instead of the random count."""
    kind = kinds[i % len(kinds)]
    noise = NOISES[(i // len(kinds)) % len(NOISES)]
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
    elif kind == "glyph":
        import cv2
        ch = glyphs[int(rng.integers(len(glyphs)))]
        font = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX)[int(rng.integers(2))]
        fns = [polyline_curve(c) for c in glyph_outlines(ch, font, int(rng.integers(40, 70)))]
    else:
        raise ValueError(f"unknown kind {kind!r} (known: {', '.join(KINDS)})")
    n = int(rng.uniform(80, 600)) * (len(fns) if kind != "glyph" else 3)
    n = n if points is None else points
    lengths = [arclength_samples(f, 8, 0.0)[1] for f in fns]
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
    a = rng.uniform(0, 2 * math.pi)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return dict(name=f"{kind}_{i}", kind=kind, noise=f"n{noise:g}", points=pts @ R.T,
                truth={"curves": [(c @ R.T).tolist() for c in truth], "n_components": len(fns)})


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


def print_summary(title: str, cases, scores, seconds: float) -> Tuple[int, int]:
    kinds = list(dict.fromkeys(c["kind"] for c in cases))
    noises = sorted({c["noise"] for c in cases}, key=lambda s: float(s[1:]))
    print(f"## {title}\n")
    print("| kind | " + " | ".join(f"topology {n}" for n in noises) + " | all | median H% |")
    print("|---|" + "---:|" * (len(noises) + 2))
    for k in kinds:
        cells = []
        for n in noises:
            ok = [bool(s["topology_ok"]) for c, s in zip(cases, scores) if c["kind"] == k and c["noise"] == n]
            cells.append(f"{sum(ok)}/{len(ok)}" if ok else "")
        ok = [bool(s["topology_ok"]) for c, s in zip(cases, scores) if c["kind"] == k]
        hs = [s["hausdorff"] for c, s in zip(cases, scores) if c["kind"] == k]
        print(f"| {k} | " + " | ".join(cells) + f" | {sum(ok)}/{len(ok)} | {100 * statistics.median(hs):.2f} |")
    cells = []
    for n in noises:
        ok = [bool(s["topology_ok"]) for c, s in zip(cases, scores) if c["noise"] == n]
        hs = [s["hausdorff"] for c, s in zip(cases, scores) if c["noise"] == n]
        cells.append(f"{sum(ok)}/{len(ok)} ({100 * statistics.median(hs):.2f}%)")
    ok = [bool(s["topology_ok"]) for s in scores]
    hs = [s["hausdorff"] for s in scores]
    print("| **all** (median H%) | " + " | ".join(cells) +
          f" | **{sum(ok)}/{len(ok)}** | {100 * statistics.median(hs):.2f} |")
    print(f"\ntopology right: {sum(ok)} of {len(ok)}; {seconds:.2f} s\n")
    return sum(ok), len(ok)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=280, help="generated shapes (default 280)")
    ap.add_argument("--seed", type=int, default=0, help="generator seed (default 0)")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma list, taken in turn (default: {','.join(KINDS)})")
    ap.add_argument("--glyphs", default=GLYPHS, help=f"characters of the glyph kind (default {GLYPHS})")
    ap.add_argument("--rotations", type=int, default=0, help="also the public cases turned by K angles (default 0)")
    ap.add_argument("--cases", default=None, help="public cases folder (default: ../shared/cases)")
    ap.add_argument("--peers", action="store_true", help="also score NN-crust and shapely.concave_hull")
    ap.add_argument("--json", default=None, help="write every case's name and score here")
    add_run_args(ap, "set")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    config = setup_run(args)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        print(f"--kinds: unknown {', '.join(unknown)} (known: {', '.join(KINDS)})", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    cases = [make_case(i, kinds, rng, args.glyphs) for i in range(args.count)]
    if args.rotations > 0:
        cases += rotated_public(resolve_dir(args.cases, REPO / ".." / "shared" / "cases"), args.rotations)
    if args.filter:
        cases = [c for c in cases if args.filter in c["name"]]
    if not cases:
        print("no set to reconstruct", file=sys.stderr)
        return 2
    print(f"{len(cases)} point set(s): {args.count} generated (seed {args.seed}), public cases at "
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
        rows = [dict(name=c["name"], kind=c["kind"], noise=c["noise"], topology_ok=bool(s["topology_ok"]),
                     hausdorff=float(s["hausdorff"]), n_closed=int(s["n_closed"])) for c, s in zip(cases, scores)]
        torch_isc.io.atomic_write(args.json, json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    run_main(main)
