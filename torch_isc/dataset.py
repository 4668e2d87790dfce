"""Datasets: many inputs, one machine or a Ray cluster, per-input outputs and one results table.

:func:`reconstruct_dataset` is the batch runner (:func:`torch_isc.runner.run_inputs`) cut into
batches that can run anywhere:

- **inputs**: files, folders (their point and image files), globs (``"scans/**/*.png"``, sorted),
  and manifests: a ``.parquet`` input, or ``manifest=`` a text file of paths (one a line, ``#``
  comments), a CSV or Parquet file with a column of paths (``manifest_column``, default
  ``"path"``); relative paths in a manifest are relative to the manifest's folder. The list is
  resolved and given its output stems once, on the driver, in input order, so the outputs do not
  depend on how the work is split.
- **batches**: the inputs in order, ``batch_size`` at a time, each through one
  :class:`BatchReconstructor` call, which runs :func:`~torch_isc.runner.run_inputs` on it (the
  same reading, batched solve, failure isolation, skip-finished and atomic writes as the CLI) and
  returns one table row per input.
- **engines**: ``"local"`` calls the batches one after the other in this process; ``"ray"``
  makes the inputs a Ray Dataset (one block per batch) and ``map_batches`` them into a pool of
  ``actors`` :class:`BatchReconstructor` actors (each holds the configs and calls the batched
  solver on every batch it gets; ``cpus_per_actor``, ``gpus_per_actor``), on the cluster at
  ``address`` or on a local one started for the run. The output files are written by the actors,
  so on a cluster ``out_dir`` must be a folder every node sees (a shared file system).
- **results table** (``table=``): one Parquet file, a row per input in input order (see
  :data:`TABLE_SCHEMA`), written by the driver as the rows stream in (row groups of
  ``table_rows``), atomically (a temporary name, then renamed). Skipped inputs get their row from
  their ``.json`` output when it is among the formats (``seconds`` null), so a rerun rebuilds the
  whole table without solving anything again.

Every input ends ``done``, ``skipped`` or ``failed``; a failed input is a row with its error, never
a failed job. Results are the same bytes on either engine and any split (the solver's results do
not depend on their batch), except on a GPU, whose float arithmetic differs from the CPU's.

Example:
    >>> import tempfile, pathlib, numpy as np
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    >>> np.savetxt(d / "ring.xy", np.c_[np.cos(t), np.sin(t)])
    >>> _ = (d / "bad.xy").write_text("1 x\\n")
    >>> rep = reconstruct_dataset([d / "*.xy"], d / "out", formats=["json"], table=d / "t.parquet")
    >>> [(r.stem, r.status) for r in rep.records]
    [('bad', 'failed'), ('ring', 'done')]
    >>> import pyarrow.parquet as pq
    >>> pq.read_table(d / "t.parquet", columns=["stem", "num_curves"]).to_pylist()[1]
    {'stem': 'ring', 'num_curves': 1}
"""
from __future__ import annotations

import csv
import fnmatch
import functools
import glob
import io
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Union

import torch_isc
from torch_isc import images
from torch_isc.runner import (DEFAULT_FORMATS, DEFAULT_IMAGE_FORMATS, ImageOptions, Record, RunError, expand_inputs,
                              inside_folder,
                              run_arguments, run_inputs, shown, unique_stems, overwritten_inputs, make_out_dir)
from torch_isc.pipeline.loop import _as_config
from torch_isc._helpers import decode_text, one_line, read_file_bytes
from torch_isc.io.json import as_written

__all__ = ["ENGINES", "TABLE_SCHEMA", "DatasetReport", "BatchReconstructor", "resolve_inputs", "read_manifest",
           "reconstruct_dataset", "records_from_table"]

PathLike = Union[str, os.PathLike]
ENGINES = ("local", "ray")
_GLOB_CHARS = set("*?[")
_MANIFEST_SUFFIXES = (".parquet", ".pq")


def _pa():
    try:
        import pyarrow as pa
        import pyarrow.parquet  # noqa: F401
    except ImportError as e:
        raise RunError("torch_isc.dataset (the results table, --table, --engine) needs pyarrow: "
                       "pip install 'torch_isc[table]'") from e
    return pa


@functools.lru_cache(maxsize=None)
def _schema():
    pa = _pa()
    point = pa.list_(pa.float64(), 2)
    return pa.schema([
        ("index", pa.int64()), ("source", pa.string()), ("stem", pa.string()), ("status", pa.string()),
        ("error", pa.string()), ("num_curves", pa.int32()), ("num_closed", pa.int32()), ("num_open", pa.int32()),
        ("converged", pa.bool_()), ("limit", pa.string()), ("levels", pa.int32()),
        ("points_beyond_tolerance", pa.int64()), ("seconds", pa.float64()),
        ("closed", pa.list_(pa.bool_())), ("polylines", pa.list_(pa.list_(point))), ("traceback", pa.string()),
    ])


