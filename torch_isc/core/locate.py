"""Point location in a packed mesh batch: containing triangle and barycentric coordinates.

Three routes, one for each situation of the reconstruction loop, all near-linear:

* :func:`locate_grid` — a uniform grid per item over its triangles' bounding boxes
  (initial meshes, and the fallback of the others);
* :func:`locate_children` — after a subdivision, a point of a split triangle is
  looked for among that triangle's children only;
* :func:`locate_walk` — after small vertex moves, a point walks from its old
  triangle across the edge whose barycentric coordinate turned negative.

Every point gets exactly one triangle, also on shared edges and vertices: the one
whose smallest barycentric coordinate is largest, ties to the lowest index
(:func:`locate_children` applies this rule among the parent's children only, so a point
on the parent's outline may get a child where a global search would pick a neighbour's).
A point outside its item's mesh gets ``-1`` (and NaN barycentrics): it is reported, not guessed.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from torch_isc.core.mesh import MeshBatch
from torch_isc.core.segments import expand_in_chunks
from torch_isc.core.simplex import TRIANGLES

__all__ = ["barycentric", "locate_grid", "locate_children", "locate_walk", "inside_tolerance", "finite_rows"]

_MAX_CANDIDATES = 1 << 22


def inside_tolerance(dtype: torch.dtype) -> float:
    """Barycentric slack under which a point still counts as inside a triangle."""
    return 64.0 * torch.finfo(dtype).eps


def barycentric(verts: torch.Tensor, faces: torch.Tensor, face_idx: torch.Tensor,
                points: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates of ``points (P, 2)`` in triangles ``faces[face_idx] (P,)``.

    Returns ``(P, 3)``; differentiable in ``verts`` and ``points``. Rows of an invalid
    ``face_idx`` (< 0) are NaN.

    Example:
        >>> v = torch.tensor([[0., 0.], [1., 0.], [0., 1.]]); f = torch.tensor([[0, 1, 2]])
        >>> barycentric(v, f, torch.tensor([0]), torch.tensor([[0.25, 0.25]]))
        tensor([[0.5000, 0.2500, 0.2500]])
    """
    fc = face_idx.clamp_min(0)
    grad = torch.is_grad_enabled() and (verts.requires_grad or points.requires_grad)
    if not grad and face_idx.shape[0] >= faces.shape[0]:
        # many points per triangle: the per-triangle part once (the same bits)
        out = TRIANGLES.barycentric_from_frames(TRIANGLES.barycentric_frames(verts[faces])[fc], points)
    else:
        out = TRIANGLES.barycentric(verts[faces[fc]], points)
    return _nan_outside(out, face_idx)


def _nan_outside(bary: torch.Tensor, face_idx: torch.Tensor) -> torch.Tensor:
    return torch.where((face_idx >= 0)[:, None], bary, torch.full_like(bary, float("nan")))


