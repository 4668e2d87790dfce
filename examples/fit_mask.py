"""Fit an implicit simplicial curve to a target mask with render.rasterize and torch.optim.Adam.

The nodal values of a fixed hexagonal mesh are the parameters; the soft occupancy image
(``mode="local"``: ``sigmoid(-f/|∇f| / tau)`` per pixel, so every value of a pixel's
triangle gets a gradient) is pulled toward the mask by a binary cross-entropy. Signs may
change during the fit, so the topology follows the mask.

    python examples/fit_mask.py [--size 48] [--steps 150] [--resolution 8]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))       # run from a checkout

import torch_isc
from torch_isc import ImplicitCurve, hexagon_mesh


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / max(1, int((a | b).sum()))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48, help="mask height and width (pixels)")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--resolution", type=int, default=8, help="hexagon mesh resolution")
    ap.add_argument("--lr", type=float, default=0.05)
    args = ap.parse_args(argv)
    D = torch.float64
    extent = (-1.0, -1.0, 1.0, 1.0)
    H = W = args.size
    px = torch_isc.render.pixel_centers(H, W, torch.tensor([extent], dtype=D))[0]      # (H,W,2)
    # target: an ellipse next to a disc (two components)
    x, y = px[..., 0], px[..., 1]
    mask = (((x - 0.25) / 0.45) ** 2 + ((y + 0.1) / 0.3) ** 2 < 1) | ((x + 0.45) ** 2 + (y - 0.35) ** 2 < 0.2 ** 2)
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=D), torch.full((1,), 1.2, dtype=D), args.resolution)
    # start: a small disc in the middle
    values = (mesh.verts.norm(dim=1) - 0.3).clone().requires_grad_()
    tau = 2.0 / args.size

    def hard(v):
        with torch.no_grad():
            c = ImplicitCurve(mesh, v.detach(), validate=False)
            return c.inside(px.reshape(-1, 2)).reshape(H, W)

    iou0 = iou(hard(values), mask)
    opt = torch.optim.Adam([values], lr=args.lr)
    target = mask.to(D)
    for _ in range(args.steps):
        opt.zero_grad()
        img = torch_isc.render.rasterize(ImplicitCurve(mesh, values, validate=False), H, W, tau,
                                         extent=extent, mode="local")[0]
        loss = torch.nn.functional.binary_cross_entropy(img.clamp(1e-6, 1 - 1e-6), target)
        loss.backward()
        opt.step()
        with torch.no_grad():          # a value of exactly 0 is invalid: nudge it outside
            values.masked_fill_(values == 0, 1e-9)
    iou1 = iou(hard(values), mask)
    comps = int(ImplicitCurve(mesh, values.detach()).num_components()[0])
    print(f"IoU {iou0:.3f} -> {iou1:.3f} after {args.steps} Adam steps; {comps} component(s) (the mask has 2)")
    return {"iou_start": iou0, "iou_end": iou1, "components": comps}


if __name__ == "__main__":
    main(sys.argv[1:])