#: The columns of the results table (a function, so pyarrow is imported only when a table is
#: made). ``index``: the input's position in the run; ``source``, ``stem``; ``status``
#: (done/skipped/failed), ``error`` (one line naming the file); ``num_curves`` (closed + open),
#: ``num_closed``, ``num_open``, ``converged``, ``limit``, ``levels``,
#: ``points_beyond_tolerance``, ``seconds`` (the input's share of its batch's wall time); ``closed``
#: (one flag per curve) and ``polylines`` (per curve its ``(n, 2)`` vertices, caller's
#: coordinates, float64); ``traceback`` of an internal error. Columns of a failed row are null.
TABLE_SCHEMA = _schema


# ============================================================================ inputs
def read_manifest(path: PathLike, column: str = "path") -> List[str]:
    """The paths a manifest lists, relative ones made relative to its folder.

    A ``.parquet``/``.pq`` file or a ``.csv`` file: the column ``column``; any other file: one
    path a line (blank lines and ``#`` comments skipped).

    Raises:
        RunError: unreadable manifest, or no such column.
    """
    p = Path(path)
    base = p.parent
    # a regular file of bounded size (a FIFO would block, /dev/zero fill the memory)
    raw = read_file_bytes(p, RunError, "a manifest")
    try:
        suffix = p.suffix.lower()
        if suffix in _MANIFEST_SUFFIXES:
            pa = _pa()
            try:
                pf = pa.parquet.ParquetFile(pa.BufferReader(raw))
                schema = pf.schema_arrow
                names = schema.names
            except (pa.ArrowException, OSError, ValueError) as e:
                raise RunError(f"{p}: not a readable Parquet manifest ({one_line(e, type(e).__name__)})") from None
            _check_column(p, names, column)
            # the type from the schema, before any read: a wrong column is refused without starting
            # Arrow's reader threads (exiting with them alive aborted the process now and then: 134)
            ct = schema.field(column).type
            t = ct.value_type if pa.types.is_dictionary(ct) else ct
            if not (pa.types.is_string(t) or pa.types.is_large_string(t) or pa.types.is_null(t)):
                raise RunError(f"{p}: manifest column '{column}' holds {ct}, not paths (strings)")
            try:
                col = pf.read(columns=[column], use_threads=False).column(column)
            except (pa.ArrowException, OSError, ValueError) as e:
                raise RunError(f"{p}: not a readable Parquet manifest ({one_line(e, type(e).__name__)})") from None
            items = [v.strip() if isinstance(v, str) else v for v in col.to_pylist()]
            for k, v in enumerate(items):
                if not v:
                    raise RunError(f"{p}: row {k + 1} of manifest column '{shown(column)}' is "
                                   f"{'null' if v is None else 'empty'} (every row must name an input)")
        elif suffix == ".csv":
            reader = csv.DictReader(io.StringIO(decode_text(raw, str(p), "CSV manifest", RunError), newline=""))
            _check_column(p, list(reader.fieldnames or []), column)
            items = []
            for row in reader:                   # a wholly blank line is skipped by the reader
                v = row.get(column)
                if not isinstance(v, str) or not v.strip():
                    raise RunError(f"{p}: line {reader.line_num}: manifest column '{shown(column)}' is "
                                   f"{'missing (a short row)' if v is None else 'empty'} (every row must name an input)")
                items.append(v.strip())
        else:
            items = [ln.strip() for ln in decode_text(raw, str(p), "text manifest", RunError).splitlines()]
            items = [ln for ln in items if ln and not ln.startswith("#")]
    except csv.Error as e:
        raise RunError(f"{p}: not a readable CSV manifest ({one_line(e, type(e).__name__)})") from None
    return [str(v) if os.path.isabs(str(v)) else str(base / str(v)) for v in items]


def _check_column(p: Path, names: List[str], column: str) -> None:
    """A :class:`RunError` unless the manifest ``p`` has exactly one column ``column`` among its
    ``names`` (of equal names, csv.DictReader keeps the last: the others' paths were dropped)."""
    if column not in names:
        raise RunError(f"{p}: manifest has no column '{shown(column)}' (columns: {_names(names)})")
    if names.count(column) > 1:
        raise RunError(f"{p}: manifest has {names.count(column)} columns named '{shown(column)}' "
                       f"(which one lists the inputs is ambiguous)")


