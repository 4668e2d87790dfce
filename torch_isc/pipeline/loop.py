"""The reconstruction loop of Fig. 3, on a packed batch of point sets.

::

    InitializeMesh
    for level in 0..max_level:
        EstimateTopology; EstimateGeometry
        if no triangle fails the test: done
        AdaptivelySubdivideMesh; RelaxMesh

Every stage is a function of the :class:`~torch_isc.pipeline.workset.WorkingSet` (the
unfinished items) and its own config section. An item that finishes leaves the working set,
so the others do not pay for it, and nothing an item computes depends on the other items of
its batch (per-item annealing streams, per-item L-BFGS and relaxation steps). Coordinates are
normalized per item (bounding box centred, diagonal 1) and all outputs are mapped back.
"""
from __future__ import annotations

import math
import time
import warnings
from typing import Any, Callable, List, Mapping, Optional, Sequence, Union

import torch

from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import MeshBatch, hexagon_mesh, square_mesh
from torch_isc.core.points import PointBatch, PointSetError, PointsLike, check_extent, prepare_points
from torch_isc.core.segments import segment_count, segment_sum
from torch_isc.pipeline.config import ConfigError, MeshConfig, ReconstructConfig, from_dict, initial_triangles
from torch_isc.pipeline import budget, graphs
from torch_isc.pipeline.band import band_stage
from torch_isc.pipeline.blobs import snap_blobs, start_blobs
from torch_isc.pipeline.denoise import denoise_knn, denoise_points
from torch_isc.pipeline.evidence import gather_evidence
from torch_isc.pipeline.noise import noise_and_frames
from torch_isc.pipeline.relax import relax_stage
from torch_isc.pipeline.result import ReconstructionResult, finish_items
from torch_isc.pipeline.signs import IsingSigns, OracleSigns, SignSource
from torch_isc.pipeline.stats import StatsRecorder
from torch_isc.core.subdivide import subdivide
from torch_isc.pipeline.tolerance import effective_tolerance, test_fit
from torch_isc.pipeline.values import estimate_values
from torch_isc.pipeline.workset import WorkingSet

__all__ = ["reconstruct", "reconstruct_batch", "initial_mesh", "initial_cover", "PointSetError"]


def initial_cover(cfg: MeshConfig) -> float:
    """The circumradius of the initial mesh in normalized units: normalized data lie in a
    disc of radius 1/2, covered with the margin (a hexagon's circumradius is 2/√3 of the
    covered disc's radius; a square's half side equals it)."""
    cover = 0.5 + cfg.margin
    return cover * 2.0 / math.sqrt(3.0) if cfg.initial_mesh == "hexagon" else cover


def initial_mesh(cfg: MeshConfig, B: int, device, dtype) -> MeshBatch:
    """InitializeMesh: ``B`` copies of the initial mesh in normalized coordinates."""
    center = torch.zeros(B, 2, device=device, dtype=dtype)
    size = torch.full((B,), initial_cover(cfg), device=device, dtype=dtype)
    if cfg.initial_mesh == "hexagon":
        return hexagon_mesh(center, size, cfg.initial_resolution)
    return square_mesh(center, size, cfg.initial_resolution)


def reconstruct(points: PointsLike, config: Optional[ReconstructConfig] = None, name: Optional[str] = None,
                sign_oracle: Optional[Callable[[torch.Tensor], torch.Tensor]] = None) -> ReconstructionResult:
    """Reconstruct the curves of one point set.

    Args:
        points: ``(N, 2)`` unorganized points (tensor, array or nested lists). An array is
            taken as the tensor of its dtype would be (unsigned 16-64 bit integers as int64,
            other real types as float64): the outputs' dtype is the input's floating dtype
            promoted with ``config.run.dtype``, or that dtype for integer input.
        config: :class:`ReconstructConfig` (defaults when None).
        name: a label carried into the result.
        sign_oracle: optional inside/outside function: maps ``(M, 2)`` points (caller's
            coordinates) to ``(M,)`` booleans, True inside. When given, vertex signs come
            from it instead of topology estimation.

    When ``points`` is a tensor that requires grad (and grad mode is on), the curve's values
    carry a gradient with respect to the points (see :func:`reconstruct_batch`).

    Example:
        >>> t = torch.linspace(0, 2 * math.pi, 101)[:-1]
        >>> res = reconstruct(torch.stack([t.cos(), t.sin()], 1))
        >>> res.num_closed, res.num_open
        (1, 0)
    """
    oracles = None if sign_oracle is None else [sign_oracle]
    return reconstruct_batch([points], config, None if name is None else [name], oracles)[0]


