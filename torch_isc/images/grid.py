"""Masks as implicit simplicial curves on their pixel-centre grid: topology by construction.

A binary mask is an exact inside/outside function, so nothing has to be estimated about its
topology. :func:`trace_masks` builds, for a whole batch of masks at once (tensor ops only):

1. **The mesh.** Every mask is padded by one background pixel (the mesh's outer boundary is
   outside) and stacked into a ``(B, H+2, W+2)`` grid. The vertices are the pixel centres of the
   2x2 cells that hold both classes (the band around the boundary; uniform cells hold no curve),
   each such cell split into two triangles along the diagonal chosen by the connectivity rule:
   with ``connectivity=8`` (OpenCV's: 8-connected foreground, 4-connected background) a cell
   whose two foreground pixels sit on a diagonal is split along that diagonal, so the
   foreground is connected through it; a cell with one odd pixel out is split along the
   diagonal that avoids it (the curve cuts the corner, as marching squares does).
   ``connectivity=4`` is the other way round. The result is one packed
   :class:`~torch_isc.core.mesh.MeshBatch`.
2. **The signs.** A vertex is negative (inside) on a foreground pixel, positive on a background
   one. Every zero crossing therefore lies on an edge between two pixel centres of different
   classes: the zero set has exactly the mask's boundaries (one closed curve per border of an
   8-connected component or of a 4-connected hole, single pixels included) and no point of it
   is more than a pixel away from the crack-edge boundary, but at an acute corner tip, which the
   mask loses where the shape is thinner than a pixel: there the band vertex of the other class
   next to the tip moves just past the apex of the extended sides (its sign kept, its triangles
   positive), so the tip vertex sits on the apex, up to a few pixels out (:func:`_stretch_band`).
3. **The magnitudes.** Only they are fitted. The crossings start at the edge midpoints (the
   crack-midpoint polygon of marching squares) and are smoothed along each curve by Taubin's
   non-shrinking lambda|mu filter, each step projected back onto the crossing's own edge and
   kept within ``reach`` of its midpoint; sharp corners (a turn of 90 degrees or more within
   two crossings) are held where they are. The vertex log-magnitudes that realise these
   crossings are then solved along each curve (a cumulative sum, the loop's closing error
   spread evenly, and a few Jacobi sweeps where a vertex serves several curves).
4. **The hierarchy.** Outer borders and holes are told apart by their orientation; the border
   enclosing each one is found by a look to the left along its start row (Suzuki and Abe's
   rule, with cracks instead of labels), and borders are listed in OpenCV's order (a preorder
   of the tree, siblings last-found first), for ``RETR_EXTERNAL``, ``RETR_LIST``,
   ``RETR_CCOMP`` or ``RETR_TREE``.

Everything is in the pixel convention of :mod:`torch_isc.images` (pixel ``(i, j)`` covers
``[j, j+1] x [i, i+1]``), so the curves stay within ``[0.5, W-0.5] x [0.5, H-0.5]``: inside
the image frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

from torch_isc.core.extract import Polylines, extract_zero_set
from torch_isc.core.mesh import MeshBatch

__all__ = ["GridCurves", "grid_mesh", "trace_masks", "padded_groups", "TRACE_PIXELS", "RETR_MODES", "retr_mode"]

#: Retrieval modes by OpenCV's names and constants (``cv2.RETR_EXTERNAL`` = 0, ``RETR_LIST`` = 1,
#: ``RETR_CCOMP`` = 2, ``RETR_TREE`` = 3).
RETR_MODES = {"external": 0, "list": 1, "ccomp": 2, "tree": 3}


def retr_mode(mode: Union[str, int]) -> str:
    """``"external" | "list" | "ccomp" | "tree"`` from a name (``"tree"``, ``"RETR_TREE"``,
    ``"cv2.RETR_TREE"``) or an OpenCV constant (0..3).

    >>> retr_mode(3), retr_mode("RETR_CCOMP"), retr_mode("list")
    ('tree', 'ccomp', 'list')
    """
    return cv_option(mode, RETR_MODES, "retr_", "retrieval mode",
                     "OpenCV's RETR_EXTERNAL=0, RETR_LIST=1, RETR_CCOMP=2, RETR_TREE=3; RETR_FLOODFILL is not supported")


def cv_option(value: Union[str, int], table: Dict[str, int], prefix: str, what: str, known: str) -> str:
    """The name in ``table`` of an OpenCV option given as its constant (``cv2.RETR_TREE``) or a
    name (``"RETR_TREE"``, ``"tree"``); a ValueError saying ``known`` otherwise."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        for k, v in table.items():
            if v == int(value):
                return k
        raise ValueError(f"unknown {what} {value} ({known})")
    name = str(value).lower().rsplit(".", 1)[-1]
    name = name[len(prefix):] if name.startswith(prefix) else name
    if name not in table:
        raise ValueError(f"unknown {what} {value!r} ({known})")
    return name


#: the padded pixels one :func:`trace_masks` call holds at most (a mask alone may exceed it): a
#: batch pads every mask to the largest height and width, so a 1 x N mask beside an N x 1 one
#: would cost N x N each
TRACE_PIXELS = 1 << 22


def padded_groups(shapes: Sequence[Tuple[int, int]], budget: int = TRACE_PIXELS) -> List[Tuple[int, int]]:
    """Consecutive runs ``[b0, b1)`` of masks of ``shapes [(H, W)]`` whose padded grid
    (count x (Hmax + 2) x (Wmax + 2) pixels, :func:`_stack`) stays within ``budget`` pixels; a
    mask alone may exceed it. Memory is then bounded by the masks themselves, not by how
    their shapes combine.

    >>> padded_groups([(1, 1000), (1000, 1), (1000, 1)], budget=10_000)
    [(0, 1), (1, 3)]
    """
    out: List[Tuple[int, int]] = []
    b0 = 0
    while b0 < len(shapes):
        b1, h, w = b0 + 1, shapes[b0][0] + 2, shapes[b0][1] + 2
        while b1 < len(shapes):
            h2, w2 = max(h, shapes[b1][0] + 2), max(w, shapes[b1][1] + 2)
            if (b1 - b0 + 1) * h2 * w2 > budget:
                break
            b1, h, w = b1 + 1, h2, w2
        out.append((b0, b1))
        b0 = b1
    return out


def _stack(masks: Sequence[torch.Tensor]) -> Tuple[torch.Tensor, torch.Tensor]:
    """Masks of any sizes as one ``(B, Hmax+2, Wmax+2)`` bool grid, one background pixel (at
    least) around each; and ``(B, 2)`` their ``(H, W)``."""
    sizes = torch.tensor([list(m.shape) for m in masks], dtype=torch.long, device="cpu")
    H, W = int(sizes[:, 0].max()), int(sizes[:, 1].max())
    dev = masks[0].device
    if all(tuple(m.shape) == (H, W) for m in masks):
        g = F.pad(torch.stack([m.bool() for m in masks]), (1, 1, 1, 1))
    else:
        g = torch.zeros((len(masks), H + 2, W + 2), dtype=torch.bool, device=dev)
        for b, m in enumerate(masks):
            g[b, 1:1 + m.shape[0], 1:1 + m.shape[1]] = m.bool()
    return g, sizes