def _names(names: Sequence[str], limit: int = 10) -> str:
    """Column names for a message: at most ``limit``, control characters escaped."""
    shown_names = [shown(n) for n in list(names)[:limit]]
    return ", ".join(shown_names) + (f", ... ({len(names)} columns)" if len(names) > limit else "")


def _match_parts(parts: Sequence[str], pats: Sequence[str]) -> bool:
    """Whether the path components ``parts`` match the glob components ``pats`` (``**``: zero or
    more folders); as :mod:`glob`, a name starting with ``.`` is matched only by a pattern
    component starting with ``.``, and never by ``**``."""
    if not pats:
        return not parts
    if pats[0] == "**":
        for i in range(len(parts) + 1):
            if _match_parts(parts[i:], pats[1:]):
                return True
            if i < len(parts) and parts[i].startswith("."):
                return False
        return False
    if not parts or (parts[0].startswith(".") and not pats[0].startswith(".")):
        return False
    return fnmatch.fnmatchcase(parts[0], pats[0]) and _match_parts(parts[1:], pats[1:])


def glob_files(pattern: str) -> List[str]:
    """The files matching ``pattern``, sorted. ``**`` spans folders and follows symlinked
    folders, but each real folder once: ``glob.glob`` walked a link to ``.`` once per level
    (duplicated inputs) and two such links for 2^depth paths (the run hung)."""
    if "**" not in pattern:
        return sorted(h for h in glob.glob(pattern) if os.path.isfile(h))
    parts = pattern.split(os.sep)
    k = next(i for i, c in enumerate(parts) if _GLOB_CHARS & set(c))
    top = os.sep.join(parts[:k]) if k else ""
    if pattern.startswith(os.sep) and not top:
        top = os.sep
    pats = [c for c in parts[k:] if c]
    hits: List[str] = []
    seen = set()
    for root, dirs, files in os.walk(top or ".", followlinks=True):
        real = os.path.realpath(root)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs.sort()
        rel = os.path.relpath(root, top or ".")
        base = [] if rel == "." else rel.split(os.sep)
        for f in files:
            if _match_parts(base + [f], pats):
                path = os.path.join(root, f) if top else os.path.normpath(os.path.join(root, f))
                if os.path.isfile(path):
                    hits.append(path)
    return sorted(hits)


def resolve_inputs(inputs: Iterable[PathLike], manifest: Union[None, PathLike, Sequence[PathLike]] = None,
                   manifest_column: str = "path", errors: Optional[Dict[str, str]] = None,
                   out_dir: Optional[PathLike] = None) -> List[str]:
    """Every input file of a run, in order: each input as :func:`~torch_isc.runner.expand_inputs`
    expands it (a folder stands for its point and image files), a glob (``*``, ``?``, ``[``, and
    ``**`` across folders) for its matches sorted, a ``.parquet`` input for the paths of its
    ``manifest_column``; then the paths of each ``manifest``. ``errors``: as for
    :func:`~torch_isc.runner.expand_inputs` (a folder that cannot be listed is kept as one input
    that fails, instead of raising). ``out_dir``: the run's output folder; a folder input in it
    is refused and a glob's matches in it are left out (this run's outputs are no inputs of the
    next). A manifest's lines are taken literally, but a folder stands for its files (an empty
    one, with ``errors``, is one failed input).

    Raises:
        RunError: an empty folder, a glob without match, a bad manifest, a folder input that is
            the output folder.
    """
    out: List[str] = []
    for src in inputs:
        s = os.fspath(src)
        if _GLOB_CHARS & set(s) and not os.path.exists(s):
            hits = glob_files(s)
            if not hits:
                raise RunError(f"{s}: no file matches")
            hits = [h for h in hits if not inside_folder(h, out_dir)]
            if not hits:
                raise RunError(f"{s}: no file matches outside the output folder {shown(out_dir)}")
            out.extend(hits)
        elif Path(s).suffix.lower() in _MANIFEST_SUFFIXES and os.path.isfile(s):
            out.extend(_listed(read_manifest(s, manifest_column), errors, out_dir))
        else:
            out.extend(expand_inputs([s], errors, out_dir))
    if manifest is not None:
        for m in ([manifest] if isinstance(manifest, (str, os.PathLike)) else manifest):
            out.extend(_listed(read_manifest(m, manifest_column), errors, out_dir))
    return out


