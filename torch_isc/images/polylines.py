"""The one converter of polylines. A curve's polylines exist in two shapes: the result's list
of ``{"closed": bool, "points": (n, 2)}`` dicts (``ReconstructionResult.polylines``, and the
JSON form where points are lists) and the packed :class:`~torch_isc.core.extract.Polylines` of
the core; everything that draws or converts curves takes either through :func:`polyline_dicts`."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Dict, List

import numpy as np
import torch

from torch_isc.core.extract import Polylines

__all__ = ["polyline_dicts", "closed_polygons"]


def polyline_dicts(src: Any) -> List[Dict[str, Any]]:
    """Polylines as the result's list of ``{"closed": bool, "points": (n, 2)}`` dicts.

    ``src``: a result (anything with a ``polylines`` attribute), a mapping with a
    ``"polylines"`` key (a result's JSON dict), a list of such dicts, or a packed ``Polylines``
    of one item. The points are passed through as they are (tensor, array or nested lists).

    >>> polyline_dicts({"polylines": [{"closed": True, "points": [[0, 0], [1, 0], [0, 1]]}]})[0]["closed"]
    True
    """
    if isinstance(src, Polylines):
        if src.num_items != 1:
            raise ValueError(f"expected the polylines of one item, got a batch of {src.num_items}")
        return src.item_lists()[0]
    if hasattr(src, "polylines"):
        src = src.polylines
    elif isinstance(src, Mapping):
        src = src["polylines"]
    out = list(src)
    for k, pl in enumerate(out):
        if not (isinstance(pl, Mapping) and "closed" in pl and "points" in pl):
            raise TypeError(f"polyline {k}: expected a dict with 'closed' and 'points', got {type(pl).__name__}")
    return out


def _as_xy(points: Any) -> np.ndarray:
    if isinstance(points, torch.Tensor):
        return points.detach().double().cpu().numpy().reshape(-1, 2)
    return np.asarray(points, np.float64).reshape(-1, 2)


def closed_polygons(src: Any) -> List[np.ndarray]:
    """The closed polylines of ``src`` (see :func:`polyline_dicts`) as ``(n, 2)`` float64 arrays
    with ``n >= 3``; a repeated last vertex is dropped, open chains are left out."""
    out = []
    for pl in polyline_dicts(src):
        if not pl["closed"]:
            continue
        a = _as_xy(pl["points"])
        if a.shape[0] >= 2 and np.array_equal(a[0], a[-1]):
            a = a[:-1]
        if a.shape[0] >= 3:
            out.append(a)
    return out
