"""bench/depth_bias.py: the oracle that takes a rendered room's depth bias pattern off, and its table."""

from __future__ import annotations

import pickle

import numpy as np

from bench import depth_bias, tables
from ctcvo.data.scenes import open_scene
from ctcvo.data.synthetic.config import resolve_preset
from ctcvo.data.synthetic.sensor import depth_bias_field


def test_debiased_room_has_its_true_pattern_taken_off_every_raw_depth_image():
    raw = open_scene("synthetic/tiny")[0]
    seq = depth_bias.debiased(open_scene("synthetic/tiny")[0], "tiny")
    cfg = resolve_preset("tiny")
    bias = depth_bias_field(cfg.sensor, (cfg.height, cfg.width), cfg.seed)
    assert bias is not None and float(np.abs(bias).max()) > 1e-4
    z, zc = raw.depth(3), seq.depth(3)
    both = (z > 0) & (zc > 0)
    assert both.sum() > 0.5 * (z > 0).sum()
    np.testing.assert_allclose(1.0 / zc[both], 1.0 / z[both] - bias[both], rtol=1e-5)
    assert not np.any(zc[z == 0])  # holes stay holes
    # the teacher's worker processes get the sequence pickled
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(seq)).depth(3), zc)


def test_table_shows_each_room_as_rendered_and_without_its_pattern():
    fig = {"ate_m": 0.0065, "rpe_gap1_m": 0.0012, "rpe_1s_m": 0.0042, "chain_ate_m": 0.0064}
    off = {"ate_m": 0.0030, "rpe_gap1_m": 0.0012, "rpe_1s_m": 0.0035, "chain_ate_m": 0.0058}
    rec = {"revision": "abc1234", "date_utc": "2026-12-06T00:00:00Z", "config": {"frames": "0:300"},
           "machine": {"cpu_count": 2, "load_average_start": [1.0], "load_average_end": [1.0]},
           "figures": {"rooms": {"lab": {"as rendered": fig, "bias removed": off}}}}
    lines = tables.depth_bias_table({"depth-bias": rec})
    assert lines[0].startswith("| room, frames 0:300 |")
    assert lines[2] == "| lab (validation) | 6.4 -> 5.8 | 6.5 -> 3.0 | 4.2 -> 3.5 |"
    assert tables.depth_bias_table({})[0].startswith("No record yet")