def _listed(paths: List[str], errors: Optional[Dict[str, str]], out_dir: Optional[PathLike]) -> List[str]:
    """A manifest's paths: a folder stands for its files (as on the command line), a folder
    without any, or one that cannot be listed, is one input that fails alone (with ``errors``;
    a bad line never sinks the run); anything else is taken literally (a ``[`` in a listed name
    is no glob)."""
    out: List[str] = []
    for p in paths:
        if not os.path.isdir(p):                 # False too where it cannot be checked
            out.append(p)
            continue
        try:
            out.extend(expand_inputs([p], errors, out_dir))
        except RunError as e:
            if errors is None:
                raise
            errors[p] = str(e)
            out.append(p)
    return out


# ============================================================================ one batch
def _null_row(index: int, source: str, stem: str) -> Dict[str, Any]:
    return {n: None for n in TABLE_SCHEMA().names} | {"index": index, "source": source, "stem": stem}


def _summary_from_json(path: Path) -> Optional[Dict[str, Any]]:
    """What a skipped input's row needs, from its ``.json`` output (None when absent or bad)."""
    try:
        d = json.loads(path.read_text())
        st = d.get("stats") or {}
        pls = d["polylines"]
        last = (st.get("levels") or [{}])[-1]
        return {"num_curves": len(pls), "num_closed": sum(bool(p["closed"]) for p in pls),
                "num_open": sum(not p["closed"] for p in pls), "converged": st.get("converged"),
                "limit": st.get("limit"), "levels": len(st.get("levels") or []) if st else None,
                # as a done row has it: 0 when there are no levels (mask mode)
                "points_beyond_tolerance": last.get("points_beyond_tolerance", 0),
                "closed": [bool(p["closed"]) for p in pls], "polylines": [p["points"] for p in pls]}
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None


class BatchReconstructor:
    """Reconstructs one batch of inputs and returns their table rows: the worker of both engines.

    Built once (a Ray actor holds one for its life: configs parsed once, torch imported once) and
    called on every batch: a table (pyarrow, or a dict of columns) with ``index``, ``source`` and
    ``stem``; returns a ``pyarrow.Table`` of :data:`TABLE_SCHEMA`, one row per input in the
    batch's order. Never raises for an input: an unexpected error of the whole batch makes every
    row of the batch ``failed`` with that error.
    """

    def __init__(self, config, image_config, out_dir: str, formats: Sequence[str], image_formats: Sequence[str],
                 overwrite: bool, image_options: ImageOptions, device: Optional[str] = None,
                 threads: Optional[int] = None, on_note: Optional[Callable[[str], None]] = None):
        import torch

        self.config, self.image_config = config, image_config
        self.out_dir = Path(out_dir)
        self.formats, self.image_formats = list(formats), list(image_formats)
        self.overwrite = overwrite
        self.image_options = image_options
        if device is None:          # a Ray actor given a GPU solves on it; anything else on the CPU
            gpus = []
            if sys.modules.get("ray") is not None:
                import ray

                gpus = ray.get_gpu_ids() if ray.is_initialized() else []
            device = "cuda" if gpus and torch.cuda.is_available() else "cpu"
        self.device = device
        if threads:
            torch.set_num_threads(int(threads))
        self.on_note = on_note

    def __call__(self, batch) -> Any:
        _pa()                                # pyarrow is needed here: a clear error if missing
        cols = batch.to_pydict() if hasattr(batch, "to_pydict") else {k: list(v) for k, v in batch.items()}
        index = [int(i) for i in cols["index"]]
        sources, stems = [_name(s) for s in cols["source"]], [_name(s) for s in cols["stem"]]
        # where to read each input: an absolute path when the driver gave one (a Ray worker's
        # folder is not the driver's); records and errors name the input as given
        paths = [_name(s) for s in cols["read"]] if "read" in cols else sources
        given = dict(zip(paths, sources))
        rows = {i: _null_row(i, s, t) for i, s, t in zip(index, sources, stems)}
        # inputs the driver already failed (their outputs would overwrite an input of the run)
        for i, err in zip(index, cols.get("error") or []):
            if err is not None:
                rows[i].update(status="failed", error=err)
        keep = [k for k, i in enumerate(index) if rows[i]["status"] is None]
        if len(keep) < len(index):
            paths, stems = [paths[k] for k in keep], [stems[k] for k in keep]
        by_stem = dict(zip(stems, [index[k] for k in keep]))
        results: Dict[int, Any] = {}

        def on_result(record: Record, result) -> None:
            results[by_stem[record.stem]] = result

        try:
            report = run_inputs(paths, self.config, self.out_dir, self.formats, self.image_formats,
                                overwrite=self.overwrite, batch_size=max(1, len(sources)),
                                image_options=self.image_options, image_config=self.image_config,
                                device=self.device, on_note=self.on_note, stems=stems, on_result=on_result)
            for rec in report.records:
                i = by_stem[rec.stem]
                row = rows[i]
                err = rec.error
                src = given[rec.source]
                if err is not None and src != rec.source:
                    err = err.replace(rec.source, src)
                row.update(status=rec.status, error=err, traceback=rec.traceback)
                res = results.get(i)
                if rec.status == "done" and res is not None:
                    s = rec.summary
                    pls = res.polylines
                    row.update(num_curves=len(pls), num_closed=s["num_closed"], num_open=s["num_open"],
                               converged=s["converged"], limit=s["limit"], levels=s["levels"],
                               points_beyond_tolerance=s["points_beyond_tolerance"], seconds=float(s["seconds"]),
                               closed=[bool(p["closed"]) for p in pls],
                               # as the JSON writes them, so a rerun's table (read from it) is the same
                               polylines=[as_written(p["points"].detach().double().cpu().numpy()) for p in pls])
                elif rec.status == "skipped" and "json" in self._formats_of(src):
                    row.update(_summary_from_json(self.out_dir / f"{rec.stem}.json") or {})
        except Exception as e:          # the batch as a whole: every input of it failed, the job goes on
            from torch_isc._helpers import one_line
            import traceback as tb

            msg, text = f"{type(e).__name__}: {one_line(e, type(e).__name__)}", tb.format_exc()
            for i, row in rows.items():
                if row["status"] is None:
                    row.update(status="failed", error=f"{row['source']}: batch failed ({msg})", traceback=text)
        return _rows_table([rows[i] for i in index])

    def _formats_of(self, source: str) -> List[str]:
        from torch_isc.io import loader_for

        return self.image_formats if loader_for(source).kind == "image" else self.formats


