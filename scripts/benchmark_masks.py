"""Masks per second: torch_isc's grid path (library and CLI) beside cv2.findContours and
skimage.measure.find_contours, on binary_blobs masks written as PNG files.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_masks.py --n 1000 --sizes 128,512 [--cli]
"""
from __future__ import annotations

import argparse
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--sizes", default="128,512")
    ap.add_argument("--cli", action="store_true", help="also time `torch-isc reconstruct folder` (reading and writing)")
    a = ap.parse_args(argv)
    from skimage import measure
    from skimage.data import binary_blobs
    print("| size | method | masks/s |\n|---|---|---|")
    for size in (int(s) for s in a.sizes.split(",")):
        d = Path(tempfile.mkdtemp()) / f"in{size}"
        d.mkdir()
        for s in range(a.n):
            cv2.imwrite(str(d / f"m{s:04d}.png"), (binary_blobs(size, blob_size_fraction=0.1, volume_fraction=0.5,
                                                                rng=s) * 255).astype(np.uint8))
        files = sorted(d.iterdir())
        rows = []
        t = time.perf_counter()
        for f in files:
            cv2.findContours((cv2.imread(str(f), 0) > 127).astype(np.uint8), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        rows.append(("cv2.findContours (read + trace)", a.n / (time.perf_counter() - t)))
        t = time.perf_counter()
        for f in files:
            measure.find_contours((cv2.imread(str(f), 0) > 127).astype(float), 0.5)
        rows.append(("skimage find_contours(0.5) (read + trace)", a.n / (time.perf_counter() - t)))
        t = time.perf_counter()
        ms = [cv2.imread(str(f), 0) > 127 for f in files]
        images.find_contours_batch(ms, "tree", batch_pixels=64 * size * size)
        rows.append(("torch_isc find_contours_batch (read + solve)", a.n / (time.perf_counter() - t)))
        if a.cli:
            out = d.parent / "out"
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "torch_isc", "reconstruct", str(d), "--out", str(out)],
                           check=True, capture_output=True, cwd=REPO)
            rows.append(("torch-isc reconstruct folder (CLI, incl. start)", a.n / (time.perf_counter() - t0)))
        for name, r in rows:
            print(f"| {size} | {name} | {r:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