def _sequence(x, what: str) -> list:
    """``x`` (a list, tuple, generator, or a tensor/array iterated along its first axis) as a
    list; :class:`PointSetError` for a string, a mapping or something not iterable."""
    if isinstance(x, (str, bytes, dict)) or not hasattr(x, "__iter__"):
        raise PointSetError(f"{what}: expected a sequence, got {type(x).__name__}")
    return list(x)


def _as_lists(point_sets, names, sign_oracles):
    """The arguments of :func:`reconstruct_batch` as lists (a generator is read once), checked
    at the boundary: every oracle callable or None."""
    shape = getattr(point_sets, "shape", None)
    if shape is not None and len(shape) == 2:
        # a tensor or array is iterated by rows: each (2,) row would be read as a point set
        raise PointSetError(f"point_sets: one {tuple(shape)} array, not a sequence of point sets: pass "
                            f"[points] (or call reconstruct(points)); a (B, N, 2) stack is B sets")
    point_sets = _sequence(point_sets, "point_sets")
    if names is not None:
        names = _sequence(names, "names")
    if sign_oracles is not None and not callable(sign_oracles):
        sign_oracles = _sequence(sign_oracles, "sign_oracles")
        for i, o in enumerate(sign_oracles):
            if o is not None and not callable(o):
                raise PointSetError(f"sign_oracles[{i}]: expected a callable or None, got {type(o).__name__}")
    return point_sets, names, sign_oracles