def _name(v) -> str:
    """A file name of the work table: bytes (os.fsencode) back to the name, or a string."""
    return os.fsdecode(v) if isinstance(v, (bytes, bytearray)) else str(v)


def _utf8(v):
    """A string Arrow can store: a file name that is not UTF-8 (a byte like 0xff, kept by
    Python as a lone surrogate) with that character backslash-escaped (pyarrow raised, and the
    whole run was lost)."""
    if isinstance(v, str):
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:
            return v.encode("utf-8", "backslashreplace").decode("utf-8")
    return v


def _rows_table(rows: List[Dict[str, Any]]):
    """A pyarrow table of :data:`TABLE_SCHEMA` from row dicts; polylines as float64 arrays or
    nested lists, packed into offsets without a Python loop over points."""
    import numpy as np

    pa = _pa()
    schema = TABLE_SCHEMA()
    cols = {n: [r[n] for r in rows] for n in schema.names if n != "polylines"}
    for n in schema.names:
        if n != "polylines" and schema.field(n).type == pa.string():
            cols[n] = [_utf8(v) for v in cols[n]]
    arrays = [pa.array(cols[n], type=schema.field(n).type) if n != "polylines" else None for n in schema.names]
    # polylines: list (input) of list (curve) of [x, y]
    curve_off, vert_off, chunks, valid = [0], [0], [], []
    for r in rows:
        pls = r["polylines"]
        valid.append(pls is not None)
        for p in pls or []:
            a = np.asarray(p, np.float64).reshape(-1, 2)
            chunks.append(a)
            vert_off.append(vert_off[-1] + a.shape[0])
        curve_off.append(len(vert_off) - 1)
    xy = np.concatenate(chunks).reshape(-1) if chunks else np.zeros(0, np.float64)
    points = pa.FixedSizeListArray.from_arrays(pa.array(xy, pa.float64()), 2)
    curves = pa.ListArray.from_arrays(pa.array(vert_off, pa.int32()), points)
    mask = pa.array([not v for v in valid], pa.bool_())
    per_input = pa.ListArray.from_arrays(pa.array(curve_off, pa.int32()), curves, mask=mask)
    arrays[schema.names.index("polylines")] = per_input.cast(schema.field("polylines").type)
    return pa.Table.from_arrays(arrays, schema=schema)


def records_from_table(table) -> List[Record]:
    """:class:`~torch_isc.runner.Record` objects of table rows (``outputs`` left empty)."""
    names = ["source", "stem", "status", "error", "traceback", "num_closed", "num_open", "levels", "converged",
             "limit", "points_beyond_tolerance", "seconds"]
    out = []
    for r in table.select(names).to_pylist():
        summary = None
        if r["status"] == "done":
            summary = {k: r[k] for k in ("num_closed", "num_open", "levels", "converged", "limit",
                                         "points_beyond_tolerance", "seconds")}
        out.append(Record(r["source"], r["stem"], r["status"], r["error"], r["traceback"], summary))
    return out


