"""The result of a reconstruction: the curve in the caller's coordinates plus statistics."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import torch

from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.core.curve import ImplicitCurve

__all__ = ["ReconstructionResult"]


@dataclass
class ReconstructionResult:
    """One reconstructed item.

    Attributes:
        curve: :class:`ImplicitCurve`, a batch of one, in the caller's coordinates.
        points: ``(N, 2)`` the input points (caller's coordinates, caller's dtype/device).
        stats: one dict per level: ``level, triangles, points, delta1, max_error,
            tolerance, noise, marked, points_beyond_tolerance, seconds`` (distances in the
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
    """
    curve: ImplicitCurve
    points: torch.Tensor
    stats: List[Dict[str, Any]]
    config: ReconstructConfig
    converged: bool
    limit: Optional[str] = None
    name: Optional[str] = None
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

    def to_json_dict(self, with_stats: bool = True) -> Dict[str, Any]:
        """The stable JSON schema: ``{"polylines": [{"closed", "points"}], "num_components",
        "bbox"}``, plus ``"stats"`` (levels, convergence, limit) when asked."""
        d: Dict[str, Any] = {
            "polylines": [{"closed": bool(p["closed"]), "points": p["points"].detach().double().cpu().tolist()}
                          for p in self.polylines],
            "num_components": self.num_components,
            "bbox": self.bbox(),
        }
        if with_stats:
            d["stats"] = {"levels": self.stats, "converged": self.converged, "limit": self.limit,
                          "num_closed": self.num_closed, "num_open": self.num_open}
        return d
