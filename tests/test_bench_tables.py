"""bench/tables.py: the documents' tables are what the committed records make."""

from __future__ import annotations

import pytest

from bench import record, tables


@pytest.mark.parametrize("doc", tables.DOCUMENTS, ids=lambda p: p.relative_to(record.REPO).as_posix())
def test_document_tables_are_not_stale(doc):
    text = doc.read_text()
    assert text.count("<!-- table: ") == text.count("<!-- /table -->") > 0
    assert tables.update(text, record.load()) == text, f"{doc.name} is stale: run python -m bench.tables"


def test_document_lengths():
    assert len((record.REPO / "README.md").read_text().splitlines()) <= 150
    assert len((record.REPO / "bench" / "README.md").read_text().splitlines()) <= 400


def test_at_least_five_records_each_with_its_table():
    recs = record.load()
    assert len(recs) >= 5
    text = "\n".join(doc.read_text() for doc in tables.DOCUMENTS)
    for name in recs:
        assert f"`{name}`" in text, f"no table names the record {name}"


def test_update_rewrites_only_between_the_markers():
    rec = {"learner-cpu": {"revision": "abc1234", "date_utc": "2026-01-01T00:00:00Z",
                           "machine": {"cpu_count": 2, "load_average_start": [1.0, 1, 1], "load_average_end": [2.0, 1, 1]},
                           "figures": {"preset": "cpu", "input": "flow", "threads": 2, "size": "64x48",
                                       **{f"{k}_pairs_per{s}": 10.0 for k in ("train_phase1", "train_phase2", "predict")
                                          for s in ("_s", "_cpu_s")}}}}
    text = "before\n<!-- table: learner -->\nold\n<!-- /table -->\nafter\n<!-- table: teacher -->\n<!-- /table -->\n"
    new = tables.update(text, rec)
    assert new.startswith("before\n<!-- table: learner -->\n| preset |") and "old" not in new
    assert "| cpu | flow | 2 | 64x48 | 10 (10) | 10 (10) | 10 (10) |" in new
    assert "`learner-cpu` (abc1234, 2026-01-01, 2 cores, load 1.0-2.0)" in new
    assert "<!-- /table -->\nafter\n<!-- table: teacher -->\nNo record yet: `python -m bench.teacher`.\n<!-- /table -->" in new
    assert tables.update(new, rec) == new
    with pytest.raises(SystemExit, match="unknown table"):
        tables.update("<!-- table: nope -->\n<!-- /table -->", rec)


def test_online_learner_cell_puts_the_learner_beside_the_same_runs_teacher():
    row = {"online_fps": 20.0, "learner_fps": 12.0, "learner_preset": "demo",
           "learner_latency_ms": {"p50": 101.2, "p95": 230.0}, "learner_30hz_latency_ms": {"p50": 90.0, "p95": 150.4}}
    assert tables.learner_cell(row) == "demo preset: 12.0 (0.60x), 101 / 230, 90 / 150"
    assert tables.learner_cell({"online_fps": 20.0}) == "-"


