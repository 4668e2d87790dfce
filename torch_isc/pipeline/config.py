"""Reconstruction settings: one dataclass, loaded from YAML, unknown keys rejected.

Every field is documented in ``configs/default.yaml``; the two must agree (a test checks).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Dict, Iterable, Mapping, Optional, Union

__all__ = ["ReconstructConfig", "ConfigError", "load_config", "parse_overrides"]


class ConfigError(ValueError):
    """A configuration key or value that cannot be used."""


_CHOICES = {
    "initial_mesh": ("hexagon", "square"),
    "tolerance_mode": ("relative", "absolute"),
    "test_statistic": ("max", "rms"),
    "dtype": ("float32", "float64"),
}


@dataclass
class ReconstructConfig:
    # mesh
    initial_mesh: str = "hexagon"
    initial_resolution: int = 4
    margin: float = 0.15
    # loop and limits
    max_level: int = 10
    max_triangles: int = 200_000
    # testing
    tolerance: float = 0.004
    tolerance_mode: str = "relative"
    test_statistic: str = "max"
    noise_factor: float = 3.0
    min_points_split: int = 6
    thin_feature_factor: float = 3.0
    min_split_size: float = 4.0
    coverage_test: bool = True
    # topology
    min_points_fit: int = 3
    empty_weight: float = 1.0
    anneal_sweeps: int = 120
    anneal_t_start: float = 3.0
    anneal_t_end: float = 0.02
    anneal_warm_t_start: float = 0.3
    anneal_replicas: int = 4
    min_island_vertices: int = 2
    # geometry
    lbfgs_iterations: int = 60
    lbfgs_history: int = 8
    magnitude_floor: float = 0.02
    smoothness: float = 1e-2
    crossing_weight: float = 1.0
    # relaxation
    relax_iterations: int = 25
    kappa_data: float = 1.0
    kappa_edge: float = 0.25
    min_quality: float = 0.15
    # run
    seed: int = 0
    dtype: str = "float32"

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            want = f.type if isinstance(f.type, type) else {"int": int, "float": float, "str": str, "bool": bool}[f.type]
            if want is float and isinstance(v, str):
                try:
                    v = float(v)
                    object.__setattr__(self, f.name, v)
                except ValueError:
                    pass
            if want is float and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)
                object.__setattr__(self, f.name, v)
            if not isinstance(v, want) or (want is int and isinstance(v, bool)):
                raise ConfigError(f"config key '{f.name}': expected {want.__name__}, got {type(v).__name__} {v!r}")
            if want is float and not math.isfinite(v):
                raise ConfigError(f"config key '{f.name}': must be finite, got {v!r}")
            if f.name in _CHOICES and v not in _CHOICES[f.name]:
                raise ConfigError(f"config key '{f.name}': must be one of {', '.join(_CHOICES[f.name])}, got {v!r}")
        positive = ["initial_resolution", "max_level", "max_triangles", "tolerance", "anneal_sweeps", "anneal_t_start",
                    "anneal_t_end", "anneal_warm_t_start", "anneal_replicas", "lbfgs_history", "min_points_fit",
                    "kappa_edge", "kappa_data"]
        for k in positive:
            if getattr(self, k) <= 0:
                raise ConfigError(f"config key '{k}': must be > 0, got {getattr(self, k)!r}")
        nonneg = ["margin", "noise_factor", "min_points_split", "thin_feature_factor", "min_split_size", "empty_weight",
                  "lbfgs_iterations", "magnitude_floor", "smoothness", "crossing_weight", "relax_iterations", "seed"]
        for k in nonneg:
            if getattr(self, k) < 0:
                raise ConfigError(f"config key '{k}': must be >= 0, got {getattr(self, k)!r}")
        if not 0 <= self.min_quality < 1:
            raise ConfigError(f"config key 'min_quality': must be in [0, 1), got {self.min_quality!r}")
        if self.magnitude_floor >= 1:
            raise ConfigError(f"config key 'magnitude_floor': must be < 1, got {self.magnitude_floor!r}")

    def replace(self, **changes) -> "ReconstructConfig":
        return from_dict({**dataclasses.asdict(self), **changes})

    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)


def from_dict(d: Mapping[str, Any], source: str = "config") -> ReconstructConfig:
    if not isinstance(d, Mapping):
        raise ConfigError(f"{source}: expected a mapping of keys to values, got {type(d).__name__}")
    names = {f.name for f in fields(ReconstructConfig)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise ConfigError(f"{source}: unknown config key '{unknown[0]}'")
    try:
        return ReconstructConfig(**d)
    except ConfigError as e:
        if source == "config":
            raise
        raise ConfigError(f"{source}: {e}") from None


ReconstructConfig.from_dict = staticmethod(from_dict)  # type: ignore[attr-defined]


def load_config(path: Optional[Union[str, Path]] = None, overrides: Optional[Mapping[str, Any]] = None) -> ReconstructConfig:
    """Load a YAML file (keys of :class:`ReconstructConfig`), then apply ``overrides``."""
    import yaml

    d: Dict[str, Any] = {}
    src = "config"
    if path is not None:
        src = str(path)
        try:
            text = Path(path).read_text()
        except OSError as e:
            raise ConfigError(f"{path}: cannot read config file ({e.strerror})") from None
        try:
            loaded = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: expected a mapping of keys to values")
        d.update(loaded)
    if overrides:
        d.update(overrides)
    return from_dict(d, src)


def parse_overrides(items: Iterable[str]) -> Dict[str, Any]:
    """``["key=value", ...]`` with YAML scalars (``tolerance=0.01``, ``dtype=float64``)."""
    import yaml

    out: Dict[str, Any] = {}
    for it in items:
        if "=" not in it:
            raise ConfigError(f"--set {it!r}: expected key=value")
        k, v = it.split("=", 1)
        try:
            out[k.strip()] = yaml.safe_load(v)
        except yaml.YAMLError:
            raise ConfigError(f"--set {it!r}: value is not a YAML scalar") from None
    return out