# ============================================================================ the run
@dataclass
class DatasetReport:
    """The records of a run in input order, where its table went, and what it took."""
    records: List[Record]
    engine: str
    table: Optional[Path] = None
    batches: int = 0
    seconds: float = 0.0
    counts: Dict[str, int] = field(default_factory=dict)

    @property
    def failed(self) -> int:
        return self.counts.get("failed", 0)


def _remove_dead_temporaries(path: Path) -> None:
    """Remove ``.<name>.<pid>.tmp`` files of ``path`` left by runs that were killed (their
    process is gone); a live run's temporary is left alone."""
    prefix = f".{path.name}."
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return
    for e in entries:
        if not (e.name.startswith(prefix) and e.name.endswith(".tmp")):
            continue
        pid = e.name[len(prefix):-len(".tmp")]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)                 # raises when no such process
            continue
        except ProcessLookupError:
            pass
        except (PermissionError, OverflowError, OSError):
            continue                             # alive under another user, or not a pid
        try:
            os.unlink(e.path)
        except OSError:
            pass


class _TableSink:
    """Rows in input order into one Parquet file, row groups of ``rows`` rows, renamed into place
    at the end (an interrupted run leaves no half-written table under the final name)."""

    def __init__(self, path: Optional[Path], rows: int):
        self.path, self.rows = path, rows
        self.buf: list = []
        self.n = 0
        self.writer = None
        if path is not None:
            # checked before any input is solved: a table that cannot be written would lose the run's rows
            if path.is_dir():
                raise RunError(f"table {shown(path)}: is a folder, not a file")
            if path.suffix.lower() not in _MANIFEST_SUFFIXES:
                # the table is Parquet: a .csv name got Parquet bytes without a word
                raise RunError(f"table {shown(path)}: the table is written as Parquet; name it .parquet or .pq")
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                _remove_dead_temporaries(path)
                self.tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
                self.writer = _pa().parquet.ParquetWriter(self.tmp, TABLE_SCHEMA(), compression="zstd")
            except (OSError, _pa().ArrowException) as e:
                raise RunError(f"table {shown(path)}: cannot be written ({getattr(e, 'strerror', None) or one_line(e)})") from None

    def add(self, t) -> None:
        if self.writer is None:
            return
        self.buf.append(t)
        self.n += t.num_rows
        if self.n >= self.rows:
            self.flush()

    def flush(self) -> None:
        if self.buf:
            pa = _pa()
            try:
                self.writer.write_table(pa.concat_tables(self.buf), row_group_size=max(self.rows, self.n))
            except (OSError, pa.ArrowException) as e:      # a full disk: one line, not "internal error"
                raise self.failed(e) from None
            self.buf, self.n = [], 0

    def failed(self, e: BaseException) -> RunError:
        return RunError(f"table {shown(self.path)}: cannot be written "
                        f"({getattr(e, 'strerror', None) or one_line(e, type(e).__name__)})")

    def close(self, ok: bool) -> None:
        """Move the table into place (``ok``) or remove the temporary file; it is removed too
        when the last write or the move fails (a full disk, a second interrupt)."""
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        placed = False
        try:
            if ok:
                self.writer = writer
                self.flush()
                self.writer = None
            try:
                writer.close()
                if ok:
                    os.replace(self.tmp, self.path)
                    placed = True
            except (OSError, _pa().ArrowException) as e:
                raise self.failed(e) from None
        finally:
            if not placed:
                try:
                    os.unlink(self.tmp)
                except OSError:
                    pass


def _batches_local(worker: BatchReconstructor, inputs, batch_size: int) -> Iterator[Any]:
    for s in range(0, inputs.num_rows, batch_size):
        yield worker(inputs.slice(s, batch_size))


