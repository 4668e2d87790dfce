"""Measure how far the curve moves under input perturbations far below the tolerance.

Run from the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_stability.py                 # 3 shapes x 4 noises x 8 seeds
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_stability.py --seeds 24 --verbose

Shapes: circle (400 points), flower (r = 1 + 0.3 cos 5t, 400 points), two circles (radii 1 and
0.8, gap 0.3, 200 points each); points uniform in the parameter, Gaussian noise of 0, 0.25, 0.5
and 1% of the bounding-box diagonal. Perturbations, each fed in the original coordinates:

- round: the 17-digit text round trip of ``x * 1e-6 + 1e7`` mapped back (the rounding of the
  shifted coordinates: up to about 0.03% of the diagonal for these sizes);
- jitter: a random relative jitter of 1e-9 of the diagonal (``--jitters``: several sizes, e.g.
  ``1e-6,1e-5,1e-4,1e-3``, each its own perturbation ``jitter<size>``; the summary then also gives
  the curve's move over the perturbation's size, median and max).

For each set and perturbation: the Hausdorff distance (dense, :func:`torch_isc.metrics.hausdorff`)
between the two curves in units of the diagonal, and whether the refinement differs (triangles per
level). With ``--verbose``, the levels of every case moved by more than ``--bound``. All sets go
through one ``reconstruct_batch`` call (an item's result does not depend on its batch). A
measuring tool: it exits 0 whatever the scores.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = Path(__file__).resolve().parent
for _p in (str(REPO), str(SCRIPTS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import torch_isc  # noqa: E402
from torch_isc.pipeline.config import parse_overrides  # noqa: E402
from torch_isc import metrics  # noqa: E402

SHAPES = ("circle", "flower", "two")
NOISES = (0.0, 0.0025, 0.005, 0.01)


def shape_points(kind: str, noise: float, seed: int) -> np.ndarray:
    """The noisy samples of one case (noise relative to the bounding-box diagonal of the truth)."""
    rng = np.random.default_rng(seed)
    if kind == "circle":
        t = rng.uniform(0, 2 * np.pi, 400)
        p, diag = np.stack([np.cos(t), np.sin(t)], 1), 2 * np.sqrt(2)
    elif kind == "flower":
        t = rng.uniform(0, 2 * np.pi, 400)
        r = 1 + 0.3 * np.cos(5 * t)
        p, diag = np.stack([r * np.cos(t), r * np.sin(t)], 1), 2.6 * np.sqrt(2)
    elif kind == "two":
        t1, t2 = rng.uniform(0, 2 * np.pi, 200), rng.uniform(0, 2 * np.pi, 200)
        a = np.stack([np.cos(t1) - 1.05, np.sin(t1)], 1)
        b = np.stack([0.8 * np.cos(t2) + 1.05, 0.8 * np.sin(t2)], 1)
        p, diag = np.concatenate([a, b]), float(np.hypot(4.1, 2.0))
    else:
        raise ValueError(kind)
    return p + noise * diag * rng.standard_normal(p.shape)


def round_trip(p: np.ndarray) -> np.ndarray:
    """The 17-digit text of ``p * 1e-6 + 1e7`` read back and mapped to the original frame."""
    q = np.array([float("%.17g" % v) for v in (p * 1e-6 + 1e7).ravel()]).reshape(p.shape)
    return (q - 1e7) / 1e-6


def jitter(p: np.ndarray, seed: int, rel: float = 1e-9) -> np.ndarray:
    diag = float(np.hypot(*(p.max(0) - p.min(0))))
    rng = np.random.default_rng(10_000 + seed)
    return p + rel * diag * rng.uniform(-1, 1, p.shape)


def first_divergence(p: np.ndarray, q: np.ndarray, cfg, amplify: float = 10.0) -> str:
    """Run ``p`` and ``q`` one by one with the loop's test stage watched, and name the first
    decision on which they part: ``relax@L`` (same decisions so far, but the mesh the test of
    level L sees has vertices moved by more than ``amplify`` times the input's perturbation: the
    relaxation before level L amplified it), ``signs@L`` (vertex signs of level L differ on the
    same mesh), ``marks@L`` (same signs, different marked triangles), ``none`` (every decision
    agrees: the curves differ by the fit alone). Also the relative change of the noise estimate
    and the largest vertex move seen before the divergence, in units of the perturbation."""
    import torch_isc.pipeline.loop as loop
    real = loop.test_fit
    seen: List[List[Dict]] = []

    def watched(ws, values, ev, tcfg, mpf):
        v = real(ws, values, ev, tcfg, mpf)
        seen[-1].append({"signs": ws.signs.clone(), "marked": v.marked.clone(), "noise": float(ws.noise[0]),
                         "nv": int(ws.mesh.verts.shape[0]), "verts": ws.mesh.verts.detach().double().clone()})
        return v
    loop.test_fit = watched
    try:
        for x in (p, q):
            seen.append([])
            torch_isc.reconstruct(x, cfg)
    finally:
        loop.test_fit = real
    a, b = seen
    dn = (b[0]["noise"] - a[0]["noise"]) / max(a[0]["noise"], 1e-300)
    # the perturbation in the loop's normalized units (diagonal 1)
    pert = float(np.abs(p - q).max()) / max(float(np.hypot(*(p.max(0) - p.min(0)))), 1e-300)
    worst = 0.0
    for lev, (u, v) in enumerate(zip(a, b)):
        tail = f" noise{dn:+.1e} move{worst / max(pert, 1e-300):.0f}x"
        if u["nv"] == v["nv"]:
            move = float((u["verts"] - v["verts"]).norm(dim=1).max())
            if move > amplify * pert:
                return f"relax@{lev} noise{dn:+.1e} move{move / max(pert, 1e-300):.0f}x"
            worst = max(worst, move)
            tail = f" noise{dn:+.1e} move{worst / max(pert, 1e-300):.0f}x"
        if u["nv"] != v["nv"] or not torch.equal(u["signs"], v["signs"]):
            return f"signs@{lev}" + tail
        if not torch.equal(u["marked"], v["marked"]):
            return f"marks@{lev}" + tail
    return ("none" if len(a) == len(b) else "levels") + f" noise{dn:+.1e} move{worst / max(pert, 1e-300):.0f}x"


def curves(res) -> List:
    return [(pl["points"].double(), pl["closed"]) for pl in res.polylines]


def main(argv=None) -> Dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--shapes", default=",".join(SHAPES))
    ap.add_argument("--noises", default=",".join(str(n) for n in NOISES))
    ap.add_argument("--bound", type=float, default=1e-3, help="report cases moved by more (units of the diagonal)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE", help="config overrides")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--diagnose", action="store_true",
                    help="for every case moved by more than --bound, the first decision that differs (reruns it)")
    ap.add_argument("--jitters", default="1e-9",
                    help="comma-separated jitter sizes (units of the diagonal), one perturbation each")
    ap.add_argument("--json", help="write every case's numbers here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = torch_isc.load_config(None, parse_overrides(args.set))
    cases, sets = [], []
    sizes = [float(x) for x in args.jitters.split(",") if x.strip()]
    names = ["round"] + (["jitter"] if sizes == [1e-9] else [f"jitter{x:g}" for x in sizes])
    K = 1 + len(names)                                   # sets per case: the base and each perturbation
    for kind in args.shapes.split(","):
        for noise in (float(x) for x in args.noises.split(",")):
            for seed in range(args.seed0, args.seed0 + args.seeds):
                p = shape_points(kind, noise, seed)
                cases.append((kind, noise, seed))
                sets += [p, round_trip(p)] + [jitter(p, seed, x) for x in sizes]
    res = torch_isc.reconstruct_batch(sets, cfg)
    rows = []
    for i, (kind, noise, seed) in enumerate(cases):
        base, *pert = res[K * i:K * i + K]
        diag = metrics.bbox_diagonal(torch.as_tensor(sets[K * i]))
        row = {"shape": kind, "noise": noise, "seed": seed, "levels": [s.triangles for s in base.stats]}
        for j, (name, r) in enumerate(zip(names, pert)):
            d = metrics.hausdorff(curves(r), curves(base)) / diag if base.polylines and r.polylines else float("inf")
            row[name] = d
            # the perturbation's size: its largest point move, units of the diagonal
            row[name + "_size"] = float(np.abs(sets[K * i + 1 + j] - sets[K * i]).max()) / diag
            row[name + "_refined_same"] = [s.triangles for s in r.stats] == row["levels"]
            row[name + "_levels"] = [s.triangles for s in r.stats]
            if args.verbose and d > args.bound:
                print(f"{kind} noise={noise} seed={seed} {name}: {d:.2e}")
                for a, b in zip(base.stats, r.stats):
                    print(f"   level {a.level}: tri {a.triangles}/{b.triangles} marked {a.marked}/{b.marked} "
                          f"noise {a.noise:.6e}/{b.noise:.6e} err {a.max_error:.4e}/{b.max_error:.4e} "
                          f"tol {a.tolerance:.6e}")
                if len(a.__dict__) and len(base.stats) != len(r.stats):
                    print(f"   levels {len(base.stats)}/{len(r.stats)}")
        if args.diagnose:
            for j, name in enumerate(names, 1):
                if row[name] > args.bound:
                    row[name + "_first"] = first_divergence(sets[K * i], sets[K * i + j], cfg)
                    print(f"{kind:7s} noise={noise:<6} seed={seed:<3d} {name:6s} {row[name]:.2e}  "
                          f"first: {row[name + '_first']}")
        rows.append(row)
    if args.diagnose:
        from collections import Counter
        for name in names:
            c = Counter(r[name + "_first"].split(" ")[0].split("@")[0] + "@" + (r[name + "_first"].split("@")[1][:1]
                        if "@" in r[name + "_first"] else "-") for r in rows if name + "_first" in r)
            print(f"first decision that differs ({name}):", dict(sorted(c.items())))
    summary = {}
    print(f"{'shape':8s} {'noise':>6s} {'pert':>11s} {'median':>9s} {'max':>9s} {'>bound':>7s} {'refine differs':>15s}"
          f" {'move/size med':>13s} {'max':>9s}")
    groups = [(k, n) for k in args.shapes.split(",") for n in (float(x) for x in args.noises.split(","))]
    for name in names:
        for k, n in groups + [("all", None)]:
            sel = [r for r in rows if (k == "all" or (r["shape"] == k and r["noise"] == n))]
            d = [r[name] for r in sel]
            diff = sum(not r[name + "_refined_same"] for r in sel)
            over = sum(x > args.bound for x in d)
            gain = [r[name] / max(r[name + "_size"], 1e-300) for r in sel]
            summary[f"{name}/{k}/{n}"] = {"median": statistics.median(d), "max": max(d), "over": over, "n": len(d),
                                          "refine_differs": diff, "gain_median": statistics.median(gain),
                                          "gain_max": max(gain)}
            print(f"{k:8s} {'' if n is None else n:>6} {name:>11s} {statistics.median(d):9.2e} {max(d):9.2e} "
                  f"{over:4d}/{len(d):<3d} {diff:6d}          {statistics.median(gain):13.3g} {max(gain):9.3g}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))
    return summary


if __name__ == "__main__":
    main()