def grid_mesh(grid: torch.Tensor, connectivity: int = 8, dtype: torch.dtype = torch.float64
              ) -> Tuple[MeshBatch, torch.Tensor, torch.Tensor]:
    """The band mesh of a padded ``(B, H2, W2)`` bool grid (see the module docstring).

    Returns:
        ``(mesh, fg (V,) bool, pix (V,) long)``: the packed mesh (vertex ``(x, y)`` of padded
        pixel ``(i, j)`` is ``(j - 0.5, i - 0.5)``, i.e. the unpadded pixel's centre), whether each
        vertex is a foreground pixel, and its flat index ``(b * H2 + i) * W2 + j`` in the grid.

    >>> g = torch.zeros(1, 4, 4, dtype=torch.bool); g[0, 1:3, 1:3] = True
    >>> m, fg, _ = grid_mesh(g)
    >>> m.verts.shape[0], m.faces.shape[0], int(fg.sum()), bool((m.signed_areas() > 0).all())
    (16, 16, 4, True)
    """
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 8 or 4 (of the foreground), got {connectivity!r}")
    B, H2, W2 = grid.shape
    dev = grid.device
    g = grid if connectivity == 8 else ~grid           # the class that is 8-connected
    tl, tr, bl, br = g[:, :-1, :-1], g[:, :-1, 1:], g[:, 1:, :-1], g[:, 1:, 1:]
    s = tl.to(torch.int8) + tr + bl + br
    mixed = (s > 0) & (s < 4)
    d1_same8 = tl & br
    d2_same8 = tr & bl
    d1_same4 = ~tl & ~br
    d2_same4 = ~tr & ~bl
    # the diagonal TR-BL when it joins two pixels of the 8-connected class (and TL-BR does
    # not), or else joins two of the other class while TL-BR joins neither
    use_d2 = (d2_same8 & ~d1_same8) | (~d1_same8 & ~d2_same8 & ~d1_same4 & d2_same4)
    b, i, j = mixed.nonzero(as_tuple=True)
    d2 = use_d2[b, i, j]
    used = torch.zeros((B, H2, W2), dtype=torch.bool, device=dev)
    used[b, i, j] = True
    used[b, i + 1, j] = True
    used[b, i, j + 1] = True
    used[b, i + 1, j + 1] = True
    flat_used = used.view(-1)
    pix = flat_used.nonzero().squeeze(1)
    vid = torch.full((B * H2 * W2,), -1, dtype=torch.long, device=dev)
    vid[pix] = torch.arange(pix.shape[0], device=dev)
    base = (b * H2 + i) * W2 + j
    TL, TR, BL, BR = (vid.index_select(0, base + o) for o in (0, 1, W2, W2 + 1))
    # positively oriented in (x, y) with y down: (TL, BR, BL), (TL, TR, BR); (TL, TR, BL), (TR, BR, BL)
    t1 = torch.where(d2[:, None], torch.stack([TL, TR, BL], 1), torch.stack([TL, BR, BL], 1))
    t2 = torch.where(d2[:, None], torch.stack([TR, BR, BL], 1), torch.stack([TL, TR, BR], 1))
    faces = torch.stack([t1, t2], 1).reshape(-1, 3)
    rem = pix % (H2 * W2)
    verts = torch.stack([(rem % W2).to(dtype) - 0.5, (rem // W2).to(dtype) - 0.5], 1)
    vpi = torch.bincount(pix // (H2 * W2), minlength=B)
    fpi = 2 * torch.bincount(b, minlength=B)
    mesh = MeshBatch(verts, faces, vpi, fpi)
    return mesh, grid.view(-1)[pix], pix


@dataclass
class GridCurves:
    """The curves of a batch of masks (:func:`trace_masks`).

    Attributes:
        mesh: the packed band mesh, with a vertex at each restored corner tip
            (:func:`_insert_tips`); values: ``(V,)`` nodal values (negative on foreground).
        polylines: the zero set, one closed loop per border, loops grouped by item; its
            ``edge`` indexes the band mesh before the tips were added (the pixel pair each
            point separates; a tip's crossings repeat the pair of the crossing before them).
        outer: ``(K,)`` bool, the loop is the outer border of a foreground component (else a hole).
        parent: ``(K,)`` long, global index of the enclosing loop (the hole around an outer
            border, the outer border around a hole), -1 for none (RETR_TREE's parent).
        start: ``(K,)`` long, raster index (in the padded grid of the batch) of the pixel at
            which OpenCV's scan starts the border: the order of discovery.
        sizes: ``(B, 2)`` the masks' ``(H, W)``.
        inner: ``(Q, 2)`` for each point of ``polylines``, the centre of the foreground pixel at
            the end of its edge (OpenCV's chain of boundary pixels, repeats aside).
        tips: ``(M, 2)`` the corner tips found (:func:`_corner_tips`; inserted as vertices
            where they fit, :func:`_insert_tips`), and tip_item ``(M,)`` their items. An acute tip may lie up to a few pixels beyond the
            band of pixel centres (:func:`_stretch_band`); everywhere else the curve is within a
            pixel of OpenCV's chain.
    """
    mesh: MeshBatch
    values: torch.Tensor
    polylines: Polylines
    outer: torch.Tensor
    parent: torch.Tensor
    start: torch.Tensor
    sizes: torch.Tensor
    inner: Optional[torch.Tensor] = None
    tips: Optional[torch.Tensor] = None
    tip_item: Optional[torch.Tensor] = None
    start_node: Optional[torch.Tensor] = None

    def loop_ranges(self) -> torch.Tensor:
        """``(B + 1,)`` the loops of item ``b`` are ``ranges[b]:ranges[b+1]``."""
        cnt = self.polylines.per_item_counts()
        return torch.cat([cnt.new_zeros(1), torch.cumsum(cnt, 0)])


def _loop_index(first: torch.Tensor, counts: torch.Tensor, n: int):
    K = first.shape[0]
    loop = torch.repeat_interleave(torch.arange(K, device=first.device), counts)
    fl = first.index_select(0, loop)
    k = torch.arange(n, device=first.device) - fl
    nk = counts.index_select(0, loop)
    prev = fl + (k - 1) % nk
    nxt = fl + (k + 1) % nk
    return loop, k, prev, nxt


def _smooth(a: torch.Tensor, d: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor, iters: int,
            reach: float, cap: Optional[torch.Tensor] = None, lam: float = 0.6307, mu: float = -0.6732) -> torch.Tensor:
    """Crossing parameters ``t (N,)`` along edges ``a + t d`` (from the foreground end), by
    Taubin's lambda|mu smoothing of the crossing points along their loops, each step projected
    on the crossing's edge and clamped to ``|t - 1/2| * |d| <= reach``; sharp corners held."""
    dd = (d * d).sum(1)
    length = dd.sqrt()
    lo = (0.5 - reach / length).clamp(min=0.02)
    hi = (0.5 + reach / length).clamp(max=0.98)
    t = torch.full_like(dd, 0.5)
    p = a + t[:, None] * d
    # corners: the turn between the chords to the second neighbours on either side
    p2, n2 = prev[prev], nxt[nxt]
    u, w = p - p.index_select(0, p2), p.index_select(0, n2) - p
    cosang = (u * w).sum(1) / (u.norm(dim=1) * w.norm(dim=1)).clamp_min(1e-12)
    corner = cosang < 0.05
    # a corner holds its two neighbours in place too (a corner is a feature, not noise)
    hold = corner | corner.index_select(0, prev) | corner.index_select(0, nxt)
    free = ~hold
    # a step moves p = a + t d to p + f (mid - p), mid = (p[prev] + p[nxt]) / 2, and projects it
    # on the edge: t' = t + f ((mid - p) . d) / |d|^2, which is affine in t, t[prev], t[nxt]:
    # t' = t + f (c0 + cp t[prev] + cn t[nxt] - t), so the loop runs on (N,) scalars only
    c0 = ((0.5 * (a[prev] + a[nxt]) - a) * d).sum(1) / dd
    cp = 0.5 * (d.index_select(0, prev) * d).sum(1) / dd
    cn = 0.5 * (d.index_select(0, nxt) * d).sum(1) / dd
    for it in range(iters):
        live = free if cap is None else free & (cap > it)
        for f in (lam, mu):
            tn = torch.addcmul(torch.addcmul(c0 - t, cp, t.index_select(0, prev)), cn, t.index_select(0, nxt)
                               ).mul_(f).add_(t).clamp_(lo, hi)     # index_select: x[idx]'s gather, faster on CPU
            t = torch.where(live, tn, t)
    return t


def _corner_tips(a: torch.Tensor, d: torch.Tensor, t: torch.Tensor, prev: torch.Tensor, nxt: torch.Tensor,
                 n_loop: torch.Tensor, side: Tuple[int, int] = (2, 7), zone: int = 3, radius: float = 2.0,
                 straight: float = 0.16, min_turn: float = 0.35, max_cos: float = 0.5,
                 min_loop: int = 24, min_side: float = 2.0, max_cos_smooth: float = 0.8,
                 max_radius: float = 5.0, straight_long: float = 0.25, stretch_side: int = 16, long_sides: Sequence[int] = (11, 16, 24, 32, 40, 48, 56, 64),
                 stretch: Optional[Callable] = None, long_span: int = 8, max_cos_long: float = 0.8,
                 max_cos_long_smooth: float = 0.68, gap: int = 2, gap_span: int = 10, corner_gap: int = 3,
                 straight_window: float = 0.22, min_loop_sure: int = 64, small_side: int = 11, separate: int = 1,
                 separate_sides: Sequence[int] = (80, 96, 128), bend: float = 1.5
                 ) -> Tuple[torch.Tensor, Optional[Tuple[torch.Tensor, torch.Tensor, torch.Tensor]]]:
    """Crossing parameters ``t`` with the sharp corners restored: at each corner of the loops
    (a turn of the chords 3 nodes either side with cosine below ``max_cos`` on the crack
    midpoints, at its sharpest node, and below ``max_cos_smooth`` on the smoothed crossings),
    a line is fitted to the smoothed crossings of either side (nodes ``side[0]..side[1]`` steps away, kept only when the fit is
    straight: RMS residual below ``straight`` px, and at least ``min_side`` px long; loops of
    ``min_loop`` crossings or more), the two lines are intersected, and the crossings
    within ``zone`` steps and ``radius`` px of that tip move along their edges to where the edges
    meet the wedge of the two extended sides (convex corners: the intersection of the two
    foreground half-planes; notches: the union). The tip a mask cuts off is drawn again, to
    within the edges' reach; smooth curves have no such corner (their sides are not straight or
    meet at too small a turn, ``sin`` below ``min_turn``) and are left as they are.
    An acute tip lies farther out: the mask loses it where the wedge is narrower than about a
    pixel, ``0.5 / tan(apex / 2)`` from the apex, so ``radius`` grows to that plus a pixel
    (at most ``max_radius``). ``stretch(nodes (C, Z), tip (C, 2), convex (C,), out (C, 2))``,
    when given, may move band vertices out toward the tips (``out``: the unit bisector beyond
    the apex) and returns the crossings' edges ``(a, d)`` on the moved mesh, on which the zone
    is then projected, and the vertex moved per corner. Obtuse corners (a turn of 50-75
    degrees, which 3-step chords of a staircase misjudge by up to 30) are candidates too where
    the chords ``long_span`` nodes long turn with cosine below ``max_cos_long`` and the smoothed
    crossings turn with cosine below ``max_cos_long_smooth`` between chords that leave out the
    ``gap`` nodes either side (nodes ``gap..gap_span`` away: chords through the corner read a
    60-degree turn that the mask rounds as 45-50), on loops of ``16 long_span`` crossings or
    more, with both sides straight over ``2 long_span`` nodes or more. A side is fitted over the
    longest straight window of ``long_sides`` (a near-axis side is one run of crossings over 24
    nodes, and its direction is only measured across a step): windows beyond 24 nodes need an
    RMS residual below ``straight_window`` and stop ``corner_gap`` nodes before the next corner
    candidate along the loop. On loops below ``min_loop_sure`` crossings (down to ``min_loop``)
    a corner needs both sides straight over ``small_side`` nodes (a small disc's arcs look
    straight over a few).
    With ``separate`` (default 1), each accepted corner's side lines are then checked against
    the pixel classes (:func:`_separating_lines`): the longest window of ``long_sides`` and
    ``separate_sides`` (within the room to the next candidate) whose foreground and background
    pixel centres a line separates, one window short of it, and where that is longer than the
    least-squares window the middle of the separating lines replaces the side's line; only
    sides whose smoothed crossings lie within ``bend`` px of their line over the first such
    window are searched (a near-axis side is one run over 24 crossings: its direction is known
    only across its steps).

    Returns ``(t, corners)``: ``corners`` is ``(node (C,), tip (C, 2), convex (C,), moved (C,))``
    of the corners found (for :func:`_insert_tips`; ``moved``: the band vertex ``stretch`` moved
    out to the corner's tip, -1 for none), None when there is none."""
    if t.numel() == 0:
        return t, None
    p = a + t[:, None] * d
    m = a + 0.5 * d
    # the turn between the chords to the nodes `span` steps away on either side, its sharpest
    # node within `span` steps: a corner candidate
    span = 3
    p3 = prev[prev[prev]]
    n3 = nxt[nxt[nxt]]
    u, w = m - m[p3], m[n3] - m
    cosang = (u * w).sum(1) / (u.norm(dim=1) * w.norm(dim=1)).clamp_min(1e-12)
    c = ((cosang < max_cos) & (n_loop >= min_loop)).nonzero().squeeze(1)      # candidates (few)
    # ... where the smoothed curve turns too (a staircase step on a smooth curve does not), at
    # the sharpest node within `span` steps
    us, ws = p[c] - p[p3[c]], p[n3[c]] - p[c]
    cos_s = (us * ws).sum(1) / (us.norm(dim=1) * ws.norm(dim=1)).clamp_min(1e-12)
    keep = cos_s < max_cos_smooth
    cb, cf, cc = c, c, cosang[c]
    for _ in range(span):
        cb, cf = prev[cb], nxt[cf]
        keep &= (cc < cosang[cb]) & (cc <= cosang[cf])
    c = c[keep]
    if long_span > 0:
        # obtuse corners: the 3-step chords of a staircase misjudge a turn of 50-75 degrees by
        # up to 30; chords `long_span` steps long measure it (a disc of a loop of 64 crossings or
        # more turns less than 40 degrees over them)
        pl_, nl_ = _walk(prev, long_span), _walk(nxt, long_span)
        ul, wl = m - m[pl_], m[nl_] - m
        cos_l = (ul * wl).sum(1) / (ul.norm(dim=1) * wl.norm(dim=1)).clamp_min(1e-12)
        cl = ((cos_l < max_cos_long) & (n_loop >= max(min_loop, 16 * long_span))).nonzero().squeeze(1)
        keep = torch.ones_like(cl, dtype=torch.bool)
        cb, cf, cc = cl, cl, cos_l[cl]
        for _ in range(long_span // 2):
            cb, cf = prev[cb], nxt[cf]
            keep &= (cc < cos_l[cb]) & (cc <= cos_l[cf])
        cl = cl[keep]
        # each side straight over 2 long_span nodes (its two halves' chords within 26 degrees),
        # as the fits below will need: cheap, and it drops the many bends of smooth curves
        for step, far in ((prev, pl_), (nxt, nl_)):
            q2, q1 = step[step[cl]], far[cl]
            q0 = far[q1]
            d1, d2 = m[q1] - m[q0], m[q2] - m[q1]
            cl = cl[(d1 * d2).sum(1) > 0.9 * (d1.norm(dim=1) * d2.norm(dim=1))]
        # not within long_span steps of a corner found on the short chords
        near = torch.zeros(a.shape[0], dtype=torch.bool, device=a.device)
        cb, cf = c, c
        near[c] = True
        for _ in range(long_span):
            cb, cf = prev[cb], nxt[cf]
            near[cb] = True
            near[cf] = True
        cl = cl[~near[cl]]
        # the turn itself is measured on the smoothed crossings between chords that leave out
        # the `gap` nodes either side of the corner (the mask rounds a corner over a few
        # crossings, and chords through it read a 60-degree turn as 45-50)
        ends = []
        for step in (prev, nxt):
            j, out = cl, {}
            for n_ in range(1, gap_span + 1):
                j = step[j]
                if n_ in (gap, gap_span):
                    out[n_] = j
            ends.append(out)
        usl, wsl = p[ends[0][gap]] - p[ends[0][gap_span]], p[ends[1][gap_span]] - p[ends[1][gap]]
        cl = cl[(usl * wsl).sum(1) / (usl.norm(dim=1) * wsl.norm(dim=1)).clamp_min(1e-12) < max_cos_long_smooth]
        c, srt = torch.cat([c, cl]).sort()
        from_long = (torch.arange(c.shape[0], device=c.device) >= c.shape[0] - cl.shape[0])[srt]
    else:
        from_long = torch.zeros(c.shape[0], dtype=torch.bool, device=c.device)
    if c.numel() == 0:
        return t, None
    steps = max([side[1], zone, gap_span] + list(long_sides) + (list(separate_sides) if separate else []))
    back, fwd = [c], [c]
    for _ in range(steps + corner_gap):
        back.append(prev[back[-1]])
        fwd.append(nxt[fwd[-1]])

    def longest(walk, reach_of, toward):
        # the longest straight fit of nodes side[0]..L, L in side_ends: a staircase of a shallow
        # side is straight only over a whole step, and a short fit on one step tilts the line.
        # All windows from one stack of the nodes outward from the corner, by prefix sums (in
        # float64, about the corner: a window's scatter is a difference of sums)
        short = [L for L in side_ends if L <= 24]
        o = p[c].double()
        q = p[torch.stack(walk[side[0]:short[-1] + 1], 1)].double() - o[:, None]        # (C, K, 2)
        best = windows(q, o, short, reach_of, toward, None)
        # the longer windows only where the side is straight over all 24 and may go on
        go = ((best[3] == short[-1]) & (reach_of > short[-1])).nonzero().squeeze(1)
        if go.numel() and len(side_ends) > len(short):
            ql = p[torch.stack([w_[go] for w_ in walk[side[0]:side_ends[-1] + 1]], 1)].double() - o[go, None]
            sub = windows(ql, o[go], side_ends[len(short):], reach_of[go], toward, tuple(x_[go] for x_ in best))
            best = tuple(x_.index_copy(0, go, y_) for x_, y_ in zip(best, sub))
        return tuple(x_.to(p.dtype) for x_ in best)

    def windows(q, o, ends_, reach_of, toward, best):
        x, y = q[..., 0], q[..., 1]
        S = torch.stack([x, y, x * x, y * y, x * y], 0).cumsum(2)                       # (5, C, K)
        for L in ends_:
            col = L - side[0]
            mx, my, mxx, myy, mxy = S[:, :, col] / (col + 1)
            sxx, syy, sxy = mxx - mx * mx, myy - my * my, mxy - mx * my
            th = 0.5 * torch.atan2(2 * sxy, sxx - syy)
            v = torch.stack([torch.cos(th), torch.sin(th)], 1)
            travel = (q[:, col] - q[:, 0]) * toward                                      # in travel order
            v = torch.where(((v * travel).sum(1) < 0)[:, None], -v, v)
            r = (0.5 * (sxx + syy) - torch.sqrt((0.5 * (sxx - syy)) ** 2 + sxy ** 2)).clamp_min(0).sqrt()
            r = torch.where(travel.norm(dim=1) >= min_side, r, torch.full_like(r, float("inf")))
            mu = torch.stack([mx, my], 1) + o
            if best is None:
                best = (mu, v, r, torch.full_like(r, float(L)))
            else:
                # a window stops short of the next corner candidate along the loop
                take = ((r < (straight if L < 16 else straight_long if L <= 24 else straight_window))
                        & ((L <= 24) | (L <= reach_of)))[:, None]
                best = (torch.where(take, mu, best[0]), torch.where(take, v, best[1]),
                        torch.where(take[:, 0], r, best[2]), torch.where(take[:, 0], float(L), best[3]))
        return best

    side_ends = [side[1]] + [L for L in long_sides if L > side[1]]
    # how far each side may be fitted: to `corner_gap` nodes before the next candidate (beyond
    # `gap_span` nodes: a corner can be found twice a few nodes apart) along the loop
    is_c = torch.zeros(a.shape[0], dtype=torch.bool, device=a.device)
    is_c[c] = True
    big = float(steps + corner_gap + 1)

    def room(walk):
        hit = torch.stack([is_c[walk[j]] for j in range(gap_span + 1, steps + corner_gap + 1)], 1)
        j = torch.arange(gap_span + 1, steps + corner_gap + 1, device=a.device, dtype=p.dtype)
        return torch.where(hit, j, torch.full_like(j, big)).min(1).values - corner_gap

    def separated(mu1, v1, mu2, v2, L1, L2, reach, back, fwd):
        # each side's line refitted to the pixel centres its crossings separate: a half-plane
        # covers half of a pixel exactly when it holds the pixel's centre, so the classes
        # bound the side's line (beyond the pixels near the corner, which the other side cuts
        # too). The window is the longest (up to the next corner candidate) whose classes a
        # line still separates: a near-axis side's direction is only known across its steps
        ends_s = [L for L in sorted(set(side_ends) | set(separate_sides))]
        Ks = torch.arange(side[0], ends_s[-1] + 1, device=a.device)
        Lw = torch.tensor(ends_s, dtype=p.dtype, device=a.device)
        for _ in range(separate):
            den_ = v1[:, 0] * v2[:, 1] - v1[:, 1] * v2[:, 0]
            dm_ = mu2 - mu1
            sol_ = (dm_[:, 0] * v2[:, 1] - dm_[:, 1] * v2[:, 0]) / torch.where(den_.abs() > 1e-9, den_, torch.ones_like(den_))
            tip_ = mu1 + sol_[:, None] * v1
            excl = 1.42 / den_.abs().clamp(0.3, 1.0)       # the other side may cut a pixel this near the tip
            new = []
            for walk, mu_, v_, L_, reach_ in ((back, mu1, v1, L1, reach[0]), (fwd, mu2, v2, L2, reach[1])):
                # only sides with room for a window two steps beyond the least-squares one
                i0 = torch.searchsorted(Lw, L_.contiguous())
                i1 = torch.searchsorted(Lw, torch.maximum(reach_, L_).contiguous(), right=True) - 1
                cand = i1 >= i0 + 2
                # ... and straight over it: its smoothed crossings within `bend` px of the
                # least-squares line (a near-axis side is off it by its next step, about a
                # pixel; a curved side by more; cheap, before the searches)
                i2 = (i0 + 2).clamp(max=len(ends_s) - 1)
                n2 = int(Lw[i2[cand]].max()) if bool(cand.any()) else side[0]      # one host read
                q_ = p[torch.stack(walk[side[0]:n2 + 1], 1)] - mu_[:, None]
                off_ = (q_[..., 0] * v_[:, None, 1] - q_[..., 1] * v_[:, None, 0]).abs()
                off_ = torch.where(Ks[None, :n2 + 1 - side[0]] <= Lw[i2][:, None], off_, torch.zeros_like(off_))
                cand &= off_.amax(1) <= bend
                sub = cand.nonzero().squeeze(1)
                if sub.numel() == 0:
                    new.append((mu_, v_))
                    continue
                i0, i1 = i0[sub], i1[sub]
                Kmax = int(Lw[i1].max()) if sub.numel() else side[0]       # one host read: the stack's depth
                nodes_ = torch.stack([w_[sub] for w_ in walk[side[0]:Kmax + 1]], 1)                  # (S, K)
                fgp = a[nodes_]
                bgp = fgp + d[nodes_]
                tip_s = tip_[sub]
                far = torch.minimum((fgp - tip_s[:, None]).norm(dim=-1), (bgp - tip_s[:, None]).norm(dim=-1)) > excl[sub, None]
                Kr = Ks[:nodes_.shape[1]]
                mu_s, v_s = mu_[sub], v_[sub]

                def fit(ix):
                    valid = (Kr[None] <= Lw[ix][:, None]) & far
                    m2, w2, gap_ = _separating_lines(fgp, bgp, valid, mu_s, v_s)   # v_: along the loop, background on its right
                    return m2, w2, (gap_ > 0) & (valid.sum(1) >= 6)

                # the longest separable window by bisection (separability only shrinks as a window grows)
                lo, hi = i0.clone(), i1.clone()
                for _ in range(max(1, math.ceil(math.log2(len(ends_s))))):
                    mid = torch.div(lo + hi + 1, 2, rounding_mode="floor")
                    sep = fit(mid)[2] & (lo < hi)
                    lo = torch.where(sep, mid, lo)
                    hi = torch.where(sep | (lo >= hi), hi, mid - 1)
                # one window short of the longest (past a convex bend the classes stay separable
                # for a pixel or two), and only where it is longer than the least-squares one
                pick = lo - 1
                m2, w2, good = fit(pick.clamp(min=0))
                good = good & (pick > i0)
                mu_n = mu_.index_copy(0, sub, torch.where(good[:, None], m2, mu_s))
                v_n = v_.index_copy(0, sub, torch.where(good[:, None], w2, v_s))
                new.append((mu_n, v_n))
            (mu1, v1), (mu2, v2) = new
        return mu1, v1, mu2, v2

    mu1, v1, r1, L1 = longest(back, room(back), -1.0)   # before the corner (travelled toward it)
    mu2, v2, r2, L2 = longest(fwd, room(fwd), 1.0)      # after it
    den = v1[:, 0] * v2[:, 1] - v1[:, 1] * v2[:, 0]                             # > 0: a left turn, convex
    dm = mu2 - mu1
    sol = (dm[:, 0] * v2[:, 1] - dm[:, 1] * v2[:, 0]) / torch.where(den.abs() > 1e-9, den, torch.ones_like(den))
    tip = mu1 + sol[:, None] * v1
    cos_turn = (v1 * v2).sum(1)
    half = 0.5 * torch.acos((-cos_turn).clamp(-1.0, 1.0))                      # half the apex angle
    reach_tip = (0.5 / torch.tan(half).clamp_min(1e-3) + 1.0).clamp(min=radius, max=max_radius)
    # a turn of at least asin(min_turn) (any acute apex too), lines not near parallel
    turn_ok = (cos_turn < math.sqrt(1.0 - min_turn ** 2)) & (den.abs() > 0.1)
    lim1, lim2 = [torch.where(L_ > 24, straight_window, straight_long) for L_ in (L1, L2)]
    ok = turn_ok & (r1 < lim1) & (r2 < lim2) & ((tip - p[c]).norm(dim=1) < reach_tip + 0.5)
    # a corner seen only on the long chords needs sides straight beyond them, on a loop of 16
    # chords or more (on a small polygon the long chords reach past a side's ends, and a
    # near-axis side of a few steps tilts its fit)
    ok &= ~from_long | (torch.minimum(L1, L2) >= 2 * long_span)
    # on a small loop (below `min_loop_sure` crossings) both sides straight over `small_side`
    # nodes or more: a small disc's arcs look straight over a few crossings, and its staircase
    # turns by 60 degrees or more
    ok &= (n_loop[c] >= min_loop_sure) | (torch.minimum(L1, L2) >= small_side)
    if not bool(ok.any()):
        return t, None
    back, fwd = [x[ok] for x in back], [x[ok] for x in fwd]
    ok_idx = ok.nonzero().squeeze(1)
    c, tip, den, v1, v2, reach_tip, ok = c[ok], tip[ok], den[ok], v1[ok], v2[ok], reach_tip[ok], ok[ok]
    # only corners with long straight sides on both hands may reach beyond the band
    sure = torch.minimum(L1[ok_idx], L2[ok_idx]) >= stretch_side
    if separate:
        mu1s, v1s, mu2s, v2s = separated(mu1[ok_idx], v1, mu2[ok_idx], v2, L1[ok_idx], L2[ok_idx],
                                         [room(back), room(fwd)], back, fwd)
        den_s = v1s[:, 0] * v2s[:, 1] - v1s[:, 1] * v2s[:, 0]
        dm = mu2s - mu1s
        sol = (dm[:, 0] * v2s[:, 1] - dm[:, 1] * v2s[:, 0]) / torch.where(den_s.abs() > 1e-9, den_s, torch.ones_like(den_s))
        tip_s = mu1s + sol[:, None] * v1s
        # the refit keeps the corner's kind and stays near it
        keep_s = ((den_s > 0) == (den > 0)) & (den_s.abs() > 0.1) & ((tip_s - p[c]).norm(dim=1) < reach_tip + 0.5)
        tip = torch.where(keep_s[:, None], tip_s, tip)
        v1 = torch.where(keep_s[:, None], v1s, v1)
        v2 = torch.where(keep_s[:, None], v2s, v2)
        den = torch.where(keep_s, den_s, den)

    # the zone's nodes, (C, 2 zone + 1)
    nodes = torch.stack([back[j] for j in range(zone, 0, -1)] + [c] + [fwd[j] for j in range(1, zone + 1)], 1)
    C, Z = nodes.shape
    moved = torch.full((C,), -1, dtype=torch.long, device=c.device)
    if stretch is not None:
        out_dir = v1 - v2
        out_dir = out_dir / out_dir.norm(dim=1, keepdim=True).clamp_min(1e-12)
        wide = torch.stack([back[j] for j in range(2 * zone, 0, -1)] + [c] + [fwd[j] for j in range(1, 2 * zone + 1)], 1)
        if bool(sure.any()):
            a, d, moved[sure] = stretch(wide[sure], tip[sure], den[sure] > 0, out_dir[sure])
    T = tip[:, None].expand(C, Z, 2)
    convex = (den > 0)[:, None].expand(C, Z)
    n1 = torch.stack([v1[:, 1], -v1[:, 0]], 1)[:, None].expand(C, Z, 2)          # outward (background) normals
    n2 = torch.stack([v2[:, 1], -v2[:, 0]], 1)[:, None].expand(C, Z, 2)
    an, dn = a[nodes], d[nodes]
    sgn = torch.where(convex, 1.0, -1.0).to(a.dtype)[..., None]
    x0 = torch.where(convex[..., None], an, an + dn)                 # start inside the convex region
    e = torch.where(convex[..., None], dn, -dn)
    inf = torch.full((C, Z), float("inf"), dtype=a.dtype, device=a.device)
    exits, inside = [], torch.ones((C, Z), dtype=torch.bool, device=a.device)
    for nrm in (n1, n2):
        mm = sgn * nrm                                                # the convex region: mm . (x - T) <= 0
        h0 = (mm * (x0 - T)).sum(-1)
        me = (mm * e).sum(-1)
        inside &= h0 <= 1e-9
        exits.append(torch.where(me > 1e-12, -h0 / torch.where(me > 1e-12, me, torch.ones_like(me)), inf))
    s = torch.minimum(exits[0], exits[1])
    tn = torch.where(convex, s, 1 - s)
    near = (p[nodes] - T).norm(dim=-1) < reach_tip[:, None]
    use = ok[:, None] & inside & (s <= 1) & near
    out = t.clone()
    out[nodes[use]] = tn[use].clamp(0.02, 0.98)
    return out, (c[ok], tip[ok], den[ok] > 0, moved[ok])



def _separating_lines(fgp: torch.Tensor, bgp: torch.Tensor, valid: torch.Tensor, mu: torch.Tensor, v: torch.Tensor,
                      span: float = 0.3, levels: int = 4, n: int = 17
                      ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A line through the middle of those that separate the foreground pixel centres
    ``fgp (C, K, 2)`` from the background ones ``bgp`` (the points ``valid (C, K)``), or the line
    ``(mu (C, 2), v (C, 2))`` itself where it separates them (background on the right of ``v``).
    A half-plane covers at least half of a pixel exactly when it holds the pixel's centre, so
    the lines a straight side's mask allows are those that separate its pixel centres. The
    slopes ``b`` (about ``v``) of the separating lines form an interval, bracketed on grids of
    ``n`` slopes within ``+-span``, ``levels`` times finer each time; the line takes the middle
    slope and, at it, the offset midway between the classes. Returns ``(mu', v', margin (C,))``:
    the margin (half the gap between the classes across the line) is <= 0 where no line
    separates them."""
    nrm = torch.stack([v[:, 1], -v[:, 0]], 1)
    rel_f, rel_b = fgp - mu[:, None], bgp - mu[:, None]
    uf, wf = (rel_f * v[:, None]).sum(-1), (rel_f * nrm[:, None]).sum(-1)
    ub, wb = (rel_b * v[:, None]).sum(-1), (rel_b * nrm[:, None]).sum(-1)
    inf = torch.tensor(float("inf"), dtype=fgp.dtype, device=fgp.device)
    grid = torch.linspace(-1.0, 1.0, n, dtype=fgp.dtype, device=fgp.device)
    idx = torch.arange(n, device=fgp.device)
    lo_b = torch.full((fgp.shape[0],), -span, dtype=fgp.dtype, device=fgp.device)
    hi_b = -lo_b
    for _ in range(levels):
        b = 0.5 * (lo_b + hi_b)[:, None] + 0.5 * (hi_b - lo_b)[:, None] * grid[None]          # (C, n)
        hi = torch.where(valid[:, None], wf[:, None] - b[..., None] * uf[:, None], -inf).amax(-1)
        lo = torch.where(valid[:, None], wb[:, None] - b[..., None] * ub[:, None], inf).amin(-1)
        feas = lo > hi
        k = (lo - hi).argmax(1)                  # none separates: about the least overlap
        first = torch.where(feas.any(1), torch.where(feas, idx, n).amin(1), k)
        last = torch.where(feas.any(1), torch.where(feas, idx, -1).amax(1), k)
        st = (hi_b - lo_b) / (n - 1)
        lo_b, hi_b = b.gather(1, first[:, None]).squeeze(1) - st, b.gather(1, last[:, None]).squeeze(1) + st
    slope = 0.5 * (lo_b + hi_b)
    hi = torch.where(valid, wf - slope[:, None] * uf, -inf).amax(-1)
    lo = torch.where(valid, wb - slope[:, None] * ub, inf).amin(-1)
    margin = 0.5 * (lo - hi) / torch.sqrt(1 + slope * slope)
    v2 = v + slope[:, None] * nrm
    v2 = v2 / v2.norm(dim=1, keepdim=True)
    mu2 = mu + (0.5 * (lo + hi))[:, None] * nrm
    # the given line kept where it puts every centre on its side
    fits = (torch.where(valid, wf, -inf).amax(-1) < 0) & (torch.where(valid, wb, inf).amin(-1) > 0)
    return torch.where(fits[:, None], mu, mu2), torch.where(fits[:, None], v, v2), margin


def _walk(step: torch.Tensor, n: int) -> torch.Tensor:
    """``step`` composed ``n >= 1`` times (by doubling: about 2 log2(n) gathers instead of n)."""
    out, pw = None, step
    while n:
        if n & 1:
            out = pw if out is None else pw[out]
        n >>= 1
        if n:
            pw = pw[pw]
    return out


def _stretch_band(verts: torch.Tensor, faces: torch.Tensor, pix: torch.Tensor, W2: int, fg: torch.Tensor, fg_v: torch.Tensor,
                  bg_v: torch.Tensor, frame: torch.Tensor, nodes: torch.Tensor, tip: torch.Tensor,
                  convex: torch.Tensor, out_dir: torch.Tensor, margin: float = 0.25,
                  margins: Sequence[float] = (0.25, 0.5, 0.1), partial: bool = True,
                  fractions: Sequence[float] = (1.0, 0.8, 0.6, 0.4, 0.2), min_area: float = 1e-3) -> torch.Tensor:
    """Vertices with the band reaching past each acute tip: of the corner's crossings (``nodes``),
    the vertex of the other class (background for a convex corner, foreground for a notch) nearest
    to ``tip + margin * out_dir`` moves there (clipped to the image ``frame (C, 2)`` = ``(W, H)``),
    so that :func:`_insert_tips` finds the tip inside a triangle of the band and the zero set can
    reach it. The sign of the moved vertex is kept, so the topology is; only a vertex whose every
    crossing belongs to the corner's zone moves (no other curve is touched), one corner per vertex,
    and only as far (``fractions`` of the way) as keeps each of its triangles at least
    ``min_area`` px^2 (positively oriented). Vertex ``(x, y)`` of padded pixel ``(i, j)`` is
    ``(j - 0.5, i - 0.5)`` before the move; ``pix`` keeps naming the pixel after it.

    Returns ``(verts, moved (C,))``: the vertices, and the vertex each corner moved (-1: none)."""
    dev, dt = verts.device, verts.dtype
    C, Z = nodes.shape
    if C == 0:
        return verts, torch.full((0,), -1, dtype=torch.long, device=dev)
    zero = torch.zeros((), dtype=dt, device=dev)

    def clip(x):
        return torch.stack([torch.minimum(torch.maximum(x[..., 0], zero), frame[:, None, 0] if x.dim() == 3 else frame[:, 0]),
                            torch.minimum(torch.maximum(x[..., 1], zero), frame[:, None, 1] if x.dim() == 3 else frame[:, 1])], -1)

    tipc = clip(tip)
    target = clip(tip + margin * out_dir)
    cand = torch.where(convex[:, None], bg_v[nodes], fg_v[nodes])                  # (C, Z)
    zone_v = torch.cat([fg_v[nodes], bg_v[nodes]], 1)                               # (C, 2Z)
    total = torch.bincount(torch.cat([fg_v, bg_v]), minlength=verts.shape[0])
    in_zone = (cand[:, :, None] == zone_v[:, None, :]).sum(-1)
    q = verts[cand]                                                                 # (C, Z, 2)
    dist = (q - target[:, None]).norm(dim=-1)
    outward = ((target[:, None] - q) * out_dir[:, None]).sum(-1) > 0
    elig = (in_zone == total[cand]) & outward & torch.isfinite(dist)
    r = torch.arange(C, device=dev)
    # the (up to) 8 triangles around each candidate: the two of each of the 4 cells that have
    # its pixel as a corner
    cell_key = pix[faces[0::2, 0]]                                                  # ascending TL pixels
    qp = pix[cand]
    fs, oks = [], []
    for off in (-W2 - 1, -W2, -1, 0):
        key = qp + off
        ci = torch.searchsorted(cell_key, key).clamp(max=max(cell_key.shape[0] - 1, 0))
        hit = cell_key[ci] == key
        fs += [2 * ci, 2 * ci + 1]
        oks += [hit, hit]
    f = torch.stack(fs, -1)                                                         # (C, Z, 8)
    fok = torch.stack(oks, -1)
    fv = faces[f]                                                                   # (C, Z, 8, 3)
    P = verts[fv]                                                                   # (C, Z, 8, 3, 2)
    # where a candidate may go: just past the tip (margins), else part of the way there
    fr = torch.tensor(list(fractions), dtype=dt, device=dev)
    beyond = clip(tip[:, None] + torch.tensor(list(margins), dtype=dt, device=dev)[None, :, None] * out_dir[:, None])
    q0 = verts[cand]                                                                # (C, Z, 2)
    part = q0[:, :, None] + fr[None, None, :, None] * (target[:, None] - q0)[:, :, None]
    moved = torch.cat([beyond[:, None].expand(C, Z, -1, 2), part], 2)               # (C, Z, S, 2)
    S = moved.shape[2]
    isq = (fv == cand[..., None, None])[:, :, None, :, :, None]                     # (C, Z, 1, 8, 3, 1)
    P2 = torch.where(isq, moved[:, :, :, None, None, :], P[:, :, None])             # (C, Z, S, 8, 3, 2)
    area = 0.5 * _cross2(P2[..., 1, :] - P2[..., 0, :], P2[..., 2, :] - P2[..., 0, :])
    fok_s = fok[:, :, None]
    flat_ok = ((area >= min_area) | ~fok_s).all(-1) & elig[..., None]                # (C, Z, S)
    # the tip inside one of the moved triangles that holds both classes: it can be inserted whole
    tq = tipc[:, None, None, None]
    lam = torch.stack([_cross2(P2[..., 1, :] - tq, P2[..., 2, :] - tq), _cross2(P2[..., 2, :] - tq, P2[..., 0, :] - tq),
                       _cross2(P2[..., 0, :] - tq, P2[..., 1, :] - tq)], -1)
    nfg = fg[fv].sum(-1)[:, :, None]                                                # (C, Z, 1, 8)
    holds = ((lam.min(-1).values > 1e-6) & (nfg > 0) & (nfg < 3) & fok_s).any(-1)
    whole = flat_ok & holds
    # the nearest candidate that takes the tip whole (its first position); else the nearest
    # movable one, as far as it goes (the tip is then pulled back into the band by _insert_tips)
    cost_w = torch.where(whole, dist[..., None] + 1e-3 * torch.arange(S, device=dev, dtype=dt), torch.full_like(area[..., 0], float("inf")))
    part_ok = flat_ok & (torch.arange(S, device=dev) >= len(margins))
    cost_p = torch.where(part_ok, dist[..., None] + 1e-3 * torch.arange(S, device=dev, dtype=dt), torch.full_like(cost_w, float("inf")))
    use_w = torch.isfinite(cost_w).flatten(1).any(1)
    cost = torch.where(use_w[:, None, None] | (not partial), cost_w, cost_p).flatten(1)   # (C, Z * S)
    pick = cost.argmin(1)
    go = torch.isfinite(cost[r, pick])
    zi, si = pick // S, pick % S
    Q = cand[r, zi]
    # one corner per vertex (the first)
    uq, inv = torch.unique(Q, return_inverse=True)
    firstc = torch.full((uq.shape[0],), C, dtype=torch.long, device=dev).scatter_reduce_(
        0, inv, torch.where(go, r, torch.full_like(r, C)), "amin")
    go &= firstc[inv] == r
    out = verts.clone()
    out[Q[go]] = moved[r, zi, si][go]
    return out, torch.where(go, Q, torch.full_like(Q, -1))


def _cross2(u: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * w[..., 1] - u[..., 1] * w[..., 0]


def _insert_tips(mesh: MeshBatch, values: torch.Tensor, fg: torch.Tensor, pix: torch.Tensor, grid_shape,
                 sizes: torch.Tensor, pts: torch.Tensor, fg_v: torch.Tensor, bg_v: torch.Tensor,
                 edge: torch.Tensor, loop: torch.Tensor, k: torch.Tensor, first: torch.Tensor,
                 counts: torch.Tensor, nxt: torch.Tensor, corners, zone: int = 6, eps: float = 1e-3,
                 fractions: Sequence[float] = (1.0, 0.85, 0.7, 0.55, 0.4, 0.25)):
    """A vertex at the tip of each corner (:func:`_corner_tips`), so the zero set reaches it.

    The band's crossings lie between pixel centres, so the tip of a corner sharper than the
    pixel staircase (it lies beyond the band of centres of its class) cannot be drawn by
    the magnitudes alone. The tip (clipped to the image frame) is located in its grid cell;
    when the triangle holding it has a vertex of the corner's class (the foreground for a
    convex corner, the background for a notch) and is crossed by the corner's own loop within
    ``zone`` nodes, the tip is inserted there (the triangle split in three) with that class's
    sign and a magnitude ``eps`` times its triangle's smallest, so the curve runs through it
    to within ``eps`` of an edge; the new region is joined to the class through the triangle,
    so no border is added or merged. A tip that does not qualify is pulled back toward the
    corner's crossing (``fractions`` of the way) until it does, or dropped. The loop gains one
    or two crossings there, which inherit the pixel pair of the crossing before them.

    Returns ``(mesh, values, (points, fg_v, bg_v, edge, first, counts))``: the mesh with the
    tip vertices (items re-packed), its values, and the spliced loops (``fg_v``, ``bg_v`` and
    ``edge`` index the band mesh before the insertion).
    """
    node, tip, convex, moved = corners
    dev, dt = values.device, values.dtype
    B, H2, W2 = grid_shape
    V, N = values.shape[0], pts.shape[0]
    verts, faces = mesh.verts, mesh.faces
    item = mesh.vert_item[fg_v[node]]                               # ascending (nodes are)
    zero = torch.zeros((), dtype=dt, device=dev)
    tip = torch.stack([torch.minimum(torch.maximum(tip[:, 0], zero), sizes[item, 1].to(dt)),
                       torch.minimum(torch.maximum(tip[:, 1], zero), sizes[item, 0].to(dt))], 1)
    p0 = pts[node]
    fr = torch.tensor(list(fractions), dtype=dt, device=dev)
    q = p0[:, None] + fr[None, :, None] * (tip - p0)[:, None]                      # (C, S, 2)
    # the grid cells around each candidate (TL pixel (i, j) of the padded grid; a point on a
    # cell's side belongs to both) and their two faces each: (C, S, 8) faces
    cell_key = pix[faces[0::2, 0]]                                # ascending: the cells' TL pixels
    fs, oks = [], []
    for dx in (-1e-7, 1e-7):
        for dy in (-1e-7, 1e-7):
            j = torch.floor(q[..., 0] + 0.5 + dx).long()
            i = torch.floor(q[..., 1] + 0.5 + dy).long()
            inside = (i >= 0) & (i < H2 - 1) & (j >= 0) & (j < W2 - 1)
            key = (item[:, None] * H2 + i.clamp(0, H2 - 2)) * W2 + j.clamp(0, W2 - 2)
            ci = torch.searchsorted(cell_key, key).clamp(max=max(cell_key.shape[0] - 1, 0))
            hit = inside & (cell_key[ci] == key)
            fs += [2 * ci, 2 * ci + 1]
            oks += [hit, hit]
    # a band vertex moved out to the tip (_stretch_band) takes its triangles beyond their cells:
    # the (up to) 8 around it are candidates too
    S = q.shape[1]
    mp = pix[moved.clamp(min=0)]
    for off in (-W2 - 1, -W2, -1, 0):
        key = mp + off
        ci = torch.searchsorted(cell_key, key).clamp(max=max(cell_key.shape[0] - 1, 0))
        hit = ((moved >= 0) & (cell_key[ci] == key))[:, None].expand(-1, S)
        fs += [(2 * ci)[:, None].expand(-1, S), (2 * ci + 1)[:, None].expand(-1, S)]
        oks += [hit, hit]
    f = torch.stack(fs, -1)
    # index_select of the flattened indices: x[idx]'s gather, 3-5x faster on CPU
    fv = faces.index_select(0, f.reshape(-1)).view(*f.shape, 3)     # (C, S, 8, 3)
    P = verts.index_select(0, fv.reshape(-1)).view(*fv.shape, 2)     # (C, S, 8, 3, 2)
    qq = q[..., None, :]
    den = _cross2(P[..., 1, :] - P[..., 0, :], P[..., 2, :] - P[..., 0, :])
    lam = torch.stack([_cross2(P[..., 1, :] - qq, P[..., 2, :] - qq), _cross2(P[..., 2, :] - qq, P[..., 0, :] - qq),
                       _cross2(P[..., 0, :] - qq, P[..., 1, :] - qq)], -1) / den[..., None]
    valid = torch.stack(oks, -1) & (lam.min(-1).values > -1e-9)
    kin = fg[fv] == convex[:, None, None, None]                      # of the corner's class
    nk = kin.sum(-1)
    valid &= (nk >= 1) & (nk <= 2)
    node_of_edge = torch.full((mesh.edges.shape[0],), -1, dtype=torch.long, device=dev)
    node_of_edge[edge] = torch.arange(N, device=dev)
    nn = node_of_edge.index_select(0, mesh.face_edges.index_select(0, f.reshape(-1)).view(-1)
                                   ).view(*f.shape, 3)               # (C, S, 8, 3), -1: not crossed
    lc = loop[node]
    cnt = counts[lc][:, None, None, None]
    dk = (k[nn.clamp(min=0)] - k[node][:, None, None, None]) % cnt
    own = (loop[nn.clamp(min=0)] == lc[:, None, None, None]) & (torch.minimum(dk, cnt - dk) <= zone)
    valid &= ((nn < 0) | own).all(-1) & ((nn >= 0).sum(-1) == 2)
    # the best-placed valid face of each candidate, then the first (farthest) valid candidate
    score = torch.where(valid, lam.min(-1).values, torch.full_like(den, -1.0))
    best = score.argmax(-1, keepdim=True)                            # (C, S, 1)
    valid = valid.gather(-1, best).squeeze(-1)
    f = f.gather(-1, best).squeeze(-1)
    lam = lam.gather(-2, best[..., None].expand(*best.shape, 3)).squeeze(-2)
    P = P.gather(-3, best[..., None, None].expand(*best.shape, 3, 2)).squeeze(-3)
    nn = nn.gather(-2, best[..., None].expand(*best.shape, 3)).squeeze(-2)
    has = valid.any(1)
    if not bool(has.any()):
        return None
    s_idx = torch.argmax(valid.to(torch.int8), 1)                  # the first (farthest) valid fraction
    r = torch.arange(node.shape[0], device=dev)
    sel = has.nonzero().squeeze(1)
    f, lam, P, nn, conv, itm = f[r, s_idx][sel], lam[r, s_idx][sel], P[r, s_idx][sel], nn[r, s_idx][sel], \
        convex[sel], item[sel]
    # one tip per triangle
    uf, inv = torch.unique(f, return_inverse=True)
    firstc = torch.full((uf.shape[0],), sel.shape[0], dtype=torch.long, device=dev).scatter_reduce_(
        0, inv, torch.arange(sel.shape[0], device=dev), "amin")
    keep = firstc[inv] == torch.arange(sel.shape[0], device=dev)
    f, lam, P, nn, conv, itm = f[keep], lam[keep], P[keep], nn[keep], conv[keep], itm[keep]
    M = f.shape[0]
    lam = lam.clamp_min(1e-3)
    lam = lam / lam.sum(1, keepdim=True)
    T = (lam[..., None] * P).sum(1)                                  # strictly inside its triangle
    fv = faces[f]
    fT = torch.where(conv, -eps, eps).to(dt) * values[fv].abs().min(1).values
    # the loop enters the triangle at one crossed edge and leaves at the other
    e2 = nn.sort(1, descending=True).values[:, :2]
    ent = torch.where(nxt[e2[:, 0]] == e2[:, 1], e2[:, 0], e2[:, 1])
    ext = torch.where(ent == e2[:, 0], e2[:, 1], e2[:, 0])
    other = lambda n: torch.where(conv, bg_v[n], fg_v[n])          # the end of the other class
    v_in, v_out = other(ent), other(ext)
    two = v_in != v_out

    def crossing(v):
        return T + (fT / (fT - values[v]))[:, None] * (verts[v] - T)

    # ---- splice the new crossings after the entry node
    ins = torch.zeros(N, dtype=torch.long, device=dev)
    ins[ent] = 1 + two.long()
    pos = torch.arange(N, device=dev) + torch.cumsum(ins, 0) - ins
    N2 = N + int(ins.sum())
    p1, p2 = pos[ent] + 1, pos[ent[two]] + 2

    def splice(old, new1, new2):
        out = old.new_empty((N2,) + tuple(old.shape[1:]))
        out[pos] = old
        out[p1] = new1
        out[p2] = new2
        return out

    pts2 = splice(pts, crossing(v_in), crossing(v_out)[two])
    fg2 = splice(fg_v, fg_v[ent], fg_v[ext[two]])
    bg2 = splice(bg_v, bg_v[ent], bg_v[ext[two]])
    ed2 = splice(edge, edge[ent], edge[ext[two]])
    counts2 = counts + torch.zeros_like(counts).index_add_(0, loop, ins)
    first2 = pos[first]
    # ---- the mesh: the tips appended to their items (in item order already), each triangle
    # split in three: (A, B, tip) in its place, (B, C, tip) and (C, A, tip) after its item's faces
    add = torch.bincount(itm, minlength=B)
    before = torch.cumsum(add, 0) - add                              # tips of the items before
    vshift = torch.repeat_interleave(before, mesh.verts_per_item, output_size=V)
    fshift = torch.repeat_interleave(2 * before, mesh.faces_per_item, output_size=faces.shape[0])
    ar_m = torch.arange(M, device=dev)
    tid = (mesh.verts_first_idx + mesh.verts_per_item)[itm] + ar_m                # new ids of the tips
    fend = (mesh.faces_first_idx + mesh.faces_per_item)[itm] + 2 * ar_m
    Vn, Tn = V + M, faces.shape[0] + 2 * M
    new_v = torch.arange(V, device=dev) + vshift
    Fo = new_v[faces]
    A, Bv, C = Fo[f, 0], Fo[f, 1], Fo[f, 2]
    Fo[f] = torch.stack([A, Bv, tid], 1)
    F2 = faces.new_empty((Tn, 3))
    F2[torch.arange(faces.shape[0], device=dev) + fshift] = Fo
    F2[fend] = torch.stack([Bv, C, tid], 1)
    F2[fend + 1] = torch.stack([C, A, tid], 1)
    V2 = verts.new_empty((Vn, 2))
    V2[new_v] = verts
    V2[tid] = T
    values2 = values.new_empty((Vn,))
    values2[new_v] = values
    values2[tid] = fT
    mesh2 = MeshBatch(V2, F2, mesh.verts_per_item + add, mesh.faces_per_item + 2 * add)
    return mesh2, values2, (pts2, fg2, bg2, ed2, first2, counts2), (T, itm)


def _realize(t: torch.Tensor, fg_v: torch.Tensor, bg_v: torch.Tensor, loop: torch.Tensor, k: torch.Tensor,
             first: torch.Tensor, counts: torch.Tensor, nxt: torch.Tensor, V: int, sweeps: int = 8) -> torch.Tensor:
    """Log-magnitudes ``s (V,)`` so that the crossing of node ``n`` (edge from the foreground
    vertex ``fg_v[n]`` to the background one ``bg_v[n]``) falls at ``t[n]``:
    ``s[fg] - s[bg] = log(t / (1 - t))``, solved along each loop (see the module docstring)."""
    dev, dt = t.device, t.dtype
    rho = torch.log(t / (1 - t))
    N = t.shape[0]
    share_fg = fg_v.index_select(0, nxt) == fg_v
    inc = torch.where(share_fg, torch.zeros_like(rho), rho[nxt] - rho)    # U[next] - U[this]
    K = first.shape[0]
    total = torch.zeros(K, dtype=dt, device=dev).index_add_(0, loop, inc)
    cs = torch.cumsum(inc, 0) - inc                                       # exclusive
    U = cs - cs.index_select(0, first.index_select(0, loop))              # U at node k, from U[0] = 0
    U = U - total[loop] * k.to(dt) / counts[loop].to(dt)                  # spread the closing error
    mean = torch.zeros(K, dtype=dt, device=dev).index_add_(0, loop, U) / counts.to(dt)
    U = U - mean[loop]
    s_sum = torch.zeros(V, dtype=dt, device=dev)
    s_cnt = torch.zeros(V, dtype=dt, device=dev)
    s_sum.index_add_(0, fg_v, U).index_add_(0, bg_v, U - rho)
    ones = torch.ones(N, dtype=dt, device=dev)
    s_cnt.index_add_(0, fg_v, ones).index_add_(0, bg_v, ones)
    s = s_sum / s_cnt.clamp_min(1)
    for _ in range(sweeps):      # Jacobi sweeps on sum (s[fg] - s[bg] - rho)^2: settles shared vertices
        tgt = torch.zeros(V, dtype=dt, device=dev)
        tgt.index_add_(0, fg_v, s.index_select(0, bg_v) + rho).index_add_(0, bg_v, s.index_select(0, fg_v) - rho)
        s = torch.where(s_cnt > 0, 0.5 * s + 0.5 * tgt / s_cnt.clamp_min(1), s)
    return s


def trace_masks(masks: Sequence[torch.Tensor], connectivity: int = 8, smooth: int = 12, reach: float = 0.5,
                dtype: torch.dtype = torch.float64, corners: bool = True, stretch_tips: bool = True) -> GridCurves:
    """The curves of a batch of bool masks ``[(H_b, W_b)]``, in one pass (module docstring).

    Args:
        connectivity: 8 (default, OpenCV's) or 4, of the foreground.
        smooth: Taubin lambda|mu iterations along the curves (0: the crack-midpoint polygon).
        reach: how far (pixels) a crossing may move from its edge's midpoint.
        corners: restore sharp corners from their extended sides (:func:`_corner_tips`).

    >>> m = torch.zeros(6, 7, dtype=torch.bool); m[1:5, 1:6] = True; m[2:4, 3] = False
    >>> gc = trace_masks([m])
    >>> len(gc.polylines), gc.outer.tolist(), gc.parent.tolist()
    (2, [True, False], [-1, 0])
    """
    from torch_isc.images.arrays import ImageError, as_masks

    if isinstance(smooth, bool) or not isinstance(smooth, int) or not 0 <= smooth <= 10_000:
        raise ImageError(f"trace_masks: smooth must be an integer in [0, 10000] (iterations), got {smooth!r:.30}")
    if connectivity not in (4, 8) or isinstance(connectivity, bool):
        raise ImageError(f"trace_masks: connectivity must be 8 or 4, got {connectivity!r:.30}")
    if dtype not in (torch.float32, torch.float64):
        raise ImageError(f"trace_masks: dtype must be torch.float32 or torch.float64, got {dtype!r:.30}")
    masks = list(masks) if not (torch.is_tensor(masks) or hasattr(masks, "shape")) else masks
    if len(masks) == 0:
        raise ImageError("trace_masks: no mask")
    if not all(torch.is_tensor(m) and m.dtype == torch.bool and m.dim() == 2 for m in masks):
        masks = as_masks(masks)              # arrays, other dtypes: one line naming the mask when bad
    grid, sizes = _stack(list(masks))
    B, H2, W2 = grid.shape
    mesh, fg, pix = grid_mesh(grid, connectivity, dtype)
    V = mesh.verts.shape[0]
    base_vals = torch.where(fg, -torch.ones(V, dtype=dtype, device=grid.device),
                            torch.ones(V, dtype=dtype, device=grid.device))
    pl = extract_zero_set(mesh, base_vals, with_points=False)      # the crossings are placed below
    dev = grid.device
    N = pl.edge.shape[0]
    ends = mesh.edges.index_select(0, pl.edge)                # (N, 2); index_select: x[idx], faster on CPU
    a_is_fg = fg[ends[:, 0]]
    fg_v = torch.where(a_is_fg, ends[:, 0], ends[:, 1])
    bg_v = torch.where(a_is_fg, ends[:, 1], ends[:, 0])
    a = mesh.verts.index_select(0, fg_v)
    d = mesh.verts.index_select(0, bg_v) - a
    loop, k, prev, nxt = _loop_index(pl.first, pl.counts, N)
    K = pl.first.shape[0]
    # small loops (a few pixels) get fewer iterations: their curvature is all signal. Under
    # about 30 crossings (shapes of 2-4 px) the lambda|mu filter rounds a square's corners
    # inward more than the crack-midpoint polygon does: 2 iterations at 18 crossings, 12 from 38
    nl = pl.counts[loop]
    cap = torch.maximum(nl // 8, (nl - 14) // 2)
    t = _smooth(a, d, prev, nxt, smooth, reach, cap) if smooth > 0 else torch.full((N,), 0.5, dtype=dtype, device=dev)
    tips = None
    verts0 = mesh.verts
    vi = mesh.vert_item
    pi, pj = (pix // W2) % H2, pix % W2
    sz = sizes.to(dev)
    pad = (pi == 0) | (pj == 0) | (pi == sz[vi, 0] + 1) | (pj == sz[vi, 1] + 1)      # padding pixels
    if corners and smooth > 0:
        frame = sz.flip(1).to(dtype)                              # (W, H) of each item

        def stretch(nodes, tip, convex, out_dir):
            nonlocal mesh
            item = mesh.vert_item[fg_v[nodes[:, 0]]]
            # a side along the image border is the frame's, not the shape's: no tip from it
            inner_c = ~(pad[fg_v[nodes]] | pad[bg_v[nodes]]).any(1)
            moved = torch.full((nodes.shape[0],), -1, dtype=torch.long, device=dev)
            if not bool(inner_c.any()):
                return mesh.verts[fg_v], mesh.verts[bg_v] - mesh.verts[fg_v], moved
            nodes, tip, convex, out_dir, item = nodes[inner_c], tip[inner_c], convex[inner_c], out_dir[inner_c], item[inner_c]
            v2, moved[inner_c] = _stretch_band(mesh.verts, mesh.faces, pix, W2, fg, fg_v, bg_v, frame[item], nodes, tip,
                                               convex, out_dir)
            mesh = mesh.with_verts(v2)
            a2 = v2.index_select(0, fg_v)
            return a2, v2.index_select(0, bg_v) - a2, moved

        t, tips = _corner_tips(a, d, t, prev, nxt, pl.counts[loop], stretch=stretch if stretch_tips else None)
    s = _realize(t, fg_v, bg_v, loop, k, pl.first, pl.counts, nxt, V)
    mag = torch.exp(s - s.max().clamp_min(0) if V else s)
    # a crossing toward a padding pixel's centre lies at most half way, on the image frame: the
    # padding vertex's magnitude is raised to that of every foreground vertex across such an edge
    need = torch.where(pad.index_select(0, bg_v), mag.index_select(0, fg_v), mag.new_zeros(()))
    mag = torch.maximum(mag, torch.zeros_like(mag).scatter_reduce_(0, bg_v, need, "amax"))
    values = torch.where(fg, -mag, mag)
    e0, e1 = ends[:, 0].contiguous(), ends[:, 1].contiguous()
    v0, v1 = mesh.verts.index_select(0, e0), mesh.verts.index_select(0, e1)
    f0, f1 = values.index_select(0, e0), values.index_select(0, e1)
    pts = v0 + (f0 / (f0 - f1))[:, None] * (v1 - v0)
    first, counts, edge, out_mesh = pl.first, pl.counts, pl.edge, mesh
    spliced = None if tips is None else _insert_tips(mesh, values, fg, pix, (B, H2, W2), sizes.to(dev), pts, fg_v,
                                                     bg_v, edge, loop, k, first, counts, nxt, tips)
    a = verts0.index_select(0, fg_v)
    if tips is None:
        tip_pts, tip_item = verts0.new_zeros((0, 2)), torch.zeros(0, dtype=torch.long, device=dev)
    else:
        tip_pts, tip_item = tips[1], mesh.vert_item[fg_v[tips[0]]]
    if spliced is not None:
        out_mesh, values, (pts, fg_v, bg_v, edge, first, counts), _ = spliced
        a = verts0.index_select(0, fg_v)
        loop, k, prev, nxt = _loop_index(first, counts, pts.shape[0])
    # an inserted tip on the frame leaves its neighbours within eps of the zero set, a hair outside
    pts = torch.minimum(pts.clamp_min(0), sz.flip(1).to(dtype).index_select(0, pl.item.index_select(0, loop)))
    pl = Polylines(pts, first, counts, pl.closed, pl.item, edge, pl.num_items)

    # ---- outer border or hole: foreground on the left, so outer loops turn positively
    p0 = pl.points
    cross = p0[:, 0] * p0[nxt, 1] - p0[nxt, 0] * p0[:, 1]
    area2 = torch.zeros(K, dtype=dtype, device=dev).index_add_(0, loop, cross)
    outer = area2 > 0
    # ---- the start pixel of OpenCV's scan: the top-left foreground pixel of an outer border,
    # the foreground pixel left of the top-left pixel of a hole
    big = torch.iinfo(torch.long).max
    pf, pb = pix.index_select(0, fg_v), pix.index_select(0, bg_v)
    key_fg = torch.full((K,), big, dtype=torch.long, device=dev).scatter_reduce_(0, loop, pf, "amin")
    key_bg = torch.full((K,), big, dtype=torch.long, device=dev).scatter_reduce_(0, loop, pb, "amin")
    start = torch.where(outer, key_fg, key_bg - 1)
    # the crossing of that pixel's crack with its left (outer) or right (hole) neighbour: OpenCV's
    # chain starts there (the start pixel may appear several times in a chain)
    at = (pf == start[loop]) & (pb == torch.where(outer[loop], pf - 1, pf + 1))
    node_ids = torch.arange(pf.shape[0], device=dev)
    start_node = torch.full((K,), big, dtype=torch.long, device=dev).scatter_reduce_(
        0, loop, torch.where(at, node_ids, torch.full_like(node_ids, big)), "amin")
    start_node = torch.where(start_node == big, first, start_node)
    # ---- the enclosing border: look left along the start row for the nearest horizontal crack
    horiz = (pf // W2) == (pb // W2)
    left = torch.minimum(pf, pb)[horiz]                       # crack between pixel `left` and `left + 1`
    crack_loop = loop[horiz]
    order = torch.argsort(left)
    left, crack_loop = left[order], crack_loop[order]
    # outer start (i, j): background at j-1, own crack at j-1: nearest crack left < j-1
    # hole start (i, j): own crack at j: nearest crack left < j
    limit = torch.where(outer, start - 2, start - 1)
    idx = torch.searchsorted(left, limit, right=True) - 1
    ok = idx >= 0
    idxc = idx.clamp(min=0)
    same_row = ok & (left[idxc] // W2 == start // W2) if left.numel() else ok & False
    near = torch.where(same_row, crack_loop[idxc] if left.numel() else idx, torch.full_like(idx, -1))
    # the nearest loop borders the same region: if it is of the other kind it encloses this
    # one, else it is a sibling and shares its parent; follow siblings (pointer doubling)
    has = near >= 0
    same_kind = has & (outer[near.clamp(min=0)] == outer)
    ar = torch.arange(K, device=dev)
    jump = torch.where(same_kind, near, ar)
    for _ in range(max(1, math.ceil(math.log2(K + 1)) + 1)):
        jump = jump[jump]
    term_near = near[jump]
    parent = torch.where(term_near >= 0, term_near, torch.full_like(term_near, -1))
    # a loop whose chain ends without a different-kind loop on its left has no parent
    parent = torch.where((term_near >= 0) & (outer[term_near.clamp(min=0)] != outer), parent,
                         torch.full_like(parent, -1))
    return GridCurves(out_mesh, values, pl, outer, parent, start, sizes, a, tip_pts, tip_item, start_node)


def cv_layout(outer: np.ndarray, parent: np.ndarray, start: np.ndarray, mode: str = "tree",
              keep: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """OpenCV's list order and hierarchy of one item's loops.

    Args:
        outer, parent, start: the item's loops (:class:`GridCurves` fields, ``parent`` as local
            indices, -1 for none).
        mode: :func:`retr_mode`.

    Returns:
        ``(order, hierarchy)``: the loops kept by the mode in OpenCV's order (a preorder of the
        mode's tree, siblings by decreasing start, i.e. last found first), and the ``(N, 4)``
        int32 ``[next, prev, first_child, parent]`` in that order.
    """
    mode = retr_mode(mode)
    K = outer.shape[0]
    par = parent.astype(np.int64).copy()
    keep = np.ones(K, bool) if keep is None else np.asarray(keep, bool).copy()
    if mode == "list":
        par[:] = -1
    elif mode == "ccomp":
        par = np.where(outer, -1, par)
    elif mode == "external":
        keep &= outer & (parent < 0)
        par[:] = -1
    idx = np.nonzero(keep)[0]
    # children of each loop, by decreasing start
    srt = idx[np.lexsort((-start[idx], par[idx]))]
    order: List[int] = []
    kids: dict = {}
    for c in srt.tolist():
        kids.setdefault(int(par[c]), []).append(c)
    stack = list(reversed(kids.get(-1, [])))
    while stack:
        c = stack.pop()
        order.append(c)
        stack.extend(reversed(kids.get(c, [])))
    order_a = np.array(order, np.int64)
    pos = np.full(K, -1, np.int64)
    pos[order_a] = np.arange(order_a.size)
    n = order_a.size
    h = np.full((n, 4), -1, np.int32)
    if n:
        p_new = np.where(par[order_a] >= 0, pos[np.maximum(par[order_a], 0)], -1)
        h[:, 3] = p_new
        for plist in kids.values():
            q = pos[np.array(plist)]
            h[q[:-1], 0] = q[1:]
            h[q[1:], 1] = q[:-1]
        firsts = [pos[plist[0]] for pp, plist in kids.items() if pp >= 0]
        for f in firsts:
            h[h[f, 3], 2] = f
    return order_a, h
