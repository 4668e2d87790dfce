"""Curves from binary masks: torch_isc against cv2.findContours and skimage.measure.find_contours.

Run from the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_masks.py
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_masks.py --out out/masks     # + overlays
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_masks.py --no-oracle          # topology estimated
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_masks.py --grid               # the grid path
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_masks.py --shapes --seeds 0,1  # analytic shapes
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_masks.py --shapes --tips --seeds 0,1  # the misses' corners

``--shapes`` scores the grid path instead on antialiased analytic shapes
(``torch_isc.images.shapes``: the fixed set ``SHAPES`` and, per seed, ``corner_shapes(seed)``:
squares of 3 to 290 px, wedges of 20 to 150 degrees, regular polygons, stars and L notches at
random rotations and offsets), each thresholded at coverage 1/2: per shape the mean distance
from each method's curves to the truth (along the curves) and the maximum distance in both
directions (curve to truth, truth to curve: a tip a method cuts off shows in the second), for
torch_isc (``images.trace_masks``), ``skimage.measure.find_contours(0.5)`` and
``cv2.findContours``; whether torch_isc's mean is below both and its maximum at most 0.55 px.
With ``--tips``, for each shape above 0.55 px instead: the corner where torch_isc is farthest
from the truth, and how far that corner can be cut (chamfered across its bisector) and extended
(moved out along it, its sides pivoting) with the mask unchanged (:func:`tip_slack`): where the
two shapes are more than 1.1 px apart, no curve drawn from that mask is within 0.55 px of both.

For each distinct truth of ``../shared/cases`` (the truth curves are the same at every noise
level, so there are 6 shapes), the region bounded by the true curves (even-odd) is rendered as
a ``SIZE x SIZE`` binary mask (default 256), the truth's bounding box scaled to fill the image
less a 10% margin. All three methods read the same masks, and every output is compared with
the analytic truth mapped into the image, in pixels (the pixel convention of
``torch_isc.images``: pixel (i, j) covers [j, j+1] x [i, i+1]):

- torch_isc: ``torch_isc.images.reconstruct_masks`` on all masks in one batch (boundary points
  on the pixel cracks, 1 pixel apart, signs from the mask), default image settings;
  with ``--grid``, ``torch_isc.images.grid_results`` instead (the mask mode of the CLI: the
  pixel-centre grid, signs from the mask, crossings smoothed; no boundary points, no solve);
- ``cv2.findContours(RETR_CCOMP, CHAIN_APPROX_NONE)``: a contour point ``(u, v)`` (a boundary
  pixel's centre in OpenCV's coordinates) is ``(u + 0.5, v + 0.5)`` here;
- ``skimage.measure.find_contours(mask, level=0.5)`` (marching squares between pixel centres): a
  point ``(row, col)`` is ``(col + 0.5, row + 0.5)`` here (needs the ``bench`` extra).

Rendering. ``cv2.fillPoly`` draws the true curves together (one call, several polygons: even-odd,
so a hole stays empty), with sub-pixel vertices (``shift``). Its rasterization rounds the
span of each scan line outward (a pixel whose centre lies up to a pixel outside the polygon is
filled: measured here, a disc comes out about half a pixel too large), which would bias every
method alike. So the polygons are filled at ``--supersample`` times the resolution (default 16,
i.e. the outward rounding is 1/32 pixel) and each mask pixel is foreground when more than half
of its sub-pixels are: a pixel is inside when the truth covers most of it. ``--direct``
renders with one plain ``fillPoly`` call instead (truth coordinates minus 0.5, OpenCV's pixel
centres), to see that bias.

Scores, per shape and method: the number of closed curves (must equal the truth's), whether
they match the truth one to one (the rule of the cases' README, within 10% of the diagonal),
the Chamfer distance (mean of the two directed mean distances, along the curves) and the
Hausdorff distance to the true curves, in pixels. The bar: the count right on every shape and
torch_isc's Chamfer below both peers' on every shape. The script prints a markdown table and
exits 0 whatever the scores (non-zero only when it cannot run).
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import cv2  # noqa: E402

from _common import resolve_dir  # noqa: E402
from torch_isc import images, metrics  # noqa: E402
from torch_isc.pipeline.config import load_config, parse_overrides  # noqa: E402
from torch_isc.io import write_overlay  # noqa: E402

DEFAULT_CASES = REPO / ".." / "shared" / "cases"


def load_truths(cases_dir: Path) -> List[Dict[str, Any]]:
    """One truth per shape (the ``_n<noise>`` suffix dropped), in name order."""
    shapes: Dict[str, Dict[str, Any]] = {}
    for tj in sorted(cases_dir.glob("*.truth.json")):
        shape = re.sub(r"_n[0-9.]+$", "", tj.name[: -len(".truth.json")])
        truth = json.loads(tj.read_text())
        if shape in shapes:
            if truth["curves"] != shapes[shape]["truth"]["curves"]:
                raise SystemExit(f"{tj}: the truth of {shape} differs between noise levels")
            continue
        shapes[shape] = dict(name=shape, truth=truth)
    if not shapes:
        raise SystemExit(f"no *.truth.json in {cases_dir}")
    return list(shapes.values())


def to_pixels(curves: List[np.ndarray], size: int, margin: float = 0.1) -> List[np.ndarray]:
    """The truth mapped into a ``size x size`` image (bbox centred, the larger side filling
    ``1 - 2 margin`` of it), as a similarity transform (y keeps its direction)."""
    allp = np.concatenate(curves)
    lo, hi = allp.min(0), allp.max(0)
    s = size * (1 - 2 * margin) / float((hi - lo).max())
    c = 0.5 * (lo + hi)
    return [(np.asarray(q) - c) * s + size / 2 for q in curves]


def render(curves_px: List[np.ndarray], size: int, supersample: int, direct: bool) -> np.ndarray:
    """Even-odd fill of the curves (pixel convention) with cv2.fillPoly; uint8 mask 0/255."""
    shift = 8
    if direct:
        img = np.zeros((size, size), np.uint8)
        polys = [np.rint((q - 0.5) * (1 << shift)).astype(np.int32) for q in curves_px]
        cv2.fillPoly(img, polys, 255, cv2.LINE_8, shift)
        return img
    k = supersample
    big = np.zeros((size * k, size * k), np.uint8)
    # sub-pixel (p, q) of the big image covers [q, q+1] x [p, p+1] / k; its centre in OpenCV's
    # integer-centre coordinates of the big image is the pixel-convention point times k minus 0.5
    polys = [np.rint((q * k - 0.5) * (1 << shift)).astype(np.int32) for q in curves_px]
    cv2.fillPoly(big, polys, 1, cv2.LINE_8, shift)
    cover = big.reshape(size, k, size, k).sum((1, 3))
    return np.where(2 * cover > k * k, 255, 0).astype(np.uint8)


def cv2_polylines(mask: np.ndarray) -> List[Dict[str, Any]]:
    found = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in found[-2]:
        p = c.reshape(-1, 2).astype(np.float64) + 0.5
        out.append({"closed": True, "points": p})
    return out


def skimage_polylines(mask: np.ndarray):
    try:
        from skimage import measure
    except ImportError:
        return None
    out = []
    for c in measure.find_contours(mask.astype(np.float64) / 255.0, 0.5):
        closed = len(c) > 2 and np.allclose(c[0], c[-1])
        p = c[:, ::-1] + 0.5
        if closed:
            p = p[:-1]
        out.append({"closed": bool(closed), "points": p})
    return out


def score(pls, truth_px: List[np.ndarray], truth_json: Dict[str, Any]) -> Dict[str, Any]:
    t = [(q, True) for q in truth_px]
    pl = [(np.asarray(p["points"], np.float64) if not isinstance(p["points"], torch.Tensor)
           else p["points"].detach().double().numpy(), bool(p["closed"])) for p in pls]
    spacing = 0.05
    d = metrics.distance_summary(pl, t, spacing) if pl else {"chamfer": float("inf"), "hausdorff": float("inf")}
    sc = metrics.score_case([{"closed": c, "points": p} for p, c in pl],
                            {**truth_json, "curves": [q.tolist() for q in truth_px]}) if pl else None
    return dict(closed=sum(1 for _, c in pl if c), open=sum(1 for _, c in pl if not c),
                match=bool(sc and sc["topology_ok"]), chamfer=d["chamfer"], hausdorff=d["hausdorff"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=None, help="cases folder (default: ../shared/cases from the repo root)")
    ap.add_argument("--size", type=int, default=256, help="mask width and height in pixels (default 256)")
    ap.add_argument("--supersample", type=int, default=16, help="fillPoly at this many times the resolution")
    ap.add_argument("--direct", action="store_true", help="one plain fillPoly at the mask resolution instead")
    ap.add_argument("--spacing", type=float, default=1.0, help="boundary point spacing in pixels (default 1)")
    ap.add_argument("--no-oracle", action="store_true", help="estimate the topology instead of reading the mask")
    ap.add_argument("--interpolation", default="bilinear", choices=("bilinear", "nearest"),
                    help="how the mask oracle samples the mask (default bilinear)")
    ap.add_argument("--grid", action="store_true",
                    help="torch_isc's grid path (images.grid_results, the CLI's mask mode) instead of the point solve")
    ap.add_argument("--config", default=None, help="YAML config file (keys of ReconstructConfig)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="config overrides on top of the image defaults")
    ap.add_argument("--out", default=None, help="write <shape>.mask.png and <shape>.overlay.png (x4) here")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--shapes", action="store_true", help="analytic shapes instead of the cases (see above)")
    ap.add_argument("--tips", action="store_true",
                    help="with --shapes: per shape above 0.55 px, whether its worst corner can be recovered from the mask")
    ap.add_argument("--seeds", default="0", help="with --shapes: seeds of corner_shapes (comma-separated; '' for none)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.shapes and args.tips:
        return tips_table([int(x) for x in args.seeds.split(",") if x.strip()])
    if args.shapes:
        return shapes_table([int(x) for x in args.seeds.split(",") if x.strip()])

    shapes = load_truths(resolve_dir(args.cases, DEFAULT_CASES))
    overrides = parse_overrides(args.set)
    cfg = images.image_config(load_config(args.config, overrides), keep=list(overrides))
    for s in shapes:
        s["truth_px"] = to_pixels([np.asarray(c, np.float64) for c in s["truth"]["curves"]], args.size)
        s["mask"] = render(s["truth_px"], args.size, args.supersample, args.direct)

    t0 = time.perf_counter()
    if args.grid:
        results = images.grid_results([s["mask"] > 127 for s in shapes], [s["name"] for s in shapes], config=cfg)
    else:
        results = images.reconstruct_masks([s["mask"] for s in shapes], cfg, spacing=args.spacing,
                                           use_oracle=not args.no_oracle, names=[s["name"] for s in shapes],
                                           interpolation=args.interpolation)
    seconds = time.perf_counter() - t0

    rows = []
    for s, res in zip(shapes, results):
        row = {"name": s["name"], "truth": len(s["truth_px"]),
               "ours": score(res.polylines, s["truth_px"], s["truth"]),
               "cv2": score(cv2_polylines(s["mask"]), s["truth_px"], s["truth"])}
        sk = skimage_polylines(s["mask"])
        row["skimage"] = score(sk, s["truth_px"], s["truth"]) if sk is not None else None
        rows.append(row)
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out / f"{s['name']}.mask.png"), s["mask"])
            write_overlay(out / f"{s['name']}.overlay.png", s["mask"] // 2 + 64, res, scale=4, points=True)

    render_how = "one plain fillPoly" if args.direct else f"fillPoly at {args.supersample}x, majority per pixel"
    if args.grid:
        how = "grid path (images.grid_results: pixel-centre grid, signs from the mask, smoothed crossings)"
    else:
        how = (f"{'topology estimated' if args.no_oracle else 'signs from the mask (' + args.interpolation + ')'}, "
               f"spacing {args.spacing:g} px, tolerance {cfg.test.tolerance:g} ({cfg.test.tolerance_mode})")
    print(f"{len(rows)} masks {args.size}x{args.size} ({render_how}); torch_isc {how}; "
          f"{seconds:.2f} s for the batch\n")
    print("| shape | truth curves | closed: torch_isc / cv2 / skimage | Chamfer px: torch_isc | cv2.findContours "
          "| skimage find_contours | Hausdorff px: torch_isc | cv2 | skimage | count ok | Chamfer lowest |")
    print("|---|---:|:---:|---:|---:|---:|---:|---:|---:|:---:|:---:|")
    n_count = n_best = 0
    sums = {"ours": 0.0, "cv2": 0.0, "skimage": 0.0}

    def f(sc, key):
        return "n/a" if sc is None else f"{sc[key]:.3f}"

    for r in rows:
        o, c, k = r["ours"], r["cv2"], r["skimage"]
        count_ok = o["closed"] == r["truth"] and o["open"] == 0
        best = o["chamfer"] < c["chamfer"] and (k is None or o["chamfer"] < k["chamfer"])
        n_count += count_ok
        n_best += best
        for key, sc in (("ours", o), ("cv2", c), ("skimage", k)):
            if sc is not None:
                sums[key] += sc["chamfer"] / len(rows)
        closed = f"{o['closed']}{'+' + str(o['open']) + ' open' if o['open'] else ''} / {c['closed']} / " + \
                 ("n/a" if k is None else str(k["closed"]))
        print(f"| {r['name']} | {r['truth']} | {closed} | **{o['chamfer']:.3f}** | {c['chamfer']:.3f} | "
              f"{f(k, 'chamfer')} | {o['hausdorff']:.3f} | {c['hausdorff']:.3f} | {f(k, 'hausdorff')} | "
              f"{'yes' if count_ok else 'NO'} | {'yes' if best else 'NO'} |")
    print(f"| mean | | | **{sums['ours']:.3f}** | {sums['cv2']:.3f} | "
          f"{'n/a' if rows[0]['skimage'] is None else format(sums['skimage'], '.3f')} | | | | | |")
    print(f"\nbar: closed-curve count right on {n_count}/{len(rows)} "
          f"({'PASS' if n_count == len(rows) else 'FAIL'}), torch_isc Chamfer lowest on {n_best}/{len(rows)} "
          f"({'PASS' if n_best == len(rows) else 'FAIL'})")
    return 0


def shapes_table(seeds: List[int], bound: float = 0.55) -> int:
    """The ``--shapes`` table (module docstring)."""
    from skimage import measure
    from torch_isc.images.shapes import SHAPES, corner_shapes, shape_mask_of
    specs = dict(SHAPES)
    for sd in seeds:
        specs.update({f"{k} (seed {sd})": v for k, v in corner_shapes(sd).items()})

    def dist(pls, truth):
        return metrics.distance_summary([(np.asarray(p, np.float64), True) for p in pls], [(t, True) for t in truth], 0.05)

    print("| shape | mean px: torch_isc | skimage | cv2 | max px (curve->truth / truth->curve): torch_isc "
          "| skimage | cv2 | mean lowest | max <= %.2f |" % bound)
    print("|---|---:|---:|---:|---:|---:|---:|:---:|:---:|")
    n_mean = n_max = 0
    t_ours = 0.0
    for name, spec in specs.items():
        m, _, truth = shape_mask_of(spec)
        t0 = time.perf_counter()
        ours = [p.numpy() for p in images.trace_masks([torch.from_numpy(m)]).polylines.polyline_list()]
        t_ours += time.perf_counter() - t0
        sk = [c[:, ::-1] + 0.5 for c in measure.find_contours(m.astype(np.float64), 0.5)]
        cc = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[-2]
        d = [dist(pl, truth) for pl in (ours, sk, [c.reshape(-1, 2) + 0.5 for c in cc])]
        ok_mean = d[0]["a_to_b_mean"] < min(d[1]["a_to_b_mean"], d[2]["a_to_b_mean"])
        ok_max = d[0]["hausdorff"] <= bound
        n_mean += ok_mean
        n_max += ok_max
        means = " | ".join(f"{x['a_to_b_mean']:.3f}" for x in d)
        maxs = " | ".join(f"{x['a_to_b_max']:.2f} / {x['b_to_a_max']:.2f}" for x in d)
        print(f"| {name} | {means} | {maxs} | {'yes' if ok_mean else 'NO'} | {'yes' if ok_max else 'NO'} |", flush=True)
    print(f"\nbar: torch_isc mean lowest on {n_mean}/{len(specs)}, max <= {bound} px on {n_max}/{len(specs)} "
          f"(torch_isc {t_ours:.2f} s in all, one mask at a time)")
    return 0


def _local_masks(polys, H: int, W: int, pixels: np.ndarray, supersample: int = 16) -> np.ndarray:
    """Coverage >= 1/2 (as ``shapes.shape_mask_of``) of the even-odd fill of ``polys`` at the
    pixels ``(P, 2)`` (row, col) only."""
    from torch_isc.images.shapes import _poly_inside
    s = supersample
    off = (np.arange(s) + 0.5) / s
    ys = (pixels[:, 0, None, None] + off[None, :, None]) + 0 * off[None, None, :]
    xs = (pixels[:, 1, None, None] + off[None, None, :]) + 0 * off[None, :, None]
    inside = np.zeros(xs.shape, bool)
    for p in polys:
        inside ^= _poly_inside(np.asarray(p, float), xs, ys)
    return inside.reshape(len(pixels), -1).mean(1) >= 0.5


def tip_slack(poly: np.ndarray, k: int, H: int, W: int, step: float = 0.05, most: float = 8.0,
              supersample: int = 16) -> Dict[str, float]:
    """How far the corner ``k`` of polygon ``poly`` can be cut (chamfered perpendicular to its
    bisector) and extended (the vertex moved out along its bisector, its two sides pivoting on
    their other ends) with the ``H x W`` mask unchanged. Two such shapes have the same mask, so
    any curve drawn from it is at least half their distance at the tip from one of them: when
    ``cut + ext`` exceeds twice a bound, no method meets the bound on both. Only the pixels near
    the corner's two sides are re-rendered (nothing else can change)."""
    n = len(poly)
    v, a, b = poly[k], poly[k - 1], poly[(k + 1) % n]
    u, w = (a - v) / np.linalg.norm(a - v), (b - v) / np.linalg.norm(b - v)
    half = 0.5 * math.acos(float(np.clip(u @ w, -1, 1)))
    bis = (u + w) / max(np.linalg.norm(u + w), 1e-12)             # into the corner's wedge
    # the pixels whose centres lie within `most` + 2 px of the corner's sides
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    c = np.c_[ii.ravel(), jj.ravel()]
    q = c[:, ::-1] + 0.5

    def seg_d(p0, p1):
        d = p1 - p0
        t = np.clip(((q - p0) @ d) / (d @ d), 0, 1)
        return np.linalg.norm(q - (p0 + t[:, None] * d), axis=1)

    near = np.minimum(seg_d(v, a), seg_d(v, b)) < most + 2
    pix = c[near]
    base = _local_masks([poly], H, W, pix, supersample)

    def largest(make):
        r = 0.0
        while r + step <= most and (_local_masks([make(r + step)], H, W, pix, supersample) == base).all():
            r += step
        return r

    def cut(r):
        s = r / max(math.cos(half), 1e-9)
        return np.concatenate([poly[:k], [v + s * u, v + s * w], poly[k + 1:]])

    def ext(e):
        p = poly.copy()
        p[k] = v - e * bis
        return p

    rc, re = largest(cut), largest(ext)
    pair = metrics.hausdorff([(cut(rc), True)], [(ext(re), True)], 0.02)
    return dict(angle=math.degrees(2 * half), cut=rc, ext=re, pair=pair)


