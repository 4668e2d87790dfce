"""ReconstructConfig, load_config, parse_overrides, and configs/default.yaml."""
import dataclasses
import re
from pathlib import Path

import pytest
import yaml

from torch_isc.pipeline.config import ConfigError, ReconstructConfig, load_config, parse_overrides

DEFAULT_YAML = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


def _fields():
    """Flat key -> default, from the section dataclasses themselves."""
    out = {}
    for sec in dataclasses.fields(ReconstructConfig):
        for f in dataclasses.fields(sec.default_factory):
            out[f.name] = f.default
    return out


# ----------------------------------------------------------------------------- default.yaml
def test_default_yaml_lists_exactly_the_fields_with_their_defaults():
    d = yaml.safe_load(DEFAULT_YAML.read_text())
    assert list(d) == [f.name for f in dataclasses.fields(ReconstructConfig)], "one block per section, in order"
    for sec in dataclasses.fields(ReconstructConfig):
        ref = {f.name: f.default for f in dataclasses.fields(sec.default_factory)}
        assert list(d[sec.name]) == list(ref), f"section {sec.name}: every field, in the dataclass order"
        for k, v in ref.items():
            got = d[sec.name][k]
            assert got == v and type(got) is type(v), f"{k}: default.yaml has {got!r}, the dataclass {v!r}"


def test_default_yaml_documents_every_field():
    lines = DEFAULT_YAML.read_text().splitlines()
    for k in _fields():
        line = next(ln for ln in lines if re.match(rf"\s+{k}:", ln))
        assert "#" in line and len(line.split("#", 1)[1].strip()) > 10, f"{k} has no comment"


def test_flat_and_sectioned_files_agree(tmp_path):
    """Older flat files keep working: the same keys by section or flat give the same config."""
    flat = _load(tmp_path, "tolerance: 0.01\nrelax_iterations: 5\nseed: 3\n")
    nested = _load(tmp_path, "test:\n  tolerance: 0.01\nrelaxation:\n  relax_iterations: 5\nrun:\n  seed: 3\n")
    assert flat == nested
    assert flat.test.tolerance == 0.01 and flat.relaxation.relax_iterations == 5 and flat.run.seed == 3
    assert flat.limits == ReconstructConfig().limits                  # untouched sections keep defaults
    with pytest.raises(ConfigError, match="unknown config key 'test.relax_iterations'"):
        _load(tmp_path, "test:\n  relax_iterations: 5\n")              # a key in the wrong section
    with pytest.raises(ConfigError, match="section 'test' must be a mapping"):
        _load(tmp_path, "test: 3\n")
    # every flat key of the old single-dataclass layout is still accepted
    for k, v in _fields().items():
        assert load_config(None, {k: v}) == ReconstructConfig()


def test_sections_declare_their_bounds():
    from torch_isc.pipeline.config import TestConfig, RelaxConfig
    with pytest.raises(ConfigError, match="'noise_factor'.*>= 0"):
        TestConfig(noise_factor=-1.0)
    with pytest.raises(ConfigError, match="'relax_max_move'.*<= 1"):
        RelaxConfig(relax_max_move=2.0)
    assert TestConfig(tolerance=1).tolerance == 1.0 and isinstance(TestConfig(tolerance=1).tolerance, float)


def test_load_default_yaml():
    cfg = load_config(DEFAULT_YAML)
    assert cfg == ReconstructConfig()
    cfg = load_config(DEFAULT_YAML, {"max_level": 3, "seed": 7})
    assert cfg.limits.max_level == 3 and cfg.run.seed == 7 and cfg.test.tolerance == ReconstructConfig().test.tolerance


# ----------------------------------------------------------------------------- errors name the key
def _load(tmp_path, text, overrides=None):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return load_config(p, overrides)


def test_unknown_key(tmp_path):
    with pytest.raises(ConfigError, match="unknown config key 'max_levels'"):
        _load(tmp_path, "max_levels: 3\n")
    with pytest.raises(ConfigError, match="'bogus'"):
        load_config(None, {"bogus": 1})


def test_wrong_type(tmp_path):
    with pytest.raises(ConfigError, match="'max_level'.*expected int"):
        _load(tmp_path, "max_level: three\n")
    with pytest.raises(ConfigError, match="'max_level'.*expected int"):
        _load(tmp_path, "max_level: 2.5\n")
    with pytest.raises(ConfigError, match="'tolerance'.*expected float"):
        _load(tmp_path, "tolerance: [1, 2]\n")
    with pytest.raises(ConfigError, match="'max_level'"):
        _load(tmp_path, "max_level: true\n")                 # a bool is not an int here
    with pytest.raises(ConfigError, match="'dtype'.*float32, float64"):
        _load(tmp_path, "dtype: float16\n")
    assert _load(tmp_path, "tolerance: 1\n").test.tolerance == 1.0   # an int is fine for a float


def test_negative_tolerance_and_zero_max_level(tmp_path):
    with pytest.raises(ConfigError, match="'tolerance'.*> 0"):
        _load(tmp_path, "tolerance: -0.01\n")
    with pytest.raises(ConfigError, match="'max_level'.*> 0"):
        _load(tmp_path, "max_level: 0\n")
    with pytest.raises(ConfigError, match="'min_quality'"):
        ReconstructConfig().replace(min_quality=1.0)
    with pytest.raises(ConfigError, match="'tolerance'.*finite"):
        ReconstructConfig().replace(tolerance=float("inf"))


def test_error_names_the_file(tmp_path):
    with pytest.raises(ConfigError) as ei:
        _load(tmp_path, "max_level: 0\n")
    assert str(tmp_path / "c.yaml") in str(ei.value)
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        _load(tmp_path, "max_level: [\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        _load(tmp_path, "- 1\n- 2\n")
    assert _load(tmp_path, "") == ReconstructConfig()        # an empty file: all defaults


def test_overrides_apply_after_the_file(tmp_path):
    cfg = _load(tmp_path, "max_level: 4\ntolerance: 0.01\n", {"max_level": 2})
    assert cfg.limits.max_level == 2 and cfg.test.tolerance == 0.01


def test_replace_and_to_dict():
    cfg = ReconstructConfig().replace(seed=3)
    assert cfg.run.seed == 3 and cfg.to_dict()["run"]["seed"] == 3 and cfg.to_flat_dict()["seed"] == 3
    with pytest.raises(ConfigError, match="'seed'"):
        ReconstructConfig().replace(seed=-1)


# ----------------------------------------------------------------------------- parse_overrides
def test_parse_overrides_yaml_scalars():
    d = parse_overrides(["max_level=3", "tolerance=0.01", "dtype=float64", "initial_mesh = square", "seed=0"])
    assert d == {"max_level": 3, "tolerance": 0.01, "dtype": "float64", "initial_mesh": "square", "seed": 0}
    assert type(d["max_level"]) is int and type(d["tolerance"]) is float
    assert parse_overrides(["a=b=c"]) == {"a": "b=c"}           # split at the first '='
    assert parse_overrides([]) == {}


def test_parse_overrides_errors():
    with pytest.raises(ConfigError, match="expected key=value"):
        parse_overrides(["max_level"])
    with pytest.raises(ConfigError, match="not a YAML scalar"):
        parse_overrides(["max_level=[1"])
    # parse_overrides parses; load_config then checks keys and types
    with pytest.raises(ConfigError, match="unknown config key 'nope'"):
        load_config(None, parse_overrides(["nope=1"]))
    with pytest.raises(ConfigError, match="'max_level'.*expected int"):
        load_config(None, parse_overrides(["max_level=abc"]))
