"""Masks per second: torch_isc's grid path (library and CLI) beside cv2.findContours and
skimage.measure.find_contours, on skimage.data.binary_blobs masks written as PNG files.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_masks.py --n 1000,200 --sizes 128,512 --cli

``--n`` is one count, or one per size. Every method reads the same PNG files. ``--cli`` also
times ``torch-isc reconstruct FOLDER --out OUT`` (default image outputs ``json,contours.npz``)
in a child process: the time of its ``main()`` (reading, solving, writing; the process start and
the imports aside), its peak RSS and the size of what it wrote.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from torch_isc import images  # noqa: E402

_CHILD = ("import resource, sys, time\n"
          "from torch_isc.cli import main\n"
          "t, c = time.perf_counter(), time.process_time()\n"
          "rc = main(sys.argv[1:])\n"
          "dt, dc = time.perf_counter() - t, time.process_time() - c\n"
          "print('BENCH', dt, dc, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, rc, file=sys.stderr)\n")


def cli_time(folder: Path, out: Path, extra=()) -> dict:
    """Run the CLI on ``folder`` in a child process; its main()'s seconds (wall and CPU: on a
    shared machine the CPU seconds are the steadier figure), peak RSS (MB), output MB."""
    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    p = subprocess.run([sys.executable, "-c", _CHILD, "reconstruct", str(folder), "--out", str(out), *extra],
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    line = [ln for ln in p.stderr.splitlines() if ln.startswith("BENCH ")]
    if p.returncode != 0 or not line:
        raise RuntimeError(f"the CLI failed ({p.returncode}): {p.stderr[-2000:]}")
    _, dt, dc, rss, rc = line[-1].split()
    size = sum(f.stat().st_size for f in out.iterdir())
    return {"seconds": float(dt), "cpu_seconds": float(dc), "rss_mb": int(rss) / 1024, "out_mb": size / 1e6}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", default="200", help="masks per size: one count or one per size (e.g. 1000,200)")
    ap.add_argument("--sizes", default="128,512")
    ap.add_argument("--cli", action="store_true", help="also time `torch-isc reconstruct folder` (reading and writing)")
    ap.add_argument("--keep", metavar="DIR", help="write the masks (and the CLI's outputs) under DIR")
    a = ap.parse_args(argv)
    from skimage import measure
    from skimage.data import binary_blobs
    sizes = [int(s) for s in a.sizes.split(",")]
    ns = [int(n) for n in a.n.split(",")]
    ns = ns * len(sizes) if len(ns) == 1 else ns
    root = Path(a.keep) if a.keep else Path(tempfile.mkdtemp())
    print("| size | masks | method | masks/s | notes |\n|---|---|---|---|---|")
    for size, n in zip(sizes, ns):
        d = root / f"in{size}_{n}"
        d.mkdir(parents=True, exist_ok=True)
        for s in range(n):
            f = d / f"m{s:04d}.png"
            if not f.exists():
                cv2.imwrite(str(f), (binary_blobs(size, blob_size_fraction=0.1, volume_fraction=0.5, rng=s)
                                     * 255).astype(np.uint8))
        files = sorted(d.iterdir())
        rows = []
        t = time.perf_counter()
        for f in files:
            cv2.findContours((cv2.imread(str(f), 0) > 127).astype(np.uint8), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        rows.append(("cv2.findContours (read + trace)", n / (time.perf_counter() - t), ""))
        t = time.perf_counter()
        for f in files:
            measure.find_contours((cv2.imread(str(f), 0) > 127).astype(float), 0.5)
        rows.append(("skimage find_contours(0.5) (read + trace)", n / (time.perf_counter() - t), ""))
        t = time.perf_counter()
        for i in range(0, n, 64):
            ms = [cv2.imread(str(f), 0) > 127 for f in files[i:i + 64]]
            images.find_contours_batch(ms, "tree", batch_pixels=64 * size * size)
        rows.append(("torch_isc find_contours_batch (read + solve)", n / (time.perf_counter() - t), ""))
        if a.cli:
            r = cli_time(d, root / f"out{size}_{n}")
            rows.append(("`torch-isc reconstruct DIR --out OUT` (read + solve + write)", n / r["seconds"],
                         f"{r['seconds']:.1f} s ({r['cpu_seconds']:.1f} CPU s: {n / r['cpu_seconds']:.1f} masks per CPU s), "
                         f"peak RSS {r['rss_mb']:.0f} MB, outputs {r['out_mb']:.0f} MB"))
        for name, rate, note in rows:
            print(f"| {size} | {n} | {name} | {rate:.1f} | {note} |", flush=True)
    if not a.keep:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
