"""Channel filling: a short run of one sign along the data's own direction, with the other sign
at both of its ends, is a cut the data do not make.

The typical miss at 1% noise is a noisy stroke (or a neck, or the band of one closed curve)
cut by a channel of the outside sign a few vertices wide, or two curves joined by a bridge of
the inside sign: one curve comes out as two loops, two as one. The tangent-notch rule
(pipeline/notches.py) fills such a cut only when it is one vertex long. Here the cut may be
longer: from each vertex, walk along the data's direction (the mean orientation of the
tangents of its star's points) over vertices of its own sign, forward and backward, until the
first vertex of the other sign; when both are reached and the two walks together are at most
``channel_noise_widths`` noise widths (or ``channel_tolerances`` tolerances, the more) long,
the vertex lies in a channel across the data and takes the other sign. A curve between it
and its ends would cross the data where they run straight on, a thing noise makes and
curves do not.

Only where the data at the vertex run one way (coherent tangents) and lie on both sides of it
(:func:`~torch_isc.pipeline.notches.between_walls`: inside a stroke or a gap, not beside one
curve), and only on noisy items. A genuine gap between two curves runs along the data, so walks
along it stay in it; where bridges interrupt it, the walks do reach the other sign, but beyond
both walls (across the data) its neighbours have the other sign too (:func:`enclosed_across`),
while a cut across one band opens onto its own sign there: a gap is never filled. Cuts (the
outside sign) are filled; bridges (the inside sign) are cut only with ``channel_bridges``.

The walks are ``rounds`` rounds of Bellman-Ford relaxation over the directed edges within
``cone`` degrees of the walking vertex's axis (fixed shapes, no host read). An axis has no sign,
so each vertex keeps two distances, one per direction of its own axis; a step to a neighbour
whose axis points the other way continues with that neighbour's other distance.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.pipeline import budget

if TYPE_CHECKING:
    from torch_isc.pipeline.signs import TopologyConfig
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["axis_walks", "wall_offsets", "enclosed_across", "channel_vertices", "channel_stage"]


def axis_walks(mesh: MeshBatch, signs: torch.Tensor, direction: torch.Tensor, cone_deg: float, cap: torch.Tensor,
               rounds: int):
    """``(forward, backward)`` ``(V,)``: per vertex, the length of the shortest path that leaves it
    along ``+direction`` (``−direction``), each step an edge within ``cone_deg`` degrees of the
    axis of the vertex it leaves (oriented to continue the walk), over vertices of its sign, to
    the first vertex of the other sign (that last edge included). ``cap (V,)`` where none is
    found within ``rounds`` edges or the path is longer."""
    e = mesh.edges
    v = mesh.verts.detach().to(direction.dtype)
    dt = direction.dtype
    src = torch.cat([e[:, 0], e[:, 1]])
    dst = torch.cat([e[:, 1], e[:, 0]])
    d = v[dst] - v[src]
    ell = d.norm(dim=1)
    c = (d * direction[src]).sum(1) / ell.clamp_min(torch.finfo(dt).tiny)
    cmin = math.cos(math.radians(float(cone_deg)))
    inf = torch.full_like(ell, float("inf"))
    same = signs[src] == signs[dst]
    flip = (direction[src] * direction[dst]).sum(1) < 0             # dst's axis points back
    cap = cap.to(dt)
    fwd = torch.where(c >= cmin, ell, inf)
    bwd = torch.where(c <= -cmin, ell, inf)
    # a step onto the other sign ends the walk: its length alone
    f_end = torch.where(same, inf, fwd)
    b_end = torch.where(same, inf, bwd)
    F = cap.clone().scatter_reduce(0, src, f_end, "amin")
    Bk = cap.clone().scatter_reduce(0, src, b_end, "amin")
    f_go = torch.where(same, fwd, inf)
    b_go = torch.where(same, bwd, inf)
    for _ in budget.rounds(rounds):
        # walking forward from src onto dst continues along dst's forward axis, or its backward
        # one where dst's axis is reversed
        nf = torch.where(flip, Bk[dst], F[dst]) + f_go
        nb = torch.where(flip, F[dst], Bk[dst]) + b_go
        F = F.scatter_reduce(0, src, nf, "amin")
        Bk = Bk.scatter_reduce(0, src, nb, "amin")
    return torch.minimum(F, cap), torch.minimum(Bk, cap)


def wall_offsets(mesh: MeshBatch, direction: torch.Tensor, points: torch.Tensor, face: torch.Tensor):
    """``(upper, lower)`` ``(V,)``: the mean offset along the normal of ``direction`` of the star's
    points on the positive side of the vertex, and on the negative side (0 where none)."""
    V = mesh.verts.shape[0]
    dt = direction.dtype
    ok = (face >= 0).to(dt)[:, None]
    corners = mesh.faces[face.clamp_min(0)]
    nrm = torch.stack([-direction[:, 1], direction[:, 0]], 1)[corners]
    y = ((points.to(dt)[:, None, :] - mesh.verts.detach().to(dt)[corners]) * nrm).sum(-1)
    c = corners.reshape(-1)
    z = torch.zeros(V, dtype=dt, device=direction.device)
    pos, neg = (y > 0).to(dt) * ok, (y < 0).to(dt) * ok
    up = z.index_add(0, c, (pos * y).reshape(-1)) / z.index_add(0, c, pos.reshape(-1)).clamp_min(1)
    lo = z.index_add(0, c, (neg * y).reshape(-1)) / z.index_add(0, c, neg.reshape(-1)).clamp_min(1)
    return up, lo


def enclosed_across(mesh: MeshBatch, signs: torch.Tensor, direction: torch.Tensor, upper: torch.Tensor,
                    lower: torch.Tensor) -> torch.Tensor:
    """``(V,)`` bool: beyond both walls (the neighbours whose offset along the normal passes
    ``upper``, and those below ``lower``) the vertex's neighbours are mostly of the other sign:
    the vertex lies in a gap between two curves, not in a band of data."""
    e = mesh.edges
    V = signs.shape[0]
    dt = direction.dtype
    v = mesh.verts.detach().to(dt)
    src = torch.cat([e[:, 0], e[:, 1]])
    dst = torch.cat([e[:, 1], e[:, 0]])
    nrm = torch.stack([-direction[:, 1], direction[:, 0]], 1)
    y = ((v[dst] - v[src]) * nrm[src]).sum(1)
    other = (signs[dst] != signs[src]).to(dt)
    z = torch.zeros(V, dtype=dt, device=direction.device)
    above = (y > upper[src]).to(dt)
    below = (y < lower[src]).to(dt)
    n_up, o_up = z.index_add(0, src, above), z.index_add(0, src, above * other)
    n_lo, o_lo = z.index_add(0, src, below), z.index_add(0, src, below * other)
    return (n_up > 0) & (2 * o_up > n_up) & (n_lo > 0) & (2 * o_lo > n_lo)


def channel_vertices(mesh: MeshBatch, signs: torch.Tensor, direction: torch.Tensor, eligible: torch.Tensor,
                     max_length: torch.Tensor, cone_deg: float, rounds: int,
                     enclosed: "torch.Tensor | None" = None) -> torch.Tensor:
    """``(V,)`` bool: the ``eligible`` vertices whose forward and backward walks
    (:func:`axis_walks`) both reach the other sign, together within ``max_length (V,)``, and that
    are not ``enclosed`` across (:func:`enclosed_across`)."""
    L = max_length.to(direction.dtype)
    cap = 2.0 * L + 1.0
    f, b = axis_walks(mesh, signs, direction, cone_deg, cap, rounds)
    out = eligible & (f < cap) & (b < cap) & (f + b <= L)
    return out if enclosed is None else out & ~enclosed


def channel_stage(ws: "WorkingSet", signs: torch.Tensor, pinned: torch.Tensor, cfg: "TopologyConfig") -> torch.Tensor:
    """Fill the channels of the working set's ``signs`` (:func:`channel_vertices`) of the outside
    sign (cuts), then, with ``channel_bridges``, those of the inside sign (bridges)."""
    from torch_isc.pipeline.notches import MIN_NOISE, between_walls, vertex_orientation
    with torch.no_grad():
        mesh = ws.mesh
        vi = mesh.vert_item
        tang = ws.frames[:, 3:5] if ws.frames.shape[1] >= 5 else ws.frames[:, :2]
        direction, coh, n = vertex_orientation(mesh, tang, ws.face)
        between = between_walls(mesh, direction, ws.points, ws.face, ws.noise[vi])
        noisy = ((ws.noise > ws.tol) & (ws.noise >= MIN_NOISE))[vi]
        eligible = (~pinned & between & noisy & (coh >= cfg.channel_coherence)
                    & (n >= cfg.channel_min_points))
        up, lo = wall_offsets(mesh, direction, ws.points, ws.face)
        length = torch.maximum(cfg.channel_noise_widths * ws.noise, cfg.channel_tolerances * ws.tol)[vi]
        for sgn in ((1.0, -1.0) if cfg.channel_bridges else (1.0,)):
            enc = enclosed_across(mesh, signs, direction, up, lo)
            fill = channel_vertices(mesh, signs, direction, eligible & (signs == sgn), length,
                                    cfg.channel_cone, cfg.channel_rounds, enc)
            signs = torch.where(fill, -signs, signs)
        return signs
