"""Per-level statistics as typed records, written by one recorder.

A :class:`LevelStats` is what one level did to one item (distances in the caller's units).
The :class:`StatsRecorder` times the stages (shared by the items of a level), writes one
record per working item and level, reading each quantity from the device once per level.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Dict, List

import torch

__all__ = ["LevelStats", "StatsRecorder", "STAGES"]

#: the timed stages of a level, in the order of Fig. 3
#: ``noise``: the noise estimate, the denoising and the small clusters' search (level 0 only)
STAGES = ("noise", "topology", "geometry", "test", "subdivide", "locate", "relax")


@dataclass
class LevelStats:
    """What one level of the loop did to one item.

    Attributes:
        level: the level (0 is the initial mesh). triangles, points: its sizes.
        delta1: Δ1 after the geometry fit (squared distance). max_error: the tested statistic's
            largest value (a distance). tolerance: the effective tolerance it was tested at.
        noise: the item's estimated noise. marked: triangles that failed the test.
        points_beyond_tolerance: points farther from the curve than the tolerance (outliers,
            which the test excuses in sparse triangles, or an unresolved feature).
        seconds: wall time of the level (shared by the items solved in it), stage_seconds: by stage.
    """
    level: int
    triangles: int
    points: int
    delta1: float
    max_error: float
    tolerance: float
    noise: float
    marked: int
    points_beyond_tolerance: int
    seconds: float = 0.0
    stage_seconds: Dict[str, float] = field(default_factory=dict)

    def to_dict(self, timings: bool = True) -> Dict[str, Any]:
        d = asdict(self)
        if not timings:
            d.pop("seconds")
            d.pop("stage_seconds")
        return d


_INT_FIELDS = frozenset(f.name for f in fields(LevelStats) if f.type in (int, "int"))


class StatsRecorder:
    """Times the stages of each level (on CUDA it synchronizes, so the times are real) and
    writes a :class:`LevelStats` per working item and level into ``per_item[b]`` (``b`` the
    caller's item). The quantities stay on the device until :meth:`flush`, which reads every
    level's at once (one host read per solve, not one per level or item)."""

    def __init__(self, device, num_items: int):
        self.cuda = torch.device(device).type == "cuda"
        self.t = self._now()
        self.acc = {k: 0.0 for k in STAGES}
        self.per_item: List[List[LevelStats]] = [[] for _ in range(num_items)]
        # per recorded level: [level, column names, (B, 1 + columns) float64 table, timings]
        self._pending: List[list] = []
        self._open: List[list] = []

    def _now(self) -> float:
        if self.cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    def tick(self, stage: str) -> None:
        """Charge the time since the last tick to ``stage``."""
        now = self._now()
        self.acc[stage] += now - self.t
        self.t = now

    def record(self, level: int, items: torch.Tensor, columns: Dict[str, torch.Tensor]) -> None:
        """One record per working item: ``items (B,)`` their caller's indices and ``columns``
        the :class:`LevelStats` fields other than ``level`` and the timings, each ``(B,)``
        (integers and float64 values, exact in float64)."""
        names = list(columns)
        with torch.no_grad():
            table = torch.stack([items.double()] + [columns[k].detach().double() for k in names], 1)
        entry = [level, names, table, (0.0, {})]
        self._pending.append(entry)
        self._open.append(entry)

    def close_level(self) -> None:
        """Write this level's stage times (the noise estimate and the initial location count to level 0) into its records."""
        st = {k: round(v, 6) for k, v in self.acc.items()}
        total = round(sum(self.acc.values()), 6)
        for entry in self._open:
            entry[3] = (total, st)
        self.acc = {k: 0.0 for k in STAGES}
        self._open = []

    def flush(self) -> None:
        """Read every pending level from the device at once and append its records."""
        if not self._pending:
            return
        widths = {e[2].shape[1] for e in self._pending}
        if len(widths) == 1:
            rows = torch.cat([e[2] for e in self._pending]).tolist()
            tables, r0 = [], 0
            for e in self._pending:
                tables.append(rows[r0:r0 + e[2].shape[0]])
                r0 += e[2].shape[0]
        else:
            tables = [e[2].tolist() for e in self._pending]
        for (level, names, _, (total, st)), rows in zip(self._pending, tables):
            conv = [int if k in _INT_FIELDS else float for k in names]
            for row in rows:
                vals = {k: c(x) for k, c, x in zip(names, conv, row[1:])}
                rec = LevelStats(level=level, seconds=total, stage_seconds=dict(st), **vals)
                self.per_item[int(row[0])].append(rec)
        self._pending = []
