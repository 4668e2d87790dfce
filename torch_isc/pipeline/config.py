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
import os
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping, Optional, Union

from torch_isc._helpers import decode_text, is_regular_file, one_line
from torch_isc.pipeline.band import BandConfig
from torch_isc.pipeline.evidence import EvidenceConfig
from torch_isc.pipeline.knobs import (Base60Text, Bool11Text, ConfigError, OctalText, UnderscoreText, check_bounds,
                                    check_section, knob)
from torch_isc.pipeline.noise import NoiseConfig
from torch_isc.pipeline.relax import RelaxConfig
from torch_isc.pipeline.signs import TopologyConfig
from torch_isc.pipeline.tolerance import TestConfig
from torch_isc.pipeline.values import GeometryConfig

__all__ = ["ReconstructConfig", "ConfigError", "MeshConfig", "LimitsConfig", "RunConfig", "NoiseConfig",
           "EvidenceConfig", "TopologyConfig", "GeometryConfig", "BandConfig", "TestConfig", "RelaxConfig", "load_config",
           "parse_overrides", "from_dict", "flat_keys", "read_config_mapping", "config_hash", "UPPER_BOUNDS",
           "MAX_CONFIG_BYTES", "MAX_CONFIG_NODES", "initial_triangles"]

#: The largest config file read (bytes): a config is a few dozen keys.
MAX_CONFIG_BYTES = 1 << 20
#: The most YAML nodes (keys, values, list items) a config may hold: parsing a 1 MiB list of
#: numbers took 37 s; the defaults hold about 200 nodes.
MAX_CONFIG_NODES = 10_000


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
    #: per item, every mesh included the initial one (checked when the config is built)
    max_triangles: int = knob(200_000, gt=0)
    #: wall-clock seconds per batch call (0: none); the inner loops stop at it and the items still
    #: working end their level with limit "max_seconds" (pipeline/budget.py)
    max_seconds: float = knob(0.0, ge=0)

    def __post_init__(self):
        check_section(self)


@dataclass
class RunConfig:
    """Seed and working precision."""
    seed: int = knob(0, ge=0)
    dtype: str = knob("float32", choices=("float32", "float64"))
    #: on a CUDA device, record a round of the fits and a sweep of the annealer once as a CUDA
    #: graph and replay it (the same kernels, one launch; pipeline/graphs.py); no effect elsewhere
    cuda_graphs: bool = knob(True)

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
    band: BandConfig = field(default_factory=BandConfig)
    run: RunConfig = field(default_factory=RunConfig)

    def __post_init__(self):
        self.check_sections()
        for f in fields(self):
            sec = getattr(self, f.name)
            for k in fields(sec):
                if k.name in UPPER_BOUNDS:
                    check_bounds(k.name, getattr(sec, k.name), le=UPPER_BOUNDS[k.name])
        if self.geometry.compile and self.limits.max_seconds > 0:
            # torch.compile's first compilation cannot be interrupted (a minute or more on a CPU)
            raise ConfigError("config key 'compile': compiling the objective cannot be stopped at a deadline "
                              "(it can take minutes), so it cannot be combined with max_seconds > 0")
        n0 = initial_triangles(self.mesh)
        if n0 > self.limits.max_triangles:
            raise ConfigError(
                f"config key 'initial_resolution': the initial {self.mesh.initial_mesh} of resolution "
                f"{self.mesh.initial_resolution} has {n0} triangles, more than max_triangles={self.limits.max_triangles}")

    def check_sections(self, note: str = "") -> None:
        """A :class:`ConfigError` where a section is not its section's type (one replaced after
        the config was built: ``cfg.test = None``); ``note`` is added to the message."""
        for f in fields(self):
            sec = getattr(self, f.name)
            if not isinstance(sec, _SECTION_TYPES[f.name]):
                raise ConfigError(f"config section '{f.name}': expected {_SECTION_TYPES[f.name].__name__}, "
                                  f"got {type(sec).__name__}{note}")

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


