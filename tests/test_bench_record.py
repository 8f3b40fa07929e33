"""bench/record.py: a benchmark record has every field and is written atomically."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from bench import record


def test_record_has_every_field_and_plain_numbers(tmp_path):
    rec = record.start("x", {"scene": record.REDKITCHEN, "frames": "0:10", "n": np.int64(3)}, tmp_path)
    path = rec.finish({"fps": np.float32(2.5), "bad": float("nan"), "rows": [{"e": np.array([1.0, 2.0])}]})
    assert path == tmp_path / "x.json"
    d = json.loads(path.read_text())
    assert all(k in d for k in record.FIELDS)
    assert d["name"] == "x" and d["command"][:2] == ["python", "-m"]
    assert len(d["revision"]) >= 7 and d["date_utc"].endswith("Z")
    m = d["machine"]
    assert m["cpu_count"] >= 1 and len(m["load_average_start"]) == 3 and len(m["load_average_end"]) == 3
    assert m["libraries"]["numpy"] == np.__version__ and m["python"].count(".") == 2
    assert d["config"] == {"scene": "../shared/data/7scenes/redkitchen/seq-sample", "frames": "0:10", "n": 3}
    assert d["figures"] == {"fps": 2.5, "bad": None, "rows": [{"e": [1.0, 2.0]}]}
    assert record.load(tmp_path)["x"] == d


def test_a_failed_write_keeps_the_previous_record(tmp_path):
    record.start("x", {}, tmp_path).finish({"fps": 1.0})
    before = (tmp_path / "x.json").read_text()
    with pytest.raises(TypeError):
        record.start("x", {}, tmp_path).finish({"fps": object()})  # not JSON: fails while writing
    assert (tmp_path / "x.json").read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]  # no temporary file left


def test_from_args_records_the_arguments_but_not_where_the_record_goes(tmp_path):
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", default="0:5")
    ap.add_argument("--out", type=Path, default=record.RUNS / "t")
    record.add_arguments(ap, "t")
    rec = record.from_args(ap.parse_args(["--results", str(tmp_path)]), extra=1)
    assert rec.name == "t" and rec.folder == tmp_path
    assert rec.config == {"frames": "0:5", "out": record.RUNS / "t", "extra": 1}
    d = json.loads(rec.finish({}).read_text())
    assert d["config"]["out"] == "runs/bench/t"
