"""twinfocus.io.atomic: a file appears whole or not at all; a failed write keeps the old file."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from twinfocus.io.atomic import atomic_writer, write_bytes_atomic, write_json_atomic, write_text_atomic


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "result.bin"
    write_bytes_atomic(path, b"old")
    with pytest.raises(RuntimeError):
        with atomic_writer(path) as f:
            f.write(b"half of the new")
            raise RuntimeError("disk full")
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.bin"]


def test_mode_is_what_a_plain_open_gives(tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    atomic = write_text_atomic(tmp_path / "sub" / "atomic.txt", "x")
    assert atomic.read_text() == "x"
    assert (atomic.stat().st_mode & 0o777) == (plain.stat().st_mode & 0o777)


def test_json_takes_numpy_values_as_plain_numbers(tmp_path):
    doc = {"a": np.float32(0.5), "b": np.arange(3), "c": (1, 2), "d": np.int64(7), "e": np.bool_(True)}
    write_json_atomic(tmp_path / "doc.json", doc)
    assert json.loads((tmp_path / "doc.json").read_text()) == {"a": 0.5, "b": [0, 1, 2], "c": [1, 2], "d": 7, "e": True}
    with pytest.raises(TypeError):
        write_json_atomic(tmp_path / "bad.json", {"x": object()})
    assert not (tmp_path / "bad.json").exists() and os.listdir(tmp_path) == ["doc.json"]