def initial_triangles(mesh: MeshConfig) -> int:
    """Triangles of the initial mesh: ``6 r^2`` for the hexagon of resolution ``r``, ``2 r^2``
    for the square."""
    r = mesh.initial_resolution
    return (6 if mesh.initial_mesh == "hexagon" else 2) * r * r


#: Upper bounds of settings whose field declares only a lower one: magnitudes the solver can
#: represent (float32 work: a weight of 1e308 overflows), counts torch can index and work that
#: stays finite. Checked when a :class:`ReconstructConfig` is built, with the key named.
UPPER_BOUNDS: Dict[str, float] = {
    "initial_resolution": 10_000, "margin": 1e3,
    "max_level": 1_000, "max_triangles": 10_000_000, "max_seconds": 1e9,
    "seed": 2 ** 63 - 1,
    "min_points_fit": 2 ** 31 - 1, "crossing_reach_slack": 1e6, "evidence_noise_widths": 1e6, "evidence_rings": 64,
    "evidence_line_widths": 1e6, "two_line_separation": 1e6, "two_line_spread": 1e6,
    "noise_neighbours": 1_000, "noise_window": 10_000, "noise_blob_aspect": 1e6, "noise_line_aspect": 1e6,
    "noise_min_subset": 2 ** 31 - 1, "denoise_iterations": 100, "denoise_neighbours": 1_000, "denoise_radius": 1e6,
    "denoise_band": 1e6, "denoise_split_band": 1e6, "denoise_refine_hops": 1_000, "denoise_window": 10_000, "denoise_max_move": 1e6,
    "relax_iterations": 100_000, "kappa_data": 1e6, "kappa_edge": 1e6, "relax_max_backtracks": 64, "relax_noisy": 1e6,
    "empty_weight": 1e6, "anneal_sweeps": 1_000_000, "anneal_t_start": 1e6, "anneal_t_end": 1e6,
    "anneal_warm_t_start": 1e6, "anneal_replicas": 1_024, "anneal_greedy_sweeps": 1_000_000,
    "min_island_vertices": 2 ** 31 - 1, "unsupported_weight": 1e6, "unsupported_noise_widths": 1e6, "cluster_rounds": 1_000,
    "open_noise_widths": 1e6, "open_tolerances": 1e6, "open_rounds": 100_000, "enclose_noise_widths": 1e6, "enclose_rings": 16, "enclose_min_points": 2 ** 31 - 1, "blob_min_points": 2 ** 31 - 1, "blob_max_points": 1_000, "blob_neighbours": 64,
    "winding_weight": 1e6, "winding_neighbours": 64, "winding_sync_iterations": 100_000, "winding_smoothing": 1e6, "notch_rounds": 1_000, "crust_weight": 1e6, "crust_noise_tolerances": 1e6, "crust_max_length": 1e6, "crust_noise_spacings": 1e6, "crust_refine": 100, "crust_sides": 1e6, "notch_min_points": 2 ** 31 - 1,
    "channel_noise_widths": 1e6, "channel_tolerances": 1e6, "channel_min_points": 2 ** 31 - 1, "channel_rounds": 1_000,
    "noise_factor": 1e6, "min_points_split": 2 ** 31 - 1, "thin_feature_factor": 1e6, "min_split_size": 1e6,
    "transverse_split_size": 1e6, "transverse_noisy": 1e6, "far_cluster_points": 1_000, "far_cluster_factor": 1e6, "far_cluster_ratio": 1e6, "cluster_split_size": 1e6,
    "lbfgs_iterations": 100_000, "precondition": 1e6, "lbfgs_history": 1_000, "lbfgs_trials": 64, "smoothness": 1e6, "crossing_weight": 1e6,
    "band_levels": 8, "band_noisy": 1e6, "band_min_points": 2 ** 31 - 1, "band_between_rounds": 1_000, "band_rings": 16, "band_min_size": 1e6, "band_smoothness": 1e6, "band_iterations": 100_000, "band_dense_max": 100_000, "band_reg": 1e6, "band_precondition": 1e6,
    # loop counts of the band stage (spike_rounds=1e6 ran for minutes on an 80-point circle)
    "spike_rounds": 1_000, "spike_reach": 1e6, "spike_keep_points": 2 ** 31 - 1, "snap_kernel": 1e6, "snap_rounds": 1_000,
}


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
    given: Dict[str, str] = {}         # flat key -> how it was set here: once only

    def _once(key: str, how: str) -> None:
        if key in given:
            raise ConfigError(f"{source}: config key '{key}' is set twice ({given[key]} and {how})")
        given[key] = how

    for k, v in d.items():
        if not isinstance(k, str):
            raise ConfigError(f"{source}: config keys must be strings, got {type(k).__name__}")
        if k in _SECTION_TYPES:
            if not isinstance(v, Mapping):
                raise ConfigError(f"{source}: config section '{k}' must be a mapping of keys to values")
            for kk, vv in v.items():
                if FLAT.get(kk) != k:
                    raise ConfigError(f"{source}: unknown config key '{_key_text(k)}.{_key_text(kk)}'")
                _once(kk, f"as '{k}.{kk}'")
                cur[k][kk] = vv
        elif k in FLAT:
            _once(k, "as a flat key")
            cur[FLAT[k]][k] = v
        else:
            raise ConfigError(f"{source}: unknown config key '{_key_text(k)}'")
    try:
        return ReconstructConfig(**{sec: _SECTION_TYPES[sec](**vals) for sec, vals in cur.items()})
    except ConfigError as e:
        if source == "config":
            raise
        raise ConfigError(f"{source}: {e}") from None


