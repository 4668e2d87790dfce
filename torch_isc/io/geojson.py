"""The result as GeoJSON (RFC 7946): a FeatureCollection with one Feature per input.

The Feature's geometry is a ``MultiPolygon`` of the regions the closed curves bound, from their
nesting (:meth:`~torch_isc.ReconstructionResult.polygons`: even depth = exterior, odd depth = hole
of its nearest enclosing curve), in the input's own coordinates (pixels for an image: x right,
y down; no reprojection). Rings are closed (first vertex repeated), exteriors counter-clockwise
and holes clockwise in the coordinates as written. Open chains, when a curve ends on the mesh
boundary, come as a ``MultiLineString`` next to it in a ``GeometryCollection``. The properties
hold the name, the curve counts and the convergence. The text is deterministic (shortest
round-trip floats, one line), so the same input gives the same bytes.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, BinaryIO, Dict, List

from torch_isc.io.files import PathLike, atomic_write

__all__ = ["geojson_feature", "geojson_dict", "encode_geojson", "write_geojson"]


def _ring(a) -> List[List[float]]:
    pts = a.tolist()
    return pts + pts[:1]


def geojson_feature(result) -> Dict[str, Any]:
    """One GeoJSON Feature of ``result`` (see the module docstring)."""
    multi = {"type": "MultiPolygon",
             "coordinates": [[_ring(ext)] + [_ring(h) for h in holes] for ext, holes in result.polygons()]}
    chains = [p["points"].detach().double().cpu().tolist() for p in result.polylines if not p["closed"]]
    geometry = multi if not chains else {
        "type": "GeometryCollection", "geometries": [multi, {"type": "MultiLineString", "coordinates": chains}]}
    props = {"name": result.name, "num_closed": result.num_closed, "num_open": result.num_open,
             "converged": bool(result.converged), "limit": result.limit}
    return {"type": "Feature", "geometry": geometry, "properties": props}


def geojson_dict(results) -> Dict[str, Any]:
    """A FeatureCollection of one result or several (one Feature each)."""
    if not isinstance(results, (list, tuple)):
        results = [results]
    return {"type": "FeatureCollection", "features": [geojson_feature(r) for r in results]}


def encode_geojson(result, fh: BinaryIO) -> None:
    """Write the FeatureCollection of ``result`` (one line, UTF-8) into ``fh``."""
    text = json.dumps(geojson_dict(result), separators=(",", ":"), allow_nan=False)
    fh.write((text + "\n").encode("utf-8"))


def write_geojson(result, path: PathLike) -> Path:
    """Atomically write ``result`` as ``path`` (``.geojson``)."""
    return atomic_write(Path(path), lambda fh: encode_geojson(result, fh))
