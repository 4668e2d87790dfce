"""torch_isc.dataset: inputs (folders, globs, manifests), the local and Ray engines giving the same
bytes, failures isolated as rows, reruns skipping, the Parquet results table; the CLI over it.

The Ray tests start one local cluster for the module (2 CPUs, no dashboard) and shut it down; a
watchdog fails them instead of letting them hang. They are skipped where Ray is not installed
(``pip install -e '.[test,ray]'`` to run them)."""
from __future__ import annotations

import os
import signal
import sys

import cv2
import numpy as np
import pytest

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

from torch_isc import load_config  # noqa: E402
from torch_isc.dataset import read_manifest, reconstruct_dataset, resolve_inputs  # noqa: E402
from torch_isc.runner import RunError  # noqa: E402

CONFIG = load_config(overrides={"max_level": 3})
FORMATS = ["json", "npz", "svg", "geojson"]
IMAGE_FORMATS = ["json", "npz", "contours.npz", "geojson"]


def _ring(path, r=1.0, n=120, seed=0):
    t = np.random.default_rng(seed).permutation(np.linspace(0, 2 * np.pi, n, endpoint=False))
    np.savetxt(path, np.stack([r * np.cos(t), r * np.sin(t)], 1))


def _mask(path, holes=False, r=12):
    m = np.zeros((40, 40), np.uint8)
    cv2.circle(m, (19, 19), r, 255, -1)
    if holes:
        cv2.circle(m, (19, 19), 5, 0, -1)
    cv2.imwrite(str(path), m)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """Points, masks and broken files; sorted: a_ring, b_broken, c_disc, d_corrupt, e_ring, f_annulus,
    g_empty, h_ring."""
    d = tmp_path_factory.mktemp("in")
    _ring(d / "a_ring.xy")
    (d / "b_broken.xy").write_text("1 2\n3 x\n")
    _mask(d / "c_disc.png")
    (d / "d_corrupt.png").write_bytes(b"not a png")
    _ring(d / "e_ring.csv", r=2.0, seed=1)
    _mask(d / "f_annulus.png", holes=True, r=15)
    (d / "g_empty.png").write_bytes(b"")
    _ring(d / "h_ring.xy", r=0.5, n=90, seed=2)
    return d


STATUS = ["done", "failed", "done", "failed", "done", "done", "failed", "done"]


def _npz_without_times(path):
    """An .npz output's arrays and metadata, less the per-level wall times its stats carry
    (the one part of the outputs that is not deterministic)."""
    import json

    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k].tobytes() + str(z[k].dtype).encode() for k in z.files if k != "metadata"}
        meta = json.loads(str(z["metadata"])) if "metadata" in z.files else {}
    for lv in meta.get("stats", []):
        for k in [k for k in lv if k.endswith("seconds")]:
            lv.pop(k)
    d["metadata"] = json.dumps(meta, sort_keys=True)
    return d


def _manifest_without_npz_hash(path):
    """A ``<stem>.manifest.json``, less the hash and size of the .npz (which holds wall times)."""
    import json

    m = json.loads(path.read_text())
    for f in m.get("files", []):
        if f["name"].endswith(".npz") and not f["name"].endswith("contours.npz"):
            f.pop("sha256", None), f.pop("bytes", None)
    return json.dumps(m, sort_keys=True)


def _files(folder):
    """Every output file's bytes (an .npz: its content less wall times; a manifest: less the
    .npz's hash)."""
    def content(f):
        if f.endswith(".npz") and not f.endswith("contours.npz"):
            return _npz_without_times(folder / f)
        if f.endswith(".manifest.json"):
            return _manifest_without_npz_hash(folder / f)
        return (folder / f).read_bytes()
    return {f: content(f) for f in sorted(os.listdir(folder))}


def _run(src, out, engine="local", **kw):
    calls = []
    rep = reconstruct_dataset([src], out, CONFIG, engine, formats=FORMATS, image_formats=IMAGE_FORMATS,
                              progress=calls.append, **kw)
    return rep, calls


def _table_without_times(path):
    t = pq.read_table(path)
    return t.drop_columns(["seconds"])


