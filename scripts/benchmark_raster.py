"""Memory and time of :func:`torch_isc.render.rasterize` per pixel (the basis of its cap,
``MAX_RASTER_PIXELS``).

    OMP_NUM_THREADS=1 python scripts/benchmark_raster.py [--sizes 250,500,1000] [--dtype float64]

Each size renders one disc curve (a hexagon mesh of resolution 6) in a fresh subprocess, with
and without gradients; memory is the growth of the peak resident set over a 64 x 64 warm-up
(``resource.getrusage``; torch's allocator is invisible to tracemalloc). Prints a markdown table.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def worker(size: int, dtype: str, grad: bool) -> dict:
    import torch
    sys.path.insert(0, str(REPO))
    from torch_isc import ImplicitCurve, hexagon_mesh
    from torch_isc.render import rasterize
    dt = getattr(torch, dtype)
    m = hexagon_mesh(torch.zeros(1, 2, dtype=dt), torch.ones(1), 6)
    v = (m.verts.norm(dim=1) - 0.55).requires_grad_(grad)
    c = ImplicitCurve(m, v)
    rasterize(c, 64, 64, 0.05)
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    img = rasterize(c, size, size, 0.05)
    if grad:
        img.sum().backward()
    seconds = time.perf_counter() - t
    grow_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - r0       # KiB on Linux
    return dict(size=size, grad=grad, seconds=seconds, bytes_per_pixel=grow_kib * 1024 / size ** 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="250,500,1000")
    ap.add_argument("--dtype", default="float64", choices=("float32", "float64"))
    ap.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        size, dtype, grad = args.worker
        print(json.dumps(worker(int(size), dtype, grad == "1")))
        return 0
    print(f"| size | gradients | seconds | peak RSS growth, bytes per pixel ({args.dtype}) |")
    print("|---:|---|---:|---:|")
    for size in (int(x) for x in args.sizes.split(",")):
        for grad in (False, True):
            p = subprocess.run([sys.executable, __file__, "--worker", str(size), args.dtype, str(int(grad))],
                               capture_output=True, text=True)
            if p.returncode != 0:
                print(f"| {size} | {grad} | failed: {p.stderr.strip().splitlines()[-1:]} | |")
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            print(f"| {size} x {size} | {'yes' if grad else 'no'} | {r['seconds']:.2f} | {r['bytes_per_pixel']:,.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
