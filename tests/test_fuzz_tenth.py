"""Fuzzing round 10: what a report-only fuzzing pass over the CUDA-graph switch, the batched
L-BFGS and the config parser found (each test fails on the commit before its fix)."""
from __future__ import annotations

import pytest
import torch

from torch_isc.pipeline.config import ConfigError, load_config, parse_overrides
from torch_isc.pipeline.optim import batched_lbfgs


@pytest.mark.parametrize("text", ["run:\n  cuda_graphs: !!bool 1\n", "seed: !!bool maybe\n"])
def test_a_yaml_bool_tag_on_a_non_boolean_is_a_config_error(tmp_path, text):
    # PyYAML's bool constructor raised a bare KeyError: "internal error", exit 1
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=r"c\.yaml: a YAML value cannot be read \(not a boolean"):
        load_config(f)


def test_a_bool_tag_in_set_is_a_config_error():
    with pytest.raises(ConfigError, match=r"cuda_graphs=!!bool x.*not a boolean: 'x'"):
        parse_overrides(["cuda_graphs=!!bool x"])


def _quadratic(B=3, n=2):
    seg = torch.arange(B).repeat_interleave(n)
    c = torch.arange(B * n, dtype=torch.float64)

    def fun(X):
        d = X - c
        return torch.zeros(X.shape[0], B, dtype=X.dtype).index_add_(1, seg, d * d), 2 * d
    return fun, torch.zeros(B * n, dtype=torch.float64), seg, B, c


@pytest.mark.parametrize("kw", [dict(check_every=0), dict(max_backtracks=0), dict(check_every=-2)])
def test_lbfgs_refuses_a_count_below_one(kw):
    # check_every=0 divided by zero once the fixed rounds began; max_backtracks=0 failed in argmax
    fun, x0, seg, B, _ = _quadratic()
    with pytest.raises(ValueError, match="batched_lbfgs: max_backtracks and check_every must be at least 1"):
        batched_lbfgs(fun, x0, seg, B, with_grad=True, stacked=True, **kw)


def test_lbfgs_at_the_smallest_counts_still_solves():
    fun, x0, seg, B, c = _quadratic()
    x, f, it = batched_lbfgs(fun, x0, seg, B, with_grad=True, stacked=True, check_every=1, max_backtracks=1,
                             trials=5, iterations=30, history=1)
    torch.testing.assert_close(x, c, rtol=0, atol=1e-9)
    assert (f < 1e-15).all() and (it >= 1).all()


def test_the_snap_is_left_out_past_the_deadline(monkeypatch):
    # band_snap's neighbour search read no deadline: a small max_seconds was overrun several-fold
    import math
    import torch_isc
    from torch_isc.pipeline import band
    called = []
    monkeypatch.setattr(band, "snap_crossings", lambda *a, **k: called.append(1))
    t = torch.linspace(0, 2 * math.pi, 401, dtype=torch.float64)[:-1]
    circle = torch.stack([t.cos(), t.sin()], 1)
    r = torch_isc.reconstruct(circle, torch_isc.ReconstructConfig().replace(band_snap=True, max_seconds=1e-9))
    assert called == [] and r.limit == "max_seconds"


def test_skip_counts_a_cut_only_past_the_deadline():
    import time
    from torch_isc.pipeline import budget
    assert not budget.skip()                          # no deadline
    with budget.deadline(60.0):
        assert not budget.skip() and budget.cuts() == 0
    with budget.deadline(1e-9, start=time.perf_counter() - 1.0):
        assert budget.skip() and budget.cuts() == 1
