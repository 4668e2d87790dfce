"""Topological simplification of an annealed sign pattern by cluster moves on the same Ising
energy.

Annealing flips one vertex at a time. A channel of wrong signs two vertices wide across a
neck, a bridge of a few vertices between two close curves or a speck of several vertices is a
local minimum for single flips (each vertex alone agrees with its partner in the cluster),
however much the energy would drop if the cluster flipped as a whole. So after annealing,
candidate clusters are flipped whole when that lowers the energy ``Σ_e H_e F_i F_j``:

- sign regions (connected vertices of one sign, no pinned vertex): removing a speck, filling
  a small hole or cutting a sliver the data do not support;
- far clusters: connected vertices of one sign that are all farther from the data than the
  tolerance allows (their stars hold no data within reach). A channel through a stroke is
  connected to the outside through the vertices beside the walls, so it is no region of its
  own; its vertices inside the stroke, away from the walls, are such a cluster.

The energy change of flipping a cluster ``C`` is ``−2 Σ H_ij F_i F_j`` over the edges that leave
``C`` (edges inside it keep their product), so every cluster's change is one scatter-add.
Clusters of one sign and one family never share an edge (an edge between two of them would
have joined them), so they are flipped together and their changes add up; the families and
signs take turns, a fixed number of rounds. Every move lowers the energy, so the result is
never worse than the annealer's by the model's own measure.
"""
from __future__ import annotations

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import edge_components

__all__ = ["cluster_flip_change", "descend_clusters"]


def cluster_flip_change(edges: torch.Tensor, H: torch.Tensor, signs: torch.Tensor, lab: torch.Tensor) -> torch.Tensor:
    """``(V,)`` indexed by label: the Ising energy change of flipping every vertex of that
    label's cluster (alone), ``−2 Σ H_ij F_i F_j`` over the edges with one end in it."""
    with torch.no_grad():
        a, b = edges[:, 0], edges[:, 1]
        cut = lab[a] != lab[b]
        t = -2.0 * H[cut] * signs[a[cut]] * signs[b[cut]]
        out = torch.zeros(signs.shape[0], dtype=H.dtype, device=H.device)
        return out.index_add_(0, lab[a[cut]], t).index_add_(0, lab[b[cut]], t)


def descend_clusters(mesh: MeshBatch, H: torch.Tensor, signs: torch.Tensor, pinned: torch.Tensor,
                     far: torch.Tensor, rounds: int) -> torch.Tensor:
    """``signs (V,)`` after ``rounds`` rounds of cluster moves (see the module): in each round,
    for the sign regions and then the far clusters (``far (V,)`` bool), first of the negative
    and then of the positive vertices, flip every cluster without a ``pinned`` vertex whose
    flip lowers the energy of the couplings ``H (E,)``."""
    with torch.no_grad():
        e = mesh.edges
        V = signs.shape[0]
        s = signs.clone()
        tiny = 1e-9 * H.abs().amax().clamp_min(torch.finfo(H.dtype).tiny) if H.numel() else 0.0
        for _ in range(int(rounds)):
            for use_far in (False, True):
                for sgn in (-1.0, 1.0):
                    mine = s == sgn
                    if use_far:
                        mine = mine & far
                    join = mine[e[:, 0]] & mine[e[:, 1]]
                    lab = edge_components(V, e, join)
                    dE = cluster_flip_change(e, H, s, lab)
                    blocked = torch.zeros(V, dtype=torch.bool, device=s.device).index_fill_(0, lab[pinned], True)
                    flip = mine & (dE[lab] < -tiny) & ~blocked[lab]
                    s = torch.where(flip, -s, s)
        return s