@pytest.fixture(scope="module")
def local_run(mixed, tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    rep, calls = _run(mixed, out / "o", batch_size=3, table=out / "t.parquet")
    return out, rep, calls


# ============================================================================ inputs
def test_inputs_folders_globs_and_manifests(mixed, tmp_path):
    files = sorted(str(mixed / f) for f in os.listdir(mixed))
    assert resolve_inputs([mixed]) == files
    assert resolve_inputs([str(mixed / "*.xy")]) == [str(mixed / f) for f in ("a_ring.xy", "b_broken.xy", "h_ring.xy")]
    (tmp_path / "deep" / "er").mkdir(parents=True)
    _ring(tmp_path / "deep" / "er" / "z.xy")
    assert resolve_inputs([str(tmp_path / "**" / "*.xy")]) == [str(tmp_path / "deep" / "er" / "z.xy")]
    with pytest.raises(RunError, match="no file matches"):
        resolve_inputs([str(mixed / "*.nothing")])
    # a text manifest: paths relative to its folder, comments and blank lines skipped
    (tmp_path / "list.txt").write_text(f"# two inputs\n{mixed / 'c_disc.png'}\n\n{mixed.name}/a_ring.xy\n")
    (tmp_path / "list.txt").rename(mixed.parent / "list.txt")
    got = read_manifest(mixed.parent / "list.txt")
    assert [os.path.realpath(p) for p in got] == [str(mixed / "c_disc.png"), str(mixed / "a_ring.xy")]
    # CSV and Parquet columns
    (tmp_path / "m.csv").write_text(f"id,file\n1,{mixed / 'a_ring.xy'}\n2,{mixed / 'e_ring.csv'}\n")
    assert read_manifest(tmp_path / "m.csv", "file") == [str(mixed / "a_ring.xy"), str(mixed / "e_ring.csv")]
    with pytest.raises(RunError, match="no column 'path'"):
        read_manifest(tmp_path / "m.csv")
    pq.write_table(pa.table({"path": [str(mixed / "h_ring.xy")], "file": ["x"]}), tmp_path / "m.parquet")
    assert resolve_inputs([tmp_path / "m.parquet"]) == [str(mixed / "h_ring.xy")]
    assert resolve_inputs([mixed / "h_ring.xy"], manifest=tmp_path / "m.csv", manifest_column="file") \
        == [str(mixed / "h_ring.xy"), str(mixed / "a_ring.xy"), str(mixed / "e_ring.csv")]


def test_bad_arguments_are_rejected_before_work(mixed, tmp_path):
    for kw, msg in [({"engine": "spark"}, "engine must be"), ({"batch_size": 0}, "batch size"),
                    ({"formats": ["obj"]}, "unknown output format")]:
        with pytest.raises(RunError, match=msg):
            reconstruct_dataset([mixed], tmp_path / "o", CONFIG, **kw)
    assert not (tmp_path / "o").exists()


# ============================================================================ local engine and table
def test_local_engine_isolates_failures_and_writes_the_table(local_run, mixed):
    out, rep, calls = local_run
    assert [r.status for r in rep.records] == STATUS and [r.stem for r in calls] == [r.stem for r in rep.records]
    assert rep.counts == {"done": 5, "skipped": 0, "failed": 3} and rep.batches == 3
    assert rep.records[1].error == f"{mixed / 'b_broken.xy'}: line 2: non-numeric value 'x'"
    t = pq.read_table(out / "t.parquet")
    assert t.num_rows == 8 and t.column("index").to_pylist() == list(range(8))
    rows = t.to_pylist()
    assert [r["status"] for r in rows] == STATUS and [r["stem"] for r in rows] == [r.stem for r in rep.records]
    assert rows[1]["error"] == rep.records[1].error and rows[1]["polylines"] is None and rows[1]["num_curves"] is None
    ann = rows[5]
    assert ann["num_curves"] == 2 and ann["closed"] == [True, True] and ann["converged"] in (True, False)
    assert ann["levels"] is not None and ann["seconds"] > 0          # (a mask solved on its pixel grid: 0 levels)
    # the table's polylines are the JSON's, float for float (float32 numbers, as a mask's curves
    # are, are written with 9 digits: the same float32, within 5e-9 relative as float64)
    import json

    for r in rows:
        if r["status"] == "done":
            d = json.loads((out / "o" / f"{r['stem']}.json").read_text())
            assert len(r["polylines"]) == len(d["polylines"]), r["stem"]
            for a, b in zip(r["polylines"], d["polylines"]):
                a, b = np.array(a, np.float64), np.array(b["points"], np.float64)
                assert a.shape == b.shape and np.array_equal(a.astype(np.float32), b.astype(np.float32)), r["stem"]
                assert np.allclose(a, b, rtol=1e-8, atol=0), r["stem"]
            assert r["closed"] == [p["closed"] for p in d["polylines"]]
    # queryable without opening a file per input
    import pyarrow.compute as pc

    done = t.filter(pc.equal(t["status"], "done"))
    assert pc.sum(done["num_curves"]).as_py() == 1 + 1 + 1 + 2 + 1


def test_rerun_skips_and_rebuilds_the_table(local_run, mixed):
    out, rep, _ = local_run
    before = _files(out / "o")
    rep2, _ = _run(mixed, out / "o", batch_size=5, table=out / "t2.parquet")
    assert [r.status for r in rep2.records] == [s if s == "failed" else "skipped" for s in STATUS]
    assert _files(out / "o") == before
    t1, t2 = pq.read_table(out / "t.parquet").to_pylist(), pq.read_table(out / "t2.parquet").to_pylist()
    for a, b in zip(t1, t2):
        for k in ("polylines", "closed", "num_curves", "converged", "limit", "levels", "error"):
            assert a[k] == b[k], (a["stem"], k)


def test_split_does_not_change_the_bytes(local_run, mixed, tmp_path):
    out, _, _ = local_run
    rep, _ = _run(mixed, tmp_path / "o", batch_size=1, table=tmp_path / "t.parquet")
    assert _files(tmp_path / "o") == _files(out / "o")
    assert _table_without_times(tmp_path / "t.parquet").equals(_table_without_times(out / "t.parquet"))


# ============================================================================ Ray
@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    pytest.importorskip("ray.data")
    if hasattr(signal, "SIGALRM"):
        def _timeout(*_):
            raise TimeoutError("Ray test ran past its 300 s watchdog")
        old = signal.signal(signal.SIGALRM, _timeout)
        signal.alarm(300)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False,
             runtime_env={"env_vars": {"PYTHONPATH": repo, "OMP_NUM_THREADS": "1"}})
    try:
        yield ray
    finally:
        ray.shutdown()
        if hasattr(signal, "SIGALRM"):
            signal.alarm(0)
            signal.signal(signal.SIGALRM, old)


