"""
The sweep's folder: rows streamed to ``envelope.csv`` as chunks finish, resume, Parquet.

``DIR/envelope.json`` (the manifest) names the sweep: the scenario file's SHA-256, the grid
cells and the poses (see :func:`sweep_spec`), plus one record per run (when it started, the
engine, how many poses it planned, whether it completed).  A run into a folder that holds
the manifest of another sweep is refused with the key that differs; into the same sweep it
resumes: the poses with a row in ``envelope.csv`` are done, only the others are planned.

``envelope.csv`` gets one line per pose, appended (flushed and synced) chunk by chunk in the
order the chunks finish, so a sweep killed at any moment leaves every finished chunk on
disk; a line torn by the kill (no end of line) is cut off when the sweep resumes.  When every
pose has its row the file is rewritten in ``pose_id`` order (atomically) and, for a large
sweep, ``envelope.parquet`` written beside it (the same table, typed columns).

No rclpy, no Dask here.
"""

from __future__ import annotations

import csv
import datetime
import hashlib
import io
import json
import os
from pathlib import Path

from .sweep import COLUMNS, PoseGrid

__all__ = ["EnvelopeStore", "read_rows", "write_parquet", "sweep_spec", "CSV_NAME", "MANIFEST_NAME",
           "PARQUET_NAME", "PARQUET_MIN_POSES"]

CSV_NAME = "envelope.csv"
MANIFEST_NAME = "envelope.json"
PARQUET_NAME = "envelope.parquet"
#: a sweep of at least this many poses also gets ``envelope.parquet`` (unless asked otherwise)
PARQUET_MIN_POSES = 10_000
_NAMES = tuple(name for name, _ in COLUMNS)
_TYPES = dict(COLUMNS)
#: the manifest's keys that name the sweep (a resume needs them equal)
SPEC_KEYS = ("scenario_sha256", "grid_cells", "poses", "columns")


def _difference(key: str, old: dict, new: dict) -> str:
    """Say how the manifest ``old``'s ``key`` (one of SPEC_KEYS) differs from the sweep ``new``'s: its values, short."""
    a, b = old.get(key), new.get(key)
    if key == "scenario_sha256":
        return (f"the folder's from {old.get('params_file', '?')} (SHA-256 {str(a)[:12]}…), "
                f"this one from {new.get('params_file', '?')} ({str(b)[:12]}…)")
    if key == "poses" and isinstance(a, dict) and isinstance(b, dict):
        return "; ".join(_values_differ(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k))
    return _values_differ(key, a, b)


def _values_differ(name: str, a, b) -> str:
    """Say ``name``'s two values (the folder's ``a``, the sweep's ``b``); read alike: the first that differs."""
    there, here = _short(a), _short(b)
    if there == here and isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        i = next(k for k, (x, y) in enumerate(zip(a, b)) if x != y)
        return f"{name}[{i}] {a[i]!r} there, {b[i]!r} here"
    return f"{name} {there} there, {here} here"


def _short(v, most: int = 4) -> str:
    """Return a manifest value as text: a list of more than ``most`` numbers as its count, ends and step (when even)."""
    if isinstance(v, list) and len(v) > most and all(isinstance(x, (int, float)) for x in v):
        steps = [y - x for x, y in zip(v, v[1:])]
        even = all(abs(d - steps[0]) <= 1e-9 * max(1.0, abs(steps[0])) for d in steps)
        return f"{len(v)} values {v[0]:g} … {v[-1]:g}" + (f" (step {steps[0]:g})" if even else "")
    if isinstance(v, list) and len(v) > most:
        return f"{len(v)} values {_short(v[0])} … {_short(v[-1])}"
    if isinstance(v, list):
        return "[" + ", ".join(_short(x) for x in v) + "]"
    return f"{v:g}" if isinstance(v, float) else str(v)


