"""The record of a batch or a sequence: ``poses.json`` (one row per photo or frame), ``poses.csv``.

A run killed at any moment loses no photo that it finished, and restarted on the same folder
skips them.

Every row is first appended to the journal ``poses.jsonl`` (one JSON line per photo, flushed to
disk); then poses.json and poses.csv are rewritten atomically, at most every
``min_rewrite_seconds`` (1 s: after every photo of a batch of 1-second photos, every ~10 frames
of a video tracked at 10 frames/s), and always at the end. A rewrite costs in proportion to the
rows already held (a 60-frame video's poses.json is ~350 kB, ~20 ms to write), so it also
waits until the time since the last one is ``1 / max_rewrite_share`` times what that one took
(rewriting takes at most ~10 % of a long run), and beyond ``rewrite_rows`` photos at least
``rewrite_seconds``. Resuming reads both; a line cut short by a kill is ignored.

    ledger = PosesLedger(out_dir, run={"model_path": ..., "queries": ...}, total=50)
    done = ledger.finished()                    # names recorded by any earlier run (or shard)
    ledger.record(row)                          # after each photo: journal, then a due rewrite
    ledger.close()                              # status "complete" once every photo has a row

A row is a JSON mapping with at least ``index`` (the photo's place in the input order), ``name``
and ``status`` (``ok | uncertain | failed``): the one row schema (``localization.types.ROW_FIELDS``,
docs/CONTRACTS.md) and the batch's own fields (``batch/records.py``).

Shards (``num_shards > 1``, e.g. the array tasks of a SLURM job): every shard writes its own part
``parts/shard-<i>-of-<n>.json`` and then merges all parts into ``poses.json`` under a file lock,
so whichever shard merges last leaves every shard's rows in ``poses.json``. The lock is
``fcntl.flock`` on ``.poses.lock`` (a no-op where fcntl is missing).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from ..checks import check_real
from ..io.atomic import file_lock, write_json_atomic, write_text_atomic
from ..localization.types import ROW_FIELDS, VERDICTS

logger = logging.getLogger(__name__)

__all__ = ["CSV_COLUMNS", "LedgerError", "PosesLedger", "counts_of", "read_poses_json"]

#: Columns of poses.csv: the photo's index, the scalar fields of the one row schema
#: (``localization.types.ROW_FIELDS``; errors are blank when the truth is unknown), whether a
#: video frame was relocalized, and the focal length it was localized with (``app/focal.py``).
CSV_COLUMNS = ("index",) + tuple(
    f for f in ROW_FIELDS if f not in ("c2w", "init_c2w", "gt_c2w", "intrinsics")
) + ("relocalized", "camera_focal_scale")

#: Keys of ``run`` that must agree between a run and the poses.json it resumes.
RUN_IDENTITY = ("kind", "model_path", "queries", "sequence")

FORMAT_VERSION = 1


class LedgerError(ValueError):
    """An output folder that cannot be resumed (another run's poses.json, an unreadable file)."""


def counts_of(rows: Sequence[Dict[str, Any]]) -> Dict[str, int]:
    """``{"ok": n, "uncertain": n, "failed": n}`` of ``rows``."""
    c = {v: 0 for v in VERDICTS}
    for r in rows:
        s = r.get("status")
        if s in c:
            c[s] += 1
    return c


def read_poses_json(path) -> Dict[str, Any]:
    """A poses.json (or a shard part) as a dict with a ``photos`` list.

    Raises:
        LedgerError: the file is unreadable or not a poses.json.
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise LedgerError(
            f"cannot read {p} ({type(e).__name__}: {e}); move it away to start over"
        ) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("photos"), list):
        raise LedgerError(f"{p} is not a poses.json of icomma (no 'photos' list)")
    return doc


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    return str(v)


class PosesLedger:
    """poses.json / poses.csv of one output folder (see the module docstring).

    Args:
        out_dir: the output folder (poses.json, poses.jsonl, poses.csv, parts/).
        run: what identifies the run (``kind``, ``model_path``, ``queries`` / ``sequence``) plus
            anything worth keeping (the config); a folder whose poses.json has another identity
            is refused (LedgerError).
        total: number of photos of the whole run (every shard), for the ``complete`` status.
        shard, num_shards: this process's share of the run.
        rewrite_rows, rewrite_seconds: beyond this many rows, poses.json is rewritten at most
            every ``rewrite_seconds`` (the journal has every row at once).
        min_rewrite_seconds: the least time between two rewrites of poses.json / poses.csv
            (0: after every photo, as long as ``max_rewrite_share`` allows).
        max_rewrite_share: the share of the run's time that rewriting may take (the module
            docstring).
    """

    def __init__(
        self,
        out_dir,
        run: Dict[str, Any],
        total: int,
        shard: int = 0,
        num_shards: int = 1,
        rewrite_rows: int = 1000,
        rewrite_seconds: float = 10.0,
        min_rewrite_seconds: float = 1.0,
        max_rewrite_share: float = 0.1,
    ):
        if not (isinstance(num_shards, int) and num_shards >= 1):
            raise ValueError(f"num_shards must be a positive int, got {num_shards!r}")
        if not (isinstance(shard, int) and 0 <= shard < num_shards):
            raise ValueError(f"shard must be an int in [0, {num_shards}), got {shard!r}")
        self.out_dir = Path(out_dir)
        self.run = dict(run)
        self.total = int(total)
        self.shard, self.num_shards = shard, num_shards
        self.rows: Dict[str, Dict[str, Any]] = {}  # this process's rows (this shard's)
        self._seen: Dict[str, Dict[str, Any]] = {}  # rows of earlier runs and other shards
        # verdict counts over every row known, kept up to date by `record` (the progress line
        # asks after every photo: a recount would make a batch quadratic); None: recount
        self._counts: Optional[Dict[str, int]] = None
        self.rewrite_rows, self.rewrite_seconds = int(rewrite_rows), float(rewrite_seconds)
        self.max_rewrite_share = check_real(max_rewrite_share, "max_rewrite_share", 0.0, 1.0,
                                            lo_open=True)
        self.min_rewrite_seconds = check_real(min_rewrite_seconds, "min_rewrite_seconds", 0.0)
        self._last_write = float("-inf")
        self._write_cost = 0.0  # seconds the last rewrite took
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._load()

    # ------------------------------------------------------------------ paths
    @property
    def poses_path(self) -> Path:
        """poses.json in the output folder."""
        return self.out_dir / "poses.json"

    @property
    def csv_path(self) -> Path:
        """poses.csv in the output folder."""
        return self.out_dir / "poses.csv"

    @property
    def part_path(self) -> Path:
        """This shard's part, ``parts/shard-<i>-of-<n>.json``."""
        return self.out_dir / "parts" / f"shard-{self.shard:03d}-of-{self.num_shards:03d}.json"

    def _part_paths(self) -> List[Path]:
        d = self.out_dir / "parts"
        return sorted(d.glob("shard-*.json")) if d.is_dir() else []

    @property
    def journal_path(self) -> Path:
        """``poses.jsonl`` (a shard: ``parts/shard-<i>-of-<n>.jsonl``)."""
        return (self.part_path if self.num_shards > 1 else self.poses_path).with_suffix(".jsonl")

    def _journal_paths(self) -> List[Path]:
        d = self.out_dir / "parts"
        own = [self.out_dir / "poses.jsonl"] if (self.out_dir / "poses.jsonl").is_file() else []
        return own + (sorted(d.glob("shard-*.jsonl")) if d.is_dir() else [])

    def _read_journal(self, path: Path) -> List[Dict[str, Any]]:
        """The rows of a journal.

        Its first line names the run (checked); a broken line (a kill in mid-write) is skipped.
        """
        rows = []
        try:
            lines = path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise LedgerError(f"cannot read {path} ({e}); move it away to start over") from None
        for n, line in enumerate(lines):
            try:
                obj = json.loads(line)
            except json.JSONDecodeError:
                logger.warning(
                    "%s: line %d is cut short (a kill while writing); ignored", path, n + 1
                )
                continue
            if isinstance(obj, dict) and "run" in obj and "name" not in obj:
                self._check_identity(obj, path)
            elif isinstance(obj, dict) and isinstance(obj.get("name"), str):
                rows.append(obj)
        return rows

    def _append_journal(self, row: Dict[str, Any]) -> None:
        p = self.journal_path
        p.parent.mkdir(parents=True, exist_ok=True)
        new = not p.is_file()
        with open(p, "a") as fh:
            if new:
                fh.write(json.dumps({"run": {k: self.run.get(k) for k in RUN_IDENTITY}}) + "\n")
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            os.fsync(fh.fileno())

    # ------------------------------------------------------------------ resume
    def _check_identity(self, doc: Dict[str, Any], path: Path) -> None:
        theirs = doc.get("run") or {}
        for k in RUN_IDENTITY:
            if theirs.get(k) != self.run.get(k):
                raise LedgerError(
                    f"{path} belongs to another run ({k} {theirs.get(k)!r}, "
                    f"this run {self.run.get(k)!r}); "
                    "choose another output folder (output.dir or hydra.run.dir) to start a new one"
                )

    def _load(self) -> None:
        self._counts = None
        sources = ([self.poses_path] if self.poses_path.is_file() else []) + self._part_paths()
        for p in sources:
            doc = read_poses_json(p)
            self._check_identity(doc, p)
            for r in doc["photos"]:
                if isinstance(r, dict) and isinstance(r.get("name"), str):
                    self._seen[r["name"]] = r
        for p in self._journal_paths():  # newer than the documents
            for r in self._read_journal(p):
                self._seen[r["name"]] = r
        for name in list(self._seen):  # keep this shard's earlier rows in its own files
            r = self._seen[name]
            if self.num_shards == 1 or r.get("shard", self.shard) == self.shard:
                self.rows[name] = self._seen.pop(name)

    def finished(self, retry_failed: bool = False) -> Dict[str, Dict[str, Any]]:
        """Rows recorded by earlier runs or other shards, by name.

        The failed ones are left out with ``retry_failed``.
        """
        rows = {**self._seen, **self.rows}
        if retry_failed:
            rows = {k: r for k, r in rows.items() if r.get("status") != "failed"}
        return rows

    def forget(self, names: Sequence[str]) -> None:
        """Drop rows that are going to be redone (``retry_failed``)."""
        self._counts = None
        for n in names:
            self.rows.pop(n, None)
            self._seen.pop(n, None)

    # ------------------------------------------------------------------ writing
    def all_rows(self) -> List[Dict[str, Any]]:
        """Every row known, earlier runs' and this run's, in input order."""
        rows = {**self._seen, **self.rows}
        return sorted(rows.values(), key=lambda r: (r.get("index", 0), r["name"]))

    def _document(self, rows: List[Dict[str, Any]], status: Optional[str] = None) -> Dict[str, Any]:
        done = len(rows)
        return {
            "format": "icomma-poses",
            "version": FORMAT_VERSION,
            "status": status or ("complete" if done >= self.total else "running"),
            "total": self.total,
            "done": done,
            "counts": counts_of(rows),
            "conventions": "c2w / w2c: 4x4, OpenCV camera axes (x right, y down, z forward), "
            "column vectors",
            "run": self.run,
            "photos": rows,
        }

    def _write_csv(self, rows: List[Dict[str, Any]]) -> None:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            w.writerow([_fmt(r.get(k)) for k in CSV_COLUMNS])
        write_text_atomic(self.csv_path, buf.getvalue())

    def _write_merged(self) -> None:
        rows = self.all_rows()
        write_json_atomic(self.poses_path, self._document(rows), rows_key="photos")
        self._write_csv(rows)

    def flush(self) -> None:
        """Write poses.json / poses.csv (and this shard's part) now."""
        t = time.monotonic()
        self._flush()
        self._last_write = time.monotonic()
        self._write_cost = self._last_write - t

    def _flush(self) -> None:
        self._counts = None  # (other shards' rows may arrive)
        if self.num_shards == 1:
            self._write_merged()
            return
        mine = sorted(self.rows.values(), key=lambda r: (r.get("index", 0), r["name"]))
        part = self._document(mine, status="running")
        part.update({"shard": self.shard, "num_shards": self.num_shards})
        write_json_atomic(self.part_path, part, rows_key="photos")
        with file_lock(self.out_dir / ".poses.lock"):
            for p in self._part_paths():  # the other shards' latest rows
                try:
                    doc = read_poses_json(p)
                except LedgerError as e:  # a part being replaced is never half-written; still
                    logger.warning("skipping %s: %s", p, e)
                    continue
                for r in doc["photos"]:
                    if (
                        isinstance(r, dict)
                        and isinstance(r.get("name"), str)
                        and r["name"] not in self.rows
                    ):
                        self._seen[r["name"]] = r
            for p in self._journal_paths():
                if p != self.journal_path:
                    for r in self._read_journal(p):
                        if r["name"] not in self.rows:
                            self._seen[r["name"]] = r
            self._write_merged()

    def _rewrite_due(self) -> bool:
        n = len(self.rows) + len(self._seen)
        wait = max(self.min_rewrite_seconds, self._write_cost / self.max_rewrite_share)
        if n > self.rewrite_rows:
            wait = max(wait, self.rewrite_seconds)
        return time.monotonic() - self._last_write >= wait

    def record(self, row: Dict[str, Any]) -> None:
        """Add one photo's row.

        To the journal at once, to poses.json / poses.csv when due (module docstring).
        """
        if not isinstance(row.get("name"), str) or row.get("status") not in VERDICTS:
            raise ValueError(
                f"a ledger row needs a name and a status in {VERDICTS}, got {row!r:.200}"
            )
        row = dict(row)
        if self.num_shards > 1:
            row["shard"] = self.shard
        self._append_journal(row)
        if self._counts is not None:
            old = self.rows.get(row["name"], self._seen.get(row["name"]))
            if old is not None and old.get("status") in self._counts:
                self._counts[old["status"]] -= 1
            self._counts[row["status"]] += 1
        self.rows[row["name"]] = row
        self._seen.pop(row["name"], None)
        if self._rewrite_due():
            self.flush()

    def close(self) -> Dict[str, Any]:
        """Final write; returns the poses.json document."""
        self.flush()
        return read_poses_json(self.poses_path)

    def counts(self) -> Dict[str, int]:
        """``{"ok": n, "uncertain": n, "failed": n}`` over every row known."""
        if self._counts is None:
            self._counts = counts_of(self.all_rows())
        return dict(self._counts)