def _frames_bary(frames: torch.Tensor, face_idx: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """:func:`barycentric` from :meth:`~torch_isc.core.simplex.Triangles.barycentric_frames`
    of the mesh (no NaN rows: ``face_idx`` must be >= 0)."""
    return TRIANGLES.barycentric_from_frames(frames.index_select(0, face_idx), points)


def _best_candidate(point_of_cand: torch.Tensor, face_of_cand: torch.Tensor, score: torch.Tensor,
                    n_points: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per point: the candidate face with the largest score, ties to the lowest face index."""
    best = torch.full((n_points,), float("-inf"), dtype=score.dtype, device=score.device)
    best = best.scatter_reduce(0, point_of_cand, score, "amax")
    is_best = score == best[point_of_cand]
    big = torch.iinfo(torch.long).max
    face = torch.full((n_points,), big, dtype=torch.long, device=score.device)
    # the other candidates propose ``big`` (no boolean-mask indexing: no host read)
    face = face.scatter_reduce(0, point_of_cand, torch.where(is_best, face_of_cand, big), "amin")
    face[face == big] = -1
    return face, best


def locate_grid(mesh: MeshBatch, points: torch.Tensor, point_item: torch.Tensor,
                cells_per_face: float = 1.0) -> Tuple[torch.Tensor, torch.Tensor]:
    """Locate ``points (P, 2)`` of items ``point_item (P,)`` in ``mesh``.

    Each item gets a uniform grid of about ``cells_per_face · T_b`` cells over its
    vertices' bounding box; triangles are listed in the cells their bounding box
    touches, and each point is tested against the triangles of its cell only.

    Returns:
        face ``(P,)`` long (-1 outside), bary ``(P, 3)``.
    """
    with torch.no_grad():
        dev, dt = points.device, mesh.verts.dtype
        P = points.shape[0]
        v = mesh.verts.detach()
        pts = points.detach().to(dt)
        if P == 0:
            return torch.empty(0, dtype=torch.long, device=dev), torch.empty(0, 3, dtype=dt, device=dev)
        if mesh.faces.shape[0] == 0:                          # no triangle at all (an all-black mask's curve)
            return (torch.full((P,), -1, dtype=torch.long, device=dev),
                    torch.full((P, 3), float("nan"), dtype=dt, device=dev))
        bbox = mesh.item_bbox()                               # (B,4)
        lo = bbox[:, :2]
        ext = (bbox[:, 2:] - bbox[:, :2]).clamp_min(torch.finfo(dt).tiny)
        g = torch.ceil(torch.sqrt(mesh.faces_per_item.to(dt) * cells_per_face)).clamp(1, 2048).long()  # (B,)
        cs = ext / g[:, None].to(dt)                          # (B,2) cell size
        cell_off = torch.cumsum(g * g, 0) - g * g

        tri = v[mesh.faces]                                   # (T,3,2)
        fi = mesh.face_item
        gi = g[fi]
        c0 = torch.floor((tri.min(1).values - lo[fi]) / cs[fi]).long()
        c1 = torch.floor((tri.max(1).values - lo[fi]) / cs[fi]).long()
        c0 = torch.minimum(c0.clamp_min(0), gi[:, None] - 1)
        c1 = torch.minimum(c1.clamp_min(0), gi[:, None] - 1)
        nx = c1[:, 0] - c0[:, 0] + 1
        ny = c1[:, 1] - c0[:, 1] + 1
        cnt = nx * ny
        pf = torch.repeat_interleave(torch.arange(mesh.faces.shape[0], device=dev), cnt)
        r = torch.arange(pf.shape[0], device=dev) - (torch.cumsum(cnt, 0) - cnt)[pf]      # a gather: no host read
        ix = c0[pf, 0] + r % nx[pf]
        iy = c0[pf, 1] + r // nx[pf]
        key = cell_off[fi[pf]] + iy * g[fi[pf]] + ix
        key, order = torch.sort(key, stable=True)
        pf = pf[order]

        pi = point_item
        pc = torch.floor((pts - lo[pi]) / cs[pi]).long()
        pc = torch.minimum(pc.clamp_min(0), g[pi][:, None] - 1)
        pkey = cell_off[pi] + pc[:, 1] * g[pi] + pc[:, 0]
        start = torch.searchsorted(key, pkey, right=False)
        stop = torch.searchsorted(key, pkey, right=True)
        ncand = stop - start

        face = torch.full((P,), -1, dtype=torch.long, device=dev)
        score = torch.full((P,), float("-inf"), dtype=dt, device=dev)
        frames = TRIANGLES.barycentric_frames(tri)
        # chunk over points to bound the candidate list
        for i0, i1, cp, off in expand_in_chunks(ncand, _MAX_CANDIDATES):
            sl = slice(i0, i1)
            cf = pf[start[cp] + off]
            bc = _frames_bary(frames, cf, pts[cp])
            s = bc.min(1).values
            f_, b_ = _best_candidate(cp - i0, cf, s, i1 - i0)
            face[sl], score[sl] = f_, b_
        face = torch.where(score < -inside_tolerance(dt), torch.full_like(face, -1), face)
        return face, _nan_outside(_frames_bary(frames, face.clamp_min(0), pts), face)


def locate_children(mesh: MeshBatch, points: torch.Tensor, parent_face: torch.Tensor,
                    children: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Hand points from a parent triangle to one of its children after subdivision.

    Args:
        mesh: the subdivided mesh.
        points: ``(P, 2)``. parent_face: ``(P,)`` each point's triangle before subdivision.
        children: ``(T_old, 4)`` new triangle indices of each old triangle (ascending,
            -1 padded; an unsplit triangle lists itself once).

    Returns:
        face ``(P,)``, bary ``(P, 3)``.
    """
    with torch.no_grad():
        v = mesh.verts.detach()
        pts = points.detach().to(v.dtype)
        cand = children[parent_face.clamp_min(0)]             # (P,4)
        cand = torch.where((parent_face < 0)[:, None], torch.full_like(cand, -1), cand)
        P = pts.shape[0]
        k = cand.shape[1]
        frames = TRIANGLES.barycentric_frames(v[mesh.faces])
        bc = _frames_bary(frames, cand.clamp_min(0).reshape(-1), pts[:, None, :].expand(P, k, 2).reshape(-1, 2))
        bc = bc.view(P, k, 3)
        s = bc.min(2).values
        s = torch.where(cand >= 0, s, torch.full_like(s, float("-inf")))
        j = torch.argmax(s, 1)                                 # first max: children are ascending
        face = cand.gather(1, j[:, None]).squeeze(1)
        best = s.gather(1, j[:, None]).squeeze(1)
        face = torch.where(best >= -inside_tolerance(v.dtype), face, torch.full_like(face, -1))
        return face, _nan_outside(bc.gather(1, j[:, None, None].expand(P, 1, 3)).squeeze(1), face)


def locate_walk(mesh: MeshBatch, points: torch.Tensor, point_item: torch.Tensor,
                start_face: torch.Tensor, max_steps: int = 16, return_bary: bool = True,
                check_every: int = 2, capacity: Optional[int] = None) -> Tuple[torch.Tensor, Optional[torch.Tensor]]:
    """Re-locate points after the mesh vertices moved a little.

    Each point starts at its old triangle and steps across the edge opposite its most
    negative barycentric coordinate; points that do not settle within ``max_steps``
    (or that started outside) are located on the grid. With ``return_bary=False`` the
    barycentrics are not computed (None is returned in their place).

    Shapes are fixed and the host reads two flags every ``check_every`` steps: the first
    step covers all points; those not strictly inside their old triangle (moved, or near
    an edge) go on in a buffer of ``capacity`` rows (default ``P/4 + 64``; points beyond
    it are located on the grid) whose steps cover the whole buffer.
    """
    with torch.no_grad():
        v = mesh.verts.detach()
        pts = points.detach().to(v.dtype)
        tol = inside_tolerance(v.dtype)
        P = pts.shape[0]
        frames = TRIANGLES.barycentric_frames(v[mesh.faces])     # (T,13): a step is one gather
        nbr = mesh.face_neighbors.reshape(-1)
        face = start_face.clone()
        if max_steps <= 0 or P == 0:
            unresolved = torch.ones_like(face, dtype=torch.bool)
            need_grid = P > 0
        else:
            mn0 = _frames_bary(frames, face.clamp_min(0), pts).min(1).values
            rest = ~((mn0 > tol) & (face >= 0))                    # the others are settled: done
            C = min(P, P // 4 + 64) if capacity is None else max(1, min(P, int(capacity)))
            rank = torch.cumsum(rest, 0) - 1
            fits = rest & (rank < C)
            slot = torch.where(fits, rank, torch.full_like(rank, C))
            ar = torch.arange(P, device=face.device)
            idx = torch.full((C + 1,), P, dtype=torch.long, device=face.device).scatter_(0, slot, ar)[:C]
            live = idx < P
            sub = idx.clamp_max(P - 1)
            bf, bun, need_grid = _walk_buffer(frames, nbr, pts[sub], torch.where(live, face[sub], -1), live,
                                              rest & ~fits, max_steps, check_every, tol)
            back = torch.where(live, idx, P)                       # row P: a dummy for empty slots
            face = torch.cat([face, face[:1]]).scatter_(0, back, bf)[:P]
            unresolved = (rest & ~fits) | torch.zeros(P + 1, dtype=torch.bool, device=face.device).scatter_(
                0, back, bun & live)[:P]
        if need_grid:
            idx = unresolved.nonzero().squeeze(1)
            f2, _ = locate_grid(mesh, pts[idx], point_item[idx])
            face[idx] = f2
        if not return_bary:
            return face, None
        return face, _nan_outside(_frames_bary(frames, face.clamp_min(0), pts), face)


def _walk_buffer(frames: torch.Tensor, nbr: torch.Tensor, pts: torch.Tensor, face: torch.Tensor,
                 live: torch.Tensor, overflow: torch.Tensor, max_steps: int, check_every: int,
                 tol: float) -> Tuple[torch.Tensor, torch.Tensor, bool]:
    """The walk of :func:`locate_walk` over a buffer of points (``live`` rows): every step
    covers the whole buffer, a settled point recomputes the same coordinates and stays.
    Returns the faces, which rows need the grid, and whether any row (or ``overflow``) does."""
    on = face >= 0                                         # not outside (from the start, or walked off)
    nb3 = nbr.view(-1, 3)
    for s in range(max_steps):
        fc = face.clamp_min(0)
        bc = _frames_bary(frames, fc, pts)
        mn, arg = bc.min(1)
        moving = (mn < -tol) & on
        face = torch.where(moving, nb3[fc, arg], face)            # -1 when it walked off the mesh
        on = face >= 0
        if (s + 1) % max(1, check_every) and s + 1 < max_steps:
            continue
        # near a vertex (two small coordinates) several triangles compete: the grid decides
        small = bc <= tol
        one = small.sum(1) == 1
        near = ~moving & on & (mn <= tol)
        unresolved = (~on | moving | (near & ~one)) & live
        go_on, need_grid = torch.stack([moving.any(), unresolved.any() | overflow.any()]).tolist()
        if not go_on:
            break
    # a point that settled on (or within tolerance of) an edge may tie with the triangle across
    # it: the tie rule (largest min-barycentric, lowest index) between the two
    other = nb3[fc, torch.argmax(small.to(torch.int8), 1)]
    tie = near & one & (other >= 0)
    m2 = _frames_bary(frames, other.clamp_min(0), pts).min(1).values
    face = torch.where(tie & ((m2 > mn) | ((m2 == mn) & (other < face))), other, face)
    return face, unresolved, need_grid


def finite_rows(points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(safe, ok)``: ``points (P, 2)`` with each row holding a NaN or an infinity replaced by
    the origin, and ``ok (P,)`` whether the row was finite. Queries compute on ``safe`` and pick
    their answer for the other rows with ``torch.where``: a NaN point's NaN would otherwise
    reach the gradient of every vertex (``0 * NaN`` in the chain rule) even where its output is
    not used."""
    ok = torch.isfinite(points).all(1)
    return torch.where(ok[:, None], points, torch.zeros_like(points)), ok