def sweep_spec(params_file, grid_cells, grid: PoseGrid) -> dict:
    """Return what names a sweep: the scenario file (path and SHA-256), the grid cells and the poses."""
    data = Path(params_file).read_bytes()
    return {"params_file": str(params_file), "scenario_sha256": hashlib.sha256(data).hexdigest(),
            "grid_cells": [int(c) for c in grid_cells], "poses": grid.to_json_dict(), "columns": list(_NAMES)}


def _text(name: str, value) -> str:
    typ = _TYPES[name]
    if typ is float:
        return repr(float(value))           # exact round trip; nan as "nan"
    if typ is int:
        return str(int(value))
    return str(value)


def _value(name: str, text: str):
    typ = _TYPES[name]
    return typ(text) if typ is not str else text


def _parse(lines_text: str, where: str) -> list:
    reader = csv.reader(io.StringIO(lines_text))
    header = next(reader, None)
    if header is None:
        return []
    if tuple(header) != _NAMES:
        raise ValueError(f"{where}: the columns {header} are not an envelope's {list(_NAMES)}")
    rows = []
    for k, fields in enumerate(reader, start=2):
        if len(fields) != len(_NAMES):
            raise ValueError(f"{where} line {k}: {len(fields)} fields, expected {len(_NAMES)}")
        rows.append({n: _value(n, t) for n, t in zip(_NAMES, fields)})
    return rows


def read_rows(path) -> list:
    """Return the rows of an ``envelope.csv`` as dicts with typed values (a torn last line is left out)."""
    data = Path(path).read_bytes()
    cut = data.rfind(b"\n") + 1
    return _parse(data[:cut].decode("utf-8"), str(path))


def write_parquet(rows, path) -> None:
    """Write rows (``COLUMNS``) to a Parquet file with typed columns."""
    import pyarrow as pa                    # loaded only when a Parquet file is written
    import pyarrow.parquet as pq
    kinds = {int: pa.int64(), float: pa.float64(), str: pa.string()}
    table = pa.table({n: pa.array([r[n] for r in rows], type=kinds[t]) for n, t in COLUMNS})
    pq.write_table(table, path)


