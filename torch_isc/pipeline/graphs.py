"""CUDA graphs for the fixed-shape inner loops (``run.cuda_graphs``).

On a GPU the solve is bound by the host: a round of the L-BFGS or a sweep of the annealer is
dozens of small kernels, each launched from Python at about 10 us. Those loops have fixed
shapes and no host read between their checks, so one round can be recorded once as a CUDA
graph and replayed: one launch for the round's kernels. The arithmetic is the same kernels on
the same tensors, so a replay gives the bits the eager round would.

A step recorded here must read and write only tensors that outlive its graph (the loop's state,
in place) and must not read the device on the host. A tensor it allocates lives in the graph's
own memory pool and must not escape it. Where a capture fails (an op the driver refuses), a
warning says so once and the loops of that kind (``fit``, ``anneal``, ...) run eagerly from then
on; the other kinds keep replaying.

``emulate`` (tests) records nothing: :func:`capture` returns a replayer that runs the step
eagerly, under a guard that raises on every host read of the device, so a CPU test checks both
that the loops give the eager bits through the replay path and that a step could be captured.
"""
from __future__ import annotations

import contextlib
import contextvars
import gc
import threading
import warnings
from typing import Callable

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from torch_isc.pipeline import budget

__all__ = ["use", "active", "capture", "iterate", "no_collection", "CaptureError"]

_MODE: contextvars.ContextVar[str] = contextvars.ContextVar("torch_isc_graphs", default="off")
_FAILED: dict = {}                          # kind -> why its capture failed (text): that kind eager from then on
_STREAMS: dict = {}                         # (device index, thread) -> the side stream captures run on
_GC_LOCK = threading.Lock()
_GC_HOLDERS = [0, True]                     # blocks inside no_collection, whether the collector was on before


class CaptureError(RuntimeError):
    """A step read the device on the host, which a CUDA graph cannot record."""


@contextlib.contextmanager
def use(mode):
    """Within the block the inner loops replay graphs: ``True`` / ``"on"`` on CUDA devices,
    ``"emulate"`` on any device (tests), ``False`` / ``"off"`` never. ``"on"`` inside an
    ``"emulate"`` block stays ``"emulate"``."""
    mode = {True: "on", False: "off"}.get(mode, mode)
    if mode not in ("on", "off", "emulate"):
        raise ValueError(f"graphs.use: mode must be on, off or emulate, not {mode!r}")
    if mode == "on" and _MODE.get() == "emulate":
        mode = "emulate"
    token = _MODE.set(mode)
    try:
        yield
    finally:
        _MODE.reset(token)


def active(device: torch.device, kind: str) -> bool:
    """Whether the loops of ``kind`` on ``device`` should record and replay their rounds."""
    mode = _MODE.get()
    if mode == "emulate":
        return True
    return mode == "on" and device.type == "cuda" and kind not in _FAILED


_HOST_READS = {torch.ops.aten._local_scalar_dense.default, torch.ops.aten.nonzero.default,
               torch.ops.aten.masked_select.default, torch.ops.aten.bincount.default,
               torch.ops.aten.equal.default, torch.ops.aten.unique_consecutive.default,
               torch.ops.aten._unique2.default}


class _NoHostReads(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in _HOST_READS:
            raise CaptureError(f"a recorded step reads the device on the host ({func})")
        return func(*args, **(kwargs or {}))


class _Emulated:
    """What :func:`capture` gives under ``emulate``: the step run eagerly at each replay, host
    reads refused."""

    def __init__(self, step: Callable[[], None]):
        self.step = step

    def replay(self) -> None:
        with _NoHostReads():
            self.step()


@contextlib.contextmanager
def no_collection():
    """Python's cycle collector off within the block (as it was after it). A collection during
    a recording could free a dropped graph, and destroying a graph while the thread records
    another is an unsafe call that invalidates the recording (seen on an H200: the fit and
    anneal recordings failed that way, with "operation not permitted when stream is
    capturing (function reset)")."""
    with _GC_LOCK:                          # threads recording at once: the last one out restores it
        if _GC_HOLDERS[0] == 0:
            _GC_HOLDERS[1] = gc.isenabled()
            gc.disable()
        _GC_HOLDERS[0] += 1
    try:
        yield
    finally:
        with _GC_LOCK:
            _GC_HOLDERS[0] -= 1
            if _GC_HOLDERS[0] == 0 and _GC_HOLDERS[1]:
                gc.enable()


def capture(step: Callable[[], None], device: torch.device, kind: str):
    """Record ``step()`` (in-place updates of tensors that outlive the graph) as a graph on
    ``device``; returns an object whose ``replay()`` runs it, or None where recording failed
    (then the caller runs ``step`` eagerly, and :func:`active` is False for ``kind`` from then
    on). Recording runs nothing: the state is untouched until the first replay."""
    if _MODE.get() == "emulate":
        return _Emulated(step)
    key = (device.index, threading.get_ident())
    stream = _STREAMS.get(key)
    if stream is None:
        stream = _STREAMS[key] = torch.cuda.Stream(device=device)
        # cuBLAS's handle and workspace for the side stream, made outside any graph's pool
        with torch.cuda.stream(stream):
            e = torch.eye(2, dtype=torch.float64, device=device).expand(3, 2, 2)
            torch.linalg.solve_triangular(e, e @ e, upper=True)
        torch.cuda.current_stream(device).wait_stream(stream)
    # each graph has its own memory pool (the default): a dropped graph's pool is held by the
    # allocator until an allocation needs it back (then freed). Sharing one pool between a
    # loop's graphs would bound that, but a pool whose graphs have all been dropped cannot be
    # recorded into again by its handle, and this path has run on a GPU as it is
    g = torch.cuda.CUDAGraph()
    # the side stream waits for what is queued; torch.cuda.graph would also empty the
    # allocator's cache at every capture: not wanted here
    stream.wait_stream(torch.cuda.current_stream(device))
    why = None
    try:
        with no_collection(), torch.cuda.stream(stream):
            g.capture_begin(capture_error_mode="thread_local")
            try:
                step()
            finally:
                g.capture_end()
    except Exception as exc:                 # an op the driver cannot record: eager from now on
        why = f"{type(exc).__name__}: {exc}"   # text: the traceback would hold the loop's tensors
    if why is not None:
        _FAILED[kind] = why
        warnings.warn(f"recording a CUDA graph of the {kind} loop failed ({why}); that loop runs eagerly",
                      RuntimeWarning, stacklevel=2)
        return None
    torch.cuda.current_stream(device).wait_stream(stream)
    return g


def iterate(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, rounds: int, kind: str) -> torch.Tensor:
    """``x`` after ``rounds`` applications of ``fn`` (a fixed-shape map with no host read),
    rounds counted by :func:`budget.rounds`; where :func:`active`, one application is recorded
    and replayed (the same bits)."""
    rounds = int(rounds)
    if rounds > 2 and active(x.device, kind):
        static = x.clone()

        def iteration():
            static.copy_(fn(static))
        g = capture(iteration, x.device, kind)
        if g is not None:
            for _ in budget.rounds(rounds):
                g.replay()
            return static
    for _ in budget.rounds(rounds):
        x = fn(x)
    return x