class _AliasError(Exception):
    pass


class _TooManyNodes(Exception):
    pass


class _DuplicateKeyError(Exception):
    def __init__(self, key: Any, line: int):
        self.key, self.line = key, line


#: YAML 1.1 base-60 integers and floats (``1:30``, ``-1:30:00.5``), which PyYAML resolves to numbers
_BASE60 = re.compile(r"^[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?$")
_BASE60_TAG = "tag:torch-isc,2026:base60"
#: YAML 1.1 octal integers (``010`` is 8 there, 10 in YAML 1.2)
_OCTAL = re.compile(r"^[-+]?0[0-7_]+$")
_OCTAL_TAG = "tag:torch-isc,2026:octal"
#: numbers written with "_" (``1_000``, ``0.00_8``), which PyYAML reads as numbers
_UNDERSCORE = re.compile(r"^(?=[^_]*_)[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)(?:[eE][-+]?[0-9_]+)?$")
_UNDERSCORE_TAG = "tag:torch-isc,2026:underscore"
#: YAML 1.1 boolean words, strings in YAML 1.2 (``true``/``false`` are PyYAML's and 1.2's both)
_BOOL11 = re.compile(r"^(?:yes|Yes|YES|no|No|NO|on|On|ON|off|Off|OFF)$")
_BOOL11_TAG = "tag:torch-isc,2026:bool11"
_LOADER = None


