"""Self-calibration of radial distortion (teacher/calibrate.py), camera files and
``--camera`` (data/undistort.py), and the colour camera's composed undistortion."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from ctcvo.data.errors import DataError
from ctcvo.data.formats import read_tum
from ctcvo.data.sensor import ColourCamera
from ctcvo.data.sequence import Intrinsics
from ctcvo.data.synthetic import synthetic_sequence
from ctcvo.data.synthetic.config import PRESETS
from ctcvo.data.undistort import Undistortion, read_camera, with_camera, write_camera
from ctcvo.teacher import cli as teacher_cli
from ctcvo.teacher.calibrate import estimate_k1

INTR = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)


def _room(tmp_path: Path, k1: float, frames: int = 70):
    """The office room's sensor with lens distortion ``k1`` (a 70-frame walk; the lab's short
    walk faces bare walls)."""
    cfg = PRESETS["office"]
    cfg = dataclasses.replace(cfg, frames=frames, sensor=dataclasses.replace(cfg.sensor, residual_distortion_k1=k1))
    return synthetic_sequence(f"office-k1-{k1}", tmp_path, config=cfg)


@pytest.mark.slow
def test_the_renderers_distortion_is_measured(tmp_path: Path) -> None:
    """The synthetic sensor's division-model distortion is OpenCV's k1 to first order: a
    room rendered with 0.03 measures about 0.03 more than the same walk rendered without.
    (On a walk this short the estimate carries a bias of about +0.02 of its own; on the
    300-frame validation rooms it is within 0.006 of the truth.)"""
    with_k1 = estimate_k1([_room(tmp_path, 0.03)])
    without = estimate_k1([_room(tmp_path, 0.0)])
    assert with_k1["pairs"] >= 50 and without["pairs"] >= 50
    assert abs((with_k1["k1"] - without["k1"]) - 0.03) < 0.01, (with_k1["k1"], without["k1"])
    assert with_k1["gain"] > without["gain"]


def test_colour_maps_compose_the_colour_camera_with_the_lens() -> None:
    """A registered colour camera gets the depth camera's maps; an unregistered one takes a
    colour pixel from where the raw colour image shows its depth pixel's raw position."""
    coeffs = (0.05, 0.0, 0.0, 0.0, 0.0)
    img = (np.arange(480 * 640) % 251).astype(np.uint8).reshape(480, 640, 1).repeat(3, 2)
    same = Undistortion(INTR, coeffs, ColourCamera(1.0, (0.0, 0.0), 0.0))
    plain = Undistortion(INTR, coeffs)
    diff = np.abs(same.rgb(img).astype(int) - plain.rgb(img).astype(int))
    assert np.median(diff) <= 1  # fixed-point and float maps of the same mapping
    cam = ColourCamera(0.91, (-3.5, -1.0), 0.0)
    und = Undistortion(INTR, coeffs, cam)
    mx, my = und._colour_maps
    u, v = 600, 60  # colour pixel -> depth pixel -> raw depth pixel -> raw colour pixel
    xd = ((320 + (u - 320 + 3.5) / 0.91) - 320) / 585
    yd = ((240 + (v - 240 + 1.0) / 0.91) - 240) / 585
    r2 = xd * xd + yd * yd
    np.testing.assert_allclose([mx[v, u], my[v, u]], [320 - 3.5 + 0.91 * 585 * xd * (1 + 0.05 * r2),
                                                     240 - 1.0 + 0.91 * 585 * yd * (1 + 0.05 * r2)], atol=1e-3)


