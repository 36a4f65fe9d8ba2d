"""icomma_plugin.io.atomic: a failed write leaves the old file, and files get the usual mode."""
from __future__ import annotations

import json
import os
import stat

import pytest

from icomma_plugin.io.atomic import atomic_path, write_json_atomic, write_text_atomic


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "result.json"
    write_json_atomic(p, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed mid-write")
    assert p.read_text().strip().startswith("{") and '"a": 1' in p.read_text()
    assert [f.name for f in tmp_path.iterdir()] == ["result.json"]


def test_new_files_get_the_umask_mode_and_replaced_files_keep_theirs(tmp_path):
    old = os.umask(0o022)
    try:
        p = tmp_path / "poses.csv"
        write_text_atomic(p, "x\n")
        # readable by others, as open() would make it
        assert stat.S_IMODE(p.stat().st_mode) == 0o644
        os.chmod(p, 0o640)
        write_text_atomic(p, "y\n")
        assert stat.S_IMODE(p.stat().st_mode) == 0o640 and p.read_text() == "y\n"
    finally:
        os.umask(old)


def test_rows_are_written_one_a_line_and_read_back_the_same(tmp_path):
    rows = [{"name": f"frame_{i}", "c2w": [[float(i), 0.5], [1e-17, -2.0]], "note": 'a "quote"'}
            for i in range(3)]
    doc = {"format": "x", "run": {"args": [1, 2]}, "photos": rows, "after": {"k": None}}
    path = tmp_path / "poses.json"
    write_json_atomic(path, doc, rows_key="photos")
    text = path.read_text()
    assert json.loads(text) == doc
    lines = text.splitlines()
    assert sum(line.strip().startswith('{"name": "frame_') for line in lines) == 3  # one a line
    assert '  "run": {' in lines  # the rest stays indented
    write_json_atomic(path, {**doc, "photos": []}, rows_key="photos")
    assert json.loads(path.read_text())["photos"] == []