def _loader_class():
    """A ``SafeLoader`` without aliases, that refuses duplicate keys (PyYAML keeps the last
    silently) and keeps base-60 and octal scalars as :class:`Base60Text` / :class:`OctalText`
    (refused with the key named)."""
    global _LOADER
    if _LOADER is not None:
        return _LOADER
    import yaml

    class _Loader(yaml.SafeLoader):
        nodes = 0

        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                raise _AliasError()
            self.nodes += 1
            if self.nodes > MAX_CONFIG_NODES:      # PyYAML takes ~70 us a node: bounds the time too
                raise _TooManyNodes()
            return super().compose_node(parent, index)

        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen = set()
                for key_node, _ in node.value:
                    if not isinstance(key_node, yaml.ScalarNode):
                        continue          # an unhashable key: PyYAML's own error follows
                    key = self.construct_object(key_node, deep=deep)
                    try:
                        dup = key in seen
                        seen.add(key)
                    except TypeError:
                        continue
                    if dup:
                        raise _DuplicateKeyError(key, key_node.start_mark.line + 1)
            return super().construct_mapping(node, deep=deep)

    # the base-60, octal, underscore and 1.1-boolean resolvers go first so that they win over
    # PyYAML's int, float and bool ones
    table = {ch: list(v) for ch, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
    for ch in "+-0123456789.":
        first = [(_BASE60_TAG, _BASE60), (_OCTAL_TAG, _OCTAL)] if ch != "." else []
        table[ch] = first + [(_UNDERSCORE_TAG, _UNDERSCORE)] + table.get(ch, [])
    for ch in "yYnNoO":
        table[ch] = [(_BOOL11_TAG, _BOOL11)] + table.get(ch, [])
    _Loader.yaml_implicit_resolvers = table
    _Loader.add_constructor(_BASE60_TAG, lambda loader, node: Base60Text(loader.construct_scalar(node)))
    _Loader.add_constructor(_OCTAL_TAG, lambda loader, node: OctalText(loader.construct_scalar(node)))
    _Loader.add_constructor(_UNDERSCORE_TAG, lambda loader, node: UnderscoreText(loader.construct_scalar(node)))
    _Loader.add_constructor(_BOOL11_TAG, lambda loader, node: Bool11Text(loader.construct_scalar(node)))
    _LOADER = _Loader
    return _Loader


def _safe_yaml(text: str):
    """``yaml.safe_load`` without aliases: ``*name`` references are rejected, so a document
    cannot expand beyond its own size (the "billion laughs" of nested aliases)."""
    loader = _loader_class()(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def _parse_yaml(text: str, where: str):
    import yaml

    try:
        return _safe_yaml(text)
    except _AliasError:
        raise ConfigError(f"{where}: YAML aliases (*name) are not allowed in a config") from None
    except _TooManyNodes:
        raise ConfigError(f"{where}: more than {MAX_CONFIG_NODES} YAML values (a config is a few dozen keys)") from None
    except _DuplicateKeyError as e:
        raise ConfigError(f"{where}: line {e.line}: duplicate key {_short_key(e.key)} (each key may be set once)") from None
    except RecursionError:
        raise ConfigError(f"{where}: YAML nested too deeply") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{where}: not valid YAML ({_first_line(str(e))})") from None
    except KeyError as e:
        # "!!bool 1": the bool constructor looks its text up in a table
        raise ConfigError(f"{where}: a YAML value cannot be read (not a boolean: {_short_key(e.args[0] if e.args else '')})") from None
    except (ValueError, TypeError, AttributeError, OverflowError) as e:
        # PyYAML's constructors raise these for values of a valid document: "2001-13-45",
        # "!!float abc", "!!timestamp x", an integer of more than 4300 digits
        raise ConfigError(f"{where}: a YAML value cannot be read ({_first_line(one_line(e, type(e).__name__), 120)})") from None


def _key_text(k: Any, limit: int = 60) -> str:
    """A key as a message shows it: control characters escaped (a newline would cut the message,
    an escape sequence would reach the terminal), at most ``limit`` characters."""
    t = "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(k))
    return t if len(t) <= limit else t[:limit - 3] + "..."


def _short_key(k: Any) -> str:
    r = repr(k)
    return r if len(r) <= 60 else r[:57] + "..."


def _first_line(s: str, limit: int = 200) -> str:
    lines = s.strip().splitlines()
    first = lines[0] if lines else ""
    return first if len(first) <= limit else first[:limit - 3] + "..."


def read_config_mapping(path: Union[str, Path]) -> Dict[str, Any]:
    """The mapping a YAML config file holds (``{}`` for an empty file), read with bounds: at
    most :data:`MAX_CONFIG_BYTES`, UTF-8 text, no aliases.

    Raises:
        ConfigError: one line naming the file.
    """
    p = Path(path)
    if os.path.exists(p) and not os.path.isdir(p) and not is_regular_file(p):       # a FIFO would block, a device never end
        raise ConfigError(f"{path}: cannot read config file (not a regular file)")
    try:
        with open(p, "rb") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config file ({e.strerror or type(e).__name__})") from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: config file larger than {MAX_CONFIG_BYTES} bytes")
    text = decode_text(raw, str(path), "YAML text file", ConfigError)
    loaded = _parse_yaml(text, str(path))
    if loaded is None:
        loaded = {}
    if not isinstance(loaded, dict):
        raise ConfigError(f"{path}: expected a mapping of keys to values")
    return loaded


def load_config(path: Optional[Union[str, Path]] = None, overrides: Optional[Mapping[str, Any]] = None,
                overrides_label: str = "config") -> ReconstructConfig:
    """Load a YAML file (sections or flat keys of :class:`ReconstructConfig`), then apply ``overrides``.

    The file is read with bounds (:func:`read_config_mapping`: size, UTF-8, no YAML aliases).
    An error in ``overrides`` starts with ``overrides_label`` (the CLI's ``--set``), not with
    the file's name: the file did not hold the value."""
    cfg = ReconstructConfig()
    if path is not None:
        cfg = from_dict(read_config_mapping(path), str(path))
    if overrides:
        cfg = from_dict(overrides, overrides_label, base=cfg)
    return cfg


#: settings of how a solve runs, not of what it computes: left out of :func:`config_hash`, so
#: turning one does not redo finished outputs (CUDA graphs replay the eager kernels)
EXECUTION_ONLY = (("run", "cuda_graphs"),)


def config_hash(cfg: ReconstructConfig, extra: Optional[Mapping[str, Any]] = None) -> str:
    """sha256 (hex) of the config's settings (and of ``extra``, e.g. image options), in a
    canonical JSON form: equal settings give equal hashes. :data:`EXECUTION_ONLY` settings are
    left out."""
    import hashlib
    import json

    settings = cfg.to_dict()
    for section, key in EXECUTION_ONLY:
        settings.get(section, {}).pop(key, None)
    doc = {"config": settings, "extra": dict(extra or {})}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=repr).encode()).hexdigest()


