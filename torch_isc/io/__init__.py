"""Inputs and outputs: point files and images in, curves / JSON / SVG / PNG / contours out.

One module per file format, each encoding or decoding only: ``points_text`` (``x y`` text and
CSV), ``npy`` (point arrays), ``npz`` (the lossless curve format), ``json`` (the result as JSON),
``svg``, ``png`` (the curve drawn), ``overlay`` (the curve over its image), ``contours``
(OpenCV contours ``.npz``), ``geojson`` (the regions as a GeoJSON FeatureCollection). ``files`` holds the reading of bytes and the one atomic writer;
``registry`` maps suffixes to loaders (:data:`LOADERS`) and format names to exporters
(:data:`EXPORTERS`), and :func:`export` writes several formats next to each other.

Every reading problem raises :class:`PointFileError` or :class:`CurveFileError` (images:
:class:`~torch_isc.images.ImageError`) with one line naming the file. Every write is atomic (a
temporary file in the destination folder, then ``os.replace``): an interrupted run never leaves
a half-written output.

This package uses numpy and OpenCV only (no matplotlib) and is not imported by the core, the
pipeline or the image code.
"""
from __future__ import annotations

from torch_isc.io.contours import encode_contours, load_contours, write_contours
from torch_isc.io.errors import CurveFileError, PointFileError
from torch_isc.io.files import atomic_write, read_file_bytes
from torch_isc.io.geojson import encode_geojson, geojson_dict, geojson_feature, write_geojson
from torch_isc.io.json import encode_json, json_dumps, result_json_dict, write_json
from torch_isc.io.npz import NPZ_FORMAT, encode_npz, load_npz, save_npz, write_npz
from torch_isc.io.overlay import encode_overlay, render_overlay, write_overlay
from torch_isc.io.png import encode_png, render_curve, render_png, write_png
from torch_isc.io.registry import (EXPORTERS, LOADERS, ExportContext, Exporter, Loader, chosen_formats, export,
                                   formats_needing, loader_for, read_points)
from torch_isc.io.svg import encode_svg, svg_text, write_svg

__all__ = [
    "PointFileError", "CurveFileError", "read_file_bytes", "read_points", "atomic_write", "NPZ_FORMAT",
    "save_npz", "load_npz", "json_dumps", "result_json_dict", "write_json", "write_npz", "write_svg",
    "svg_text", "render_curve", "render_png", "write_png", "render_overlay", "write_overlay", "write_contours",
    "load_contours", "encode_json", "encode_npz", "encode_svg", "encode_png", "encode_overlay",
    "encode_contours", "Loader", "LOADERS", "loader_for", "ExportContext", "Exporter", "EXPORTERS",
    "chosen_formats", "formats_needing", "export", "encode_geojson", "geojson_dict", "geojson_feature",
    "write_geojson",
]
