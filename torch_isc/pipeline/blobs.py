"""Small isolated clusters of points (blobs): small closed curves of a few samples.

A satellite of 7-9 noisy points is no curve the line fits can describe (a triangle of three
points says nothing about which side is inside), and the enclosure rule
(:func:`simplify.enclosed_vertices`) needs a mesh vertex inside the ring, well off the data,
which a coarse mesh seldom has and a ring of radius a few noise widths never has. Here the
clusters are found from the points alone, independent of the mesh:

* :func:`find_blobs`: the connected components of the symmetric graph of each point's
  ``k`` nearest neighbours. A curve sampled densely enough is one component (every point's
  nearest neighbours are on both sides of it); a cluster whose points' nearest neighbours are
  all inside it is a component of its own. A component of ``min_points`` to ``max_points``
  points is a blob: a small closed curve of its own (an isolated outlier joins the curve its
  neighbours lie on, so scattered outliers make no blob). With the data's tangents, a blob must
  lie off the side of the curve next to it, not on its continuation (the open end of a noisy
  band cut off by a gap is round and one-sided too).
* :func:`snap_blobs`: before each level, one corner of the triangle that holds a blob's
  centroid moves onto the centroid (the corner whose star keeps the best quality, never below a
  floor), so a vertex sits inside every blob.
* :func:`blob_stage`: after the sign rules, the vertex at the centroid of a blob that no curve
  explains (none of its points lies in a triangle the signs cross, and the vertex's star is not
  crossed) takes the other sign: the fit then closes a loop around it through the blob's points.

Everything is a few tensor ops over the packed batch; the labels are per point (the working
set carries them like the points).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Tuple

import torch

from torch_isc.core.locate import locate_grid, locate_walk
from torch_isc.core.segments import sym2_eigvals, sym2_eigvec
from torch_isc.pipeline.noise import take

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["find_blobs", "blob_centroids", "snap_blobs", "blob_vertices", "blob_stage"]

#: the smallest star quality a snap may leave (the relaxation's floor is 0.15; a snap is one
#: vertex per blob, and a sliver there costs less than a missed component)
SNAP_MIN_QUALITY = 0.05
#: a blob's nearest other point is at least this many of its mean radii away
GAP_RADII = 1.5
#: a blob's smaller principal variance is at least this fraction of its larger
ROUNDNESS = 0.2
#: the mean direction to a blob's nearest outside points is at least this long (one-sided)
ONE_SIDED = 0.5
#: noise widths the noise of one side takes off the gap between two noisy bands
GAP_NOISE = 2.0
#: under noise, a blob's radius less the noise's part is at least this many noise widths
MIN_RADIUS = 2.0
#: a neighbour beyond the nearest joins when the point is among its MUTUAL·k nearest
MUTUAL = 2
#: hops of neighbour descent on the Morton neighbours (denoise.refine_knn)
REFINE_HOPS = 4
#: the Morton-order window of the neighbour search (each side, two orders)
WINDOW = 16
#: the mean |cos| between the tangent at each blob point's nearest outside point and the direction
#: from there to the point is below this (the blob lies off the curve's side, not on its
#: continuation past a gap); cos 41 degrees
CONTINUES = 0.75
#: steps of descent toward the true nearest outside point (the neighbour lists are approximate)
NEAREST_DESCENT = 4


def find_blobs(points: torch.Tensor, point_item: torch.Tensor, k: int, min_points: int,
               max_points: int, noise: Optional[torch.Tensor] = None, gap_noise_widths: float = 3.0,
               tangents: Optional[torch.Tensor] = None, knn=None) -> torch.Tensor:
    """``(P,)`` long: each point's blob label (the smallest point index of its blob), −1 for a
    point in no blob. A blob is a connected component of ``min_points`` to ``max_points``
    points of the graph joining every point to its ``k`` nearest neighbours (of its item) that
    is round and isolated: its smaller principal variance is at least :data:`ROUNDNESS` of its
    larger (a piece of a sparse curve between two gaps is elongated) and no other point of its
    item is nearer to it than :data:`GAP_RADII` of its mean radii (the mean distance of its points
    to their centroid), and the other points nearest it lie on one side of it (the mean of the
    unit directions from its centroid to its points' nearest outside points is at least
    :data:`ONE_SIDED` long: a piece of a curve has the curve's rest on both sides). With ``noise (B,)`` the graph also joins every two points of an item less
    than ``gap_noise_widths`` noise widths apart (a noisy curve's k-nearest-neighbour graph
    falls apart into small groups along its band), so a blob is that far from the rest too.

    Beyond its nearest, a point's neighbour joins only when the point is among that neighbour's
    2k nearest too (a satellite beside a curve is not tied to it by its third neighbour). Under
    noise the radius is taken less the noise's part (``sqrt(rms² − 2σ²)``), the gap may be
    ``2 GAP_NOISE σ`` short of ``GAP_RADII`` radii (the noise of its two sides), and a ring whose
    radius less the noise is under ``MIN_RADIUS σ`` is none (a clump of a noisy band).

    With ``tangents (P, 2)`` (the data's unit tangent at each point), a blob also lies off the
    side of the curve next to it, not on its continuation: the nearest point of a smooth curve to
    a separate small curve sees it along its normal, while the end of an open stroke (a noisy
    band's last few points cut off by a gap) sees the rest along its tangent. The mean of
    ``|t·u|`` over the blob's points (``t`` the tangent at a point's nearest outside point ``o``,
    ``u`` the unit direction from ``o`` to the point) must be below :data:`CONTINUES` for ``t``
    either of two estimates: ``tangents[o]`` or the major axis of the covariance of ``o``'s
    neighbours (among the ``max(k, max_points + 8)`` nearest) outside the blob.

    ``knn``: ``(nbr (P, K), d2 (P, K))`` approximate nearest neighbours already found (the
    denoising's, :func:`~torch_isc.pipeline.denoise.denoise_knn`), used where ``K`` is at least
    ``max(k, max_points + 8)``; otherwise the search runs here."""
    with torch.no_grad():
        from torch_isc.pipeline.denoise import refine_knn
        from torch_isc.pipeline.noise import approximate_knn
        P = points.shape[0]
        dev, dt = points.device, points.dtype
        none = torch.full((P,), -1, dtype=torch.long, device=dev)
        if P == 0 or min_points <= 0 or k <= 0:
            return none
        kk = max(k, max_points + 8)
        x = points.detach()
        if knn is not None and knn[0].shape[1] >= kk:
            nbr, d2 = knn[0][:, :kk], knn[1][:, :kk]
        else:
            nbr, d2 = approximate_knn(x, point_item, kk, max(WINDOW, (kk + 1) // 2))
            # Morton candidates stop at quadtree cell walls: a few points of a dense noisy curve
            # beside such a wall lose their neighbours across it and fall off as a "blob"
            nbr, d2 = refine_knn(x, nbr, d2, REFINE_HOPS)
        fin = torch.isfinite(d2)
        src = torch.arange(P, device=dev)[:, None].expand_as(nbr)
        join = fin.clone()
        join[:, k:] = False
        # beyond the nearest, a neighbour joins only when the point is among that neighbour's
        # 2k nearest too: the third nearest neighbour of a satellite's point on the side facing
        # another curve can be on that curve (second neighbours on a ring of 8 points are 1.4
        # radii apart), while that curve's points have their 2k nearest along it. The nearest
        # always joins (an outlier joins the curve it lies by)
        k2 = min(MUTUAL * k, nbr.shape[1]) if MUTUAL > 0 else nbr.shape[1]
        mine = torch.arange(P, device=dev)[:, None, None]
        nk = nbr[:, :k]
        back = ((take(nbr, nk)[:, :, :k2] == mine) & take(fin, nk)[:, :, :k2]).any(2)
        back[:, 0] = True
        join[:, :k] &= back
        if noise is not None:
            # and to every point within a few noise widths: a noisy band's k-nearest-neighbour
            # graph falls apart into small groups along it, whose gaps are about the noise
            join |= fin & (d2 <= (gap_noise_widths * noise.to(dt)[point_item, None]) ** 2)
        # only the joining edges go to the label propagation (a quarter of the candidates or
        # less); one host read, once per solve
        edges = torch.stack([src[join], nbr[join]], 1)
        # a point of a component too large to be a blob is its own label (never a candidate)
        small = small_components(P, edges, max_points)
        lab = torch.where(small >= 0, small, torch.arange(P, device=dev))
        size = take(torch.zeros(P, dtype=torch.long, device=dev).index_add_(0, lab, torch.ones_like(lab)), lab)
        cand = (small >= 0) & (size >= min_points) & (size <= max_points)
        # the rest concerns the candidates' points alone (their components are whole): every
        # per-component sum below takes the same entries in the same order as over all points
        # with zero weights elsewhere, so the same bits. One host read
        ci = cand.nonzero().squeeze(1)
        if ci.numel() == 0:
            return none
        xc, nc, d2c, fc, lc = take(x, ci), take(nbr, ci), take(d2, ci), take(fin, ci), take(lab, ci)
        # the gap: the nearest point of another component, over the component
        out = fc & (take(lab, nc) != lc[:, None])
        dout = torch.where(out, d2c, torch.full_like(d2c, float("inf"))).amin(1).sqrt()
        gap = torch.full((P,), float("inf"), dtype=dt, device=dev).scatter_reduce(0, lc, dout, "amin")
        cnt = torch.zeros(P, dtype=dt, device=dev).index_add_(0, lc, torch.ones_like(dout)).clamp_min(1)
        cen = torch.zeros(P, 2, dtype=dt, device=dev).index_add_(0, lc, xc) / cnt[:, None]
        d = xc - take(cen, lc)
        rad = torch.zeros(P, dtype=dt, device=dev).index_add_(0, lc, d.norm(dim=1)) / cnt
        # round: the smaller principal variance at least ROUNDNESS of the larger (a ring, or a
        # blob at high noise; a piece of a sparse curve between two gaps is elongated)
        cov = torch.zeros(P, 3, dtype=dt, device=dev).index_add_(
            0, lc, torch.stack([d[:, 0] ** 2, d[:, 0] * d[:, 1], d[:, 1] ** 2], 1)) / cnt[:, None]
        lo, hi = sym2_eigvals(cov[:, 0], cov[:, 1], cov[:, 2])
        round_ = lo >= ROUNDNESS * hi
        if noise is not None:
            # the radius the noise leaves: a ring of radius r under noise σ (per coordinate) has
            # mean squared distance r² + 2σ² to its centre, so a small satellite's measured radius
            # is mostly noise and the gap it needs is inflated with it (σ of a component: its
            # label is one of its points)
            sg = noise.to(dt)[point_item]
            rms2 = torch.zeros(P, dtype=dt, device=dev).index_add_(0, lc, (d * d).sum(1)) / cnt
            # and the gap between two noisy bands is their nearest pair: the noise of each side
            # takes up to about GAP_NOISE noise widths off it
            r_eff = torch.minimum(rad, (rms2 - 2 * sg ** 2).clamp_min(0).sqrt())
            sgc = take(sg, ci)
            need = torch.maximum(take(GAP_RADII * r_eff, lc) - 2 * GAP_NOISE * sgc, gap_noise_widths * sgc)
            # a ring whose radius the noise leaves is below MIN_RADIUS noise widths cannot be told
            # from a clump of a noisy band cut off by the graph (its loop would fit the noise)
            round_ = round_ & (r_eff >= MIN_RADIUS * sg)
        else:
            need = take(GAP_RADII * rad, lc)
        # one-sided: a piece of a curve has the rest of the curve on both sides of it, a small
        # closed curve beside another has its neighbour on one side. The mean of the unit
        # directions from the centroid to each point's nearest outside point: near 1 when they
        # are all on one side, near 0 when they are on opposite sides
        jo = torch.where(out, d2c, torch.full_like(d2c, float("inf"))).argmin(1)
        o = nc.gather(1, jo[:, None]).squeeze(1)
        xo = take(x, o)
        u = xo - take(cen, lc)
        u = u / u.norm(dim=1, keepdim=True).clamp_min(torch.finfo(dt).tiny)
        has = torch.isfinite(dout)
        su = torch.zeros(P, 2, dtype=dt, device=dev).index_add_(0, lc, u * has[:, None].to(dt))
        nh = torch.zeros(P, dtype=dt, device=dev).index_add_(0, lc, has.to(dt))
        side = (nh == 0) | (su.norm(dim=1) >= ONE_SIDED * nh)
        if tangents is not None:
            # off the curve's side, not on its continuation past a gap (the open end of a noisy
            # band is one-sided and round like a satellite). From each point's own nearest
            # outside point o, whose curve sees a point off its side along its normal.
            # o's neighbours outside the point's component: computed once per o, used by the
            # descent and then by the axis estimate below
            no = take(nbr, o)
            wo = take(fin, o) & (take(lab, no) != lc[:, None])
            # the approximate neighbour lists can miss the true nearest outside point (a ring of
            # 8 points 11 spacings off a dense circle gets circle points 12 spacings along): a
            # few steps of descent along o's own neighbours, which lie on o's curve
            for _ in range(NEAREST_DESCENT):
                dn = torch.where(wo, ((take(x, no) - xc[:, None, :]) ** 2).sum(-1), torch.full_like(d2c, float("inf")))
                dmin, j = dn.min(1)
                closer = dmin < ((xo - xc) ** 2).sum(-1)
                o = torch.where(closer, no.gather(1, j[:, None]).squeeze(1), o)
                xo = take(x, o)
                no = take(nbr, o)
                wo = take(fin, o) & (take(lab, no) != lc[:, None])
            up = xc - xo
            up = up / up.norm(dim=1, keepdim=True).clamp_min(torch.finfo(dt).tiny)
            hw = has.to(dt)
            # two estimates of the tangent at o, each wrong in its own way: the data's (the
            # denoising fit's, whose radius may take in the blob's own points beside a noise
            # spike) and the major axis of o's neighbours outside the blob (which a sparse curve
            # spreads over other structure); only both along u mean a continuation
            qn = take(x, no) - xo[:, None, :]
            wn = wo.to(dt)
            cw = wn.sum(1).clamp_min(1)
            qd = qn - ((qn * wn[..., None]).sum(1) / cw[:, None])[:, None, :]
            ca, cb, cd = ((wn * qd[..., 0] ** 2).sum(1) / cw, (wn * qd[..., 0] * qd[..., 1]).sum(1) / cw,
                          (wn * qd[..., 1] ** 2).sum(1) / cw)
            al = None
            for t in (take(tangents.to(dt), o), sym2_eigvec(ca, cb, cd, sym2_eigvals(ca, cb, cd)[1])):
                # no axis (no neighbour outside the blob): no sign of a continuation
                t = torch.nan_to_num(t / t.norm(dim=1, keepdim=True).clamp_min(torch.finfo(dt).tiny), 0.0, 0.0, 0.0)
                a = torch.zeros(P, dtype=dt, device=dev).index_add_(0, lc, (t * up).sum(1).abs() * hw)
                al = a if al is None else torch.minimum(al, a)
            side &= (nh == 0) | (al < CONTINUES * nh)
        blob = (take(gap, lc) >= need) & take(round_, lc) & take(side, lc)
        return none.index_copy(0, ci, torch.where(blob, lc, torch.full_like(lc, -1)))


def small_components(num_verts: int, edges: torch.Tensor, max_size: int) -> torch.Tensor:
    """``(V,)`` long: for each vertex of a component of at most ``max_size`` vertices of the
    graph ``edges (E, 2)``, the smallest vertex of its component; −1 for a vertex of a larger
    one (converged or not). Min-label propagation for ``max_size`` rounds, no host read: after ``r`` rounds a label
    is at most the smallest vertex within ``r`` hops and never below its component's smallest, so
    a component of ``max_size`` vertices or fewer (diameter below ``max_size``) has converged; a
    label group that an edge leaves is part of a larger, unconverged component (a group without
    such an edge is a whole component). A long chain (a dense curve of 1e5 points) needs
    hundreds of rounds to converge, but no more than ``max_size`` to be known as large."""
    with torch.no_grad():
        lab = torch.arange(num_verts, device=edges.device)
        a, b = edges[:, 0], edges[:, 1]
        # (gathers by index_select: the same values as lab[b], several times faster on a CPU)
        for _ in range(max(int(max_size), 1)):
            lab = lab.scatter_reduce(0, a, lab.index_select(0, b), "amin")
            lab = lab.scatter_reduce(0, b, lab.index_select(0, a), "amin")
        la, lb = lab.index_select(0, a), lab.index_select(0, b)
        cut = (la != lb).long()
        leaves = torch.zeros_like(lab).scatter_reduce(0, la, cut, "amax").scatter_reduce(0, lb, cut, "amax")
        size = torch.zeros_like(lab).index_add_(0, lab, torch.ones_like(lab))
        large = (leaves > 0) | (size > max_size)
        return torch.where(large.index_select(0, lab), torch.full_like(lab, -1), lab)


def blob_rows(blob: torch.Tensor) -> Tuple[torch.Tensor, int]:
    """The labels ``blob (P,)`` renumbered ``0..K−1`` in their order (−1 stays) and ``K``. Two
    host reads; a solve makes them once (:func:`start_blobs`), and with the rows and ``K``
    :func:`blob_centroids` reads nothing."""
    m = blob >= 0
    uniq, inv = torch.unique(blob[m], return_inverse=True)
    row = torch.full_like(blob, -1)
    row[m] = inv
    return row, int(uniq.shape[0])


def blob_centroids(points: torch.Tensor, point_item: torch.Tensor, blob: torch.Tensor, count: Optional[int] = None
                   ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The blobs of the labels ``blob (P,)``: centroids ``(K, 2)``, items ``(K,)``, mean radii
    ``(K,)`` (mean distance of the points to the centroid), each point's blob ``(P,)`` (0..K−1,
    −1 for none) and which blobs have points ``(K,)``. With ``count``, the labels are the rows
    ``0..count−1`` already (:func:`blob_rows`; a row whose points are gone is empty) and nothing
    is read on the host; else one host read (the number of blobs)."""
    with torch.no_grad():
        dev, dt = points.device, points.dtype
        if count is None:
            blob, count = blob_rows(blob)
        K = count
        # the points of no blob go to a dummy row K (no boolean-mask indexing); each row sums
        # its own points in the same order either way
        r = torch.where(blob >= 0, blob, K)
        x = points.detach()
        cnt = torch.zeros(K + 1, dtype=dt, device=dev).index_add_(0, r, torch.ones_like(x[:, 0]))
        c = torch.zeros(K + 1, 2, dtype=dt, device=dev).index_add_(0, r, x) / cnt.clamp_min(1)[:, None]
        rad = torch.zeros(K + 1, dtype=dt, device=dev).index_add_(0, r, (x - c[r]).norm(dim=1)) / cnt.clamp_min(1)
        item = torch.zeros(K + 1, dtype=torch.long, device=dev).index_copy_(0, r, point_item)
        return c[:K], item[:K], rad[:K], blob, cnt[:K] > 0


def _explained(mesh, signs: torch.Tensor, face: torch.Tensor, row: torch.Tensor, K: int) -> torch.Tensor:
    """``(K,)`` bool: the blobs (``row (P,)`` each point's, −1 for none) with a point in a
    triangle (``face (P,)``) that the ``signs`` cross: a curve passes there."""
    neg = signs < 0
    fn = neg[mesh.faces]
    face_cut = fn.any(1) & ~fn.all(1)
    inb = (row >= 0) & (face >= 0)
    # the other points go to a dummy row K (no boolean-mask indexing)
    return torch.zeros(K + 1, dtype=torch.long, device=signs.device).scatter_reduce(
        0, torch.where(inb, row, K), (face_cut[face.clamp_min(0)] & inb).long(), "amax")[:K] > 0


def snap_blobs(ws: "WorkingSet") -> "WorkingSet":
    """The working set with one vertex moved onto the centroid of each blob (``ws.blob``), where
    one of the corners of the centroid's triangle can move there keeping every triangle of its
    star above :data:`SNAP_MIN_QUALITY` (of those, the one leaving the best worst quality);
    boundary vertices stay. Once the signs of an item cross somewhere (after level 0), only the
    blobs they leave unexplained (no point in a crossed triangle): a blob on a curve the signs
    follow is a piece of that curve (a noisy band falls apart into round groups now and then),
    and a vertex moved onto it would sit on the data. The points are re-located."""
    if ws.blob is None:
        return ws
    with torch.no_grad():
        mesh = ws.mesh
        c, item, _, row, has = blob_centroids(ws.points, ws.point_item, ws.blob, getattr(ws, "blob_count", None))
        K = c.shape[0]
        if K == 0:
            return ws
        v = mesh.verts.detach()
        V, dev = v.shape[0], v.device
        neg = ws.signs < 0
        e = mesh.edges
        any_cut = torch.zeros(ws.num_items, dtype=torch.bool, device=dev).index_fill_(
            0, mesh.edge_item[neg[e[:, 0]] != neg[e[:, 1]]], True)
        want = (~any_cut[item] | ~_explained(mesh, ws.signs, ws.face, row, K)) & has
        face, _ = locate_grid(mesh, c.to(v.dtype), item)
        ok = (face >= 0) & want
        tri = mesh.faces[face.clamp_min(0)]                                 # (K,3)
        F = mesh.faces
        best_q = torch.full((K,), -float("inf"), dtype=v.dtype, device=dev)
        best_v = torch.full((K,), -1, dtype=torch.long, device=dev)
        for j in range(3):
            cand = tri[:, j]
            # one blob per vertex (two blobs in one triangle: neither moves this corner)
            n = torch.zeros(V, dtype=torch.long, device=dev).index_add_(0, cand, ok.long())
            use = ok & (n[cand] == 1) & ~mesh.is_boundary_vert[cand]
            # the blobs that do not use this corner write a dummy row V (no boolean-mask indexing)
            vt = torch.cat([v, v[:1]]).index_copy_(0, torch.where(use, cand, V), c.to(v.dtype))[:V]
            q = mesh.kernel.quality(vt[F])                                   # (T,)
            # the worst quality of each moved vertex's star
            qs = torch.full((V,), float("inf"), dtype=v.dtype, device=dev)
            qs = qs.scatter_reduce(0, F.reshape(-1), q.repeat_interleave(3), "amin")
            qk = torch.where(use, qs[cand], torch.full_like(best_q, -float("inf")))
            better = use & (qk >= SNAP_MIN_QUALITY) & (qk > best_q)
            best_q = torch.where(better, qk, best_q)
            best_v = torch.where(better, cand, best_v)
        go = best_v >= 0
        if not bool(go.any()):
            return ws
        vn = torch.cat([v, v[:1]]).index_put_((torch.where(go, best_v, V),), c.to(v.dtype))[:V]
        new = mesh.with_verts(vn)
        f, bary = locate_walk(new, ws.points, ws.point_item, ws.face)
        # the other items' points keep their barycentrics bit for bit (an item's result does
        # not depend on its batch)
        B = ws.num_items
        touched = torch.zeros(B + 1, dtype=torch.bool, device=dev).index_fill_(
            0, torch.where(go, item, B), True)[ws.point_item]
        f = torch.where(touched, f, ws.face)
        bary = torch.where(touched[:, None], bary, ws.bary)
        return ws.replace(mesh=new, face=f, bary=bary)


def blob_vertices(mesh, signs: torch.Tensor, points: torch.Tensor, point_item: torch.Tensor,
                  face: torch.Tensor, blob: torch.Tensor, count: Optional[int] = None) -> torch.Tensor:
    """``(V,)`` bool: the vertices that sit inside a blob no curve explains. Such a vertex is
    the corner nearest the blob's centroid of the triangle holding it, at most a quarter of the
    blob's mean radius from it; it is no boundary vertex, its star is not crossed by the signs,
    and no point of the blob lies in a crossed triangle. ``count``: see :func:`blob_centroids`."""
    with torch.no_grad():
        V = signs.shape[0]
        dev = signs.device
        hit = torch.zeros(V, dtype=torch.bool, device=dev)
        c, item, rad, row, has = blob_centroids(points, point_item, blob, count)
        K = c.shape[0]
        if K == 0:
            return hit
        v = mesh.verts.detach()
        neg = signs < 0
        # a blob with a point in a crossed triangle is explained by a curve
        expl = _explained(mesh, signs, face, row, K)
        e = mesh.edges
        cut = neg[e[:, 0]] != neg[e[:, 1]]
        # the ends of uncut edges go to a dummy row V (no boolean-mask indexing)
        crossed = torch.zeros(V + 1, dtype=torch.bool, device=dev)
        crossed = crossed.index_fill_(0, torch.where(cut, e[:, 0], V), True).index_fill_(
            0, torch.where(cut, e[:, 1], V), True)[:V]
        f, _ = locate_grid(mesh, c.to(v.dtype), item)
        tri = mesh.faces[f.clamp_min(0)]                                     # (K,3)
        d = (v[tri] - c.to(v.dtype)[:, None, :]).norm(dim=2)
        dmin, j = d.min(1)
        vc = tri.gather(1, j[:, None]).squeeze(1)
        good = has & (f >= 0) & ~expl & (dmin <= 0.25 * rad.to(v.dtype)) & ~crossed[vc] & ~mesh.is_boundary_vert[vc]
        return torch.cat([hit, hit[:1]]).index_fill_(0, torch.where(good, vc, V), True)[:V]


def blob_stage(ws: "WorkingSet", signs: torch.Tensor) -> torch.Tensor:
    """``signs`` with :func:`blob_vertices` flipped (unchanged when ``ws.blob`` is None)."""
    if ws.blob is None:
        return signs
    hit = blob_vertices(ws.mesh, signs, ws.points, ws.point_item, ws.face, ws.blob, getattr(ws, "blob_count", None))
    return torch.where(hit, -signs, signs)


def start_blobs(points: torch.Tensor, point_item: torch.Tensor, k: int, min_points: int,
                max_points: int, noise: Optional[torch.Tensor] = None,
                tangents: Optional[torch.Tensor] = None, knn=None) -> Optional[Tuple[torch.Tensor, int]]:
    """:func:`find_blobs` as :func:`blob_rows` (each point's blob row and the number of blobs),
    or None when the batch has no blob (then no stage pays for them). The rows are made once per
    solve: the stages read nothing on the host for them (``WorkingSet.blob_count``)."""
    if min_points <= 0:
        return None
    row, K = blob_rows(find_blobs(points, point_item, k, min_points, max_points, noise, tangents=tangents, knn=knn))
    return (row, K) if K > 0 else None
