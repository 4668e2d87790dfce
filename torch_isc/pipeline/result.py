"""The result of a reconstruction: the curve in the caller's coordinates plus statistics."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch

from torch_isc.core.curve import ImplicitCurve
from torch_isc.core.nesting import polygons_with_holes, signed_area
from torch_isc.core.points import output_dtypes
from torch_isc.core.segments import segment_any
from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.pipeline.stats import LevelStats

if TYPE_CHECKING:
    from torch_isc.core.points import PointBatch
    from torch_isc.pipeline.workset import WorkingSet

__all__ = ["ReconstructionResult", "finish_items"]


@dataclass
class ReconstructionResult:
    """One reconstructed item.

    Attributes:
        curve: :class:`ImplicitCurve`, a batch of one, in the caller's coordinates.
        points: ``(N, 2)`` the input points (caller's coordinates, caller's dtype/device).
        stats: one :class:`~torch_isc.pipeline.stats.LevelStats` per level (distances in the
            caller's units). ``points_beyond_tolerance`` counts the points farther from the
            curve than the tolerance: outliers, which the test excuses in triangles holding
            too few points to split, show there even when ``converged`` is True.
        config: the :class:`ReconstructConfig` used.
        converged: every triangle met the tolerance at the last level.
        limit: ``None``; ``"max_level"`` / ``"max_triangles"`` when a cap stopped the loop;
            ``"no_curve"`` when the data defined no curve (e.g. three points), with
            ``converged`` False.
        The curve's dtype is the input's floating dtype promoted with the working dtype.
        name: an optional label (file stem) carried to the outputs.
        far_outliers: how many points lay so far from the rest that they were left out (more
            than 16 median distances from the median centre, at most 1% of the points or 4:
            ``torch_isc.core.points.drop_far_outliers``); ``points`` still holds them.
    """
    curve: ImplicitCurve
    points: torch.Tensor
    stats: List[LevelStats]
    config: ReconstructConfig
    converged: bool
    limit: Optional[str] = None
    name: Optional[str] = None
    far_outliers: int = 0
    _polylines: Optional[List[Dict[str, Any]]] = field(default=None, repr=False)

    @property
    def polylines(self) -> List[Dict[str, Any]]:
        """``[{"closed": bool, "points": (n, 2) tensor}, ...]`` of the zero set."""
        if self._polylines is None:
            self._polylines = self.curve._zero_set_detached.item_lists()[0]
        return self._polylines

    @property
    def num_components(self) -> int:
        return len(self.polylines)

    @property
    def num_closed(self) -> int:
        return sum(1 for p in self.polylines if p["closed"])

    @property
    def num_open(self) -> int:
        return sum(1 for p in self.polylines if not p["closed"])

    def bbox(self) -> List[float]:
        """``[xmin, ymin, xmax, ymax]`` of the curve (of the points if there is no curve)."""
        if self.polylines:
            pts = torch.cat([p["points"] for p in self.polylines])
        else:
            pts = self.points
        if pts.numel() == 0:
            return [0.0, 0.0, 0.0, 0.0]
        lo, hi = pts.min(0).values, pts.max(0).values
        return [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]

    def polygons(self) -> List[Tuple[np.ndarray, List[np.ndarray]]]:
        """The regions the closed curves bound, from their nesting: ``[(exterior, [holes])]``
        of ``(n, 2)`` float64 rings (caller's coordinates, last vertex not repeated). A curve
        at even depth is an exterior, one at odd depth a hole of its nearest enclosing curve;
        an island in a hole is an exterior again. Exteriors are counter-clockwise and holes
        clockwise (positive / negative shoelace area in the coordinates as given); open chains
        are left out."""
        rings = []
        for pl in self.polylines:
            if not pl["closed"]:
                continue
            a = pl["points"].detach().double().cpu().numpy().reshape(-1, 2)
            if a.shape[0] >= 2 and np.array_equal(a[0], a[-1]):
                a = a[:-1]
            if a.shape[0] >= 3:
                rings.append(a)

        def oriented(a: np.ndarray, ccw: bool) -> np.ndarray:
            return a if (signed_area(a) > 0) == ccw else np.ascontiguousarray(a[::-1])

        return [(oriented(rings[e], True), [oriented(rings[h], False) for h in holes])
                for e, holes in polygons_with_holes(rings)]

    def to_shapely(self):
        """The regions as a ``shapely.MultiPolygon`` (:meth:`polygons`: even depth = exterior,
        odd depth = hole of its nearest enclosing curve), in the caller's coordinates; empty
        when there is no closed curve. Needs shapely (``pip install shapely``)."""
        try:
            import shapely
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise ImportError("to_shapely() needs shapely: pip install shapely") from e
        return shapely.MultiPolygon([shapely.Polygon(ext, holes) for ext, holes in self.polygons()])

    def to_json_dict(self, with_stats: bool = True, arrays: bool = False) -> Dict[str, Any]:
        """The stable JSON schema: ``{"polylines": [{"closed", "points"}], "num_components",
        "bbox"}``, plus ``"stats"`` (levels, convergence, limit) when asked, its non-finite
        values as None (strict JSON); with ``arrays`` the points are ``(n, 2)`` float64 numpy
        arrays instead of lists (for a fast JSON writer)."""
        def pts(p):
            a = p.detach().double().cpu()
            return a.numpy() if arrays else a.tolist()

        d: Dict[str, Any] = {
            "polylines": [{"closed": bool(p["closed"]), "points": pts(p["points"])} for p in self.polylines],
            "num_components": self.num_components,
            "bbox": self.bbox(),
        }
        if with_stats:
            from torch_isc.io.json import jsonable          # non-finite values (max_error inf) as null
            d["stats"] = jsonable({"levels": [lv.to_dict() for lv in self.stats], "converged": self.converged,
                                   "limit": self.limit, "num_closed": self.num_closed, "num_open": self.num_open,
                                   "far_outliers": self.far_outliers})
        return d


def finish_items(ws: "WorkingSet", fin: torch.Tensor, n_marked: torch.Tensor, over: torch.Tensor,
                 batch: "PointBatch", cfg: ReconstructConfig, stats: Sequence[List[LevelStats]],
                 names: Sequence[Optional[str]], unresolved: Optional[torch.Tensor] = None
                 ) -> Iterator[Tuple[int, ReconstructionResult]]:
    """``(caller's item, result)`` for the working items ``fin``: each curve back in the
    caller's frame in float64 (an offset of 1e7 must not be rounded away), then in the caller's
    precision, at least the working one. An item that passed the test with points left in
    clusters far from every curve (``unresolved``, per working item) did not converge: its limit
    is ``"unresolved"`` (components smaller than the size floor lets the mesh resolve)."""
    with torch.no_grad():
        dtype = ws.dtype
        mesh, B, K = ws.mesh, ws.num_items, fin.shape[0]
        vi = mesh.vert_item
        neg = (ws.values < 0) & ~ws.flat[vi]                     # a flat item is all outside: no curve
        inside = segment_any(neg, vi, B)[fin]
        # everything the host needs, read at once: per item its caller, test outcome and sizes
        unres = torch.zeros_like(n_marked) if unresolved is None else unresolved
        host = torch.stack([ws.items[fin], n_marked[fin], over[fin].long(), inside.long(), ws.flat[fin].long(),
                            mesh.verts_per_item[fin], mesh.faces_per_item[fin], unres[fin]]).tolist()
        caller_l, nv, nf = host[0], host[5], host[6]
        sub, kept_verts, _ = mesh.select_items(fin, (sum(nv), sum(nf)))
        vitem = sub.vert_item
        flat = ws.flat[fin]
        vals = torch.where(flat[vitem], ws.values[kept_verts].abs(), ws.values[kept_verts])
        scale, center = ws.scale[fin], ws.center[fin]
        verts64 = sub.verts.double() * scale[vitem, None] + center[vitem]
        vals64 = vals.double() * scale[vitem]
        # the caller's precision, at least the working one; cast once per precision, then every
        # item's curve is a view (no device work per item)
        odts = output_dtypes([batch.raw[b] for b in caller_l], dtype)
        v_first = [0] * K
        for j in range(1, K):
            v_first[j] = v_first[j - 1] + nv[j - 1]
        views = {}
        for odt in dict.fromkeys(odts):
            vals_o = vals64.to(odt)
            meshes = sub.with_verts(verts64.to(odt)).items_list((nv, nf))
            views[odt] = [(m, vals_o[v0:v0 + n]) for m, v0, n in zip(meshes, v_first, nv)]
        rows = zip(caller_l, host[1], host[2], host[3], host[4], odts, host[7])
        for jj, (b, mk, ov, has_in, fl, odt, un) in enumerate(rows):
            limit = None
            if mk > 0:
                limit = "max_triangles" if ov else "max_level"
            elif un > 0:
                limit = "unresolved"
            raw = batch.raw[b]
            m, v = views[odt][jj]
            curve = ImplicitCurve(m, v, validate=False)
            converged = mk == 0 and un == 0
            if fl or (not has_in and limit in (None, "unresolved")):
                # no inside vertex, so no curve: the data did not define one (too few points, or
                # all of them on one line); a run cut short by a limit keeps that limit as its reason
                converged, limit = False, "no_curve"
            yield b, ReconstructionResult(curve=curve, points=raw, stats=stats[b], config=cfg, converged=converged,
                                          limit=limit, name=names[b],
                                          far_outliers=batch.far_outliers[b] if batch.far_outliers else 0)
