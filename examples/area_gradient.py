"""The gradient of the enclosed area with respect to every input point, drawn as arrows.

``torch_isc.reconstruct`` of points that require grad returns a curve whose values carry
the gradient (implicit differentiation of the refit of the magnitudes, mesh and signs
frozen). ``area(curve).backward()`` gives ``∂A/∂p`` for every point; it is checked against
central finite differences of the converged re-solve, and drawn (cv2) as arrows on the points.

    python examples/area_gradient.py out.png [--points 100] [--noise 0.01]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))       # run from a checkout

import torch_isc  # noqa: E402
from torch_isc import ImplicitCurve  # noqa: E402
from torch_isc.measures import area  # noqa: E402


def draw(path: str, pts: np.ndarray, grad: np.ndarray, polylines, size: int = 640) -> None:
    import cv2
    lo, hi = pts.min(0) - 0.35, pts.max(0) + 0.35
    s = (size - 20) / float((hi - lo).max())

    def px(p):
        q = (p - lo) * s + 10
        return np.stack([q[..., 0], size - q[..., 1]], -1)          # y up

    img = np.full((size, size, 3), 255, np.uint8)
    for pl in polylines:
        q = px(pl["points"].detach().numpy()).round().astype(np.int32)
        cv2.polylines(img, [q.reshape(-1, 1, 2)], bool(pl["closed"]), (160, 160, 160), 2, cv2.LINE_AA)
    scale = 0.25 / max(1e-12, float(np.linalg.norm(grad, axis=1).max()))        # longest arrow 0.25 units
    a, b = px(pts), px(pts + scale * grad)
    for p, q in zip(a, b):
        cv2.arrowedLine(img, tuple(int(v) for v in p.round()), tuple(int(v) for v in q.round()), (200, 60, 0), 1,
                        cv2.LINE_AA, tipLength=0.25)
        cv2.circle(img, tuple(int(v) for v in p.round()), 2, (0, 0, 0), -1, cv2.LINE_AA)
    cv2.imwrite(path, img)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("png", help="output image")
    ap.add_argument("--points", type=int, default=100)
    ap.add_argument("--noise", type=float, default=0.01)
    ap.add_argument("--checks", type=int, default=10, help="coordinates checked by finite differences")
    args = ap.parse_args(argv)
    g = torch.Generator().manual_seed(0)
    t = torch.arange(args.points, dtype=torch.float64) * (2 * math.pi / args.points)
    r = 1.0 + 0.25 * torch.cos(3 * t)                                # a three-lobed curve
    p0 = torch.stack([r * t.cos(), r * t.sin()], 1) + args.noise * torch.randn(args.points, 2, generator=g,
                                                                                dtype=torch.float64)
    p = p0.clone().requires_grad_()
    res = torch_isc.reconstruct(p)
    A = area(res.curve)
    A.sum().backward()
    grad = p.grad
    # finite differences of the converged re-solve (mesh and signs frozen)
    frozen = res.curve.detach()
    sm = torch_isc.ReconstructConfig().band.band_smoothness      # the refit reconstruct's gradient uses
    F0 = torch_isc.refit(frozen, p0, smoothness=sm).values

    def area_of(q):
        return float(area(ImplicitCurve(frozen.mesh, frozen.values + torch_isc.refit(frozen, q, smoothness=sm).values - F0)))

    eps, worst = 1e-6, 0.0
    idx = torch.randperm(2 * args.points, generator=g)[:args.checks].tolist()
    for k in idx:
        i, j = divmod(k, 2)
        e = torch.zeros_like(p0)
        e[i, j] = eps
        fd = (area_of(p0 + e) - area_of(p0 - e)) / (2 * eps)
        worst = max(worst, abs(fd - float(grad[i, j])) / max(1e-3, abs(fd)))
    # points move the curve outward along their normals: the area grows, so dA/dp points outward
    # (up to the smoothing's small negative side lobes at concave necks)
    outward = float(((grad * p0).sum(1) > 0).double().mean())
    draw(args.png, p0.numpy(), grad.numpy(), res.polylines)
    total = float(grad.norm(dim=1).sum())
    perim = float(torch_isc.measures.length(res.curve.detach()))
    A = A.detach()
    # moving every point outward by d moves the curve by about d: sum |dA/dp| ~ the perimeter
    print(f"area {float(A):.4f}; sum |dA/dp| {total:.3f} (perimeter {perim:.3f}); "
          f"{100 * outward:.0f}% of the gradients point outward; finite differences: worst relative error {worst:.1e} "
          f"over {len(idx)} coordinates; wrote {args.png}")
    return {"area": float(A), "perimeter": perim, "grad_norm_sum": total, "outward_fraction": outward, "fd_worst_rel": worst, "grad": grad, "points": p0, "png": args.png}


if __name__ == "__main__":
    main(sys.argv[1:])
