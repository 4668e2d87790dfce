"""The reconstruction loop of Fig. 3, on a packed batch of point sets.

::

    InitializeMesh
    for level in 0..max_level:
        EstimateTopology; EstimateGeometry
        if no triangle fails the test: done
        AdaptivelySubdivideMesh; RelaxMesh

Every stage runs on all unfinished items at once; an item that finishes leaves the
working set, so the others do not pay for it, and nothing an item computes depends on
the other items of its batch (per-item annealing streams, per-item L-BFGS and relaxation
steps). Coordinates are normalized per item (bounding box centred, diagonal 1) and all
outputs are mapped back, so results do not depend on translation or scale.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Union

import numpy as np
import torch

from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.core.curve import ImplicitCurve
from torch_isc.pipeline.values import fit_geometry, vertex_data_distance, vertex_data_distance_near
from torch_isc.pipeline.relax import relax_mesh
from torch_isc.pipeline.subdivide import subdivide
from torch_isc.pipeline.tolerance import (curve_coverage_excess, effective_tolerance, estimate_noise, mark_triangles,
                             point_curve_distance2)
from torch_isc.pipeline.signs import (anneal, crossing_reach, edge_weights, line_fits, pooled_moments, remove_small_islands,
                            triangle_moments)
from torch_isc.core.locate import locate_children, locate_grid
from torch_isc.core.mesh import MeshBatch, hexagon_mesh, square_mesh
from torch_isc.pipeline.result import ReconstructionResult

__all__ = ["reconstruct", "reconstruct_batch", "PointSetError"]

PointsLike = Union[torch.Tensor, np.ndarray, Sequence[Sequence[float]]]


class PointSetError(ValueError):
    """A point set that cannot be reconstructed (too few points, NaN, wrong shape...)."""


def _check_points(x: PointsLike, label: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(np.asarray(x, dtype=np.float64))
        except (TypeError, ValueError) as e:
            raise PointSetError(f"{label}: not an array of numbers ({e})") from None
    if x.dim() != 2 or x.shape[1] != 2:
        raise PointSetError(f"{label}: expected points of shape (N, 2), got {tuple(x.shape)}")
    if not (x.dtype.is_floating_point or x.dtype in (torch.int16, torch.int32, torch.int64, torch.uint8, torch.int8)):
        raise PointSetError(f"{label}: expected real coordinates, got dtype {x.dtype}")
    if x.shape[0] == 0:
        raise PointSetError(f"{label}: no points")
    bad = ~torch.isfinite(x.double()).all(1)
    if bad.any():
        raise PointSetError(f"{label}: {int(bad.sum())} point(s) have NaN or Inf coordinates")
    return x


def _distinct(sets: Sequence[torch.Tensor], labels: Sequence[str]):
    """The point *sets*: every item's points without exact repeats, in the order of first
    occurrence, packed in float64 (exact for the inputs' float32/float64/integer values).
    Repeats say nothing about the curve, but they would fool the noise estimate (a point's
    nearest neighbours would be its own copies: noise 0, tolerance floor gone) and the
    point-count guards of the test, and noisy data would be refined into spurious loops.

    Returns ``(points (P, 2) float64, point_item (P,), counts (B,))``, for the whole batch at
    once: rows ``(item, x, y)`` sorted by three stable sorts (``unique(dim=0)`` is several
    times slower), equal neighbours grouped."""
    dev = sets[0].device
    B = len(sets)
    n = torch.tensor([p.shape[0] for p in sets], device=dev)
    item = torch.repeat_interleave(torch.arange(B, device=dev), n)
    x = torch.cat([p.to(torch.float64) for p in sets])
    o = torch.argsort(x[:, 1], stable=True)
    o = o[torch.argsort(x[o, 0], stable=True)]
    o = o[torch.argsort(item[o], stable=True)]
    xs, its = x[o], item[o]
    new = torch.ones(o.shape[0], dtype=torch.bool, device=dev)
    new[1:] = (its[1:] != its[:-1]) | (xs[1:] != xs[:-1]).any(1)
    gid = torch.cumsum(new.long(), 0) - 1
    G = int(gid[-1]) + 1
    counts = torch.bincount(its[new], minlength=B)
    few = (counts < 3).nonzero().squeeze(1)
    if few.numel():
        b = int(few[0])
        raise PointSetError(f"{labels[b]}: needs at least 3 distinct points, got {int(counts[b])}")
    if G == x.shape[0]:
        return x, item, counts
    first = torch.full((G,), x.shape[0], dtype=torch.long, device=dev).scatter_reduce_(0, gid, o, "amin")
    keep = first.sort().values                       # item-major, first occurrence within an item
    return x[keep], item[keep], counts


def _collinear(pts64: torch.Tensor, point_item: torch.Tensor, B: int, slack: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: every point of the item lies within ``slack`` of one line (float64,
    normalized coordinates). Measured as the largest distance to the principal axis, so no
    cancellation in an eigenvalue limits the precision."""
    n = torch.bincount(point_item, minlength=B).to(pts64.dtype)
    mean = torch.zeros(B, 2, dtype=pts64.dtype, device=pts64.device).index_add_(0, point_item, pts64) / n[:, None]
    d = pts64 - mean[point_item]
    cov = torch.zeros(B, 3, dtype=pts64.dtype, device=pts64.device).index_add_(
        0, point_item, torch.stack([d[:, 0] * d[:, 0], d[:, 0] * d[:, 1], d[:, 1] * d[:, 1]], 1))
    theta = 0.5 * torch.atan2(2 * cov[:, 1], cov[:, 0] - cov[:, 2])        # principal direction
    normal = torch.stack([-theta.sin(), theta.cos()], 1)
    off = (d * normal[point_item]).sum(1).abs()
    worst = torch.zeros(B, dtype=pts64.dtype, device=pts64.device).scatter_reduce_(0, point_item, off, "amax")
    return worst <= slack


def _initial_mesh(cfg: ReconstructConfig, B: int, device, dtype) -> MeshBatch:
    center = torch.zeros(B, 2, device=device, dtype=dtype)
    # normalized data lie in a disc of radius 1/2; cover it with the margin
    cover = 0.5 + cfg.margin
    if cfg.initial_mesh == "hexagon":
        radius = torch.full((B,), cover * 2.0 / math.sqrt(3.0), device=device, dtype=dtype)
        return hexagon_mesh(center, radius, cfg.initial_resolution)
    half = torch.full((B,), cover, device=device, dtype=dtype)
    return square_mesh(center, half, cfg.initial_resolution)


def reconstruct(points: PointsLike, config: Optional[ReconstructConfig] = None, name: Optional[str] = None,
                sign_oracle: Optional[Callable[[torch.Tensor], torch.Tensor]] = None) -> ReconstructionResult:
    """Reconstruct the curves of one point set.

    Args:
        points: ``(N, 2)`` unorganized points (tensor, array or nested lists).
        config: :class:`ReconstructConfig` (defaults when None).
        name: a label carried into the result.
        sign_oracle: optional inside/outside function: maps ``(M, 2)`` points (caller's
            coordinates) to ``(M,)`` booleans, True inside. When given, vertex signs come
            from it instead of topology estimation.

    Example:
        >>> t = torch.linspace(0, 2 * math.pi, 101)[:-1]
        >>> res = reconstruct(torch.stack([t.cos(), t.sin()], 1))
        >>> res.num_closed, res.num_open
        (1, 0)
    """
    oracles = None if sign_oracle is None else [sign_oracle]
    return reconstruct_batch([points], config, None if name is None else [name], oracles)[0]


def reconstruct_batch(point_sets: Sequence[PointsLike], config: Optional[ReconstructConfig] = None,
                      names: Optional[Sequence[Optional[str]]] = None,
                      sign_oracles: Union[None, Callable, Sequence[Optional[Callable]]] = None
                      ) -> List[ReconstructionResult]:
    """Reconstruct many point sets in one batched solve; one result per set, in order.

    An item's result does not depend on the other items of the batch.

    Args:
        point_sets: B point sets, each ``(N_b, 2)``.
        config: :class:`ReconstructConfig` (defaults when None).
        names: optional labels, one per set (used in errors and results).
        sign_oracles: inside/outside information replacing topology estimation (Section 3.2):
            either one callable per set, ``oracle(points (M, 2)) -> (M,)`` booleans (True
            inside), or a single *batched* callable ``oracle(points (M, 2), item (M,)) ->
            (M,)`` booleans, called once per level with the mesh vertices of every unfinished
            set (``item`` is the set's index in ``point_sets``). Points are float64 in the
            caller's coordinates. Boundary vertices are always outside.
    """
    cfg = config if config is not None else ReconstructConfig()
    if len(point_sets) == 0:
        return []
    names = list(names) if names is not None else [None] * len(point_sets)
    labels = [n if n is not None else f"point set {i}" for i, n in enumerate(names)]
    raw = [_check_points(p, lab) for p, lab in zip(point_sets, labels)]
    device = raw[0].device
    for p, lab in zip(raw, labels):
        if p.device != device:
            raise PointSetError(f"{lab}: on {p.device}, but the batch is on {device}")
    dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
    B = len(raw)

    with torch.no_grad():
        pts64, point_item, counts = _distinct(raw, labels)
        # normalize in float64, then cast: large offsets (1e7) must not cost precision
        big = torch.finfo(torch.float64).max
        lo = torch.full((B, 2), big, dtype=torch.float64, device=device).scatter_reduce(
            0, point_item[:, None].expand(-1, 2), pts64, "amin")
        hi = torch.full((B, 2), -big, dtype=torch.float64, device=device).scatter_reduce(
            0, point_item[:, None].expand(-1, 2), pts64, "amax")
        center64 = 0.5 * (lo + hi)
        scale64 = (hi - lo).norm(dim=1)
        norm64 = (pts64 - center64[point_item]) / scale64[point_item, None]
        pts = norm64.to(dtype)
        # points on one line (up to the rounding of the input) enclose no region: such an item
        # stops at level 0 with no curve (limit "no_curve"), not with a loop the data cannot support
        ulp = torch.tensor([torch.finfo(p.dtype).eps if p.dtype.is_floating_point else 0.0 for p in raw],
                           dtype=torch.float64, device=device)
        reach = torch.maximum(lo.abs(), hi.abs()).amax(1)
        flat = _collinear(norm64, point_item, B, 1e-12 + 8 * ulp * reach / scale64)
        del norm64
        scale = scale64.to(dtype)
        tol = torch.full((B,), cfg.tolerance, dtype=dtype, device=device)
        if cfg.tolerance_mode == "absolute":
            tol = (cfg.tolerance / scale64).to(dtype)
        noise, frames = estimate_noise(pts, point_item, B, return_frames=True)

    results: List[Optional[ReconstructionResult]] = [None] * B
    stats: List[List[Dict[str, Any]]] = [[] for _ in range(B)]
    orig = torch.arange(B, device=device)              # working item -> original item

    mesh = _initial_mesh(cfg, B, device, dtype)
    clock = _StageClock(device)
    face, bary = locate_grid(mesh, pts, point_item)
    clock.tick("locate")
    signs = torch.ones(mesh.verts.shape[0], dtype=dtype, device=device)

    for level in range(cfg.max_level + 1):
        level_stats: List[Dict[str, Any]] = []
        nb = mesh.num_items
        with torch.no_grad():
            mom = triangle_moments(mesh, pts, face, bary)
            fixed = mesh.is_boundary_vert
            if sign_oracles is not None:
                signs = _oracle_signs(mesh, sign_oracles, orig, center64, scale64, dtype)
            else:
                L, eps, nrm = line_fits(mesh, mom)
                # triangles too small to hold a line borrow their neighbours' points
                pooled = pooled_moments(mesh, mom)
                Lp, epsp, nrmp = line_fits(mesh, pooled)
                few = mom.count < cfg.min_points_fit
                reach = torch.where(few[:, None], crossing_reach(mesh, pooled, Lp, nrmp),
                                    crossing_reach(mesh, mom, L, nrm))
                H = edge_weights(mesh, torch.where(few[:, None], Lp, L), torch.where(few, epsp, eps), mom.count,
                                 cfg.min_points_fit, cfg.empty_weight,
                                 pooled_count=torch.where(few, pooled.count, mom.count), reach=reach,
                                 noise2=noise[orig] ** 2)
                init = torch.where(fixed, torch.ones_like(signs), signs)
                signs = anneal(mesh, H, init, fixed, cfg.anneal_sweeps, cfg.anneal_t_start, cfg.anneal_t_end,
                               cfg.anneal_replicas, cfg.seed,
                               warm_t_start=None if level == 0 else cfg.anneal_warm_t_start)
                signs = remove_small_islands(mesh, signs, fixed, cfg.min_island_vertices)
            init_mag = vertex_data_distance(mesh, pts, face)
            near = vertex_data_distance_near(mesh, pts, face) if cfg.crossing_weight > 0 else None
            clock.tick("topology")
        values, d1 = fit_geometry(mesh, mom, signs, init_mag, tol[orig], cfg.lbfgs_iterations, cfg.lbfgs_history,
                                  cfg.magnitude_floor, cfg.smoothness, data_dist=near,
                                  slack=effective_tolerance(tol, noise, cfg.noise_factor)[orig],
                                  crossing_weight=cfg.crossing_weight)
        clock.tick("geometry")
        with torch.no_grad():
            values = values.detach()
            residual = point_curve_distance2(mesh, values, pts, face)
            if sign_oracles is None:
                eps_t = eps
            else:
                eps_t = line_fits(mesh, mom)[1]
            marked, eff_tol, worst = mark_triangles(
                mesh, residual, face, mom.count, eps_t, tol[orig], noise[orig], cfg.test_statistic,
                cfg.noise_factor, cfg.min_points_split, cfg.min_points_fit, cfg.thin_feature_factor,
                cfg.min_split_size,
                coverage=curve_coverage_excess(mesh, values, pts, face, frames) if cfg.coverage_test else None)
            if sign_oracles is not None:
                marked |= _oracle_disagreements(mesh, values, sign_oracles, orig, center64, scale64, 2.0 * eff_tol)
            n_marked = torch.zeros(nb, dtype=torch.long, device=device).index_add_(0, mesh.face_item, marked.long())
            # points farther from the curve than the tolerance (outliers, or a feature the mesh
            # has not resolved): reported, since the test excuses them in sparse triangles
            beyond = torch.zeros(nb, dtype=torch.long, device=device).index_add_(
                0, point_item, (residual > eff_tol[point_item] ** 2).long())
            # a subdivision at most quadruples the marked triangles and their neighbours
            grow = torch.zeros(nb, dtype=torch.long, device=device).index_add_(0, mesh.face_item, marked.long() * 9)
            over = (mesh.faces_per_item + grow) > cfg.max_triangles
            done = (n_marked == 0) | over | (level == cfg.max_level) | flat[orig]
            clock.tick("test")
            pts_per_item = torch.bincount(point_item, minlength=nb)
            # one transfer per quantity (on a GPU every scalar read is a synchronization)
            sc_t = scale[orig].double()
            cols = zip(orig.tolist(), mesh.faces_per_item.tolist(), pts_per_item.tolist(),
                       (d1.double() * sc_t * sc_t).tolist(), (worst.double() * sc_t).tolist(),
                       (eff_tol.double() * sc_t).tolist(), (noise[orig].double() * sc_t).tolist(),
                       n_marked.tolist(), beyond.tolist())
            for b, tri, npts, dl, mx, tl, ns, mk, bt in cols:       # bookkeeping, plain Python numbers
                level_stats.append({
                    "level": level, "triangles": tri, "points": npts, "delta1": dl, "max_error": mx,
                    "tolerance": tl, "noise": ns, "marked": mk, "points_beyond_tolerance": bt})
                stats[b].append(level_stats[-1])
            fin = done.nonzero().squeeze(1)
            if fin.numel():
                sub, vk, _ = mesh.select_items(fin)
                ob = orig[fin]
                vitem = sub.vert_item
                vals = values[vk]
                vals = torch.where(flat[ob][vitem], vals.abs(), vals)        # all outside: no curve
                inside = torch.zeros(fin.shape[0], dtype=torch.bool, device=device).index_put_(
                    (vitem[vals < 0],), torch.ones((), dtype=torch.bool, device=device))
                # back to the caller's frame in float64 (an offset of 1e7 must not be rounded
                # away), then to the caller's precision, at least the working one
                verts64 = sub.verts.double() * scale64[ob][vitem, None] + center64[ob][vitem]
                vals64 = vals.double() * scale64[ob][vitem]
                first = sub.verts_first_idx.tolist() + [sub.verts.shape[0]]
                for jj, (b, mk, ov, has_in, fl) in enumerate(zip(ob.tolist(), n_marked[fin].tolist(),
                                                               over[fin].tolist(), inside.tolist(),
                                                               flat[ob].tolist())):
                    limit = None
                    if mk > 0:
                        limit = "max_triangles" if ov else "max_level"
                    odt = torch.promote_types(raw[b].dtype if raw[b].dtype.is_floating_point else dtype, dtype)
                    v0, v1 = first[jj], first[jj + 1]
                    out_mesh = sub[jj].with_verts(verts64[v0:v1].to(odt))
                    curve = ImplicitCurve(out_mesh, vals64[v0:v1].to(odt), validate=False)
                    converged = mk == 0
                    if fl or (not has_in and limit is None):
                        # no inside vertex, so no curve: the data did not define one (too few
                        # points, or all of them on one line); a run cut short by a limit
                        # keeps that limit as its reason
                        converged, limit = False, "no_curve"
                    results[b] = ReconstructionResult(curve=curve, points=raw[b], stats=stats[b], config=cfg,
                                                      converged=converged, limit=limit, name=names[b])
            keep = (~done).nonzero().squeeze(1)
            if keep.numel() == 0:
                clock.close_level(level_stats)
                break
            # shrink the working set to the unfinished items
            if fin.numel():
                n_faces_before = mesh.faces.shape[0]
                mesh, vk, fk = mesh.select_items(keep)
                values, signs, marked = values[vk], signs[vk], marked[fk]
                keep_p = (~done)[point_item]
                remap_f = torch.full((n_faces_before,), -1, dtype=torch.long, device=device)
                remap_f[fk] = torch.arange(fk.shape[0], device=device)
                new_item = torch.full((nb,), -1, dtype=torch.long, device=device)
                new_item[keep] = torch.arange(keep.shape[0], device=device)
                fkp = face[keep_p]
                pts, face = pts[keep_p], torch.where(fkp >= 0, remap_f[fkp.clamp_min(0)], fkp)
                frames = frames[keep_p]
                point_item = new_item[point_item[keep_p]]
                orig = orig[keep]
            old_edges = mesh.edges
            sd = subdivide(mesh, marked)
            mesh = sd.mesh
            values = sd.interpolate(values, old_edges)
            signs = torch.where(values < 0, -1.0, 1.0).to(dtype)
            clock.tick("subdivide")
            face, bary = locate_children(mesh, pts, face, sd.children)
            clock.tick("locate")
        if cfg.relax_iterations > 0:
            mesh, face, bary = relax_mesh(mesh, pts, point_item, face, cfg.relax_iterations, cfg.kappa_data,
                                          cfg.kappa_edge, cfg.min_quality)
            clock.tick("relax")
        clock.close_level(level_stats)
    return results  # type: ignore[return-value]


class _StageClock:
    """Wall time per stage of a level (shared by the items solved in it); on CUDA it
    synchronizes so the times are real."""
    STAGES = ("topology", "geometry", "test", "subdivide", "locate", "relax")

    def __init__(self, device):
        self.cuda = torch.device(device).type == "cuda"
        self.t = self._now()
        self.acc = {k: 0.0 for k in self.STAGES}

    def _now(self) -> float:
        if self.cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    def tick(self, stage: str) -> None:
        now = self._now()
        self.acc[stage] += now - self.t
        self.t = now

    def close_level(self, level_stats: List[Dict[str, Any]]) -> None:
        """Write this level's stage times (the initial location counts to level 0) into its stats."""
        st = {k: round(v, 6) for k, v in self.acc.items()}
        total = round(sum(self.acc.values()), 6)
        for d in level_stats:
            d["seconds"] = total
            d["stage_seconds"] = dict(st)
        self.acc = {k: 0.0 for k in self.STAGES}


def _oracle_inside(x: torch.Tensor, item: torch.Tensor, oracles, orig, center64, scale64) -> torch.Tensor:
    """``(M,)`` bool, the oracles' inside/outside at points ``x (M, 2)`` (normalized coordinates)
    of working items ``item (M,)`` (non-decreasing), asked in the caller's coordinates."""
    b = orig[item]
    xc = x.detach().double() * scale64[b, None] + center64[b]
    if callable(oracles):                                   # batched: one call for all items
        inside = torch.as_tensor(oracles(xc, b), device=x.device).bool().reshape(-1)
        if inside.shape[0] != xc.shape[0]:
            raise PointSetError(f"sign oracle returned {inside.shape[0]} values for {xc.shape[0]} points")
        return inside
    out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    counts = torch.bincount(item, minlength=orig.shape[0])
    starts = (torch.cumsum(counts, 0) - counts).tolist()
    for j, (ob, s0, n) in enumerate(zip(orig.tolist(), starts, counts.tolist())):   # one call per item
        o = oracles[ob]
        if o is None:
            raise PointSetError(f"item {ob}: sign oracles must be given for every item or none")
        if n:
            got = torch.as_tensor(o(xc[s0:s0 + n]), device=x.device).bool().reshape(-1)
            if got.shape[0] != n:
                raise PointSetError(f"item {ob}: sign oracle returned {got.shape[0]} values for {n} points")
            out[s0:s0 + n] = got
    return out


def _oracle_signs(mesh: MeshBatch, oracles, orig, center64, scale64, dtype) -> torch.Tensor:
    """Vertex signs from the inside/outside oracles; boundary vertices are outside."""
    inside = _oracle_inside(mesh.verts, mesh.vert_item, oracles, orig, center64, scale64)
    out = torch.where(inside, -1.0, 1.0).to(dtype)
    out[mesh.is_boundary_vert] = 1.0
    return out


def _oracle_disagreements(mesh: MeshBatch, values: torch.Tensor, oracles, orig, center64, scale64,
                          min_len: torch.Tensor) -> torch.Tensor:
    """``(T,)`` bool: triangles next to an interior edge longer than ``min_len`` (per item) at
    whose midpoint the oracle and the piecewise-linear function disagree on inside/outside.
    Vertex signs alone cannot see a thin stroke or a gap that passes between two vertices; the
    points near it may still lie close to some piece of curve, so the distance test passes."""
    e = mesh.edges
    v = mesh.verts.detach()
    inside = _oracle_inside(0.5 * (v[e[:, 0]] + v[e[:, 1]]), mesh.edge_item, oracles, orig, center64, scale64)
    pl_inside = (values[e[:, 0]] + values[e[:, 1]]) < 0
    long = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1) > min_len[mesh.edge_item]
    bad = (inside != pl_inside) & long & ~mesh.is_boundary_edge
    out = torch.zeros(mesh.faces.shape[0], dtype=torch.bool, device=v.device)
    ef = mesh.edge_faces[bad].reshape(-1)
    out[ef[ef >= 0]] = True
    return out
