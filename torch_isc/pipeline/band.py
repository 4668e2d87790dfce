"""The last stage: refine the mesh around the curve, signs fixed, and refit the magnitudes so
the zero set follows the mean of the noisy band.

The loop stops refining once the test passes, which under noise leaves triangles of a few
noise widths whose zero set is a polygon with one straight piece per triangle. This stage
splits the triangles the zero set crosses (and ``band_rings`` rings of neighbours) for
``band_levels`` rounds (the magnitudes refitted before each later round, so a round splits
the fitted curve's triangles, not the loop's), never a triangle whose longest edge is below ``band_min_size`` noise
widths: a triangle narrower than the noise band has too few points on either side of the
curve for its line to average them, and the zero set would start chasing points. Later
rounds split only noisy items' triangles (``band_noisy``) that hold ``band_min_points`` points
or more (where samples are sparse a finer band has nothing to average), and their refits
change only those items' values, so an item's result does not depend on its batch. New
vertices take the piecewise-linear ``f`` (the zero set does not move and the topology is
kept, see :meth:`ImplicitCurve.refine_band`). The magnitudes are then refitted with the
loop's objective (:class:`~torch_isc.pipeline.values.GeometryObjective`: ``Δ1`` plus the
jump of ``∇f`` across interior edges plus the dead-zoned crossing term) with a stronger
smoothness weight, so residuals of points on both sides of the curve cancel rather than bend it.

``band_solver`` picks the refit's solver: ``lbfgs`` (``band_iterations`` L-BFGS iterations in
log-magnitudes scaled by ``band_precondition``, which stop short of the minimum) or ``newton`` (:meth:`RefitProblem.geometry
<torch_isc.pipeline.refit.RefitProblem.geometry>`: the same objective plus tiny ``reg``/scale
terms, solved to convergence by projected damped Newton). Newton's dense per-item Hessians are
bounded: items in groups of about ``_DENSE_BUDGET`` entries, items with more than
``band_dense_max`` vertices near the curve by L-BFGS.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch

from torch_isc.core.curve import crossed_triangles
from torch_isc.core.segments import segment_sum
from torch_isc.core.subdivide import subdivide
from torch_isc.pipeline.evidence import triangle_moments
from torch_isc.pipeline.knobs import check_section, knob
from torch_isc.pipeline.noise import take
from torch_isc.pipeline.refit import RefitProblem
from torch_isc.pipeline.values import GeometryConfig, fit_geometry, vertex_data_distance, vertex_data_distance_near
from torch_isc.pipeline import budget

if TYPE_CHECKING:
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["BandConfig", "band_marks", "wrap_fraction", "spike_vertices", "band_stage", "mls_candidates",
           "mls_distance", "snap_crossings"]


@dataclass
class BandConfig:
    """The band stage (flat keys of configs/default.yaml)."""
    #: rounds of refinement around the curve before the final refit; 0 disables the stage
    band_levels: int = knob(2, ge=0)
    #: rounds after the first refine only items whose estimated noise is above this fraction of
    #: their tolerance: on clean data a finer band only puts vertices into the gaps between
    #: samples, where the curve's side of each is a coin toss the refit then bends round
    band_noisy: float = knob(0.1, ge=0)
    #: ...and split only triangles holding at least this many points: where the samples are
    #: sparse (a sampling gap, a thin stretch of few points) a finer band has nothing for its
    #: new vertices to average, and the refit bends the curve round them
    band_min_points: int = knob(4, ge=0)
    #: spike rounds of the refits between two splits (at most spike_rounds; the final refit runs
    #: spike_rounds): each round is a whole fit, and the final refit flips what is left
    band_between_rounds: int = knob(1, ge=0)
    #: rings of neighbours of the crossed triangles split with them
    band_rings: int = knob(1, ge=0)
    #: a triangle whose longest edge is below this many noise widths is not split
    band_min_size: float = knob(4.0, ge=0)
    #: smoothness weight of the final refit (the loop's is ``smoothness``)
    band_smoothness: float = knob(3.0, ge=0)
    #: the final refit's solver: "newton" (damped Newton on closed-form Hessians, run to
    #: convergence; :class:`~torch_isc.pipeline.refit.RefitProblem`) or "lbfgs" (``band_iterations``
    #: L-BFGS iterations of the loop's objective)
    band_solver: str = knob("lbfgs", choices=("newton", "lbfgs"))
    #: iteration cap of the final refit (Newton iterations; L-BFGS iterations with band_solver=lbfgs)
    band_iterations: int = knob(25, ge=0)
    #: L-BFGS: the refits run in log-magnitudes scaled by the inverse square root of the
    #: Gauss-Newton diagonal at the start plus this share of the item's mean diagonal (the
    #: loop's ``precondition``); 0 runs them in the log-magnitudes themselves. The band's
    #: vertices differ in scale by the triangles around them: unscaled, 40 iterations stopped
    #: far from the minimum (the objective still fell by more than 1e-4 an iteration)
    band_precondition: float = knob(0.3, ge=0)
    #: Newton: an item with more vertices near its curve than this is refitted by L-BFGS (its
    #: dense Hessian would be too large); a batch is solved in groups of about 2**24 entries
    band_dense_max: int = knob(1500, ge=0)
    #: Newton: weight of the mean squared log-magnitude change from the start (each vertex's
    #: distance to the data); it also makes the minimizer unique
    band_reg: float = knob(0.1, ge=0)
    #: rounds of the spike rule (flip simple vertices the curve wraps around, then refit); 0 disables
    spike_rounds: int = knob(2, ge=0)
    #: a vertex is a spike's tip when more than this fraction of the angle around it lies across the curve
    spike_wrap: float = knob(0.7, gt=0.5, le=1)
    #: ...and it lies within this many noise widths of the data
    spike_reach: float = knob(2.0, ge=0)
    #: a spike whose flip would leave this many points of its triangles and their neighbours
    #: farther than the tested tolerance from the curve (and half as far again as before) is
    #: kept (a sharp tip the data run into); 0 disables the check
    spike_keep_points: int = knob(3, ge=0)
    #: the spike rounds after the first also flip outside vertices next to the curve whose flip
    #: brings spike_keep_points points or more back within the tested tolerance and strands none
    #: (a tip the refit pulled back from the data it runs into)
    spike_extend: bool = knob(True)
    #: the spike rounds also flip unsupported tips (pipeline/tips.py: simple vertices at least
    #: half of whose crossings lie farther than the tested tolerance from the data)
    spike_unsupported: bool = knob(True)
    #: place the final crossings on the data's moving-least-squares curve (:func:`snap_crossings`):
    #: the curve is then a continuous function of the data, not of the mesh the loop happened to
    #: make (issue 18: a perturbation far below the tolerance moves it by about as much); meant
    #: with band_levels 3 (the band's chords fine enough); off by default (not yet judged on the
    #: generated evaluations)
    band_snap: bool = knob(False)
    #: the snap's kernel width in noise widths (never below the distance to the 5th nearest point)
    snap_kernel: float = knob(4.0, gt=0)
    #: rounds of flips of simple vertices on the wrong side of that curve before the snap
    snap_rounds: int = knob(8, ge=0)

    def __post_init__(self):
        check_section(self)


def band_marks(ws: "WorkingSet", cfg: BandConfig, max_triangles: Optional[int] = None) -> torch.Tensor:
    """``(T,)`` bool: the triangles the zero set crosses plus ``band_rings`` rings of
    neighbours, longer (longest edge) than ``band_min_size`` times the item's noise, in items
    that have a curve; none in an item whose mesh could then exceed ``max_triangles`` (a split
    at most quadruples the marked triangles and their neighbours, as in the loop)."""
    with torch.no_grad():
        m = ws.mesh
        marked = crossed_triangles(m, ws.values, cfg.band_rings)
        longest = m.kernel.longest_edge(m.verts.detach()[m.faces])
        fi = m.face_item
        marked = marked & (longest > cfg.band_min_size * ws.noise[fi]) & ~ws.flat[fi]
        if max_triangles is not None:
            grow = segment_sum(marked.long() * 9, fi, ws.num_items)
            marked = marked & ((m.faces_per_item + grow) <= max_triangles)[fi]
        return marked


def wrap_fraction(mesh, values: torch.Tensor) -> torch.Tensor:
    """``(V,)`` the fraction of the angle around each vertex that lies on the other side of the
    piecewise-linear zero set, counted per incident triangle: its angle at the vertex times the
    share of its two other corners whose sign differs (1/2 for a triangle the curve cuts
    between them and the vertex on one side only). About 1/2 on a straight curve; near 1 at
    the tip of a spike (the curve runs around the vertex and back)."""
    with torch.no_grad():
        f = mesh.faces
        p = mesh.verts.detach()[f]                                   # (T,3,2)
        a = p.roll(-1, 1) - p
        b = p.roll(1, 1) - p
        cos = (a * b).sum(2) / (a.norm(dim=2) * b.norm(dim=2)).clamp_min(torch.finfo(p.dtype).tiny)
        ang = torch.acos(cos.clamp(-1.0, 1.0))                       # (T,3) angle at each corner
        neg = values.detach()[f] < 0
        other = (neg.roll(-1, 1) != neg).to(p.dtype) + (neg.roll(1, 1) != neg).to(p.dtype)
        V = mesh.verts.shape[0]
        tot = torch.zeros(V, dtype=p.dtype, device=p.device).index_add_(0, f.reshape(-1), ang.reshape(-1))
        op = torch.zeros(V, dtype=p.dtype, device=p.device).index_add_(0, f.reshape(-1), (0.5 * other * ang).reshape(-1))
        return op / tot.clamp_min(torch.finfo(p.dtype).tiny)


def spike_vertices(ws: "WorkingSet", values: torch.Tensor, cfg: BandConfig) -> torch.Tensor:
    """``(V,)`` bool: vertices the zero set wraps around (:func:`wrap_fraction` above
    ``spike_wrap``) that lie within ``spike_reach`` noise widths of the data. The fit keeps
    such a vertex on its side of the curve by making ``|f|`` there tiny, which draws the zero
    set into a spike (or a notch) toward it; the data cannot tell on which side of a curve a
    vertex inside the noise band lies, so its sign is a free choice there."""
    with torch.no_grad():
        near = vertex_data_distance_near(ws.mesh, ws.points, ws.face)
        reach = cfg.spike_reach * ws.noise[ws.mesh.vert_item]
        return (wrap_fraction(ws.mesh, values) > cfg.spike_wrap) & (near <= reach)


def stranded_points(ws: "WorkingSet", values: torch.Tensor, trial: torch.Tensor, slack: torch.Tensor) -> torch.Tensor:
    """``(V,)`` how many points near each vertex (:func:`_ring_votes`) the curve of ``trial``
    leaves farther than ``slack (B,)`` and half as far again as the curve of ``values`` did: what
    a change of signs would cut off (the sliver of a sharp tip the data run into), not what it
    would tidy up."""
    from torch_isc.pipeline.tolerance import point_curve_distance2
    m = ws.mesh
    allow = slack.to(values.dtype)[ws.point_item] ** 2
    before = point_curve_distance2(m, values, ws.points, ws.face)
    after = point_curve_distance2(m, trial, ws.points, ws.face)
    # a point already beyond it counts when the change takes the curve half as far again away
    lost = (ws.face >= 0) & (after > allow) & (after > 2.25 * before)
    return _ring_votes(ws, lost)


def _ring_votes(ws: "WorkingSet", flag: torch.Tensor) -> torch.Tensor:
    """``(V,)`` for each vertex, how many flagged points (``flag (P,)``) have it as a corner of
    their triangle or of one of that triangle's neighbours (each point once): a tip cut back
    leaves the points beyond it a triangle or so past the flipped vertex's star."""
    m = ws.mesh
    f = ws.face.clamp_min(0)
    nb = take(m.face_neighbors, f)                                         # (P,3)
    ring = torch.cat([f[:, None], nb.where(nb >= 0, f[:, None])], 1)      # (P,4)
    corners = take(m.faces, ring).reshape(-1, 12).sort(1).values
    first = torch.ones_like(corners, dtype=torch.bool)
    first[:, 1:] = corners[:, 1:] != corners[:, :-1]                      # each vertex once per point
    out = torch.zeros(m.verts.shape[0], dtype=torch.long, device=flag.device)
    return out.index_add_(0, corners.reshape(-1), (first & flag[:, None]).long().reshape(-1))


