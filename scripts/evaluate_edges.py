"""Edge mode's topology on generated gray images: the closed curves found against the boundary
count of the shape drawn (cv2.findContours of its mask, RETR_LIST), by family.

Families: a few discs of radius 4-30 px; two discs 3-8 px apart; a ring 3-8 px wide; one to
three rectangles (they may overlap); a strip 14-24 px high of discs 3-6 px apart. Each image is
the mask at gray 30 / 230, blurred by a Gaussian of 0.7 px, 64-320 px a side (strips 300-900 px
long). The reconstruction is ``images.reconstruct_edges`` with the edge settings, one batch.

    OMP_NUM_THREADS=1 python scripts/evaluate_edges.py [--seed 0] [--count 40] [--set KEY=VALUE ...]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import run_main, setup_run  # noqa: E402

FAMILIES = ("discs", "pair", "ring", "rects", "strip")


def make_image(kind: str, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """``(gray uint8 image, bool mask)`` of one generated shape of family ``kind``."""
    import cv2
    H, W = int(rng.integers(64, 320)), int(rng.integers(64, 320))
    if kind == "strip":
        H, W = int(rng.integers(14, 24)), int(rng.integers(300, 900))
    yy, xx = np.mgrid[:H, :W] + 0.5
    m = np.zeros((H, W), bool)
    if kind == "discs":
        for _ in range(int(rng.integers(1, 6))):
            r = rng.uniform(4, 30)
            cx, cy = rng.uniform(r + 2, W - r - 2), rng.uniform(r + 2, H - r - 2)
            m |= (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
    elif kind == "pair":
        r, g = rng.uniform(8, 25), rng.uniform(3, 8)
        for cx in (W / 2 - r - g / 2, W / 2 + r + g / 2):
            m |= (xx - cx) ** 2 + (yy - H / 2) ** 2 < r * r
    elif kind == "ring":
        R, w = rng.uniform(15, min(H, W) / 2 - 4), rng.uniform(3, 8)
        d = np.sqrt((xx - W / 2) ** 2 + (yy - H / 2) ** 2)
        m |= (d < R) & (d > R - w)
    elif kind == "rects":
        for _ in range(int(rng.integers(1, 4))):
            a, b = rng.uniform(5, W / 2), rng.uniform(5, H / 2)
            x0, y0 = rng.uniform(2, W - a - 2), rng.uniform(2, H - b - 2)
            m |= (xx > x0) & (xx < x0 + a) & (yy > y0) & (yy < y0 + b)
    else:
        r = rng.uniform(4, (H - 4) / 2)
        p = 2 * r + rng.uniform(3, 6)
        for k in range(int((W - 4) // p)):
            m |= (xx - (2 + r + k * p)) ** 2 + (yy - H / 2) ** 2 < r * r
    img = cv2.GaussianBlur((m * 200 + 30).astype(np.uint8), (0, 0), 0.7)
    return img, m


def main() -> int:
    import cv2
    import torch_isc  # noqa: F401
    from torch_isc.images import image_config, reconstruct_edges
    from torch_isc.pipeline.config import parse_overrides
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--count", type=int, default=40, help="images, the families taken in turn (default 40)")
    ap.add_argument("--config", default=None, help="YAML config file (keys of ReconstructConfig)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="config overrides (YAML scalars), kept over the edge settings")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args()
    base = setup_run(args)
    cfg = image_config(base, keep=tuple(parse_overrides(args.set)), mode="edges")
    rng = np.random.default_rng(args.seed)
    kinds = [FAMILIES[i % len(FAMILIES)] for i in range(args.count)]
    made = [make_image(k, rng) for k in kinds]
    truth = [len(cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[0]) for _, m in made]
    t0 = time.perf_counter()
    results = reconstruct_edges([img for img, _ in made], cfg)
    seconds = time.perf_counter() - t0
    table: Dict[str, List[int]] = {k: [0, 0, 0] for k in FAMILIES}
    wrong = []
    for i, (k, want, r) in enumerate(zip(kinds, truth, results)):
        got = sum(1 for p in r.polylines if p["closed"])
        row = table[k]
        row[0] += got == want
        row[1] += 1
        row[2] += bool(r.converged and got != want)
        if got != want:
            wrong.append(f"{k}_{i}: {got} of {want}" + ("" if r.converged else f" ({r.limit})"))
    print(f"{args.count} images (seed {args.seed}); overrides: {' '.join(args.set) or 'none'}; {seconds:.1f} s\n")
    print("| family | right / images | wrong and 'converged' |")
    print("|---|---:|---:|")
    for k, (ok, n, silent) in table.items():
        print(f"| {k} | {ok}/{n} | {silent} |")
    tot = [sum(v[j] for v in table.values()) for j in range(3)]
    print(f"| **all** | **{tot[0]}/{tot[1]}** | {tot[2]} |\n")
    if wrong:
        print("wrong: " + "; ".join(wrong))
    return 0


if __name__ == "__main__":
    run_main(main)
