"""Reconstruction settings: one section per stage, loaded from YAML, unknown keys rejected.

Each stage owns its section (``TestConfig`` beside the test, ``RelaxConfig`` beside the
relaxation, ...) and receives it whole. A YAML file names sections::

    test:
      tolerance: 0.006
    relaxation:
      relax_iterations: 10

or, as older files do, the flat keys alone (``tolerance: 0.006``): every field name is unique
across the sections, so a flat key says where it belongs. Every field is documented in
``configs/default.yaml``; the two must agree (a test checks).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping, Optional, Union

from torch_isc.pipeline.evidence import EvidenceConfig
from torch_isc.pipeline.knobs import ConfigError, check_section, knob
from torch_isc.pipeline.noise import NoiseConfig
from torch_isc.pipeline.relax import RelaxConfig
from torch_isc.pipeline.signs import TopologyConfig
from torch_isc.pipeline.tolerance import TestConfig
from torch_isc.pipeline.values import GeometryConfig

__all__ = ["ReconstructConfig", "ConfigError", "MeshConfig", "LimitsConfig", "RunConfig", "NoiseConfig",
           "EvidenceConfig", "TopologyConfig", "GeometryConfig", "TestConfig", "RelaxConfig", "load_config",
           "parse_overrides", "from_dict", "flat_keys"]


@dataclass
class MeshConfig:
    """InitializeMesh (Fig. 3)."""
    initial_mesh: str = knob("hexagon", choices=("hexagon", "square"))
    #: triangles along each side of the initial hexagon (cells per side of the square)
    initial_resolution: int = knob(4, gt=0)
    #: how far the initial mesh extends beyond the data, relative to the data's size
    margin: float = knob(0.15, ge=0)

    def __post_init__(self):
        check_section(self)


@dataclass
class LimitsConfig:
    """What bounds the loop."""
    max_level: int = knob(10, gt=0)
    max_triangles: int = knob(200_000, gt=0)

    def __post_init__(self):
        check_section(self)


@dataclass
class RunConfig:
    """Seed and working precision."""
    seed: int = knob(0, ge=0)
    dtype: str = knob("float32", choices=("float32", "float64"))

    def __post_init__(self):
        check_section(self)


@dataclass
class ReconstructConfig:
    """Every setting of a reconstruction, by stage.

    Example:
        >>> cfg = ReconstructConfig().replace(max_level=3, relaxation={"relax_iterations": 5})
        >>> cfg.limits.max_level, cfg.relaxation.relax_iterations, cfg.test.tolerance
        (3, 5, 0.004)
    """
    mesh: MeshConfig = field(default_factory=MeshConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    topology: TopologyConfig = field(default_factory=TopologyConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    test: TestConfig = field(default_factory=TestConfig)
    relaxation: RelaxConfig = field(default_factory=RelaxConfig)
    run: RunConfig = field(default_factory=RunConfig)

    def __post_init__(self):
        for f in fields(self):
            if not isinstance(getattr(self, f.name), _SECTION_TYPES[f.name]):
                raise ConfigError(f"config section '{f.name}': expected {_SECTION_TYPES[f.name].__name__}")

    def replace(self, **changes: Any) -> "ReconstructConfig":
        """A copy with ``changes``: flat keys (``tolerance=0.01``) or sections as mappings
        (``test={"tolerance": 0.01}``), checked like a file."""
        return from_dict(changes, base=self)

    def to_dict(self) -> Dict[str, Dict[str, Any]]:
        """``{section: {key: value}}``, the layout of ``configs/default.yaml``."""
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in fields(self)}

    def to_flat_dict(self) -> Dict[str, Any]:
        """``{key: value}`` over all sections (the flat keys of older files)."""
        return {k: v for sec in self.to_dict().values() for k, v in sec.items()}


_SECTION_TYPES = {f.name: f.default_factory for f in fields(ReconstructConfig)}      # type: ignore[misc]
#: flat key -> its section
FLAT = {k.name: sec for sec, cls in _SECTION_TYPES.items() for k in fields(cls)}
assert len(FLAT) == sum(len(fields(c)) for c in _SECTION_TYPES.values()), "flat keys must be unique"


def flat_keys(d: Mapping[str, Any]) -> List[str]:
    """The flat keys a config mapping (flat or by section) sets, e.g. to know which settings a
    user named."""
    out: List[str] = []
    for k, v in d.items():
        if k in _SECTION_TYPES and isinstance(v, Mapping):
            out.extend(str(x) for x in v)
        else:
            out.append(str(k))
    return out


def from_dict(d: Mapping[str, Any], source: str = "config", base: Optional[ReconstructConfig] = None
              ) -> ReconstructConfig:
    """Build a config from ``d`` (sections and/or flat keys) over ``base`` (defaults when None)."""
    if not isinstance(d, Mapping):
        raise ConfigError(f"{source}: expected a mapping of keys to values, got {type(d).__name__}")
    cur = (base or ReconstructConfig()).to_dict()
    for k, v in d.items():
        if not isinstance(k, str):
            raise ConfigError(f"{source}: config keys must be strings, got {type(k).__name__}")
        if k in _SECTION_TYPES:
            if not isinstance(v, Mapping):
                raise ConfigError(f"{source}: config section '{k}' must be a mapping of keys to values")
            for kk, vv in v.items():
                if FLAT.get(kk) != k:
                    raise ConfigError(f"{source}: unknown config key '{k}.{kk}'")
                cur[k][kk] = vv
        elif k in FLAT:
            cur[FLAT[k]][k] = v
        else:
            raise ConfigError(f"{source}: unknown config key '{k}'")
    try:
        return ReconstructConfig(**{sec: _SECTION_TYPES[sec](**vals) for sec, vals in cur.items()})
    except ConfigError as e:
        if source == "config":
            raise
        raise ConfigError(f"{source}: {e}") from None


def load_config(path: Optional[Union[str, Path]] = None, overrides: Optional[Mapping[str, Any]] = None) -> ReconstructConfig:
    """Load a YAML file (sections or flat keys of :class:`ReconstructConfig`), then apply ``overrides``."""
    import yaml

    src = "config"
    cfg = ReconstructConfig()
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
        cfg = from_dict(loaded, src)
    if overrides:
        cfg = from_dict(overrides, src, base=cfg)
    return cfg


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
