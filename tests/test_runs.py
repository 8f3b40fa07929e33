"""The rerun rule every stage follows (data/runs.py) and the run layout, stage by stage:
the same inputs are skipped, other inputs need --overwrite and the error names what
differs; fit makes teacher labels for every range it uses; predict never writes into a
training run; Ctrl-C in fit is one line and --resume --out DIR needs nothing else."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data.errors import ConfigError
from ctcvo.data.runs import (
    Fingerprint,
    StaleOutputError,
    claim,
    differences,
    frames_id,
    output_folder,
    stage_dir,
    write_fingerprint,
)

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------------
# the helper
# ----------------------------------------------------------------------------------
def test_stage_dir_is_the_one_layout() -> None:
    assert stage_dir("synthetic/office", "teacher") == Path("runs/synthetic-office/teacher")
    assert stage_dir("/data/7scenes/redkitchen/seq-01", "predict") == Path("runs/seq-01/predict")  # not a sequence
    with pytest.raises(ValueError):
        stage_dir("synthetic/office", "nope")


def test_frames_id_and_differences() -> None:
    assert frames_id(np.arange(450, 600)) == "450..599 (150 frames)"
    assert frames_id(np.arange(0, 20, 2)) == "0..18 (10 frames, step 2)"
    assert frames_id(np.array([0, 1, 5])).startswith("0..5 (3 frames, ids ")
    d = differences({"frames": "a", "cfg": {"gaps": 5, "n": 1}}, {"frames": "b", "cfg": {"gaps": 2, "n": 1}})
    assert d == "frames: a -> b; cfg.gaps: 5 -> 2"


def test_claim_same_other_and_overwrite(tmp_path) -> None:
    out = tmp_path / "stage"
    fp = Fingerprint("x", {"frames": "0..9 (10 frames)", "k": 1})
    assert claim(out, fp, done=False, has_outputs=False, overwrite=False) is False  # nothing there: run
    out.mkdir()
    (out / "result.txt").write_text("old")
    write_fingerprint(out, fp)
    assert claim(out, fp, done=True, has_outputs=True, overwrite=False) is True  # same: skip
    assert claim(out, fp, done=False, has_outputs=True, overwrite=False) is False  # same, unfinished: resume
    other = Fingerprint("x", {"frames": "0..9 (10 frames)", "k": 2})
    with pytest.raises(StaleOutputError, match=r"holds outputs of other inputs \(k: 1 -> 2\); pass --overwrite"):
        claim(out, other, done=True, has_outputs=True, overwrite=False)
    assert (out / "result.txt").read_text() == "old"
    assert claim(out, other, done=True, has_outputs=True, overwrite=True, outputs=["result.txt"]) is False
    assert not (out / "result.txt").exists() and not (out / "fingerprint.json").exists()


def test_a_code_version_bump_makes_kept_outputs_stale(tmp_path, monkeypatch) -> None:
    """The same inputs written by an older version of a stage's code are not kept: the
    error says which version wrote them; a folder from before versions were recorded
    (no ``version``) counts as version 0."""
    import ctcvo.data.runs as runs

    out = tmp_path / "stage"
    out.mkdir()
    (out / "result.txt").write_text("old")
    fp = Fingerprint("teacher", {"frames": "0..9 (10 frames)"})
    write_fingerprint(out, fp)
    assert json.loads((out / "fingerprint.json").read_text())["version"] == runs.STAGE_VERSIONS["teacher"]
    assert claim(out, fp, done=True, has_outputs=True, overwrite=False) is True
    monkeypatch.setitem(runs.STAGE_VERSIONS, "teacher", runs.STAGE_VERSIONS["teacher"] + 1)
    newer = Fingerprint("teacher", {"frames": "0..9 (10 frames)"})
    assert newer.digest != fp.digest
    v = runs.STAGE_VERSIONS["teacher"]
    with pytest.raises(StaleOutputError, match=rf"outputs of version {v - 1} of the teacher stage's code "
                                               rf"\(now version {v}\); pass --overwrite"):
        claim(out, newer, done=True, has_outputs=True, overwrite=False)
    old = json.loads((out / "fingerprint.json").read_text())
    del old["version"]
    (out / "fingerprint.json").write_text(json.dumps(old))
    with pytest.raises(StaleOutputError, match="outputs of version 0 of the teacher stage's code"):
        claim(out, newer, done=True, has_outputs=True, overwrite=False)
    assert (out / "result.txt").read_text() == "old"


def test_output_folder_removes_only_what_a_failure_left_empty(tmp_path) -> None:
    with pytest.raises(RuntimeError):
        with output_folder(tmp_path / "a" / "b" / "c") as d:
            (d / "cache").mkdir(parents=True)
            raise RuntimeError
    assert not (tmp_path / "a").exists()
    with pytest.raises(RuntimeError):
        with output_folder(tmp_path / "k" / "l") as d:
            d.mkdir(parents=True)
            (d / "kept.txt").write_text("finished work")
            raise RuntimeError
    assert (tmp_path / "k" / "l" / "kept.txt").is_file()
    (tmp_path / "ro").mkdir()
    (tmp_path / "ro").chmod(0o500)
    try:
        if not os.access(tmp_path / "ro", os.W_OK):  # root writes anyway
            with pytest.raises(ConfigError, match="not writable"):
                with output_folder(tmp_path / "ro" / "x"):
                    pass
    finally:
        (tmp_path / "ro").chmod(0o700)


# ----------------------------------------------------------------------------------
# learner fit / predict
# ----------------------------------------------------------------------------------
@pytest.fixture()
def tiny_run(tmp_path, monkeypatch):
    """Work in tmp_path (the default runs/ folders land there)."""
    import torch

    monkeypatch.chdir(tmp_path)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield tmp_path
    torch.set_num_threads(before)


@pytest.mark.slow
def test_fit_labels_every_range_reruns_and_predict_keeps_out_of_the_run(tiny_run, caplog) -> None:
    """With teacher labels over 0:20 in the default folder, fit on 0:8 validating on 8:20
    of the same sequence reads both ranges' labels from it. A second identical fit is kept;
    other inputs are an error until --overwrite. predict writes to runs/<scene>/predict
    (never the training run, even for the training scene) and is skipped when rerun."""
    from ctcvo.learner.predict import predict
    from ctcvo.learner.train import fit
    from ctcvo.teacher.generate import generate

    generate("synthetic/tiny", frames="0:20")

    kw = dict(variant="cnn-unsup", preset="tiny", frames="0:8", val_scenes=["synthetic/tiny"], val_frames="8:20",
              steps=2)
    res = fit(["synthetic/tiny"], **kw)
    teacher = tiny_run / "runs" / "synthetic-tiny" / "teacher"
    assert json.loads((teacher / "fingerprint.json").read_text())["inputs"]["frames"] == "0..19 (20 frames)"
    assert res.run_dir == Path("runs/synthetic-tiny/learner") and res.calibration is not None
    fp = json.loads((res.run_dir / "fingerprint.json").read_text())
    assert fp["stage"] == "learner" and [s[2] for s in fp["inputs"]["val_sequences"]] == ["8..19 (12 frames)"]
    mtime = res.checkpoint.stat().st_mtime_ns
    caplog.clear()
    caplog.set_level("INFO")
    again = fit(["synthetic/tiny"], **kw)
    assert again.checkpoint.stat().st_mtime_ns == mtime and again.history == res.history
    assert "finished training of the same inputs" in caplog.text
    with pytest.raises(StaleOutputError, match=r"train.steps: 2 -> 4"):
        fit(["synthetic/tiny"], **{**kw, "steps": 4})
    assert res.checkpoint.stat().st_mtime_ns == mtime
    longer = fit(["synthetic/tiny"], **{**kw, "steps": 4}, overwrite=True)
    assert len(longer.history) == 2 and longer.checkpoint.stat().st_mtime_ns != mtime

    pred = predict(longer.checkpoint, "synthetic/tiny", frames="8:16")
    out = tiny_run / "runs" / "synthetic-tiny" / "predict"
    assert pred.out_dirs == [Path("runs/synthetic-tiny/predict")] and (out / "edges.g2o").is_file()
    assert not (res.run_dir / "edges.g2o").exists() and not (res.run_dir / "report.json").exists()
    mtime = (out / "edges.g2o").stat().st_mtime_ns
    again = predict(longer.checkpoint, "synthetic/tiny", frames="8:16")
    assert (out / "edges.g2o").stat().st_mtime_ns == mtime and again.reports == pred.reports
    with pytest.raises(StaleOutputError, match="frames: 8..15"):
        predict(longer.checkpoint, "synthetic/tiny", frames="0:8")
    with pytest.raises(ConfigError, match="training run's folder"):
        predict(longer.checkpoint, "synthetic/tiny", out=res.run_dir)


def test_cli_ctrl_c_is_one_line_and_resume_needs_only_out(tiny_run, monkeypatch, capsys, caplog) -> None:
    import ctcvo.learner.train as T
    from ctcvo.learner import cli
    from ctcvo.teacher.generate import generate

    generate("synthetic/tiny", frames="0:10")
    real = T._train_epoch

    def second_epoch_interrupted(*a, **k):
        if a[8] == 1:  # epoch index
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(T, "_train_epoch", second_epoch_interrupted)
    out = tiny_run / "r"
    args = ["fit", "--scene", "synthetic/tiny", "--frames", "0:10", "--variant", "cnn-unsup", "--preset", "tiny",
            "--steps", "4", "--out", str(out)]
    assert cli.main(args) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"interrupted at epoch 2; `learner fit --resume --out {out}` continues"]
    monkeypatch.setattr(T, "_train_epoch", real)
    caplog.clear()
    caplog.set_level("INFO")
    assert cli.main(["fit", "--resume", "--out", str(out)]) == 0
    assert f"resuming {out} after epoch 1/2 (step 2 of 4)" in caplog.text
    assert T.load_checkpoint(out / "checkpoint.pt")["epoch"] == 2
    # asked to train on other frames with --resume: refused, saying what differs
    assert cli.main(["fit", "--resume", "--out", str(out), "--frames", "0:12"]) == 1
    err = capsys.readouterr().err
    assert "trained with other options than those given with --resume (frames: 0:10 -> 0:12)" in err


# ----------------------------------------------------------------------------------
# command lines
# ----------------------------------------------------------------------------------
def _parsers():
    from ctcvo.learner.cli import _parser as learner_parser
    from ctcvo.posegraph.cli import _parser as posegraph_parser
    from ctcvo.teacher.cli import build_parser as teacher_parser

    for p in (teacher_parser(), learner_parser(), posegraph_parser()):
        yield p
        for action in p._actions:
            if action.choices and isinstance(action.choices, dict):
                yield from action.choices.values()


def test_every_option_has_help_and_no_sphinx_markup() -> None:
    for p in _parsers():
        text = p.format_help()
        assert ":func:" not in text and "``" not in text and ":class:" not in text, p.prog
        assert "-v, --verbose" in text, p.prog  # -v before or after the command, in every CLI
        for a in p._actions:
            if a.option_strings and a.dest != "help":
                assert a.help and len(a.help) > 8, (p.prog, a.option_strings)
    from ctcvo.learner.cli import _parser

    fit_help = " ".join(_parser()._subparsers._group_actions[0].choices["fit"].format_help().split())
    assert "'tiny' - a toy network for the tests only" in fit_help and "(default: auto)" in fit_help


def test_verbose_in_one_place_for_every_cli() -> None:
    from ctcvo.learner.cli import _parser as lp
    from ctcvo.posegraph.cli import _parser as pp
    from ctcvo.teacher.cli import build_parser as tp

    for parser, cmd in ((tp(), ["generate", "--scene", "x"]), (lp(), ["predict", "--checkpoint", "c", "--scene", "x"]),
                        (pp(), ["optimize", "--scene", "x"])):
        assert parser.parse_args(["-v", *cmd]).verbose is True
        assert parser.parse_args([*cmd, "-v"]).verbose is True
        assert parser.parse_args(cmd).verbose is False


def test_posegraph_imports_neither_learner_nor_teacher_nor_torch() -> None:
    mods = ["ctcvo.posegraph." + f.stem for f in sorted((REPO / "ctcvo" / "posegraph").glob("*.py")) if f.stem != "__init__"]
    assert len(mods) > 5, mods
    code = (f"import sys; import {', '.join(mods)}\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'torch' or m.startswith(('ctcvo.learner', "
            "'ctcvo.teacher', 'ctcvo.pipeline')))\n"
            "assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_sequences_of_two_scenes_never_share_a_default_folder(tmp_path) -> None:
    """7-Scenes chess/seq-01 and office/seq-01: two default folders, named as the logs name
    the sequences (``chess-seq-01``); synthetic/NAME and other folders keep their names."""
    seqs = []
    for scene in ("chess", "office"):
        d = tmp_path / "7scenes" / scene / "seq-01"
        d.mkdir(parents=True)
        (d / "frame-000000.depth.png").touch()
        seqs.append(d)
    dirs = [stage_dir(str(d), "teacher") for d in seqs]
    assert dirs == [Path("runs/chess-seq-01/teacher"), Path("runs/office-seq-01/teacher")]
    assert stage_dir(str(tmp_path / "7scenes" / "chess"), "teacher") == Path("runs/chess/teacher")
    assert stage_dir("synthetic/lab", "teacher") == Path("runs/synthetic-lab/teacher")



def test_slug_is_the_name_the_logs_use(redkitchen) -> None:
    from ctcvo.data.scenes import open_scene

    [seq] = open_scene(str(redkitchen), frames="0:3")
    assert stage_dir(str(redkitchen), "teacher") == Path("runs") / seq.name / "teacher"
    assert seq.name == "redkitchen-seq-sample"