def test_ray_engine_same_bytes_failures_isolated_rerun_skips(ray_cluster, local_run, mixed, tmp_path):
    out, rep_local, _ = local_run
    rep, calls = _run(mixed, tmp_path / "o", "ray", batch_size=2, actors=2, table=tmp_path / "t.parquet")
    assert [r.status for r in rep.records] == STATUS and len(calls) == 8 and rep.batches == 4
    assert [r.error for r in rep.records] == [r.error for r in rep_local.records]
    assert _files(tmp_path / "o") == _files(out / "o")                    # byte for byte
    assert _table_without_times(tmp_path / "t.parquet").equals(_table_without_times(out / "t.parquet"))
    rep2, _ = _run(mixed, tmp_path / "o", "ray", batch_size=4, actors=2)
    assert [r.status for r in rep2.records] == [s if s == "failed" else "skipped" for s in STATUS]


def test_cli_engine_ray_and_table(ray_cluster, local_run, mixed, tmp_path, capsys, monkeypatch):
    from torch_isc.cli import main

    out, _, _ = local_run
    monkeypatch.chdir(mixed.parent)                 # a relative input: the actors read it all the same
    code = main(["reconstruct", mixed.name, "--out", str(tmp_path / "o"), "--engine", "ray", "--actors", "2",
                 "--batch-size", "3", "--formats", ",".join(FORMATS), "--set", "max_level=3",
                 "--table", str(tmp_path / "t.parquet")])
    o, err = capsys.readouterr()
    assert code == 1 and "Traceback" not in err
    assert sum(line.startswith("torch-isc: error: ") for line in err.splitlines()) == 3
    assert f"torch-isc: error: {os.path.join(mixed.name, 'b_broken.xy')}: line 2: non-numeric value 'x'" in err
    assert "c_disc: 1 closed, 0 open" in o
    t = pq.read_table(tmp_path / "t.parquet")
    assert t.column("status").to_pylist() == STATUS


def test_without_json_a_skipped_row_has_no_polylines_and_records_can_be_dropped(mixed, tmp_path):
    kw = dict(formats=["svg"], image_formats=["svg"], batch_size=4, table=tmp_path / "t.parquet")
    rep = reconstruct_dataset([mixed / "a_ring.xy", mixed / "b_broken.xy"], tmp_path / "o", CONFIG, **kw)
    assert rep.counts == {"done": 1, "skipped": 0, "failed": 1}
    rep = reconstruct_dataset([mixed / "a_ring.xy", mixed / "b_broken.xy"], tmp_path / "o", CONFIG,
                              keep_records=False, **kw)
    assert rep.records == [] and rep.counts == {"done": 0, "skipped": 1, "failed": 1}
    row = pq.read_table(tmp_path / "t.parquet").to_pylist()[0]
    assert row["status"] == "skipped" and row["polylines"] is None and row["seconds"] is None
    assert sorted(os.listdir(tmp_path)) == ["o", "t.parquet"]                 # no temporary table left
