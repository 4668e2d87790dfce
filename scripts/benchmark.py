"""Speed and memory benchmark of torch_isc (the input for the optimization work).

Run from the repository root:

    .venv/bin/python scripts/benchmark.py --threads 1              # default run (a few minutes)
    .venv/bin/python scripts/benchmark.py --threads 1 --quick      # under 2 minutes
    .venv/bin/python scripts/benchmark.py --parts a --sizes 1000,100000 --set relax_iterations=10
    .venv/bin/python scripts/benchmark.py --device cuda            # synchronizes before every clock read

It prints markdown tables:

a. ONE closed curve (the flower r = 1 + 0.3 cos 5t, sampled uniformly in arclength with a
   random phase, Gaussian noise of 0.1% of the bounding-box diagonal, fixed seed) with
   N = 1e3, 1e4, 1e5 points (``--sizes``): median seconds of each stage (the sum over levels
   of ``stats[level]["stage_seconds"]``), of the whole ``torch_isc.reconstruct`` call, and of
   the polyline extraction that follows it (``result.polylines``, lazy); levels, triangles of
   the final mesh, closed/open curves, and peak memory. Each size runs in a fresh subprocess
   and the memory is the growth of ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` (peak
   resident set) over the process's level after imports, data generation and a small warm-up
   (tracemalloc cannot see torch's allocator); on CUDA also ``torch.cuda.max_memory_allocated``.
b. batches of B = 1, 16, 64, 256 shapes of about 500 points (``--batches``, ``--shape-points``):
   circles, ellipses, flowers, two disjoint circles and annuli in turn (every prefix of the list
   is a balanced mix), each with a random scale, rotation and translation and the same 0.1%
   noise, fixed seed. Shapes per second solved in ONE ``reconstruct_batch`` call, and the speed-up
   over reconstructing the same shapes one call each. One-by-one times are measured per shape on
   the first ``--subset`` (32) shapes only; for a larger B the one-by-one time is the mean time
   per shape of that subset times B (extrapolated, marked ``*``).
c. the same first 64 shapes (``--peer-batch``) through NN-crust (Delaunay) and
   ``shapely.concave_hull`` (the peers of scripts/evaluate_cases.py, imported from it), for scale.
d. the hard mix: ``--hard-batch`` (64) shapes of about 500 points (``--shape-points``) from the
   harder families of scripts/evaluate_synthetic.py (its ``make_case``): glyph outlines, three
   nested rings, annuli, an ellipse with 3-24 outliers, a circle and a flower with one or two
   sampling gaps, in turn, with its noise levels 0-1% in turn, a random rotation, scale and
   translation, fixed seed. Shapes per second in ONE ``reconstruct_batch`` call (the slowest
   items set the number of levels) and one call per shape on the first ``--subset`` shapes
   (extrapolated to the batch, marked ``*``).

Then the targets of the speed issue, PASS / FAIL. Every time is the median of ``--repeats``
runs (default 3), all ratios are taken within one run of this script. ``--threads N`` (default 1)
calls ``torch.set_num_threads(N)`` before any work: on a small shared machine torch's default
thread count is often far slower for this method's many small ops. The script is a measuring
tool: it exits 0 whatever the numbers, non-zero only when it could not run.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = Path(__file__).resolve().parent
for _p in (str(REPO), str(SCRIPTS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import torch_isc  # noqa: E402
from torch_isc.pipeline.stats import STAGES  # noqa: E402
from _common import arclength_samples, ellipse, flower, run_main  # noqa: E402

NOISE = 0.001          # Gaussian noise sigma, fraction of the bounding-box diagonal
KINDS = ("circle", "ellipse", "flower", "two circles", "annulus")
KIND_CURVES = {"circle": 1, "ellipse": 1, "flower": 1, "two circles": 2, "annulus": 2}

# the targets of the speed issues (issue 15: a batched solve whose cost does not grow with the batch)
TARGET_1K_S = 0.15
TARGET_100K_S = 2.0
TARGET_RATIO = 12.0
TARGET_BATCH_B = 256
TARGET_BATCH_RATE = 100.0
TARGET_BATCH_SPEEDUP = 10.0
TARGET_HARD_B = 64
TARGET_HARD_RATE = 30.0

#: part d: the harder families of scripts/evaluate_synthetic.py, taken in turn
HARD_KINDS = ("glyph", "nested3", "annulus", "outliers", "gapcircle", "gapflower")


# ----------------------------------------------------------------------------- data

def sample_closed(fn, n: int, rng: np.random.Generator, dense: int = 20000) -> np.ndarray:
    """``n`` points uniformly spaced in arclength (random phase) on the closed curve ``fn``."""
    if n <= 0:
        return np.zeros((0, 2))
    return arclength_samples(fn, n, rng.uniform(), max(dense, 20 * n))[0]


def add_noise(p: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    diag = float(np.hypot(*(p.max(0) - p.min(0))))
    return p + rng.normal(0.0, NOISE * diag, p.shape)


def star_points(n: int, seed: int) -> np.ndarray:
    """Part a: the flower r = 1 + 0.3 cos 5t, n points, 0.1% noise."""
    rng = np.random.default_rng(seed)
    return add_noise(sample_closed(flower(0.3, 5), n, rng), rng)


def split_count(n: int, lengths: Sequence[float]) -> List[int]:
    """Split n points over curves in proportion to their lengths."""
    tot = sum(lengths)
    counts = [int(round(n * l / tot)) for l in lengths[:-1]]
    return counts + [n - sum(counts)]


def curve_length(fn) -> float:
    p = fn(np.linspace(0, 2 * math.pi, 4001))
    return float(np.hypot(*(p[1:] - p[:-1]).T).sum())


def make_shape(i: int, n: int, rng: np.random.Generator) -> Dict[str, Any]:
    """Shape i of part b: kind ``KINDS[i % 5]`` with random parameters and pose."""
    kind = KINDS[i % len(KINDS)]
    if kind == "circle":
        fns = [ellipse(1.0, 1.0)]
    elif kind == "ellipse":
        fns = [ellipse(1.0, rng.uniform(0.3, 0.7))]
    elif kind == "flower":
        fns = [flower(rng.uniform(0.2, 0.35), int(rng.integers(3, 7)))]
    elif kind == "two circles":
        r2 = rng.uniform(0.5, 1.0)
        gap = rng.uniform(0.5, 1.0)
        fns = [ellipse(1.0, 1.0), ellipse(r2, r2, 1.0 + gap + r2, 0.0)]
    else:  # annulus
        r2 = rng.uniform(0.4, 0.6)
        fns = [ellipse(1.0, 1.0), ellipse(r2, r2)]
    counts = split_count(n, [curve_length(f) for f in fns])
    p = np.concatenate([sample_closed(f, c, rng) for f, c in zip(fns, counts)])
    th = rng.uniform(0, 2 * math.pi)
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    p = (p @ rot.T) * 10 ** rng.uniform(-1, 1) + rng.uniform(-100, 100, 2)
    p = add_noise(p, rng)
    return dict(kind=kind, points=p, curves=KIND_CURVES[kind])


def make_shapes(count: int, n: int, seed: int) -> List[Dict[str, Any]]:
    rng = np.random.default_rng(seed + 1)
    return [make_shape(i, n, rng) for i in range(count)]


def make_hard_shapes(count: int, n: int, seed: int) -> List[Dict[str, Any]]:
    """Part d: ``count`` cases of :data:`HARD_KINDS` in turn, ``n`` samples on their curves
    (gaps take some away, outliers add 3-24), random rotation (``make_case``), scale 0.1-10 and
    translation +-100."""
    import evaluate_synthetic as es
    rng = np.random.default_rng(seed + 2)
    out = []
    for i in range(count):
        c = es.make_case(i, HARD_KINDS, rng, points=n)
        p = c["points"] * 10 ** rng.uniform(-1, 1) + rng.uniform(-100, 100, 2)
        out.append(dict(kind=c["kind"], points=p, curves=c["truth"]["n_components"]))
    return out


# ----------------------------------------------------------------------------- timing helpers

def sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def clock(device: str) -> float:
    sync(device)
    return time.perf_counter()


def stage_sums(stats: List[Dict[str, Any]]) -> Dict[str, float]:
    """Sum over levels of the per-stage seconds of one result (in a batch a level's times are
    shared by the items solved in it, so the item with the most levels sees them all)."""
    out = {k: 0.0 for k in STAGES}
    for lv in stats:
        for k, v in lv.stage_seconds.items():
            out[k] = out.get(k, 0.0) + float(v)
    return out


def batch_stage_sums(results) -> Dict[str, float]:
    longest = max(results, key=lambda r: len(r.stats))
    return stage_sums(longest.stats)


def median(xs: Sequence[float]) -> float:
    return float(statistics.median(xs)) if xs else math.nan


def fmt_s(x: Optional[float], digits: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:.{digits}f}"


def as_tensor(p: np.ndarray, device: str) -> torch.Tensor:
    return torch.as_tensor(p, dtype=torch.float64, device=device)


def warm_up(device: str, config) -> None:
    """One small reconstruction so lazy initialization does not count to the first measurement."""
    t = torch.linspace(0, 2 * math.pi, 101, dtype=torch.float64)[:-1]
    torch_isc.reconstruct(torch.stack([t.cos(), t.sin()], 1).to(device), config).polylines


def maxrss_mib() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / 2 ** 20   # KiB on Linux, bytes on macOS


# ----------------------------------------------------------------------------- part a

def size_worker(args, config) -> Dict[str, Any]:
    """Runs in a fresh subprocess: ``--repeats`` reconstructions of the flower with N points."""
    n, device = args.size_worker, args.device
    pts = as_tensor(star_points(n, args.seed), device)
    warm_up(device, config)
    gc.collect()
    cuda = torch.device(device).type == "cuda"
    if cuda:
        torch.cuda.reset_peak_memory_stats()
        cuda_base = torch.cuda.memory_allocated()
    rss0 = maxrss_mib()
    runs = []
    for _ in range(args.repeats):
        t0 = clock(device)
        res = torch_isc.reconstruct(pts, config)
        t1 = clock(device)
        pl = res.polylines
        t2 = clock(device)
        runs.append(dict(total=t1 - t0, extract=t2 - t1, stages=stage_sums(res.stats), levels=len(res.stats),
                         triangles=res.stats[-1].triangles,
                         closed=sum(1 for p in pl if p["closed"]), open=sum(1 for p in pl if not p["closed"]),
                         converged=bool(res.converged)))
        del res, pl
        gc.collect()
    out = dict(n=n, runs=runs, rss_delta_mib=maxrss_mib() - rss0, rss_base_mib=rss0)
    if cuda:
        out["cuda_peak_mib"] = (torch.cuda.max_memory_allocated() - cuda_base) / 2 ** 20
    return out


def worker_argv(args, n: int) -> List[str]:
    argv = [sys.executable, str(Path(__file__).resolve()), "--size-worker", str(n), "--threads", str(args.threads),
            "--repeats", str(args.repeats), "--device", args.device, "--seed", str(args.seed)]
    if args.config:
        argv += ["--config", args.config]
    if args.set:
        argv += ["--set", *args.set]
    return argv


def part_a(args) -> Dict[int, Dict[str, Any]]:
    print("## a. One closed curve, N points\n")
    print(f"Flower r = 1 + 0.3 cos 5t, uniform in arclength, noise {100 * NOISE:g}% of the diagonal, "
          f"seed {args.seed}; `torch_isc.reconstruct` on {args.device}, median of {args.repeats} run(s), "
          f"each size in a fresh subprocess.\n")
    rows: Dict[int, Dict[str, Any]] = {}
    for n in args.sizes:
        env = dict(os.environ)
        p = subprocess.run(worker_argv(args, n), capture_output=True, text=True, env=env, cwd=str(REPO))
        line = [l for l in p.stdout.splitlines() if l.startswith("{")]
        if p.returncode != 0 or not line:
            print(f"N={n}: worker failed (exit {p.returncode}):\n```\n{p.stderr[-3000:]}\n```\n")
            continue
        rows[n] = json.loads(line[-1])
        sys.stdout.flush()
    cuda = torch.device(args.device).type == "cuda"
    head = ("| N | levels | triangles | closed | open | " + " | ".join(STAGES) +
            " | other | **total s** | extract s | peak RSS +MiB |" + (" CUDA peak MiB |" if cuda else ""))
    print(head)
    print("|" + "---:|" * (head.count("|") - 1))
    for n, d in rows.items():
        runs = d["runs"]
        st = {k: median([r["stages"].get(k, 0.0) for r in runs]) for k in STAGES}
        other = median([r["total"] - sum(r["stages"].values()) for r in runs])
        total = median([r["total"] for r in runs])
        d["total"] = total
        d["stage_median"] = st
        d["other"] = other
        last = runs[-1]
        conv = "" if all(r["converged"] for r in runs) else " (not converged)"
        levels = "/".join(sorted({str(r["levels"]) for r in runs}))
        line = (f"| {n:,} | {levels} | {last['triangles']} | {last['closed']} | {last['open']}{conv} | " +
                " | ".join(fmt_s(st[k]) for k in STAGES) +
                f" | {fmt_s(other)} | **{fmt_s(total)}** | {fmt_s(median([r['extract'] for r in runs]))} | "
                f"{d['rss_delta_mib']:.1f} |")
        if cuda:
            line += f" {d.get('cuda_peak_mib', math.nan):.1f} |"
        print(line)
    print("\nStage columns: median over runs of the sum over levels of `stage_seconds`; other = total minus "
          "the stages (input checks, normalization, result assembly); total = wall time of "
          "the `reconstruct` call; extract = the lazy `result.polylines` after it (not in total). "
          "Peak RSS +MiB: growth of `resource.getrusage(RUSAGE_SELF).ru_maxrss` during the runs over the "
          "subprocess's level after imports, data and a 100-point warm-up (psutil is not installed; "
          "tracemalloc cannot see torch's allocator).")
    if 10_000 in rows and 100_000 in rows:
        ratio = rows[100_000]["total"] / rows[10_000]["total"]
        print(f"\ntime(1e5) / time(1e4) = {rows[100_000]['total']:.3f} / {rows[10_000]['total']:.3f} = "
              f"**{ratio:.2f}**")
    dom = _dominant(rows)
    if dom:
        print(f"\nLargest stage per size: {dom}")
    print()
    return rows


def _dominant(rows) -> str:
    parts = []
    for n, d in rows.items():
        st = dict(d["stage_median"], other=d["other"])
        k = max(st, key=st.get)
        parts.append(f"N={n:,}: {k} {100 * st[k] / max(d['total'], 1e-12):.0f}%")
    return "; ".join(parts)


# ----------------------------------------------------------------------------- part b

def topo_ok(results, shapes) -> int:
    ok = 0
    for r, s in zip(results, shapes):
        pl = r.polylines
        ok += (sum(1 for p in pl if p["closed"]) == s["curves"] and not any(not p["closed"] for p in pl))
    return ok


def part_b(args, config, shapes) -> Dict[int, Dict[str, Any]]:
    device = args.device
    print("## b. Batches of shapes\n")
    counts: Dict[str, int] = {}
    for s in shapes:
        counts[s["kind"]] = counts.get(s["kind"], 0) + 1
    npts = [len(s["points"]) for s in shapes]
    span = f"{min(npts)}" if min(npts) == max(npts) else f"{min(npts)}-{max(npts)}"
    print(f"{len(shapes)} shapes of {span} points ({', '.join(f'{v} {k}' for k, v in counts.items())}; "
          f"in turn, so every prefix is a mix), random scale 0.1-10, rotation, translation +-100, "
          f"noise {100 * NOISE:g}%, seed {args.seed}; the first B shapes make the batch of size B. "
          f"Median of {args.repeats} run(s).\n")
    tensors = [as_tensor(s["points"], device) for s in shapes]

    # one by one, per shape, on the subset
    n_sub = min(args.subset, len(shapes))
    per_shape = [[] for _ in range(n_sub)]
    for _ in range(args.repeats):
        for i in range(n_sub):
            t0 = clock(device)
            torch_isc.reconstruct(tensors[i], config)
            per_shape[i].append(clock(device) - t0)
    per_shape_med = [median(x) for x in per_shape]

    rows: Dict[int, Dict[str, Any]] = {}
    for B in args.batches:
        B = min(B, len(shapes))
        times, stage_runs, results = [], [], None
        for _ in range(args.repeats):
            t0 = clock(device)
            results = torch_isc.reconstruct_batch(tensors[:B], config)
            times.append(clock(device) - t0)
            stage_runs.append(batch_stage_sums(results))
        t = median(times)
        if B <= n_sub:
            one, extrap = sum(per_shape_med[:B]), False
        else:
            one, extrap = statistics.fmean(per_shape_med) * B, True
        rows[B] = dict(seconds=t, rate=B / t, one_by_one=one, one_rate=B / one, speedup=one / t, extrap=extrap,
                       levels=max(len(r.stats) for r in results), topo=topo_ok(results, shapes[:B]),
                       stages={k: median([s[k] for s in stage_runs]) for k in STAGES})
        print(f"# part b, B={B}: {t:.3f} s ({B / t:.1f} shapes/s)", file=sys.stderr, flush=True)
        sys.stdout.flush()
    print("| B | batch s | **shapes/s (batch)** | one-by-one s | shapes/s (one-by-one) | **speed-up** | levels | "
          "topology ok | " + " | ".join(STAGES) + " |")
    print("|" + "---:|" * (9 + len(STAGES)))
    for B, r in rows.items():
        star = "*" if r["extrap"] else ""
        print(f"| {B} | {fmt_s(r['seconds'])} | **{r['rate']:.1f}** | {fmt_s(r['one_by_one'])}{star} | "
              f"{r['one_rate']:.1f}{star} | **{r['speedup']:.2f}x**{star} | {r['levels']} | {r['topo']}/{B} | " +
              " | ".join(fmt_s(r["stages"][k]) for k in STAGES) + " |")
    print(f"\nbatch s: wall time of one `reconstruct_batch` call on the B shapes; one-by-one: one `reconstruct` "
          f"call per shape, per-shape median over runs, summed; `*`: B > {n_sub}, so it is the mean per-shape "
          f"time of the first {n_sub} shapes ({statistics.fmean(per_shape_med):.3f} s) times B (extrapolated). "
          f"topology ok: closed curves = truth (1 or 2) and no open curve. Stage columns: the batch call's "
          f"seconds per stage, summed over its levels (median over runs).\n")
    return rows


# ----------------------------------------------------------------------------- part c

def part_c(args, shapes, isc_rows) -> Dict[str, Dict[str, Any]]:
    print("## c. Peers on the same shapes\n")
    from evaluate_cases import PEERS

    B = min(args.peer_batch, len(shapes))
    sub = shapes[:B]
    rows: Dict[str, Dict[str, Any]] = {}
    for name, fn in PEERS.items():
        times = []
        try:
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                outs = [fn(s["points"]) for s in sub]
                times.append(time.perf_counter() - t0)
        except ImportError as e:
            print(f"{name}: skipped ({e})\n")
            continue
        ok = sum(sum(1 for p in o if p["closed"]) == s["curves"] and not any(not p["closed"] for p in o)
                 for o, s in zip(outs, sub))
        t = median(times)
        rows[name] = dict(seconds=t, rate=B / t, topo=ok)
    print(f"| method (B = {B}) | seconds | shapes/s | topology ok |")
    print("|---|---:|---:|---:|")
    if B in isc_rows:
        r = isc_rows[B]
        print(f"| torch_isc, one reconstruct_batch call | {fmt_s(r['seconds'])} | {r['rate']:.1f} | {r['topo']}/{B} |")
        print(f"| torch_isc, one call per shape | {fmt_s(r['one_by_one'])}{'*' if r['extrap'] else ''} | "
              f"{r['one_rate']:.1f}{'*' if r['extrap'] else ''} | - |")
    for name, r in rows.items():
        print(f"| {name} | {fmt_s(r['seconds'])} | {r['rate']:.1f} | {r['topo']}/{B} |")
    print("\nPeers: the functions of scripts/evaluate_cases.py on the numpy points, one shape after another "
          "(CPU, scipy / shapely), median of the runs; topology ok as in b.\n")
    return rows


# ----------------------------------------------------------------------------- part d

def part_d(args, config) -> Dict[str, Any]:
    device = args.device
    print("## d. The hard mix\n")
    shapes = make_hard_shapes(args.hard_batch, args.shape_points, args.seed)
    counts: Dict[str, int] = {}
    for s in shapes:
        counts[s["kind"]] = counts.get(s["kind"], 0) + 1
    npts = [len(s["points"]) for s in shapes]
    print(f"{len(shapes)} shapes of {min(npts)}-{max(npts)} points (median {int(statistics.median(npts))}; "
          f"{', '.join(f'{v} {k}' for k, v in counts.items())}; in turn), noise 0-1% of the diagonal in turn, "
          f"random rotation, scale 0.1-10, translation +-100, seed {args.seed}. Median of {args.repeats} run(s).\n")
    tensors = [as_tensor(s["points"], device) for s in shapes]
    B = len(shapes)
    times, results = [], None
    for _ in range(args.repeats):
        t0 = clock(device)
        results = torch_isc.reconstruct_batch(tensors, config)
        times.append(clock(device) - t0)
    t = median(times)
    print(f"# part d, B={B}: {t:.3f} s ({B / t:.1f} shapes/s)", file=sys.stderr, flush=True)
    n_sub = min(args.subset, B)
    one = []
    for i in range(n_sub):
        ts = []
        for _ in range(args.repeats):
            t0 = clock(device)
            torch_isc.reconstruct(tensors[i], config)
            ts.append(clock(device) - t0)
        one.append(median(ts))
    extrap = n_sub < B
    one_s = statistics.fmean(one) * B
    levels = [len(r.stats) for r in results]
    row = dict(B=B, seconds=t, rate=B / t, one_by_one=one_s, one_rate=B / one_s, speedup=one_s / t, extrap=extrap,
               levels=max(levels), topo=topo_ok(results, shapes), stages=batch_stage_sums(results))
    star = "*" if extrap else ""
    print("| B | batch s | **shapes/s (batch)** | one-by-one s | shapes/s (one-by-one) | speed-up | "
          "levels (max / median) | topology ok | " + " | ".join(STAGES) + " |")
    print("|" + "---:|" * (8 + len(STAGES)))
    print(f"| {B} | {fmt_s(t)} | **{row['rate']:.1f}** | {fmt_s(one_s)}{star} | {row['one_rate']:.1f}{star} | "
          f"{row['speedup']:.2f}x{star} | {max(levels)} / {int(statistics.median(levels))} | {row['topo']}/{B} | " +
          " | ".join(fmt_s(row["stages"][k]) for k in STAGES) + " |")
    print(f"\nbatch s: wall time of one `reconstruct_batch` call on the {B} shapes; one-by-one: one `reconstruct` "
          f"call per shape on the first {n_sub} shapes (per-shape median over runs), mean times {B}"
          f"{' (extrapolated, `*`)' if extrap else ''}. topology ok: closed curves = truth and no open curve. "
          f"Stage columns: the batch call's seconds per stage, summed over its levels.\n")
    return row


# ----------------------------------------------------------------------------- targets

def print_targets(a_rows, b_rows, d_row=None) -> None:
    print("## Targets\n")
    lines = []

    def line(ok: Optional[bool], text: str) -> None:
        lines.append(ok)
        tag = "n/a " if ok is None else ("PASS" if ok else "FAIL")
        print(f"- [{tag}] {text}")

    t1k = a_rows.get(1_000, {}).get("total")
    line(None if t1k is None else t1k < TARGET_1K_S,
         f"1,000 points < {TARGET_1K_S:g} s: " + ("not measured" if t1k is None else f"{t1k:.3f} s"))
    t100k = a_rows.get(100_000, {}).get("total")
    line(None if t100k is None else t100k < TARGET_100K_S,
         f"100,000 points < {TARGET_100K_S:g} s: " + ("not measured" if t100k is None else f"{t100k:.3f} s"))
    t10k = a_rows.get(10_000, {}).get("total")
    if t10k is None or t100k is None:
        line(None, f"time(1e5)/time(1e4) <= {TARGET_RATIO:g}: not measured")
    else:
        line(t100k / t10k <= TARGET_RATIO, f"time(1e5)/time(1e4) <= {TARGET_RATIO:g}: {t100k / t10k:.2f}")
    b = b_rows.get(TARGET_BATCH_B)
    if b is None:
        line(None, f"batch of {TARGET_BATCH_B} >= {TARGET_BATCH_RATE:g} shapes/s: not measured")
        line(None, f"batch of {TARGET_BATCH_B} >= {TARGET_BATCH_SPEEDUP:g}x the one-by-one rate: not measured")
    else:
        line(b["rate"] >= TARGET_BATCH_RATE,
             f"batch of {TARGET_BATCH_B} >= {TARGET_BATCH_RATE:g} shapes/s: {b['rate']:.1f} shapes/s")
        line(b["speedup"] >= TARGET_BATCH_SPEEDUP,
             f"batch of {TARGET_BATCH_B} >= {TARGET_BATCH_SPEEDUP:g}x the one-by-one rate: {b['speedup']:.2f}x"
             + (" (one-by-one extrapolated)" if b["extrap"] else ""))
    if d_row is None:
        line(None, f"hard mix, batch of {TARGET_HARD_B} >= {TARGET_HARD_RATE:g} shapes/s: not measured")
    else:
        same = d_row["B"] == TARGET_HARD_B
        line(d_row["rate"] >= TARGET_HARD_RATE if same else None,
             f"hard mix, batch of {TARGET_HARD_B} >= {TARGET_HARD_RATE:g} shapes/s: {d_row['rate']:.1f} shapes/s"
             + ("" if same else f" (measured on a batch of {d_row['B']}, not the target's)"))
    n_pass = sum(1 for x in lines if x)
    n_meas = sum(1 for x in lines if x is not None)
    print(f"\ntargets: {n_pass} of {n_meas} measured pass ({len(lines) - n_meas} not measured)\n")


# ----------------------------------------------------------------------------- main

def int_list(s: str) -> List[int]:
    return [int(float(x)) for x in s.split(",") if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads(N) before any work (default 1)")
    ap.add_argument("--repeats", type=int, default=None, help="runs per measurement, median taken (default 3; 1 with --quick)")
    ap.add_argument("--sizes", type=int_list, default=None, help="part a point counts (default 1000,10000,100000)")
    ap.add_argument("--batches", type=int_list, default=None, help="part b batch sizes (default 1,16,64,256)")
    ap.add_argument("--shape-points", type=int, default=500, help="points per shape in parts b and c (default 500)")
    ap.add_argument("--subset", type=int, default=None,
                    help="part b: shapes timed one by one; larger B extrapolate (default 32; 8 with --quick)")
    ap.add_argument("--peer-batch", type=int, default=64, help="part c: shapes given to the peers (default 64)")
    ap.add_argument("--hard-batch", type=int, default=TARGET_HARD_B, help="part d: shapes in the hard mix (default 64)")
    ap.add_argument("--parts", default="abcd", help="which parts to run, e.g. a, bd (default abcd)")
    ap.add_argument("--quick", action="store_true",
                    help="one run per measurement, one-by-one on 8 shapes (under 2 minutes on 2 cores)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (synchronized before every clock read)")
    ap.add_argument("--seed", type=int, default=0, help="data seed (default 0)")
    ap.add_argument("--config", default=None, help="YAML config file (keys of ReconstructConfig)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="config overrides, e.g. --set relax_iterations=10")
    ap.add_argument("--size-worker", type=int, default=None, help=argparse.SUPPRESS)
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    if args.repeats is None:
        args.repeats = 1 if args.quick else 3
    args.repeats = max(1, args.repeats)
    if args.subset is None:
        args.subset = 8 if args.quick else 32
    if args.sizes is None:
        args.sizes = [1_000, 10_000, 100_000]
    if args.batches is None:
        args.batches = [1, 16, 64, 256]
    from torch_isc.pipeline.config import parse_overrides
    config = torch_isc.load_config(args.config, parse_overrides(args.set))
    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        print(f"--device {args.device}: CUDA is not available here", file=sys.stderr)
        return 2

    if args.size_worker is not None:
        print(json.dumps(size_worker(args, config)))
        return 0

    t_start = time.perf_counter()
    cmd = " ".join([".venv/bin/python", "scripts/benchmark.py", *(argv if argv is not None else sys.argv[1:])])
    print("# torch_isc benchmark\n")
    print(f"`{cmd}` — torch {torch.__version__}, {torch.get_num_threads()} torch thread(s), device {args.device}, "
          f"{os.cpu_count()} CPU(s), {platform.python_implementation()} {platform.python_version()}, "
          f"{platform.machine()}; config overrides: {args.set or 'none'}"
          f"{'; config file ' + args.config if args.config else ''}; {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
    sys.stdout.flush()

    a_rows: Dict[int, Dict[str, Any]] = {}
    b_rows: Dict[int, Dict[str, Any]] = {}
    if "a" in args.parts:
        a_rows = part_a(args)
        sys.stdout.flush()
    if "b" in args.parts or "c" in args.parts:
        need = max([*(args.batches if "b" in args.parts else []), *([args.peer_batch] if "c" in args.parts else []),
                    args.subset if "b" in args.parts else 0, 1])
        shapes = make_shapes(need, args.shape_points, args.seed)
        warm_up(args.device, config)
        if "b" in args.parts:
            b_rows = part_b(args, config, shapes)
            sys.stdout.flush()
        if "c" in args.parts:
            part_c(args, shapes, b_rows)
            sys.stdout.flush()
    d_row = None
    if "d" in args.parts:
        warm_up(args.device, config)
        d_row = part_d(args, config)
        sys.stdout.flush()
    print_targets(a_rows, b_rows, d_row)
    print(f"benchmark wall time: {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    run_main(main)