class EnvelopeStore:
    """
    One sweep's folder (see the module docstring).

    Parameters
    ----------
        out_dir: the folder (made when absent).
        spec: :func:`sweep_spec` of the sweep.

    """

    def __init__(self, out_dir, spec: dict):
        self.dir = Path(out_dir)
        self.spec = dict(spec)
        self.csv_path = self.dir / CSV_NAME
        self.manifest_path = self.dir / MANIFEST_NAME
        self.parquet_path = self.dir / PARQUET_NAME
        self._file = None
        self._run = None
        self._made = []             # what open() made: the table (header only), the folder

    # ------------------------------------------------------------------ open
    def open(self, grid: PoseGrid | None = None) -> set:
        """
        Open the folder for writing; return the ``pose_id`` of every pose already done.

        ValueError when the folder holds another sweep (naming the key that differs) or a
        damaged ``envelope.csv``; with ``grid`` (the sweep's), also when a row of
        ``envelope.csv`` is not one of its poses (another sweep's table, its manifest gone).
        """
        if not self.dir.exists():
            self.dir.mkdir(parents=True)
            self._made.append(self.dir)
        if self.manifest_path.exists():
            old = json.loads(self.manifest_path.read_text(encoding="utf-8"))
            for key in SPEC_KEYS:
                if old.get(key) != self.spec.get(key):
                    raise ValueError(f"--out {self.dir}: it holds another sweep ({key} differs from this one's: "
                                     f"{_difference(key, old, self.spec)}); "
                                     "choose another folder, or delete that one to start again")
            self.manifest = old
        else:
            self.manifest = dict(self.spec, runs=[])
        done = set()
        if self.csv_path.exists():
            data = self.csv_path.read_bytes()
            cut = data.rfind(b"\n") + 1
            if cut < len(data):             # a line torn by a kill: cut it off, its pose is planned again
                with open(self.csv_path, "r+b") as f:
                    f.truncate(cut)
            rows = _parse(data[:cut].decode("utf-8"), str(self.csv_path))
            if grid is not None:
                self._check_rows(rows, grid)
            done = {r["pose_id"] for r in rows}
            if cut == 0:
                self.csv_path.unlink()
        if not self.csv_path.exists():
            with open(self.csv_path, "w", encoding="utf-8", newline="") as f:
                csv.writer(f, lineterminator="\n").writerow(_NAMES)
            self._made.insert(0, self.csv_path)
        self._file = open(self.csv_path, "a", encoding="utf-8", newline="")
        self._writer = csv.writer(self._file, lineterminator="\n")
        return done

    def _check_rows(self, rows, grid: PoseGrid) -> None:
        """Raise ValueError naming the first row of ``rows`` that is not the pose its id numbers in ``grid``."""
        for k, r in enumerate(rows, start=2):
            i = r["pose_id"]
            want = grid.pose(i) if 0 <= i < grid.n_poses else None
            if want is not None and (r["x_m"], r["y_m"], r["yaw_deg"], r["start_index"]) == (
                    float(want.x_m), float(want.y_m), float(want.yaw_deg), want.start_index):
                continue
            where = (f"this sweep has {grid.n_poses} poses" if want is None else
                     f"this sweep's pose {i} is x {float(want.x_m):g} m, y {float(want.y_m):g} m, yaw "
                     f"{float(want.yaw_deg):g}°, start {want.start_index}")
            raise ValueError(
                f"--out {self.dir}: {CSV_NAME} line {k} is another sweep's pose (pose {i}: x {r['x_m']:g} m, "
                f"y {r['y_m']:g} m, yaw {r['yaw_deg']:g}°, start {r['start_index']}; {where})"
                + ("" if self.manifest_path.exists() else f", and no {MANIFEST_NAME} says which sweep it holds")
                + "; choose another folder, or delete that one to start again")

    def discard_new(self) -> None:
        """Remove what :meth:`open` made (a header-only table; the folder, when it made it and it is empty)."""
        for path in self._made:
            try:
                if path == self.csv_path:
                    path.unlink()
                else:
                    path.rmdir()
            except OSError:
                pass            # something else was put there meanwhile: left as it is
        self._made = []

    # ----------------------------------------------------------------- runs
    def start_run(self, **info) -> None:
        """Record a new run in the manifest (``info``: engine, workers, poses to plan, ...)."""
        now = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        self._run = dict(started=now, planned=0, complete=False, **info)
        self.manifest.setdefault("runs", []).append(self._run)
        self._write_manifest()

    @property
    def running(self) -> bool:
        """Tell whether a run was recorded by :meth:`start_run` in this store."""
        return self._run is not None

    def end_run(self, planned: int, complete: bool, seconds: float) -> None:
        """Record how the current run ended."""
        self._run.update(planned=int(planned), complete=bool(complete), seconds=round(float(seconds), 3))
        self._write_manifest()

    def _write_manifest(self) -> None:
        tmp = self.manifest_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.manifest, indent=1) + "\n", encoding="utf-8")
        os.replace(tmp, self.manifest_path)

    # ---------------------------------------------------------------- rows
    def append(self, rows) -> None:
        """Append rows (dicts of ``COLUMNS``) and put them on disk before returning."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        for r in rows:
            w.writerow([_text(n, r[n]) for n in _NAMES])
        self._file.write(buf.getvalue())        # one write per chunk
        self._file.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def finish(self, parquet: bool) -> list:
        """
        Rewrite ``envelope.csv`` in ``pose_id`` order (every pose done); write Parquet when asked.

        Returns the rows, sorted.
        """
        self.close()
        rows = sorted(read_rows(self.csv_path), key=lambda r: r["pose_id"])
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(_NAMES)
        for r in rows:
            w.writerow([_text(n, r[n]) for n in _NAMES])
        tmp = self.csv_path.with_suffix(".csv.tmp")
        tmp.write_text(buf.getvalue(), encoding="utf-8")
        os.replace(tmp, self.csv_path)
        if parquet:
            write_parquet(rows, self.parquet_path)
        return rows
