"""CPU against GPU: the same inputs solved on both devices, compared item by item.

    python scripts/device_agreement.py --device cuda [--batch 256] [--hard 64] [--masks 200]

Three sets, each solved as ONE batch on the CPU and ONE batch on ``--device``:
- the benchmark's mix (``scripts/benchmark.py`` part b: circles, ellipses, flowers, two circles,
  annuli; ``--batch`` shapes of 500 points, 0.1% noise);
- the hard mix (part d: glyphs, three nested rings, annuli, outliers, sampling gaps, noise 0-1%;
  ``--hard`` shapes);
- ``--masks`` skimage ``binary_blobs`` masks of 128 x 128 through
  :func:`torch_isc.images.contours.find_contours_batch` (the mask tensors on each device).

Per set: items whose curve counts (closed, open) differ, and the symmetric Hausdorff distance
between the two devices' curves (every vertex of one to the segments of the other) over the
item's diagonal (pixels for masks): max and count above 1e-3 (of the diagonal) or 0.05 px. The
hard mix is also solved twice on ``--device`` (run to run). The
two devices sum in different orders (atomic scatters on a GPU), so bit equality is not expected;
a different topology is a finding. Prints a markdown table; exits 0 whatever it finds.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import List, Sequence, Tuple

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

import torch_isc  # noqa: E402


def _seg_dist(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(n,)`` distance of each point of ``p (n, 2)`` to the nearest segment ``a[k] b[k]``."""
    d = b - a
    t = ((p[:, None] - a[None]) * d[None]).sum(-1) / (d * d).sum(-1).clamp_min(1e-300)[None]
    q = a[None] + t.clamp(0, 1)[..., None] * d[None]
    return (p[:, None] - q).norm(dim=-1).min(1).values


def _segments(polys: Sequence[Tuple[np.ndarray, bool]]) -> Tuple[torch.Tensor, torch.Tensor]:
    a, b = [], []
    for p, closed in polys:
        p = torch.as_tensor(np.asarray(p, np.float64).reshape(-1, 2))
        if len(p) == 0:
            continue
        q = torch.roll(p, -1, 0) if closed else p[1:]
        a.append(p if closed else p[:-1])
        b.append(q)
        if len(p) == 1:
            a.append(p)
            b.append(p)
    if not a:
        z = torch.zeros(0, 2, dtype=torch.float64)
        return z, z
    return torch.cat(a), torch.cat(b)


def hausdorff(pa, pb) -> float:
    """Symmetric Hausdorff distance between two sets of ``(points, closed)`` polylines."""
    va = [torch.as_tensor(np.asarray(p, np.float64).reshape(-1, 2)) for p, _ in pa]
    vb = [torch.as_tensor(np.asarray(p, np.float64).reshape(-1, 2)) for p, _ in pb]
    va = torch.cat(va) if va else torch.zeros(0, 2, dtype=torch.float64)
    vb = torch.cat(vb) if vb else torch.zeros(0, 2, dtype=torch.float64)
    if len(va) == 0 and len(vb) == 0:
        return 0.0
    if len(va) == 0 or len(vb) == 0:
        return float("inf")
    sa, sb = _segments(pa), _segments(pb)
    return max(float(_seg_dist(va, *sb).max()), float(_seg_dist(vb, *sa).max()))


def _polys(result) -> List[Tuple[np.ndarray, bool]]:
    return [(d["points"].detach().double().cpu().numpy(), bool(d["closed"])) for d in result.polylines]


def _row(name: str, n: int, topo_diff: int, dists: List[float], bound: float, unit: str,
         t_cpu: float, t_dev: float) -> str:
    big = sum(d > bound for d in dists)
    mx = max(dists) if dists else 0.0
    return (f"| {name} | {n} | {topo_diff} | {mx:.2e} {unit} | {big} (> {bound:g} {unit}) | "
            f"{t_cpu:.2f} | {t_dev:.2f} |")


def _timed(fn, device: str):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    out = fn()
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
    return out, time.perf_counter() - t


def point_sets(name: str, shapes, device: str, twice: bool = False) -> str:
    pts = [np.asarray(s["points"], np.float64) for s in shapes]
    run = lambda dev: torch_isc.reconstruct_batch([torch.as_tensor(p, device=dev) for p in pts])  # noqa: E731
    run(device) if torch.device(device).type == "cuda" else None      # lazy CUDA set-up out of the time
    rc, tc = _timed(lambda: run("cpu"), "cpu")
    rd, td = _timed(lambda: run(device), device)
    rows = []
    for label, first in ((name, rc), (f"{name}, {device} run twice", run(device) if twice else None)):
        if first is None:
            continue
        topo, dists = 0, []
        for p, a, b in zip(pts, first, rd):
            topo += (a.num_closed, a.num_open) != (b.num_closed, b.num_open)
            diag = float(np.linalg.norm(p.max(0) - p.min(0))) or 1.0
            dists.append(hausdorff(_polys(a), _polys(b)) / diag)
        rows.append(_row(label, len(pts), topo, dists, 1e-3, "diag", tc, td))
    return "\n".join(rows)


def mask_set(count: int, size: int, device: str) -> str:
    from skimage.data import binary_blobs
    from torch_isc.images.contours import find_contours_batch
    masks = [np.asarray(binary_blobs(size, rng=k), np.uint8) for k in range(count)]
    run = lambda dev: find_contours_batch([torch.as_tensor(m, device=dev) for m in masks])  # noqa: E731
    run(device)
    rc, tc = _timed(lambda: run("cpu"), "cpu")
    rd, td = _timed(lambda: run(device), device)
    topo, dists = 0, []
    for (ca, ha), (cb, hb) in zip(rc, rd):
        same = len(ca) == len(cb) and (ha is None) == (hb is None) and (ha is None or np.array_equal(ha, hb))
        topo += not same
        dists.append(hausdorff([(c[:, 0], True) for c in ca], [(c[:, 0], True) for c in cb]))
    return _row(f"masks {size}x{size}", count, topo, dists, 0.05, "px", tc, td)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batch", type=int, default=256, help="shapes of the benchmark's mix (default 256)")
    ap.add_argument("--hard", type=int, default=64, help="shapes of the hard mix (default 64)")
    ap.add_argument("--masks", type=int, default=200, help="binary_blobs masks (default 200)")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads for the CPU runs")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        print("device_agreement: CUDA is not available here", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    import benchmark as bm
    print(f"CPU ({torch.get_num_threads()} threads) against {args.device}; torch {torch.__version__}\n")
    print("| set | items | topology differs | max Hausdorff | items above | CPU s | device s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    rows = []
    if args.batch:
        rows.append(point_sets("benchmark mix", bm.make_shapes(args.batch, 500, args.seed), args.device))
        print(rows[-1], flush=True)
    if args.hard:
        rows.append(point_sets("hard mix", bm.make_hard_shapes(args.hard, 500, args.seed), args.device, twice=True))
        print(rows[-1], flush=True)
    if args.masks:
        rows.append(mask_set(args.masks, 128, args.device))
        print(rows[-1], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