def test_ablation_table_ratio_to_the_teacher_and_seed_means():
    machine = {"cpu_count": 2, "load_average_start": [1.0, 1, 1], "load_average_end": [2.0, 1, 1]}
    base = {"ate_rmse_m": 0.05, "rpe_trans_rmse_m": 0.006, "rpe_rot_rmse_deg": 0.3}
    rows = {"teacher": {**base, "se3_l2_mean": 0.008, "se3_l2_x_teacher": 1.0, "vs_teacher": {"se3_l2_mean": 0.0}},
            "ctc seed 0": {**base, "variant": "ctc", "seed": 0, "se3_l2_mean": 0.006, "se3_l2_x_teacher": 0.75,
                           "vs_teacher": {"se3_l2_mean": 0.009}},
            "ctc seed 1": {**base, "variant": "ctc", "seed": 1, "se3_l2_mean": 0.010, "se3_l2_x_teacher": 1.25,
                           "vs_teacher": {"se3_l2_mean": 0.011}}}
    rec = {"ablation-x": {"revision": "abc1234", "date_utc": "2026-01-01T00:00:00Z", "machine": machine,
                          "figures": {"rows": rows, "seeds": {"ctc": {
                              "seeds": [0, 1], "se3_l2_mean": {"mean": 0.008, "std": 0.002, "n": 2},
                              "se3_l2_x_teacher": {"mean": 1.0, "std": 0.25, "n": 2},
                              "rpe_trans_rmse_m": {"mean": 0.006, "std": 0.0, "n": 2},
                              "rpe_rot_rmse_deg": {"mean": 0.3, "std": 0.0, "n": 2}}}}}}
    lines = tables.ablation_table(rec)
    assert "| ablation-x | teacher | 0.00800 | 1.00 | 6.00 | 0.300 | 50.0 |" in lines
    assert "| ablation-x | ctc (2 seeds) | 0.00800 +- 0.00200 | 1.00 +- 0.25 | 6.00 +- 0.00 | " \
           "0.300 +- 0.000 | - |" in lines
    assert len([x for x in lines if x.startswith("| ablation-x")]) == 2  # the seeds' own rows stay in the record
    one = {"ablation-y": {**rec["ablation-x"], "figures": {"rows": {"ctc": rows["ctc seed 0"]}, "seeds": {
        "ctc": {"seeds": [0], "se3_l2_mean": {"mean": 0.006, "std": 0.0, "n": 1}}}}}}
    assert "| ablation-y | ctc | 0.00600 | 0.75 | 6.00 | 0.300 | 50.0 |" in tables.ablation_table(one)
    # a reference row two records share (the same test frames) is shown once, naming both
    both = tables.ablation_table({**rec, "ablation-z": rec["ablation-x"]})
    assert "| ablation-x, ablation-z | teacher | 0.00800 | 1.00 | 6.00 | 0.300 | 50.0 |" in both
    assert sum(x.startswith("| ablation-z | ctc (2 seeds)") for x in both) == 1


def test_online_validation_table_puts_each_setting_in_its_column():
    machine = {"cpu_count": 2, "load_average_start": [1.0, 1, 1], "load_average_end": [1.0, 1, 1]}

    def rec(gaps, after, ate, p95):
        row = {"scene": "lab", "online_gaps": gaps, "pose_after_gap1": after, "ate_m": {"final": ate, "causal": ate},
               "online_latency_ms": {"p95": p95}, "online_30hz_latency_ms": {"p95": p95 / 2}}
        return {"revision": "abc", "date_utc": "2026-01-01T00:00:00Z", "machine": machine,
                "config": {"frames": "0:200"}, "figures": {"rows": [row]}}

    lines = tables.online_validation_table({"val-a": rec(5, True, 0.010, 30.0), "val-b": rec(5, False, 0.011, 140.0),
                                            "val-c": rec(3, True, 0.012, 20.0)})
    row = next(x for x in lines if x.startswith("| lab"))
    assert row.split(" | ")[1:] == ["11.0 / 10.0 / - / 12.0", "11.0 / 10.0 / - / 12.0", "140 / 30 / - / 20",
                                    "70 / 15 / - / 10 |"]
    assert "`val-a`" in lines[-1] and "`val-b`" in lines[-1]


def test_noise_table_puts_each_learner_beside_its_teacher_and_the_baselines():
    def err(x):
        return {"se3_l2_mean": x}

    fig = {"ranges": {"held-out": "450:600", "transductive": "0:450"},
           "baselines": {n: {"zero motion": err(0.013), "constant velocity": err(0.011)} for n in ("held-out", "transductive")},
           "teachers": {"noisy52": {"held-out": err(0.005), "transductive": err(0.0052)}},
           "learners": {"noisy52/ctc": {"teacher": "noisy52", "variant": "ctc",
                                        "held-out": {**err(0.008), "vs_teacher": 1.6},
                                        "transductive": {**err(0.0039), "vs_teacher": 0.75}}}}
    rec = {"teacher-noise": {"name": "teacher-noise", "revision": "abc1234", "date_utc": "2026-01-01T00:00:00Z",
                             "machine": {"cpu_count": 2, "load_average_start": [1.0], "load_average_end": [2.0]},
                             "figures": fig}}
    lines = tables.noise_table(rec)
    assert lines[0] == "| record | teacher's labels: held-out / transductive se(3) L2 | ctc |"
    assert lines[2] == "| teacher-noise | noisy52: 0.00500 / 0.00520 | 0.00800 (1.60x) / 0.00390 (0.75x) |"
    assert lines[4] == ("`teacher-noise` (held-out 450:600 / transductive 0:450): zero motion 0.01300 / 0.01300, "
                        "constant velocity 0.01100 / 0.01100.")
