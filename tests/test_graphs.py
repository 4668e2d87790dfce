"""CUDA graph replay of the inner loops (pipeline/graphs.py, ``run.cuda_graphs``).

On the CPU the replay is emulated: the recorded step runs eagerly at each replay, under a guard
that refuses host reads. So these tests check what can be checked without a GPU: the replay
path (fixed state buffers, blocks of rounds, re-recording after each compaction of the working
set) gives the eager loops' bits, and the steps it records would be accepted by a capture.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torch_isc
from torch_isc.pipeline import graphs
from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.pipeline.optim import batched_lbfgs


def _shapes():
    rng = np.random.default_rng(3)
    t = rng.uniform(0, 2 * math.pi, 400)
    circle = np.stack([np.cos(t), np.sin(t)], 1) + rng.normal(0, 0.01, (400, 2))
    u = rng.uniform(0, 2 * math.pi, 500)
    r = np.where(np.arange(500) % 2 == 0, 1.0, 0.55)
    annulus = np.stack([r * np.cos(u), r * np.sin(u)], 1)
    v = rng.uniform(0, 2 * math.pi, 300)
    flower = (1 + 0.3 * np.cos(5 * v))[:, None] * np.stack([np.cos(v), np.sin(v)], 1)
    two = np.concatenate([circle[:200] * 0.4 - 0.6, circle[200:] * 0.4 + 0.6])
    return [torch.tensor(p, dtype=torch.float32) for p in (circle, annulus, flower, two)]


def _close(a, b, frac: float) -> None:
    """The same curves per item, each pair within ``frac`` of the item's diagonal (symmetric
    Hausdorff between their vertices)."""
    assert [x.num_components for x in a] == [x.num_components for x in b]
    for x, y in zip(a, b):
        diag = float((x.points.amax(0) - x.points.amin(0)).norm())
        for p, q in zip(x.polylines, y.polylines):
            d = torch.cdist(p["points"].double(), q["points"].double())
            assert max(d.min(0).values.max(), d.min(1).values.max()) < frac * diag


def _segments(B: int = 12, n: int = 5):
    """``B`` segments of ``n`` entries: ``seg``, a scale per segment over four decades (so the
    segments converge at different rounds) and a random centre per entry."""
    torch.manual_seed(1)
    seg = torch.arange(B).repeat_interleave(n)
    return B, n, seg, torch.logspace(-2, 2, B, dtype=torch.float64), torch.randn(B * n, dtype=torch.float64)


def _same(a, b):
    assert [len(x.polylines) for x in a] == [len(x.polylines) for x in b]
    for x, y in zip(a, b):
        assert len(x.stats) == len(y.stats)
        for p, q in zip(x.polylines, y.polylines):
            assert p["closed"] == q["closed"] and torch.equal(p["points"], q["points"])


@pytest.fixture
def recorded(monkeypatch):
    """The names of the steps recorded (``_sweep_classes``: the annealer's; ``step``: a block of
    L-BFGS rounds) and how many replays each had."""
    seen = []
    capture = graphs.capture

    def counting(step, device, kind):
        g = capture(step, device, kind)
        entry = [getattr(step, "func", step).__name__, 0]
        seen.append(entry)
        replay = g.replay

        def counted():
            entry[1] += 1
            replay()
        g.replay = counted
        return g
    monkeypatch.setattr(graphs, "capture", counting)
    return seen


def test_replayed_rounds_give_the_eager_bits(recorded):
    shapes = _shapes()
    eager = torch_isc.reconstruct_batch(shapes)
    assert not recorded                              # off by default on the CPU
    with graphs.use("emulate"):
        replayed = torch_isc.reconstruct_batch(shapes)
    names = {n for n, _ in recorded}
    # the annealer's sweeps (cooling, zero temperature), the fits' rounds, the region
    # distances' relaxations (simplify.py)
    assert names == {"_sweep_from_row", "_sweep_classes", "step", "iteration"}
    # replayed many times each, on average: recording is not the whole of it
    for name in names:
        caps = [k for n, k in recorded if n == name]
        assert sum(caps) > 2 * len(caps)
    _same(eager, replayed)


def test_fits_from_a_zero_history_replay_to_their_eager_bits(recorded, monkeypatch):
    # the fixed-shape rounds from the first (as on a GPU): eager and replayed agree bit for bit,
    # and both agree with the CPU's lockstep fill in topology and to rounding amplified
    from torch_isc.pipeline import optim
    shapes = _shapes()
    lockstep = torch_isc.reconstruct_batch(shapes)
    monkeypatch.setitem(optim._LOCKSTEP_FILL, "cpu", False)
    eager = torch_isc.reconstruct_batch(shapes)
    with graphs.use("emulate"):
        replayed = torch_isc.reconstruct_batch(shapes)
    _same(eager, replayed)
    _close(eager, lockstep, 0.05)


def test_lbfgs_from_a_zero_history_follows_the_lockstep_trajectory(monkeypatch):
    from torch_isc.pipeline import optim
    B, n, seg, scale, c = _segments()

    def fun(X):                                       # a non-convex term: curvature pairs get skipped
        d = X - c
        e = scale[seg] * d * d + d ** 4 + 0.3 * torch.sin(3 * X)
        g = 2 * scale[seg] * d + 4 * d ** 3 + 0.9 * torch.cos(3 * X)
        return torch.zeros(X.shape[0], B, dtype=X.dtype).index_add_(1, seg, e), g
    x0 = torch.zeros(B * n, dtype=torch.float64)
    kw = dict(iterations=40, history=6, with_grad=True, stacked=True, trials=2, check_every=3)
    a = batched_lbfgs(fun, x0, seg, B, **kw)
    monkeypatch.setitem(optim._LOCKSTEP_FILL, "cpu", False)
    b = batched_lbfgs(fun, x0, seg, B, **kw)
    assert torch.equal(a[2], b[2]) and int(a[2].max()) > 6          # past the history's length
    torch.testing.assert_close(b[0], a[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(b[1], a[1], rtol=0, atol=1e-12)


def test_a_refused_recording_leaves_the_loops_eager(monkeypatch):
    # as where the driver refuses a capture: capture() returns None, the loops run eagerly
    # (the same bits) and stop asking after their first refusal
    asked = []

    def refuse(step, device, kind):
        asked.append(getattr(step, "func", step).__name__)
        return None
    shapes = _shapes()[:2]
    eager = torch_isc.reconstruct_batch(shapes)
    monkeypatch.setattr(graphs, "capture", refuse)
    with graphs.use("emulate"):
        refused = torch_isc.reconstruct_batch(shapes)
    _same(eager, refused)
    assert asked and len(asked) < 40                  # one ask per loop call at most, not per round


def test_the_config_switch_turns_replay_off(recorded):
    cfg = ReconstructConfig().replace(cuda_graphs=False)
    with graphs.use("emulate"):
        torch_isc.reconstruct_batch(_shapes()[:1], cfg)
    assert recorded == []


def test_lbfgs_rounds_with_compaction_match_the_eager_loop(recorded):
    # per segment a convex quartic with its own scale: the segments stop at different rounds,
    # so the working set is compacted (and the round re-recorded) several times
    B, n, seg, scale, c = _segments()

    def make(keep):
        k = int(keep.sum())                           # read once, outside the rounds
        sc, cc, sg = scale[keep], c[keep.repeat_interleave(n)], torch.arange(k).repeat_interleave(n)

        def fun(X):
            d = X - cc
            e = sc[sg] * d * d + d ** 4
            g = 2 * sc[sg] * d + 4 * d ** 3
            return torch.zeros(X.shape[0], k, dtype=X.dtype).index_add_(1, sg, e), g

        def restrict(items):
            idx = torch.nonzero(keep).squeeze(1)[items]
            k2 = torch.zeros(B, dtype=torch.bool)
            k2[idx] = True
            return make(k2)
        return fun, restrict

    fun, restrict = make(torch.ones(B, dtype=torch.bool))
    x0 = torch.zeros(B * n, dtype=torch.float64)
    kw = dict(iterations=80, history=4, with_grad=True, stacked=True, trials=2, check_every=3, restrict=restrict)
    a = batched_lbfgs(fun, x0, seg, B, **kw)
    with graphs.use("emulate"):
        b = batched_lbfgs(fun, x0, seg, B, **kw)
    assert len(recorded) >= 2                         # re-recorded after a compaction
    for u, v in zip(a, b):
        assert torch.equal(u, v)
    assert int(a[2].min()) < int(a[2].max())          # the segments did stop apart


def test_iterate_replays_to_the_loop_bits(recorded):
    torch.manual_seed(2)
    w = torch.rand(50)
    a, b = torch.randint(0, 30, (50,)), torch.randint(0, 30, (50,))

    def relax(d):                                     # shortest paths by rounds of edge relaxations
        return d.scatter_reduce(0, a, d[b] + w, "amin").scatter_reduce(0, b, d[a] + w, "amin")
    d0 = torch.full((30,), float("inf"))
    d0[0] = 0.0
    want = d0
    for _ in range(7):
        want = relax(want)
    assert graphs.iterate(relax, d0, 7, "test") is not d0 and not recorded       # eager: off
    with graphs.use("emulate"):
        got = graphs.iterate(relax, d0, 7, "test")
    assert recorded == [["iteration", 7]]
    assert torch.equal(got, want) and torch.isinf(d0[1:]).all()          # the start untouched
    assert torch.isfinite(want).sum() > 1


def test_a_step_that_reads_the_host_is_refused():
    x = torch.ones(3)

    def step():
        if bool(x.sum() > 0):                         # a host read: no graph can record it
            x.add_(1)
    with graphs.use("emulate"):
        g = graphs.capture(step, x.device, "test")
        with pytest.raises(graphs.CaptureError, match="reads the device on the host"):
            g.replay()


def test_a_failed_kind_stays_eager_alone(monkeypatch):
    cuda = torch.device("cuda")
    monkeypatch.setattr(graphs, "_FAILED", {"anneal": "RuntimeError: refused"})
    with graphs.use(True):
        assert not graphs.active(cuda, "anneal")
        assert graphs.active(cuda, "fit")             # the fits' graphs keep replaying


def test_modes_nest():
    cpu = torch.device("cpu")
    assert not graphs.active(cpu, "fit")
    with graphs.use(True):
        assert not graphs.active(cpu, "fit")          # a real capture needs CUDA
    with graphs.use("emulate"):
        assert graphs.active(cpu, "fit")
        with graphs.use(True):                        # the loop's config inside a test's emulation
            assert graphs.active(cpu, "fit")
        with graphs.use(False):                       # the config's off wins
            assert not graphs.active(cpu, "fit")
    cuda = torch.device("cuda")                       # a device object: no GPU needed to ask
    with graphs.use(True):
        assert graphs.active(cuda, "fit") and graphs.active(cuda, "anneal")
    with pytest.raises(ValueError, match="on, off or emulate"):
        with graphs.use("sometimes"):
            pass


def test_no_collection_holds_the_collector_off_and_restores_it():
    import gc
    assert gc.isenabled()
    with graphs.no_collection():
        assert not gc.isenabled()
    assert gc.isenabled()
    with pytest.raises(KeyError):
        with graphs.no_collection():
            raise KeyError("inside")
    assert gc.isenabled()
    gc.disable()
    try:
        with graphs.no_collection():
            pass
        assert not gc.isenabled()                     # off before: left off
    finally:
        gc.enable()
    # two threads' recordings overlapping: the collector stays off until the last one ends
    import threading
    inside, release = threading.Event(), threading.Event()

    def other():
        with graphs.no_collection():
            inside.set()
            release.wait(10)
    t = threading.Thread(target=other)
    with graphs.no_collection():
        t.start()
        inside.wait(10)
    assert not gc.isenabled()                         # the other thread still records
    release.set()
    t.join(10)
    assert gc.isenabled()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_recording_survives_dropped_graphs_in_cycles(monkeypatch):
    """A graph dropped in a reference cycle is destroyed by the cycle collector; a collection
    inside a recording (many Python objects made by its step) destroyed such graphs there and
    invalidated the recording on an H200."""
    import gc
    monkeypatch.setattr(graphs, "_FAILED", {})
    x = torch.zeros(64, device="cuda")
    with graphs.use(True):
        for _ in range(4):                            # cyclic garbage that holds graphs
            cyc = {"graph": graphs.capture(lambda: x.add_(1), x.device, "test")}
            cyc["self"] = cyc
        del cyc
        old = gc.get_threshold()
        gc.set_threshold(1, 1, 1)                     # collect at almost every allocation
        try:
            def step():
                junk = [[i] for i in range(2000)]     # container objects: collections happen
                x.mul_(2).add_(len(junk) > 0)
            g = graphs.capture(step, x.device, "test")
        finally:
            gc.set_threshold(*old)
    assert g is not None and not graphs._FAILED, graphs._FAILED
    x.zero_()
    g.replay()
    g.replay()
    torch.cuda.synchronize()
    assert torch.equal(x, torch.full_like(x, 3.0))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_graphs_on_cuda_agree_with_eager():
    shapes = [p.cuda() for p in _shapes()]
    on = torch_isc.reconstruct_batch(shapes)
    off = torch_isc.reconstruct_batch(shapes, ReconstructConfig().replace(cuda_graphs=False))
    assert not graphs._FAILED, graphs._FAILED
    # the same kernels; CUDA's atomic adds still sum in any order, run to run (two eager runs
    # of the hard mix differed by up to 2.9% of the diagonal, docs/device_runs.md)
    _close(on, off, 0.1)


def test_a_compiled_objective_is_not_recorded(recorded, monkeypatch):
    # compile=true: the fits' rounds stay eager (a recompilation cannot run inside a capture),
    # the annealer's sweeps still replay; the compiled objective stubbed by the eager one
    from torch_isc.pipeline import values
    monkeypatch.setattr(values, "_compiled_value_and_grad", lambda: values.GeometryObjective.value_and_grad)
    cfg = ReconstructConfig().replace(compile=True)
    with graphs.use("emulate"):
        torch_isc.reconstruct_batch(_shapes()[:1], cfg)
    names = {n for n, _ in recorded}
    assert "_sweep_from_row" in names and "step" not in names