def parse_overrides(items: Iterable[str]) -> Dict[str, Any]:
    """``["key=value", ...]`` with YAML scalars (``tolerance=0.01``, ``dtype=float64``; no aliases);
    a key may name its section (``test.tolerance=0.01``)."""
    out: Dict[str, Any] = {}
    for it in items:
        shown = repr(it) if len(it) <= 80 else repr(it[:77]) + "..."
        if "=" not in it:
            raise ConfigError(f"--set {shown}: expected key=value")
        k, v = it.split("=", 1)
        if not k.strip():
            raise ConfigError(f"--set {shown}: empty key")
        if not v.strip():          # YAML reads "" as null: say what happened
            raise ConfigError(f"--set {shown}: empty value")
        if len(v) > MAX_CONFIG_BYTES:
            raise ConfigError(f"--set {shown}: value longer than {MAX_CONFIG_BYTES} characters")
        try:
            val = _parse_yaml(v, f"--set {shown}")
        except ConfigError as e:
            if "aliases" in str(e) or "deeply" in str(e) or "cannot be read" in str(e) or "duplicate key" in str(e):
                raise
            raise ConfigError(f"--set {shown}: value is not a YAML scalar") from None
        k = k.strip()
        sec, dot, key = k.partition(".")
        if dot and sec in _SECTION_TYPES and key:
            # section.key, the form the config's own messages use ('limits.max_level')
            part = out.setdefault(sec, {})
            if not isinstance(part, dict):
                raise ConfigError(f"--set {shown}: section '{sec}' is also given whole")
            part[key] = val
        elif k in _SECTION_TYPES and isinstance(out.get(k), dict):
            raise ConfigError(f"--set {shown}: section '{k}' is also given key by key")
        else:
            out[k] = val
    return out
