"""Reading text point files: time and peak Python memory (tracemalloc, numpy's buffers included)
of ``io.points_text.decode_points`` on generated files of ``x y`` and ``x,y`` rows, as a table.

    OMP_NUM_THREADS=1 python scripts/benchmark_read.py [--rows 3000000] [--repeats 2]
"""
from __future__ import annotations

import argparse
import time
import tracemalloc
from pathlib import Path

import numpy as np

from torch_isc.io.points_text import decode_points


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=3_000_000)
    ap.add_argument("--repeats", type=int, default=2, help="timed runs per file (the fastest is shown)")
    args = ap.parse_args()
    a = np.random.default_rng(0).normal(size=(args.rows, 2))
    print("| file | MB | seconds | peak MB (Python) | peak / file |")
    print("|---|---:|---:|---:|---:|")
    for name, sep in (("spaces", " "), ("commas", ",")):
        raw = "".join(f"{x:.9f}{sep}{y:.9f}\n" for x, y in a).encode()
        best = float("inf")
        for _ in range(args.repeats):
            t = time.perf_counter()
            decode_points(Path(f"{name}.xy"), raw)
            best = min(best, time.perf_counter() - t)
        tracemalloc.start()
        try:
            decode_points(Path(f"{name}.xy"), raw)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        mb = len(raw) / 2 ** 20
        print(f"| {name} | {mb:.1f} | {best:.2f} | {peak / 2 ** 20:.0f} | {peak / len(raw):.1f}x |")


if __name__ == "__main__":
    main()