def _batches_ray(settings: Dict[str, Any], inputs, batch_size: int, address: Optional[str], actors: int,
                 cpus_per_actor: float, gpus_per_actor: float, ray_init: Optional[Dict[str, Any]],
                 quiet: bool) -> Iterator[Any]:
    try:
        import ray
        import ray.data
    except ImportError as e:
        raise RunError("engine 'ray' needs Ray: pip install 'torch_isc[ray]'") from e
    started = False
    if not ray.is_initialized():
        kw = dict(ray_init or {})
        kw.setdefault("include_dashboard", False)
        kw.setdefault("log_to_driver", False)
        # the workers import this torch_isc: the one the driver imported (an editable checkout too)
        pkg_root = str(Path(torch_isc.__file__).resolve().parent.parent)
        env = kw.setdefault("runtime_env", {}).setdefault("env_vars", {})
        env.setdefault("PYTHONPATH", os.pathsep.join(p for p in (pkg_root, os.environ.get("PYTHONPATH")) if p))
        ray.init(address=address, **kw)
        started = True
    ctx = ray.data.DataContext.get_current()
    old = (ctx.execution_options.preserve_order, ctx.enable_progress_bars, ctx.print_on_execution_start)
    ctx.execution_options.preserve_order = True          # rows come back in input order
    if quiet:                                             # the caller reports progress itself
        ctx.enable_progress_bars, ctx.print_on_execution_start = False, False
    try:
        # actors the cluster cannot place would wait for ever (--actors 1000000 hung the run)
        res = ray.cluster_resources()
        for kind, per in (("CPU", cpus_per_actor), ("GPU", gpus_per_actor)):
            have = float(res.get(kind, 0.0))
            if per and actors * per > have + 1e-9:
                raise RunError(f"actors: {actors} actor(s) x {per:g} {kind}(s) need {actors * per:g} {kind}s, "
                               f"the Ray cluster has {have:g} (at most {int(have // per)} such actor(s) fit)")
        blocks = [inputs.slice(s, batch_size) for s in range(0, inputs.num_rows, batch_size)]
        ds = ray.data.from_arrow(blocks)
        remote = {"num_gpus": gpus_per_actor} if gpus_per_actor else {}
        ds = ds.map_batches(BatchReconstructor, fn_constructor_kwargs=settings, batch_size=batch_size,
                            batch_format="pyarrow", concurrency=actors, num_cpus=cpus_per_actor, **remote)
        yield from ds.iter_batches(batch_size=None, batch_format="pyarrow")
    finally:
        ctx.execution_options.preserve_order, ctx.enable_progress_bars, ctx.print_on_execution_start = old
        if started:
            ray.shutdown()