def test_camera_files_and_their_errors(tmp_path: Path) -> None:
    path = tmp_path / "camera.json"
    write_camera(path, INTR, (0.01, 0.0, 0.0, 0.0, 0.0), {"calibration": {"k1": 0.01}})
    assert read_camera(path) == (INTR, (0.01, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(DataError, match="not found"):
        read_camera(tmp_path / "none.json")
    for body in ("{", '{"intrinsics": {}}', json.dumps({"intrinsics": dataclasses.asdict(INTR), "model": "opencv",
                                                        "distortion": [0.1, "nan", 0, 0]})):
        path.write_text(body)
        with pytest.raises(DataError, match="camera file|finite"):
            read_camera(path)


def test_with_camera_checks_the_camera_and_the_reader(tmp_path: Path, tum_images: Path) -> None:
    seq = synthetic_sequence("tiny", tmp_path)
    other = tmp_path / "other.json"
    write_camera(other, INTR, (0.01, 0, 0, 0, 0), {})
    if seq.intrinsics != INTR:
        with pytest.raises(DataError, match="camera of fx 585"):
            with_camera(seq, other)
    own = tmp_path / "own.json"
    write_camera(own, seq.intrinsics, (0.01, 0, 0, 0, 0), {})
    view = with_camera(seq, own)
    assert view.undistortion is not None and seq.undistortion is None
    assert not np.array_equal(view.depth(1), seq.depth(1))
    from ctcvo.data.tum import TumSequence

    fr1 = TumSequence(tum_images)
    write_camera(own, fr1.intrinsics, (0.01, 0, 0, 0, 0), {})
    with pytest.raises(DataError, match="already undistorts"):
        with_camera(fr1, own)


@pytest.mark.slow
def test_calibrate_then_generate_with_the_camera(tmp_path: Path) -> None:
    """`teacher calibrate` writes a camera file (kept on a rerun of the same inputs), and
    `teacher generate --camera` undistorts with it: recorded in config.json and in the
    fingerprint, and the trajectory differs from the run without it."""
    cam = tmp_path / "cam" / "camera.json"
    args = ["calibrate", "--scene", "synthetic/lab", "--frames", "0:70", "--out", str(cam)]
    assert teacher_cli.main(args) == 0
    k1 = read_camera(cam)[1][0]
    assert 0.005 < k1 < 0.03  # the lab's sensor: 0.015
    mtime = cam.stat().st_mtime_ns
    assert teacher_cli.main(args) == 0 and cam.stat().st_mtime_ns == mtime
    gen = ["generate", "--scene", "synthetic/lab", "--frames", "0:20", "--preset", "tiny", "--workers", "1",
           "--no-keyframes"]
    assert teacher_cli.main([*gen, "--out", str(tmp_path / "raw")]) == 0
    assert teacher_cli.main([*gen, "--camera", str(cam), "--out", str(tmp_path / "und")]) == 0
    conf = json.loads((tmp_path / "und" / "config.json").read_text())
    assert conf["undistortion"][0] == pytest.approx(k1)
    assert "undistortion" not in json.loads((tmp_path / "raw" / "config.json").read_text())
    fp = json.loads((tmp_path / "und" / "fingerprint.json").read_text())
    assert fp["inputs"]["undistortion"][0] == pytest.approx(k1)
    a, b = read_tum(tmp_path / "raw" / "trajectory.tum"), read_tum(tmp_path / "und" / "trajectory.tum")
    assert not np.allclose(a.poses, b.poses)
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    assert teacher_cli.main([*gen, "--camera", str(bad), "--out", str(tmp_path / "bad")]) != 0


@pytest.mark.slow
def test_online_with_a_camera_makes_the_batch_edges(tmp_path: Path) -> None:
    """`ctcvo online --camera` undistorts as `teacher generate --camera` does: the same
    edges.csv, and the camera's distortion in both fingerprints."""
    from ctcvo.pipeline import online
    from ctcvo.teacher.config import PRESETS as TEACHER_PRESETS
    from ctcvo.teacher.generate import generate

    cfg = dataclasses.replace(TEACHER_PRESETS["tiny"], workers=1)
    seq = synthetic_sequence("tiny", None)
    cam = tmp_path / "camera.json"
    write_camera(cam, seq.intrinsics, (0.02, 0.0, 0.0, 0.0, 0.0), {})
    generate("synthetic/tiny", tmp_path / "batch", config=cfg, progress=False, camera=cam)
    res = online.online("synthetic/tiny", tmp_path / "online", teacher_cfg=cfg, progress=False, camera=cam)
    assert (res.out / "teacher" / "edges.csv").read_text() == (tmp_path / "batch" / "edges.csv").read_text()
    for fp in (tmp_path / "batch" / "fingerprint.json", res.out / "fingerprint.json"):
        assert json.loads(fp.read_text())["inputs"]["undistortion"][0] == 0.02
