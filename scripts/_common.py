"""Small helpers shared by the scripts (not part of the library)."""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Callable, Optional, Tuple

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def resolve_dir(arg: Optional[str], default: Path) -> Path:
    """``arg`` as given when it exists from the current folder, else relative to the repo root."""
    if arg is None:
        return default.resolve()
    p = Path(arg)
    if p.is_absolute() or p.exists():
        return p.resolve()
    return (REPO / p).resolve()


def json_text(obj: Any) -> str:
    from torch_isc.io import json_dumps
    return json_dumps(obj)


def add_run_args(ap, what: str) -> None:
    """The options every reconstruction script shares (``what``: the unit, e.g. ``"case"``)."""
    ap.add_argument("--config", default=None, help="YAML config file (keys of ReconstructConfig)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="config overrides (YAML scalars), e.g. --set tolerance=0.006 seed=1")
    ap.add_argument("--filter", default=None, metavar="SUBSTR", help=f"only {what}s whose name contains SUBSTR")
    ap.add_argument("--one-by-one", action="store_true", help=f"one reconstruct_batch call per {what}")
    ap.add_argument("--device", default="cpu", help="device of the point tensors (cpu, cuda)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")


def run_main(main) -> None:
    """Exit with ``main()``'s status: 130 on Ctrl-C, 1 with the traceback on a crash."""
    import traceback
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        sys.exit(130)
    except Exception:
        traceback.print_exc()
        sys.exit(1)


def setup_run(args):
    """Apply ``--threads`` and return the :class:`ReconstructConfig` of ``--config`` / ``--set``."""
    import torch
    import torch_isc
    from torch_isc.pipeline.config import parse_overrides
    if args.threads:
        torch.set_num_threads(args.threads)
    return torch_isc.load_config(args.config, parse_overrides(args.set))


# ----------------------------------------------------------------------------- shapes with truth
Curve = Callable[[np.ndarray], np.ndarray]


def ellipse(a: float, b: float, cx: float = 0.0, cy: float = 0.0) -> Curve:
    return lambda t: np.stack([cx + a * np.cos(t), cy + b * np.sin(t)], 1)


def flower(a: float = 0.3, k: int = 5) -> Curve:
    """r = 1 + a cos(k t)."""
    return lambda t: np.stack([(1 + a * np.cos(k * t)) * np.cos(t), (1 + a * np.cos(k * t)) * np.sin(t)], 1)


def arclength_samples(fn: Curve, n: int, phase: float, dense: int = 20000) -> Tuple[np.ndarray, float]:
    """``n`` points evenly spaced in arclength, shifted by ``phase`` of a spacing, on the closed
    curve ``fn(t), t in [0, 2 pi)`` (``fn`` maps an array of t to ``(len(t), 2)``), and the
    curve's length (measured on ``dense`` segments)."""
    t = np.linspace(0.0, 2 * math.pi, dense + 1)
    p = fn(t)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*(p[1:] - p[:-1]).T))])
    if n <= 0:
        return np.zeros((0, 2)), float(s[-1])
    u = (phase + np.arange(n)) / n * s[-1]
    i = np.clip(np.searchsorted(s, u, side="right"), 1, dense)
    w = ((u - s[i - 1]) / np.maximum(s[i] - s[i - 1], 1e-300))[:, None]
    return p[i - 1] * (1 - w) + p[i] * w, float(s[-1])