def _flip_spikes(ws: "WorkingSet", values: torch.Tensor, cfg: BandConfig,
                 slack: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``(V,)`` values with the simple spike vertices flipped (both signs, each an independent
    set: :meth:`ImplicitCurve.flip_simple`, so every item keeps its topology). With ``slack
    (B,)``, a spike whose flip would strand ``spike_keep_points`` points or more
    (:func:`stranded_points`) is kept: the data run into it."""
    from torch_isc.core.curve import ImplicitCurve
    with torch.no_grad():
        cand = spike_vertices(ws, values, cfg)
        if slack is not None and cfg.spike_keep_points > 0:
            trial = torch.where(cand, -0.5 * values, values)
            cand = cand & (stranded_points(ws, values, trial, slack) < cfg.spike_keep_points)
        c = ImplicitCurve(ws.mesh, values, validate=False)
        c, _ = c.flip_simple(candidates=cand, grow=True, ratio=0.5)
        c, _ = c.flip_simple(candidates=cand, grow=False, ratio=0.5)
        return c.values


def _extend_to_data(ws: "WorkingSet", values: torch.Tensor, cfg: BandConfig, slack: torch.Tensor) -> torch.Tensor:
    """``(V,)`` values with the simple outside vertices next to the curve (corners of its crossed
    triangles and their neighbours) flipped inside, at half their magnitude, whose flip brings
    ``spike_keep_points`` or more points back within ``slack (B,)`` of the curve and strands none
    (counted by :func:`_ring_votes`): a tip the refit pulled back from the data it runs into."""
    from torch_isc.core.curve import ImplicitCurve
    from torch_isc.pipeline.tolerance import point_curve_distance2
    with torch.no_grad():
        m = ws.mesh
        allow = slack.to(values.dtype)[ws.point_item] ** 2
        before = point_curve_distance2(m, values, ws.points, ws.face)
        ok = ws.face >= 0
        off = ok & (before > allow)
        # the corners of the triangles holding points off the curve, outside and next to it
        tri = m.faces[ws.face.clamp_min(0)]
        V = m.verts.shape[0]
        cand = torch.zeros(V, dtype=torch.long, device=values.device).index_add_(
            0, tri.reshape(-1), off.long()[:, None].expand(-1, 3).reshape(-1)) > 0
        mixed = crossed_triangles(m, values, 1).long()[:, None].expand(-1, 3).reshape(-1)
        near = torch.zeros(V, dtype=torch.long, device=values.device).index_add_(0, m.faces.reshape(-1), mixed) > 0
        cand = cand & near & (values > 0)
        # on trial: an independent set of simple ones (:meth:`ImplicitCurve.flip_simple`), so
        # any subset of it can flip and keep the topology
        trial, flip = ImplicitCurve(m, values, validate=False).flip_simple(candidates=cand, grow=True, ratio=0.5)
        trial = trial.values
        after = point_curve_distance2(m, trial, ws.points, ws.face)
        n_back = _ring_votes(ws, ok & (before > allow) & (after <= allow))
        n_lost = _ring_votes(ws, ok & (after > allow) & (before <= allow))
        keep = flip & (n_back >= cfg.spike_keep_points) & (n_lost == 0)
        return torch.where(keep, trial, values)


def _flip_tips(ws: "WorkingSet", values: torch.Tensor, slack: torch.Tensor, neighbours: int = 8) -> torch.Tensor:
    """``(V,)`` values with the unsupported tips (:func:`~torch_isc.pipeline.tips.unsupported_tips`)
    flipped, at half their magnitude (as :func:`_flip_spikes`). ``neighbours``: the count whose
    farthest made the frames' column 2 (``noise_neighbours``)."""
    from torch_isc.pipeline.tips import MIN_REGION, crossing_support, region_sizes, surrounded_vertices, unsupported_tips
    with torch.no_grad():
        m = ws.mesh
        # a sample spacing where the samples are sparser than the tolerance: the frames' column 2
        # is the distance to the farthest of the k nearest points, about k/2 spacings along a curve
        spacing = ws.frames[:, 2].to(values.dtype) / max(neighbours / 2, 1.0)
        reach = torch.maximum(slack.to(values.dtype)[ws.point_item], spacing)
        supported = crossing_support(m, values, ws.points, ws.face, reach)
        signs = torch.where(values < 0, -1.0, 1.0).to(values.dtype)
        pinned = (m.is_boundary_vert | ws.flat[m.vert_item] | surrounded_vertices(m, ws.points, ws.face)
                  | (region_sizes(m, signs) < MIN_REGION))
        flip = unsupported_tips(m, signs, supported, pinned)
        return torch.where(flip, -0.5 * values, values)


#: about the most entries of the dense Hessians one Newton group holds (the sum of its items' squared sizes)
_DENSE_BUDGET = 2 ** 24


def band_stage(ws: "WorkingSet", cfg: BandConfig, geometry: GeometryConfig, slack: torch.Tensor,
               max_triangles: Optional[int] = None, exact_signs: bool = False, neighbours: int = 8) -> "WorkingSet":
    """The working set with its mesh refined around the curve and its magnitudes refitted
    (signs of every old vertex kept; new vertices take the sign of ``f`` where they sit).
    ``slack (B,)``: the crossing term's dead zone (the tolerance each item was tested at);
    ``max_triangles``: no item's mesh grows beyond it; ``exact_signs``: the signs came from an
    inside/outside oracle, so no tip is flipped for lack of data (``spike_unsupported``);
    ``neighbours``: the noise estimate's ``noise_neighbours`` (the tip rule's sample spacing is
    the reach of that many neighbours over half their count)."""
    if cfg.band_levels <= 0 or ws.num_items == 0:
        return ws
    if exact_signs and cfg.spike_unsupported:
        cfg = dataclasses.replace(cfg, spike_unsupported=False)
    gcfg = dataclasses.replace(geometry, smoothness=cfg.band_smoothness, lbfgs_iterations=cfg.band_iterations,
                               precondition=cfg.band_precondition)
    for level in range(cfg.band_levels):
        if level > 0:
            # later levels only for noisy items (the others keep their values, so an item's
            # result does not depend on its batch)
            later = ws.noise > cfg.band_noisy * slack
            keep = later.nonzero().squeeze(1)                # one host read
            if keep.numel() == 0:
                break
            # refit before the next split: split again on the loop's interpolated f, a
            # new vertex next to the data inherits a tiny |f| and the final fit draws a
            # spike toward it (public circle_n2: Hausdorff 1.2% -> 5.7% without this)
            between = dataclasses.replace(cfg, spike_rounds=min(cfg.spike_rounds, cfg.band_between_rounds))
            lv = later[ws.mesh.vert_item]
            if keep.numel() == ws.num_items:
                fit = _refit_any(ws, between, gcfg, slack, neighbours)
            else:
                # only the later items are refitted (an item's fit does not depend on the
                # others: the same bits), packed item by item as their vertices are
                fit = ws.values.masked_scatter(lv, _refit_any(ws.select(keep), between, gcfg, slack[keep], neighbours))
            ws = _with_values(ws, torch.where(lv, fit, ws.values))
        marked = band_marks(ws, cfg, max_triangles)
        if level > 0:
            marked = marked & later[ws.mesh.face_item]
            if cfg.band_min_points > 0:
                count = segment_sum((ws.face >= 0).long(), ws.face.clamp_min(0), ws.mesh.faces.shape[0])
                marked = marked & (count >= cfg.band_min_points)
        if not bool(marked.any()):
            break
        ws = ws.follow(subdivide(ws.mesh, marked))
    ws = _with_values(ws, _refit_any(ws, cfg, gcfg, slack, neighbours))
    # the snap's neighbour search is one large step: past the deadline it is left out (the
    # items then end "max_seconds") rather than overrun it
    if cfg.band_snap and not budget.skip():
        ws = _with_values(ws, snap_crossings(ws, ws.values, cfg))
    return ws


def _refit_any(ws: "WorkingSet", cfg: BandConfig, gcfg: GeometryConfig, slack: torch.Tensor,
               neighbours: int = 8) -> torch.Tensor:
    """``(V,)`` the refitted values by ``band_solver``."""
    if cfg.band_solver == "lbfgs":
        return _refit(ws, cfg, gcfg, slack, "lbfgs", neighbours)
    return _refit_grouped(ws, cfg, gcfg, slack, neighbours)


def _with_values(ws: "WorkingSet", values: torch.Tensor) -> "WorkingSet":
    """The working set with ``values`` (and their signs), flat items keeping what the loop made (no curve)."""
    values = torch.where(ws.flat[ws.mesh.vert_item], ws.values, values)
    return ws.replace(values=values, signs=torch.where(values < 0, -1.0, 1.0).to(values.dtype))


def _refit_grouped(ws: "WorkingSet", cfg: BandConfig, gcfg: GeometryConfig, slack: torch.Tensor,
                   neighbours: int = 8) -> torch.Tensor:
    """:func:`_refit` by Newton with the dense Hessians bounded: consecutive items in groups of
    about ``_DENSE_BUDGET`` entries (by an upper bound of each item's active vertices: those of
    the triangles within 3 rings of the crossed ones; the blocks are ragged, so a group holds
    about the sum of its items' squares), items above ``band_dense_max`` by L-BFGS. One group
    (no selection) in the common case; one host read of the group labels."""
    m = ws.mesh
    with torch.no_grad():
        near = crossed_triangles(m, ws.values, 3)
        vmask = torch.zeros(m.verts.shape[0], dtype=torch.bool, device=m.device)
        vmask[m.faces[near].reshape(-1)] = True
        bound = torch.zeros(ws.num_items, dtype=torch.long, device=m.device).index_add_(0, m.vert_item, vmask.long())
        big = bound > cfg.band_dense_max
        cost = torch.where(big, torch.zeros_like(bound), bound * bound)
        # a group starts where the running sum of the items before crosses a multiple of the budget;
        # -1 labels the L-BFGS items
        group = torch.where(big, torch.full_like(bound, -1), (torch.cumsum(cost, 0) - cost) // _DENSE_BUDGET)
        labels = torch.unique(group).tolist()
    if len(labels) == 1:
        return _refit(ws, cfg, gcfg, slack, "lbfgs" if labels[0] < 0 else "newton", neighbours)
    values = ws.values.clone()
    for g in labels:
        keep = (group == g).nonzero().squeeze(1)
        sel = (group == g)[m.vert_item]
        values[sel] = _refit(ws.select(keep), cfg, gcfg, slack[keep], "lbfgs" if g < 0 else "newton", neighbours)
    return values


def _refit(ws: "WorkingSet", cfg: BandConfig, gcfg: GeometryConfig, slack: torch.Tensor, solver: str,
           neighbours: int = 8) -> torch.Tensor:
    """``(V,)`` the refitted values: ``spike_rounds`` rounds of spike flips, each followed by
    a fit of the magnitudes with the signs fixed."""
    with torch.no_grad():
        # the fit explains the points near the curve it has (crossed triangles and their
        # neighbours): a point farther out is an outlier to this topology, and in a triangle
        # where f is flat (magnitudes at the floor) it would weigh without bound
        m = ws.mesh
        near_t = crossed_triangles(m, ws.values, 1)
        face = torch.where((ws.face >= 0) & near_t[ws.face.clamp_min(0)], ws.face, torch.full_like(ws.face, -1))
        mom = triangle_moments(m, ws.points, face, ws.bary)
        near = vertex_data_distance_near(m, ws.points, ws.face) if gcfg.crossing_weight > 0 else None
    # the fit is normalized by the tested tolerance (never below the noise), not the user's:
    # Δ1 at the noise level then weighs O(1), and the smoothness term can hold its own
    # started, as the loop is, at each vertex's distance to the data: the floor is a fraction
    # of the mean start, and the loop's far magnitudes grew (a floor taken from them flattens f
    # near the curve); a warm start from the loop's values also kept more of its spikes
    values = ws.values
    with torch.no_grad():
        init = vertex_data_distance(m, ws.points, ws.face)
    # the loop's curve already has its spikes: flip first, then fit (each later round flips
    # what the refit left and fits again)
    for r in budget.rounds(max(cfg.spike_rounds, 1)):
        if cfg.spike_rounds > 0:
            values = _flip_spikes(ws, values, cfg, slack)
            if r > 0 and cfg.spike_extend and cfg.spike_keep_points > 0:
                values = _extend_to_data(ws, values, cfg, slack)
            if cfg.spike_unsupported:
                values = _flip_tips(ws, values, slack, neighbours)
        signs = torch.where(values < 0, -1.0, 1.0).to(values.dtype)
        start = init if r == 0 else values.abs()
        if solver == "lbfgs":
            values, _ = fit_geometry(m, mom, signs, start, slack, gcfg, data_dist=near, slack=slack)
        else:
            with torch.no_grad():
                pb = RefitProblem.geometry(m, mom.count, signs, start, slack, gcfg.magnitude_floor, gcfg.smoothness,
                                           gcfg.crossing_weight, near, slack, reg=cfg.band_reg)
                values = pb.values(pb.solve(mom.M, cfg.band_iterations))
        values = values.detach()
    return values


#: data points each query of the moving-least-squares curve weighs (its nearest, found once per edge)
MLS_NEIGHBOURS = 32
#: the kernel is never narrower than the distance to this nearest point (sparse data)
MLS_MIN_POINTS = 5


def mls_candidates(points: torch.Tensor, point_item: torch.Tensor, queries: torch.Tensor,
                   query_item: torch.Tensor, k: int = MLS_NEIGHBOURS) -> torch.Tensor:
    """``(Q, k)`` indices of about the ``k`` nearest data points of each query (same item), by
    :func:`~torch_isc.pipeline.noise.approximate_knn` over the points and queries together (the
    queries' own rows are dropped); ``-1`` where fewer were found."""
    from torch_isc.pipeline.noise import approximate_knn
    P = points.shape[0]
    allp = torch.cat([points.to(queries.dtype), queries])
    item = torch.cat([point_item, query_item])
    window = 4 * k          # queries crowd the band: look wider than k
    nbr, d2 = approximate_knn(allp, item, 4 * window, window)
    nbr, d2 = nbr[P:], d2[P:]
    d2 = torch.where(nbr < P, d2, torch.full_like(d2, float("inf")))
    d2, j = torch.topk(d2, min(k, d2.shape[1]), dim=1, largest=False)
    return torch.where(torch.isfinite(d2), nbr.gather(1, j), torch.full_like(j, -1))


def mls_distance(x: torch.Tensor, cand: torch.Tensor, points: torch.Tensor, width: torch.Tensor,
                 ref: torch.Tensor) -> torch.Tensor:
    """``(Q,)`` the signed distance of ``x (Q, 2)`` to the line fitted to its candidate points
    ``cand (Q, k)`` with Gaussian weights of width ``sqrt(width² + d_5²)`` about ``x`` (``d_5``:
    the distance to its 5th nearest candidate), the normal turned toward ``ref (Q, 2)``. Its zero
    set is the data's moving-least-squares curve: a continuous function of the points and of
    ``x``, whatever mesh asks."""
    dt = torch.float64
    x = x.to(dt)
    c = points.to(dt)[cand.clamp_min(0)]                                 # (Q,k,2)
    ok = cand >= 0
    d2 = ((c - x[:, None]) ** 2).sum(-1)
    d2 = torch.where(ok, d2, torch.full_like(d2, float("inf")))
    dk = torch.kthvalue(d2, min(MLS_MIN_POINTS, d2.shape[1]), dim=1).values
    dk = torch.where(torch.isfinite(dk), dk, torch.zeros_like(dk))
    we = width.to(dt) ** 2 + dk
    wt = torch.where(ok, torch.exp(-d2 / (2 * we[:, None]).clamp_min(torch.finfo(dt).tiny)), torch.zeros_like(d2))
    sw = wt.sum(1).clamp_min(torch.finfo(dt).tiny)
    mu = (wt[..., None] * c).sum(1) / sw[:, None]
    q = c - mu[:, None]
    cov = torch.einsum("qk,qki,qkj->qij", wt, q, q)
    n = torch.linalg.eigh(cov)[1][:, :, 0]                                # smallest eigenvalue's
    n = n * torch.where((n * ref.to(dt)).sum(1) < 0, -1.0, 1.0)[:, None]
    return ((x - mu) * n).sum(1)


def _crossed_edges(mesh, values: torch.Tensor):
    """The edges whose ends differ in sign, each as ``(i, j)`` from its negative end to its positive one."""
    e = mesh.edges
    neg = values[e] < 0
    cross = (neg[:, 0] != neg[:, 1]).nonzero().squeeze(1)
    e = e[cross]
    first = neg[cross, 0]
    return torch.where(first, e[:, 0], e[:, 1]), torch.where(first, e[:, 1], e[:, 0])


def snap_crossings(ws: "WorkingSet", values: torch.Tensor, cfg: BandConfig, bisections: int = 30,
                   cg_iterations: int = 200, reg: float = 1e-3) -> torch.Tensor:
    """``(V,)`` values whose zero set crosses every crossed edge where the data's
    moving-least-squares curve (:func:`mls_distance`, kernel ``snap_kernel`` noise widths) does.

    1. ``snap_rounds`` rounds: a vertex of a crossed edge on the wrong side of that curve (its
       distance has the other sign) flips when it is simple (:meth:`ImplicitCurve.flip_simple`:
       the topology is kept). 2. The crossing parameter ``t_e`` of each crossed edge ``(i, j)``
       is found by bisection on the curve's distance along it (next to the wrong end where the
       curve misses the edge). 3. The log-magnitudes solve ``s_i - s_j = log(t_e / (1 - t_e))``
       in the least-squares sense (linear interpolation crosses at ``t_e``), with a small pull
       ``reg`` toward the refit's (a gauge: the zero set ignores a common scale), by conjugate
       gradients with per-item steps. Signs are kept; vertices on no crossed edge keep their values.
    """
    from torch_isc.core.curve import ImplicitCurve
    m = ws.mesh
    with torch.no_grad():
        verts = m.verts.detach().to(torch.float64)
        vi = m.vert_item
        width = cfg.snap_kernel * ws.noise.to(torch.float64)
        vals = values.detach()

        def edge_data(v):
            i, j = _crossed_edges(m, v)
            mid = 0.5 * (verts[i] + verts[j])
            cand = mls_candidates(ws.points, ws.point_item, mid, vi[i])
            return i, j, cand, verts[j] - verts[i], width[vi[i]]
        for _ in budget.rounds(cfg.snap_rounds):
            i, j, cand, ref, w = edge_data(vals)
            gi = mls_distance(verts[i], cand, ws.points, w, ref)
            gj = mls_distance(verts[j], cand, ws.points, w, ref)
            wrong = torch.zeros(verts.shape[0], dtype=torch.bool, device=verts.device)
            wrong[i[gi >= 0]] = True
            wrong[j[gj <= 0]] = True
            # which of two adjacent candidates flips first goes by their distance to the data's
            # curve (the largest first: flip_simple takes the smallest key), not by the refit's
            # magnitudes, which a tiny perturbation reorders
            far = torch.zeros(verts.shape[0], dtype=torch.float64, device=verts.device)
            far = far.scatter_reduce(0, torch.cat([i, j]), torch.cat([gi, gj]).abs(), "amax")
            proxy = torch.where(vals < 0, -1.0, 1.0).to(torch.float64) / (1.0 + far)
            c = ImplicitCurve(m, proxy, validate=False)
            c, f1 = c.flip_simple(candidates=wrong, grow=True, ratio=0.5)
            c, f2 = c.flip_simple(candidates=wrong, grow=False, ratio=0.5)
            flipped = f1 | f2
            vals = torch.where(flipped, -0.5 * vals, vals)
            if not bool(flipped.any()):
                break
        i, j, cand, ref, w = edge_data(vals)
        gi = mls_distance(verts[i], cand, ws.points, w, ref)
        gj = mls_distance(verts[j], cand, ws.points, w, ref)
        lo = torch.zeros_like(gi)
        hi = torch.ones_like(gi)
        for _ in range(bisections):
            mid = 0.5 * (lo + hi)
            below = mls_distance(verts[i] + mid[:, None] * ref, cand, ws.points, w, ref) < 0
            lo, hi = torch.where(below, mid, lo), torch.where(below, hi, mid)
        t = 0.5 * (lo + hi)
        t = torch.where(gi >= 0, torch.zeros_like(t), torch.where(gj <= 0, torch.ones_like(t), t))
        t = t.clamp(1e-3, 1.0 - 1e-3)
        a = torch.log(t / (1.0 - t))
        # (L + reg I) s = A^T a + reg s0 on every vertex (one on no crossed edge keeps s0), by
        # Jacobi-preconditioned conjugate gradients with per-item step sizes
        V, B = verts.shape[0], ws.num_items
        tiny = torch.finfo(torch.float64).tiny
        s0 = vals.abs().to(torch.float64).clamp_min(tiny).log()
        deg = torch.zeros(V, dtype=torch.float64, device=verts.device)
        deg.index_add_(0, i, torch.ones_like(a)).index_add_(0, j, torch.ones_like(a))
        diag = deg + reg

        def op(x):
            d = x[i] - x[j]
            return reg * x + torch.zeros_like(x).index_add_(0, i, d).index_add_(0, j, -d)
        rhs = reg * s0 + torch.zeros_like(s0).index_add_(0, i, a).index_add_(0, j, -a)
        x = s0.clone()
        r = rhs - op(x)
        z = r / diag
        pdir = z.clone()
        rz = segment_sum(r * z, vi, B)
        for _ in budget.rounds(cg_iterations):
            ap = op(pdir)
            pap = segment_sum(pdir * ap, vi, B)
            alpha = torch.where(pap > 0, rz / pap.clamp_min(tiny), torch.zeros_like(rz))
            x = x + alpha[vi] * pdir
            r = r - alpha[vi] * ap
            z = r / diag
            rz_new = segment_sum(r * z, vi, B)
            beta = torch.where(rz > 0, rz_new / rz.clamp_min(tiny), torch.zeros_like(rz))
            pdir = z + beta[vi] * pdir
            rz = rz_new
        x = torch.where(deg > 0, x, s0)
        out = torch.where(vals < 0, -1.0, 1.0).to(torch.float64) * x.exp()
        return out.to(values.dtype)
