"""Dataset engines on one machine: the local engine against Ray with N actors, same inputs, same
outputs.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_dataset.py --count 2000 --size 128 --actors 2

Writes ``--count`` masks of ``--size`` x ``--size`` pixels (random discs, annuli and two-disc
shapes, some with an island in the hole, fixed seed) into a temporary folder, then runs
:func:`torch_isc.dataset.reconstruct_dataset` on them with the local engine and with Ray
(``--actors`` actors of one CPU each, a local Ray cluster of ``--actors`` CPUs started for the
run and timed separately), both writing the ``--formats`` outputs and the Parquet table into their
own folder, and prints a markdown table: wall time, inputs per second, speed-up over local, Ray's
start-up and the time to the first result back, and whether every output file and the table
(less wall times) are identical. ``--points N`` uses point sets of N points (text files) instead
of masks. A measuring tool: it exits 0 whatever the numbers.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def make_masks(folder: Path, count: int, size: int, seed: int) -> None:
    import cv2

    rng = np.random.default_rng(seed)
    for i in range(count):
        m = np.zeros((size, size), np.uint8)
        c = size / 2 + rng.uniform(-0.1, 0.1, 2) * size
        r = size * rng.uniform(0.2, 0.4)
        kind = i % 3
        if kind == 0:                                   # an ellipse
            cv2.ellipse(m, (int(c[0]), int(c[1])), (int(r), int(r * rng.uniform(0.5, 1))), rng.uniform(0, 180),
                        0, 360, 255, -1)
        elif kind == 1:                                 # an annulus, sometimes with an island
            cv2.circle(m, (int(c[0]), int(c[1])), int(r), 255, -1)
            cv2.circle(m, (int(c[0]), int(c[1])), int(r * 0.55), 0, -1)
            if rng.uniform() < 0.5:
                cv2.circle(m, (int(c[0]), int(c[1])), int(r * 0.2), 255, -1)
        else:                                           # two discs
            for s in (-1, 1):
                cv2.circle(m, (int(c[0] + s * r * 0.6), int(c[1])), int(r * 0.45), 255, -1)
        cv2.imwrite(str(folder / f"m{i:06d}.png"), m)


def make_points(folder: Path, count: int, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    for i in range(count):
        t = rng.uniform(0, 2 * np.pi, n)
        r = 1 + 0.3 * np.cos(5 * t + rng.uniform(0, 6.3)) if i % 2 else np.ones(n)
        p = np.c_[r * np.cos(t), r * np.sin(t)] * rng.uniform(0.5, 2) + rng.normal(0, 0.002, (n, 2))
        np.savetxt(folder / f"p{i:06d}.xy", p)


def same_outputs(a: Path, b: Path) -> bool:
    """Every output identical (an .npz: arrays and metadata less the wall times of its stats; a
    manifest: less the .npz's hash)."""
    import json

    fa, fb = sorted(os.listdir(a)), sorted(os.listdir(b))
    if fa != fb:
        return False
    for f in fa:
        if f.endswith(".npz") and not f.endswith("contours.npz"):
            za, zb = np.load(a / f), np.load(b / f)
            for k in za.files:
                if k == "metadata":
                    ma, mb = json.loads(str(za[k])), json.loads(str(zb[k]))
                    for m in (ma, mb):
                        for lv in m.get("stats", []):
                            for key in [key for key in lv if key.endswith("seconds")]:
                                lv.pop(key)
                    if ma != mb:
                        return False
                elif not np.array_equal(za[k], zb[k]):
                    return False
        elif f.endswith(".manifest.json"):              # less the .npz's hash (it holds wall times)
            ma, mb = json.loads((a / f).read_text()), json.loads((b / f).read_text())
            for m in (ma, mb):
                for e in m.get("files", []):
                    if e["name"].endswith(".npz") and not e["name"].endswith("contours.npz"):
                        e.pop("sha256", None), e.pop("bytes", None)
            if ma != mb:
                return False
        elif (a / f).read_bytes() != (b / f).read_bytes():
            return False
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=2000)
    ap.add_argument("--size", type=int, default=128, help="mask side in pixels")
    ap.add_argument("--points", type=int, default=0, help="point sets of this many points instead of masks")
    ap.add_argument("--actors", type=int, default=2)
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--formats", default="json,npz", help="outputs written by both engines")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (default: a temporary folder)")
    ap.add_argument("--skip-local", action="store_true", help="only the Ray run (no comparison)")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from torch_isc import load_config
    from torch_isc.dataset import reconstruct_dataset

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="isc_bench_"))
    src = work / "in"
    src.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    if args.points:
        make_points(src, args.count, args.points, args.seed)
        what = f"{args.count} point sets of {args.points} points"
    else:
        make_masks(src, args.count, args.size, args.seed)
        what = f"{args.count} masks of {args.size}x{args.size}"
    print(f"{what} written in {time.perf_counter() - t:.1f} s ({src})", file=sys.stderr, flush=True)
    formats = [f for f in args.formats.split(",") if f]
    cfg = load_config()
    rows = []

    def run(engine, **kw):
        out = work / f"out_{engine}"
        shutil.rmtree(out, ignore_errors=True)
        first = []
        t0 = time.perf_counter()
        rep = reconstruct_dataset([src], out, cfg, engine, formats=formats, image_formats=formats,
                                  batch_size=args.batch_size, table=work / f"{engine}.parquet",
                                  progress=lambda r: first or first.append(time.perf_counter()), **kw)
        wall = time.perf_counter() - t0
        print(f"{engine}: {wall:.1f} s, {rep.counts}", file=sys.stderr, flush=True)
        return rep, wall, (first[0] - t0) if first else float("nan"), out

    local = None
    if not args.skip_local:
        rep, wall, first, out = run("local")
        local = (wall, out)
        rows.append(("local (1 process)", wall, args.count / wall, 1.0, 0.0, first, "-", rep.counts["failed"]))

    import ray

    t0 = time.perf_counter()
    ray.init(num_cpus=args.actors, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1",
                                       "PYTHONPATH": str(Path(__file__).resolve().parents[1])}})
    start = time.perf_counter() - t0
    try:
        rep, wall, first, out = run("ray", actors=args.actors)
    finally:
        ray.shutdown()
    same = "-"
    if local is not None:
        import pyarrow.parquet as pq

        ta = pq.read_table(work / "local.parquet").drop_columns(["seconds"])
        tb = pq.read_table(work / "ray.parquet").drop_columns(["seconds"])
        same = "yes" if same_outputs(local[1], out) and ta.equals(tb) else "NO"
    speed = (local[0] / wall) if local else float("nan")
    rows.append((f"ray, {args.actors} actors", wall, args.count / wall, speed, start, first, same,
                 rep.counts["failed"]))

    print(f"\n{what}, batch size {args.batch_size}, formats {','.join(formats)} + Parquet table, "
          f"{os.cpu_count()} CPUs\n")
    print("| engine | wall s | inputs/s | speed-up | cluster start s | first result s | same outputs | failed |")
    print("|---|---:|---:|---:|---:|---:|:---:|---:|")
    for name, w, rate, sp, st, fi, sm, fa in rows:
        print(f"| {name} | {w:.1f} | {rate:.1f} | {sp:.2f} | {st:.1f} | {fi:.1f} | {sm} | {fa} |")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