def reconstruct_dataset(inputs: Iterable[PathLike], out_dir: PathLike, config=None, engine: str = "local", *,
                        manifest=None, manifest_column: str = "path", formats: Sequence[str] = DEFAULT_FORMATS,
                        image_formats: Sequence[str] = DEFAULT_IMAGE_FORMATS, overwrite: bool = False,
                        batch_size: int = 64, image_options: ImageOptions = ImageOptions(), image_config=None,
                        device: Optional[str] = None, table: Optional[PathLike] = None, table_rows: int = 8192,
                        address: Optional[str] = None, actors: int = 2, cpus_per_actor: float = 1.0,
                        gpus_per_actor: float = 0.0, ray_init: Optional[Dict[str, Any]] = None,
                        progress: Optional[Callable[[Record], None]] = None,
                        on_note: Optional[Callable[[str], None]] = None, keep_records: bool = True,
                        resolved: bool = False) -> DatasetReport:
    """Reconstruct every input, write its outputs and, if asked, the results table (see the
    module docstring).

    Args:
        inputs: files, folders, globs, ``.parquet`` manifests (:func:`resolve_inputs`).
        out_dir: the output folder (on a cluster: one every node sees).
        config: the config of point files (default :func:`torch_isc.load_config`).
        engine: ``"local"`` (this process) or ``"ray"``.
        manifest, manifest_column: more inputs from manifest files (:func:`read_manifest`).
        formats, image_formats, overwrite, image_options, image_config: as for
            :func:`~torch_isc.runner.run_inputs`.
        batch_size: inputs per batch (one batched solve, one Ray block).
        device: torch device of the solves (default: ``cuda`` in a Ray actor given a GPU, else ``cpu``).
        table: path of the results table (Parquet), or None for none.
        table_rows: rows per Parquet row group.
        address: Ray: the cluster to connect to (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``);
            None starts a local one for the run (``ray_init`` passes more ``ray.init`` arguments).
            When Ray is already initialized it is used as it is.
        actors: Ray: actors in the pool (each holds the configs and solves whole batches).
        cpus_per_actor, gpus_per_actor: Ray resources of each actor; an actor given a GPU solves on it.
        progress: ``progress(record)`` for every input as its batch comes back, in input order.
        on_note: remarks that are not errors (renamed outputs; local engine: all-white masks).
        keep_records: keep every :class:`~torch_isc.runner.Record` in the report (for a run of
            millions, False keeps only the counts: the table holds the rows).
        resolved: ``inputs`` are files already (:func:`resolve_inputs` of the caller, as the CLI
            does), taken as they are: resolving twice expanded a manifest's glob-like names.

    Returns:
        a :class:`DatasetReport`.

    Raises:
        RunError: bad arguments, no inputs, an unknown engine, a missing optional dependency.
    """
    t0 = time.perf_counter()
    if engine not in ENGINES:
        raise RunError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    inputs, formats, image_formats = run_arguments(inputs, formats, image_formats, batch_size, image_options)
    if not isinstance(table_rows, int) or table_rows < 1:
        raise RunError(f"table_rows must be an integer >= 1, got {table_rows!r:.50}")
    if engine == "ray" and actors < 1:
        raise RunError(f"actors must be >= 1, got {actors}")
    from torch_isc.io import chosen_formats

    known = chosen_formats()
    for f in list(formats) + list(image_formats):
        if f not in known:
            raise RunError(f"unknown output format '{f}' (known: {', '.join(known)})")
    if image_options.mode not in ("mask", "edges"):
        raise RunError(f"image mode must be 'mask' or 'edges', got {image_options.mode!r}")
    pa = _pa()
    config = _as_config(config)
    if image_config is not None:
        image_config = _as_config(image_config)
    if image_config is None:
        image_config = images.image_config(config, mode=image_options.mode)
    inputs = list(inputs)
    sources = list(inputs) if resolved else resolve_inputs(inputs, manifest, manifest_column, errors={},
                                                            out_dir=out_dir)
    if not sources:
        raise RunError("no input")
    stems = unique_stems(sources, on_note)
    out = make_out_dir(out_dir)
    if table is not None:           # before any work: a table that cannot be written would lose the rows
        if os.path.realpath(table) in {os.path.realpath(src) for src in sources}:
            raise RunError(f"table {shown(table)}: is an input of the run; writing it would overwrite that input")
        if Path(table).is_dir():
            raise RunError(f"table {shown(table)}: is a folder, not a file")
        given = [manifest] if isinstance(manifest, (str, os.PathLike)) else list(manifest or [])
        given += [m for m in inputs if Path(os.fspath(m)).suffix.lower() in _MANIFEST_SUFFIXES and os.path.isfile(m)]
        if os.path.realpath(table) in {os.path.realpath(m) for m in given}:
            raise RunError(f"table {shown(table)}: is a manifest of the run; writing it would overwrite that manifest")
        if os.path.realpath(Path(table).parent) == os.path.realpath(out):
            names = {f"{st}.{f}" for st in stems for f in (*formats, *image_formats, "manifest.json")}
            if Path(table).name in names:
                raise RunError(f"table {shown(table)}: is an output file of the run ({Path(table).name}); "
                               f"writing it would overwrite that output")
    # names as bytes (os.fsencode): a file name that is not UTF-8 cannot be an Arrow string
    todo = pa.table({"index": pa.array(range(len(sources)), pa.int64()),
                     "source": pa.array([os.fsencode(s) for s in sources], pa.binary()),
                     "stem": pa.array([os.fsencode(s) for s in stems], pa.binary())})
    from torch_isc.io import loader_for

    clobber = overwritten_inputs(sources, stems, out, lambda src: image_formats
                                 if loader_for(src).kind == "image" else formats)
    if clobber:
        todo = todo.append_column("error", pa.array([_utf8(clobber.get(i)) for i in range(len(sources))], pa.string()))
    if engine == "ray":
        todo = todo.append_column("read", pa.array([os.fsencode(os.path.abspath(s)) for s in sources], pa.binary()))
    settings = dict(config=config, image_config=image_config, out_dir=str(out.resolve()), formats=list(formats),
                    image_formats=list(image_formats), overwrite=overwrite, image_options=image_options,
                    device=device)
    if engine == "local":
        batches = _batches_local(BatchReconstructor(**settings, on_note=on_note), todo, batch_size)
    else:
        settings["threads"] = max(1, int(cpus_per_actor))
        batches = _batches_ray(settings, todo, batch_size, address, actors, cpus_per_actor, gpus_per_actor, ray_init,
                               quiet=progress is not None)
    sink = _TableSink(Path(table) if table is not None else None, table_rows)
    records: List[Record] = []
    counts = {"done": 0, "skipped": 0, "failed": 0}
    n_batches, ok = 0, False
    try:
        for t in batches:
            n_batches += 1
            sink.add(t)
            for rec in records_from_table(t):
                counts[rec.status] = counts.get(rec.status, 0) + 1
                if keep_records:
                    records.append(rec)
                if progress is not None:
                    progress(rec)
        ok = True
    finally:
        sink.close(ok)
    return DatasetReport(records, engine, Path(table) if table is not None else None, n_batches,
                         time.perf_counter() - t0, counts)