def reconstruct_batch(point_sets: Sequence[PointsLike], config: Optional[ReconstructConfig] = None,
                      names: Optional[Sequence[Optional[str]]] = None,
                      sign_oracles: Union[None, Callable, Sequence[Optional[Callable]]] = None,
                      packed: bool = False):
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
        packed: also return all the curves as one packed :class:`ImplicitCurve` batch (item
            ``b`` is set ``b``): ``(results, curve)``.

    Returns the list of :class:`ReconstructionResult` (``(results, curve)`` with ``packed``).

    Gradients: when grad mode is on and a point set is a tensor that requires grad, every
    result's curve values carry a gradient with respect to its own points (the values are
    unchanged; the gradient is that of the refit of the magnitudes to the points with mesh
    and signs frozen, with the band stage's smoothness when it ran, by implicit differentiation, see
    :func:`torch_isc.pipeline.refit.attach_point_gradients`). Otherwise nothing changes.
    """
    if torch.is_inference_mode_enabled():
        # the relaxation differentiates its energy, which inference mode forbids even under
        # enable_grad: solve outside it, on copies of the caller's inference tensors
        with torch.inference_mode(False):
            def copy(p):
                return p.clone() if torch.is_tensor(p) else p
            sets = copy(point_sets) if torch.is_tensor(point_sets) else [copy(p) for p in point_sets]
            return reconstruct_batch(sets, config, names, sign_oracles, packed)
    cfg = _as_config(config)
    point_sets, names, sign_oracles = _as_lists(point_sets, names, sign_oracles)
    if len(point_sets) == 0:
        return ([], None) if packed else []
    if sign_oracles is not None and not callable(sign_oracles) and len(sign_oracles) != len(point_sets):
        raise PointSetError(f"sign_oracles: {len(sign_oracles)} oracle(s) for {len(point_sets)} point set(s)")
    dtype = torch.float64 if cfg.run.dtype == "float64" else torch.float32
    batch = prepare_points(point_sets, names, dtype, drop_far=sign_oracles is None)
    check_extent(batch, initial_cover(cfg.mesh), dtype)
    source: SignSource = (OracleSigns(sign_oracles) if sign_oracles is not None
                          else IsingSigns(cfg.topology, cfg.evidence, cfg.run.seed))
    results = run_loop(batch, cfg, source, names)
    if torch.is_grad_enabled() and any(torch.is_tensor(p) and p.requires_grad for p in point_sets):
        from torch_isc.pipeline.refit import attach_point_gradients
        # the band stage's meshes are finer than the loop's: their refit needs its smoothness
        # (with the loop's, triangles of one or two points make the point gradients erratic)
        kw = {"smoothness": cfg.band.band_smoothness} if cfg.band.band_levels > 0 else {}
        results = attach_point_gradients(results, point_sets, **kw)
    if packed:
        from torch_isc.core.curve import ImplicitCurve
        return results, ImplicitCurve.cat([r.curve for r in results])
    return results


def _as_config(config: Union[None, ReconstructConfig, Mapping[str, Any]]) -> ReconstructConfig:
    """The config of a call: defaults, a :class:`ReconstructConfig`, or a mapping of its keys
    (checked like a file); a :class:`ConfigError` otherwise, or when the initial mesh alone
    exceeds ``max_triangles`` (a config changed after it was built)."""
    if config is None:
        return ReconstructConfig()
    if isinstance(config, Mapping):
        config = from_dict(config)
    if not isinstance(config, ReconstructConfig):
        raise ConfigError(f"config: expected a ReconstructConfig or a mapping of its keys, got {type(config).__name__}")
    # checked again: a section's field set after construction (cfg.limits.max_level = -3) was
    # used unchecked (reconstruct returned None); a whole section replaced (cfg.test = None)
    # failed in dataclasses.asdict
    config.check_sections(" (a value set after the config was built)")
    try:
        config = from_dict(config.to_dict())
    except ConfigError as e:
        raise ConfigError(f"{e} (a value set after the config was built)") from None
    n0 = initial_triangles(config.mesh)
    if n0 > config.limits.max_triangles:
        raise ConfigError(f"config key 'initial_resolution': the initial mesh has {n0} triangles, more than "
                          f"max_triangles={config.limits.max_triangles}")
    return config


#: The smallest tolerance the working precision resolves, in units of the item's diagonal
#: (normalized coordinates are within 1 of the origin): 64 ulps. A smaller one is raised to it.
TOLERANCE_FLOOR_ULPS = 64.0
#: The largest tolerance used, in units of the diagonal (anything above accepts every mesh alike).
TOLERANCE_CEILING = 1e6


def _tolerance(batch: PointBatch, cfg: ReconstructConfig, dtype) -> torch.Tensor:
    """``(B,)`` the tolerance of each item in normalized units, within what the working precision
    resolves (a warning names the items whose tolerance was raised)."""
    if cfg.test.tolerance_mode == "absolute":
        tol64 = cfg.test.tolerance / batch.scale
    else:
        tol64 = torch.full((batch.num_items,), cfg.test.tolerance, dtype=torch.float64, device=batch.scale.device)
    floor = TOLERANCE_FLOOR_ULPS * torch.finfo(dtype).eps
    low = tol64 < floor
    if bool(low.any()):
        idx = low.nonzero().squeeze(1).tolist()
        shown = ", ".join(batch.labels[i] for i in idx[:3]) + (f" and {len(idx) - 3} more" if len(idx) > 3 else "")
        warnings.warn(f"{shown}: tolerance below what {str(dtype).replace('torch.', '')} resolves "
                      f"({floor:.3g} of the bounding-box diagonal): raised to it", RuntimeWarning, stacklevel=4)
    return tol64.clamp(floor, TOLERANCE_CEILING)


def _start(batch: PointBatch, cfg: ReconstructConfig, rec: StatsRecorder, source_blobs: bool = False) -> WorkingSet:
    """The working set at level 0: priors (tolerance, noise) per item, the initial mesh, the
    points located in it."""
    B, dtype, device = batch.num_items, batch.points.dtype, batch.points.device
    with torch.no_grad():
        tol = _tolerance(batch, cfg, dtype).to(dtype)
        est = noise_and_frames(batch.points, batch.point_item, B, cfg.noise, batch.source)
        # the loop sees the points averaged at their noise scale (identity when disabled); with
        # denoise_use evidence (geometry) only the sign evidence (the fit and the test) does
        knn = denoise_knn(batch.points, batch.point_item, cfg.noise)      # the denoising's and the blobs'
        den, tang = denoise_points(batch.points, batch.point_item, est.level, est.frames, cfg.noise,
                                   return_tangents=True, knn=knn)
        # frames columns 3-4: the denoising fit's tangents (over its radius of several noise
        # widths; the noise estimate's come from 8 neighbours, a blob under dense noise)
        frames = torch.cat([est.frames, tang.to(est.frames.dtype)], 1)
        use = cfg.noise.denoise_use
        points = batch.points if use == "evidence" else den
        sign_points = None if den is batch.points or use == "all" else (den if use == "evidence" else batch.points)
        # what noise the loop's rules assume (tolerance floor, thin features, band size): the
        # denoised points' residual spread is below the raw estimate
        level = est.level if den is batch.points else est.level * cfg.noise.denoise_noise_scale
        # small isolated clusters (pipeline/blobs.py), found on the raw points (a parabola
        # through a ring of 8 points flattens it); the loop sees them denoised like the rest:
        # with blob points kept raw, glyph_B at 1% noise (public cases) lost its counter
        # ...on the denoising's neighbours where they had the neighbour descent (not for masks,
        # whose config drops it): without it Morton cell walls cut a dense curve into "blobs"
        blob = start_blobs(batch.points, batch.point_item, cfg.topology.blob_neighbours,
                           cfg.topology.blob_min_points, cfg.topology.blob_max_points, est.level,
                           tang, knn=knn if cfg.noise.denoise_refine_hops > 0 else None) if source_blobs else None
    rec.tick("noise")
    mesh = initial_mesh(cfg.mesh, B, device, dtype)
    face, bary = locate_grid(mesh, points, batch.point_item)
    rec.tick("locate")
    ws = WorkingSet.start(mesh, points, batch.point_item, face, bary, frames, batch.center,
                          batch.scale, tol, level, batch.flat, sign_points=sign_points)
    # the blobs' rows and their number, once per solve (no host read for them per level)
    return ws if blob is None else ws.replace(blob=blob[0], blob_count=blob[1])


def run_loop(batch: PointBatch, cfg: ReconstructConfig, source: SignSource,
             names: Optional[Sequence[Optional[str]]] = None) -> List[ReconstructionResult]:
    """The loop of Fig. 3 over a prepared batch, signs from ``source``. ``limits.max_seconds``
    holds within a level too: the inner loops stop at the deadline (:mod:`budget`)."""
    t_start = time.perf_counter()
    with budget.deadline(cfg.limits.max_seconds, t_start), graphs.use(cfg.run.cuda_graphs):
        return _run_loop(batch, cfg, source, names, t_start)


def _run_loop(batch: PointBatch, cfg: ReconstructConfig, source: SignSource,
              names: Optional[Sequence[Optional[str]]], t_start: float) -> List[ReconstructionResult]:
    B = batch.num_items
    names = list(names) if names is not None else [None] * B
    rec = StatsRecorder(batch.points.device, B)
    results: List[Optional[ReconstructionResult]] = [None] * B
    cuts = 0                                   # inner loops the deadline has cut short so far
    ws = _start(batch, cfg, rec, isinstance(source, IsingSigns))
    finished: list = []                        # per finishing level: (working set, slack, marked, over, unresolved)
    for level in range(cfg.limits.max_level + 1):
        ws = snap_blobs(ws)                                            # a vertex inside each cluster
        ev = gather_evidence(ws, cfg.evidence)                         # EstimateTopology
        ws = ws.replace(signs=source.signs(ws, ev if ws.sign_points is None else _sign_evidence(ws, cfg), level))
        rec.tick("topology")
        slack = effective_tolerance(ws.tol, ws.noise, cfg.test.noise_factor)
        values, d1 = estimate_values(ws, ev, cfg.geometry, slack)      # EstimateGeometry
        ws = ws.replace(values=values)
        rec.tick("geometry")
        verdict = test_fit(ws, values, ev, cfg.test, cfg.evidence.min_points_fit)   # the test
        extra = source.marks(ws, values, 2.0 * verdict.tolerance)
        marked = verdict.marked if extra is None else verdict.marked | extra
        ws = ws.replace(marked=marked)
        done, n_marked, over = _decide(ws, verdict, cfg, level)
        timed: set = set()
        if budget.cuts() > cuts:
            # a loop of this level was cut short: every item of the level is not what it would be
            cuts = budget.cuts()
            timed = set(ws.items.tolist())
            done = torch.ones_like(done)
        elif cfg.limits.max_seconds > 0 and time.perf_counter() - t_start > cfg.limits.max_seconds:
            timed = set(ws.items[~done].tolist())          # stopped by the clock alone
            done = torch.ones_like(done)
        rec.tick("test")
        _record(rec, level, ws, verdict, d1, n_marked)
        nb = ws.num_items
        n_done = int(done.sum())                                       # the level's one read of the verdict
        if n_done:
            # finished items last, each part ascending: no second host read for the split
            order = torch.argsort(done.to(torch.uint8), stable=True)
            fin = order[nb - n_done:]
            finished.append((ws if n_done == nb else ws.select(fin), slack[fin], n_marked[fin], over[fin],
                             verdict.unresolved[fin]))
        if n_done == nb:
            # the band stage refines and refits the finished items of every level in one call
            # (its cost is per call, not per item: once per solve, not once per finishing level)
            sub = band_stage(WorkingSet.cat([f[0] for f in finished]), cfg.band, cfg.geometry,
                             torch.cat([f[1] for f in finished]), cfg.limits.max_triangles,
                             exact_signs=isinstance(source, OracleSigns), neighbours=cfg.noise.noise_neighbours)
            rec.tick("geometry")
            band_cut = budget.cuts() > cuts              # the deadline cut the band stage short
            local = torch.arange(sub.num_items, device=sub.device)
            n_mk, ovr = torch.cat([f[2] for f in finished]), torch.cat([f[3] for f in finished])
            unres = torch.cat([f[4] for f in finished])
            for b, res in finish_items(sub, local, n_mk, ovr, batch, cfg, rec.per_item, names, unres):
                if b in timed or band_cut:
                    res.converged, res.limit = False, "max_seconds"
                results[b] = res
            rec.close_level()
            break
        if n_done:                                                     # the others go on
            ws = ws.select(order[:nb - n_done])
        sd = subdivide(ws.mesh, ws.marked)                             # AdaptivelySubdivideMesh
        rec.tick("subdivide")
        ws = ws.follow(sd)
        rec.tick("locate")
        ws = relax_stage(ws, cfg.relaxation)                           # RelaxMesh
        if cfg.relaxation.relax_iterations > 0:
            rec.tick("relax")
        rec.close_level()
    rec.flush()
    return results  # type: ignore[return-value]


def _sign_evidence(ws: WorkingSet, cfg: ReconstructConfig):
    """The evidence of the signs from ``ws.sign_points`` (located in this level's mesh)."""
    face, bary = locate_grid(ws.mesh, ws.sign_points, ws.point_item)
    return gather_evidence(ws.replace(points=ws.sign_points, face=face, bary=bary), cfg.evidence)


def _decide(ws: WorkingSet, verdict, cfg: ReconstructConfig, level: int):
    """``(B,)`` which items stop here, their marked-triangle counts and whether the triangle
    cap stopped them."""
    with torch.no_grad():
        nb = ws.num_items
        n_marked = segment_sum(ws.marked.long(), ws.mesh.face_item, nb)
        # a subdivision at most quadruples the marked triangles and their neighbours
        grow = segment_sum(ws.marked.long() * 9, ws.mesh.face_item, nb)
        over = (ws.mesh.faces_per_item + grow) > cfg.limits.max_triangles
        done = (n_marked == 0) | over | (level == cfg.limits.max_level) | ws.flat
        return done, n_marked, over


def _record(rec: StatsRecorder, level: int, ws: WorkingSet, verdict, d1: torch.Tensor, n_marked: torch.Tensor) -> None:
    """This level's :class:`~torch_isc.pipeline.stats.LevelStats` of every working item, in the
    caller's units."""
    with torch.no_grad():
        nb = ws.num_items
        sc = ws.scale.double()                   # float64 frame: a float32 item of scale 1e-300 is not 0
        # points farther from the curve than the tolerance (outliers, or a feature the mesh has
        # not resolved): reported, since the test excuses them in sparse triangles
        beyond = segment_sum((verdict.residual > verdict.tolerance[ws.point_item] ** 2).long(), ws.point_item, nb)
        rec.record(level, ws.items, {
            "triangles": ws.mesh.faces_per_item, "points": segment_count(ws.point_item, nb),
            "delta1": d1.double() * sc * sc, "max_error": verdict.worst.double() * sc,
            "tolerance": verdict.tolerance.double() * sc, "noise": ws.noise.double() * sc,
            "marked": n_marked, "points_beyond_tolerance": beyond})
