"""Tangent notches: a sign change along the data's own direction is a crossing the data do not
make.

The zero set of a good sign pattern runs along the data. Where the points near a vertex all
run one way (a stroke's two walls, a gap's two walls, one curve), the vertex's neighbours in
that direction lie beside the same stretch of data as the vertex itself: a curve between them
would cross the data at a right angle, where no point lies. So a vertex whose neighbours along
the data's direction, on both sides, all have the other sign is a one-vertex notch in a strip
parallel to the data — a channel cut across a thin stroke (a stroke cut in two, a counter
opened to the outside) or a bridge thrown across a thin gap (two strokes or two curves joined)
— and takes their sign. Across the data (along its normal) nothing is said: that is where
curves are.

The direction at a vertex is the mean orientation of the tangents (the denoising fit's, columns
3-4 of ``ws.frames``, else the noise estimate's) of the points in its star, as an orientation tensor (``t tᵀ`` has no sign
ambiguity); it counts only where they agree (coherence ``(λ1 − λ2)/(λ1 + λ2)``): at a corner,
a stroke's end, a small closed curve or isotropic noise they do not, and nothing flips.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import segment_sum
from torch_isc.pipeline import budget

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["vertex_orientation", "between_walls", "tangent_notches", "notch_stage"]


def vertex_orientation(mesh: MeshBatch, tangent: torch.Tensor, face: torch.Tensor):
    """Per vertex the orientation tensor of the tangents of the points in its star.

    Args:
        tangent: ``(P, 2)`` unit tangents of the points. face: ``(P,)`` their triangle (``< 0``:
            none, ignored).
    Returns ``(direction (V, 2), coherence (V,), count (V,))``: the unit major axis of
    ``Σ t tᵀ`` over the star's points, ``(λ1 − λ2)/(λ1 + λ2)`` (1 when all agree, 0 when
    isotropic or empty) and the number of points (a point counts at each corner of its triangle).
    """
    V = mesh.verts.shape[0]
    dt = mesh.dtype
    ok = (face >= 0).to(dt)
    t = tangent.to(dt)
    q = torch.stack([t[:, 0] * t[:, 0], t[:, 0] * t[:, 1], t[:, 1] * t[:, 1], torch.ones_like(t[:, 0])], 1) * ok[:, None]
    corners = mesh.faces[face.clamp_min(0)]                              # (P, 3)
    acc = torch.zeros(V, 4, dtype=dt, device=t.device)
    acc.index_add_(0, corners.reshape(-1), q[:, None, :].expand(-1, 3, -1).reshape(-1, 4))
    a, b, d, n = acc.unbind(1)
    diff = torch.sqrt((a - d) ** 2 + 4 * b * b)
    coh = torch.where(n > 0, diff / (a + d).clamp_min(torch.finfo(dt).tiny), torch.zeros_like(n))
    theta = 0.5 * torch.atan2(2 * b, a - d)
    return torch.stack([torch.cos(theta), torch.sin(theta)], 1), coh, n


#: the two sides' mean offsets must lie this many noise widths apart (a vertex near one noisy
#: wall has points on both sides of it too, about 1.6 noise widths apart)
SIDE_SEPARATION = 2.0
#: the rule acts on items whose noise estimate is at least this fraction of their diagonal (and
#: above their tolerance): the sampling of noise-free curves reads as noise of about 1e-4
MIN_NOISE = 1e-3


def between_walls(mesh: MeshBatch, direction: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                  noise: torch.Tensor) -> torch.Tensor:
    """``(V,)`` bool: the points of the vertex's star lie on both sides of the line through it
    along ``direction``, the sides' mean offsets at least :data:`SIDE_SEPARATION` noise widths
    apart (``noise (V,)``): the vertex sits between two walls (in a stroke or a gap), not beside
    one curve. A vertex just inside a convex curve sees all its points on one side, and its
    neighbours along the tangent lie outside the curve as it bends away: no notch."""
    V = mesh.verts.shape[0]
    dt = direction.dtype
    ok = face >= 0
    corners = mesh.faces[face.clamp_min(0)]                              # (P, 3)
    v = mesh.verts.detach().to(dt)[corners]                              # (P, 3, 2)
    nrm = torch.stack([-direction[:, 1], direction[:, 0]], 1)[corners]   # (P, 3, 2)
    y = ((points.to(dt)[:, None, :] - v) * nrm).sum(-1)                  # (P, 3)
    w = ok.to(dt)[:, None].expand(-1, 3)
    pos = (y > 0).to(dt) * w
    neg = (y < 0).to(dt) * w
    c = corners.reshape(-1)
    z = torch.zeros(V, dtype=dt, device=direction.device)
    npos, nneg = z.index_add(0, c, pos.reshape(-1)), z.index_add(0, c, neg.reshape(-1))
    spos, sneg = z.index_add(0, c, (pos * y).reshape(-1)), z.index_add(0, c, (neg * y).reshape(-1))
    sep = spos / npos.clamp_min(1) - sneg / nneg.clamp_min(1)
    return (npos > 0) & (nneg > 0) & (sep >= SIDE_SEPARATION * noise.to(dt))


def tangent_notches(mesh: MeshBatch, signs: torch.Tensor, direction: torch.Tensor, coherence: torch.Tensor,
                    count: torch.Tensor, pinned: torch.Tensor, min_coherence: float, cone_deg: float,
                    min_points: float) -> torch.Tensor:
    """``(V,)`` bool: the vertices to flip. A vertex flips when its star holds at least
    ``min_points`` points whose tangents agree (``coherence >= min_coherence``), it has at least
    one neighbour within ``cone_deg`` degrees of its direction on each side, and every such
    neighbour has the other sign. ``pinned`` vertices never flip."""
    e = mesh.edges
    v = mesh.verts.detach().to(direction.dtype)
    V = v.shape[0]
    d = v[e[:, 1]] - v[e[:, 0]]
    d = d / d.norm(dim=1, keepdim=True).clamp_min(torch.finfo(d.dtype).tiny)
    cmin = math.cos(math.radians(float(cone_deg)))
    src = torch.cat([e[:, 0], e[:, 1]])
    dst = torch.cat([e[:, 1], e[:, 0]])
    dd = torch.cat([d, -d])                                              # from src toward dst
    c = (dd * direction[src]).sum(1)
    along = c.abs() >= cmin
    same = signs[src] == signs[dst]
    fwd = segment_sum((along & (c > 0)).long(), src, V) > 0
    back = segment_sum((along & (c < 0)).long(), src, V) > 0
    n_same = segment_sum((along & same).long(), src, V)
    return (fwd & back & (n_same == 0) & (coherence >= min_coherence) & (count >= min_points) & ~pinned)


def notch_stage(ws: "WorkingSet", signs: torch.Tensor, pinned: torch.Tensor, rounds: int, min_coherence: float,
                cone_deg: float, min_points: float) -> torch.Tensor:
    """Flip tangent notches (:func:`tangent_notches`) for ``rounds`` rounds (a round flips all its
    notches at once; a flip can make the next notch of a two-vertex cut)."""
    if rounds <= 0:
        return signs
    with torch.no_grad():
        direction, coh, n = vertex_orientation(ws.mesh, ws.frames[:, 3:5] if ws.frames.shape[1] >= 5 else ws.frames[:, :2], ws.face)
        between = between_walls(ws.mesh, direction, ws.points, ws.face, ws.noise[ws.mesh.vert_item])
        # a rule about noise: items whose noise is below their tolerance (noise-free data, where
        # a vertex inside a tightly curved stretch also sees points on both sides) are left alone
        noisy = ((ws.noise > ws.tol) & (ws.noise >= MIN_NOISE))[ws.mesh.vert_item]
        pinned = pinned | ~between | ~noisy
        for _ in budget.rounds(rounds):
            flip = tangent_notches(ws.mesh, signs, direction, coh, n, pinned, min_coherence, cone_deg, min_points)
            signs = torch.where(flip, -signs, signs)
        return signs
