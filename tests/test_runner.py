"""The batch runner (torch_isc.runner): failure isolation, skipping finished inputs, records in
input order, one progress call per input, bad arguments rejected before any work."""
from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

import torch_isc
from torch_isc import load_config
from torch_isc.runner import ImageOptions, RunError, expand_inputs, run_inputs, unique_stems


def _listdir(d):
    """The outputs in ``d`` without the manifests (tested in test_robustness_fuzz)."""
    return [f for f in os.listdir(d) if not f.endswith(".manifest.json")]

CONFIG = load_config(overrides={"max_level": 3})


def _ring(path, r=1.0, n=120, seed=0):
    t = np.random.default_rng(seed).permutation(np.linspace(0, 2 * np.pi, n, endpoint=False))
    np.savetxt(path, np.stack([r * np.cos(t), r * np.sin(t)], 1))
    return str(path)


def _disc_png(path):
    m = np.zeros((40, 40), np.uint8)
    cv2.circle(m, (19, 19), 12, 255, -1)
    cv2.imwrite(str(path), m)
    return str(path)


@pytest.fixture
def mixed(tmp_path):
    """A folder of good and broken inputs; sorted by name: a_ring, b_broken, c_disc, d_corrupt, e_ring."""
    d = tmp_path / "in"
    d.mkdir()
    _ring(d / "a_ring.xy")
    (d / "b_broken.xy").write_text("1 2\n3 x\n")
    _disc_png(d / "c_disc.png")
    (d / "d_corrupt.png").write_bytes(b"not a png")
    _ring(d / "e_ring.csv", r=2.0, seed=1)
    return d


def _run(src, out, **kw):
    calls = []
    rep = run_inputs([src], CONFIG, out, formats=["json", "svg"], image_formats=["json", "contours.npz"],
                     progress=calls.append, **kw)
    return rep, calls


def test_a_broken_input_loses_no_other_and_records_come_in_input_order(mixed, tmp_path):
    out = tmp_path / "out"
    rep, calls = _run(mixed, out, batch_size=2)
    assert [r.stem for r in rep.records] == ["a_ring", "b_broken", "c_disc", "d_corrupt", "e_ring"]
    assert [r.status for r in rep.records] == ["done", "failed", "done", "failed", "done"]
    assert rep.failed == 2 and rep.batches == 2
    bad, corrupt = rep.records[1], rep.records[3]
    assert bad.error == f"{mixed / 'b_broken.xy'}: line 2: non-numeric value 'x'"
    assert corrupt.error == f"{mixed / 'd_corrupt.png'}: not a readable image (unknown format, truncated or corrupt)"
    assert all("\n" not in r.error for r in (bad, corrupt)) and bad.outputs == [] and bad.summary is None
    # the others are written: point files their formats, the image its formats (no overlay unless asked)
    assert sorted(_listdir(out)) == ["a_ring.json", "a_ring.svg", "c_disc.contours.npz", "c_disc.json",
                                       "e_ring.json", "e_ring.svg"]
    assert [p.name for p in rep.records[2].outputs] == ["c_disc.json", "c_disc.contours.npz"]
    s = rep.records[0].summary
    assert (s["num_closed"], s["num_open"]) == (1, 0) and s["levels"] >= 1 and s["seconds"] >= 0
    # one progress call per input, each with its final status
    assert sorted(r.stem for r in calls) == sorted(r.stem for r in rep.records)
    assert all(r.status in ("done", "failed") for r in calls)


def test_finished_inputs_are_skipped_and_overwrite_redoes_them(mixed, tmp_path):
    out = tmp_path / "out"
    _run(mixed, out)
    before = {f: (out / f).read_bytes() for f in _listdir(out)}
    (out / "e_ring.svg").unlink()                       # an incomplete input is redone
    rep, _ = _run(mixed, out)
    assert [r.status for r in rep.records] == ["skipped", "failed", "skipped", "failed", "done"]
    assert rep.batches == 1 and {f: (out / f).read_bytes() for f in _listdir(out)} == before
    rep, _ = _run(mixed, out, overwrite=True)
    assert [r.status for r in rep.records] == ["done", "failed", "done", "failed", "done"]


def test_a_solve_that_fails_is_isolated(mixed, tmp_path, monkeypatch):
    real = torch_isc.reconstruct

    def sink_batch(points, config=None, names=None):
        raise RuntimeError("the batch sank")

    def picky(points, config=None, name=None):
        if name == "e_ring":
            raise RuntimeError("boom\nsecond line")
        return real(points, config, name=name)

    monkeypatch.setattr(torch_isc, "reconstruct_batch", sink_batch)
    monkeypatch.setattr(torch_isc, "reconstruct", picky)
    rep = run_inputs([mixed / "a_ring.xy", mixed / "e_ring.csv"], CONFIG, tmp_path / "out", formats=["json"])
    assert [r.status for r in rep.records] == ["done", "failed"]
    assert rep.records[1].error == f"{mixed / 'e_ring.csv'}: reconstruction failed (RuntimeError: boom)"
    assert "RuntimeError" in rep.records[1].traceback
    assert _listdir(tmp_path / "out") == ["a_ring.json"]


def test_edges_mode_and_mixed_configs(mixed, tmp_path):
    rep = run_inputs([mixed / "c_disc.png", mixed / "a_ring.xy"], CONFIG, tmp_path / "out", formats=["json"],
                     image_formats=["json"], image_options=ImageOptions(mode="edges"))
    assert [r.status for r in rep.records] == ["done", "done"]
    assert rep.records[0].summary["num_closed"] == 1


def test_bad_arguments_are_rejected_before_any_work(mixed, tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RunError, match=r"batch size must be an integer in \[1, "):
        run_inputs([mixed], CONFIG, out, batch_size=0)
    with pytest.raises(RunError, match="unknown output format 'obj'"):
        run_inputs([mixed], CONFIG, out, formats=["json", "obj"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunError, match="folder has no point or image file"):
        run_inputs([tmp_path / "empty"], CONFIG, out)
    assert not out.exists()


def test_expand_inputs_and_unique_stems(mixed, tmp_path):
    (mixed / "notes.md").write_text("not an input")
    files = expand_inputs([mixed, tmp_path / "missing.xy"])
    assert [os.path.basename(f) for f in files] == ["a_ring.xy", "b_broken.xy", "c_disc.png", "d_corrupt.png",
                                                    "e_ring.csv", "missing.xy"]
    notes = []
    assert unique_stems(["a/x.xy", "b/x.png", "x_2.xy"], notes.append) == ["x_xy", "x_png", "x_2"]
    assert notes == ["note: another input is also named 'x': a/x.xy is written as 'x_xy'",
                     "note: another input is also named 'x': b/x.png is written as 'x_png'"]
    assert unique_stems(["b/x.png", "x_2.xy", "a/x.xy"]) == ["x_png", "x_2", "x_xy"]     # order-free