def tips_table(seeds: List[int], bound: float = 0.55) -> int:
    """The ``--tips`` table: for each shape whose maximum distance exceeds ``bound``, the corner
    where torch_isc's curve is farthest from the truth, its error there, and :func:`tip_slack`."""
    from torch_isc.images.shapes import SHAPES, corner_shapes, shape_mask_of
    specs = {k: v for k, v in SHAPES.items() if len(v[3]) == 1}
    for sd in seeds:
        specs.update({f"{k} (seed {sd})": v for k, v in corner_shapes(sd).items()})
    print(f"| shape | max px | worst corner (deg) | error there | cut | extend | pair distance | bound {bound} |")
    print("|---|---:|---:|---:|---:|---:|---:|:---|")
    n_miss = n_imp = 0
    for name, spec in specs.items():
        H, W, _, truth = spec
        m = shape_mask_of(spec)[0]
        ours = [p.numpy() for p in images.trace_masks([torch.from_numpy(m)]).polylines.polyline_list()]
        d = metrics.distance_summary([(p, True) for p in ours], [(t, True) for t in truth], 0.05)
        if d["hausdorff"] <= bound:
            continue
        n_miss += 1
        poly = np.asarray(truth[0], float)
        # the error near each corner: both directions, within 4 px of it
        tq = metrics.resample_polyline(poly, True, 0.05)
        oq = np.concatenate([metrics.resample_polyline(p, True, 0.05) for p in ours])
        dt = metrics.point_distances(torch.from_numpy(tq), [(torch.from_numpy(p), True) for p in ours]).numpy()
        do = metrics.point_distances(torch.from_numpy(oq), [(torch.from_numpy(poly), True)]).numpy()
        err = []
        for k in range(len(poly)):
            e1 = dt[np.linalg.norm(tq - poly[k], axis=1) < 4]
            e2 = do[np.linalg.norm(oq - poly[k], axis=1) < 4]
            err.append(max(e1.max(initial=0), e2.max(initial=0)))
        k = int(np.argmax(err))
        s = tip_slack(poly, k, H, W)
        imp = s["pair"] > 2 * bound
        n_imp += imp
        print(f"| {name} | {d['hausdorff']:.2f} | {s['angle']:.0f} | {err[k]:.2f} | {s['cut']:.2f} | {s['ext']:.2f} | "
              f"{s['pair']:.2f} | {'out of reach from the mask' if imp else 'reachable in principle'} |", flush=True)
    print(f"\n{n_miss} shapes above {bound} px; on {n_imp} of them two shapes with the same mask differ by more "
          f"than {2 * bound:.2f} px at the worst corner")
    return 0


if __name__ == "__main__":
    sys.exit(main())
