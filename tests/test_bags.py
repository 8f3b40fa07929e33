"""ROS1 and ROS2 bags as scenes (data/bag.py): bags written with rosbags from the real TUM
frames read back as the folder reads, the teacher gives the same trajectory from either,
and damaged or ambiguous bags give one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ctcvo.data import bag, bag_write
from ctcvo.data.errors import ConfigError
from ctcvo.data.formats import read_tum
from ctcvo.data.scenes import open_scene, scene_slug
from ctcvo.data.sensor import KINECT_V1_READOUT_S, Sensor
from ctcvo.data.undistort import Undistortion
from ctcvo.teacher import cli as teacher_cli

FRAMES = "0:24"


@pytest.fixture(scope="module")
def tum_seq(tum_images):
    return open_scene(str(tum_images), frames=FRAMES)[0]


@pytest.fixture(scope="module")
def bags(tum_seq, tmp_path_factory) -> dict[str, Path]:
    """The same 24 TUM frames as bags: ROS1 raw (32FC1 depth, exact metres), ROS1 bgr8 +
    16UC1, ROS2 sqlite3 raw, ROS2 mcap with JPEG-compressed colour."""
    d = tmp_path_factory.mktemp("bags")
    return {
        "ros1": bag_write.write_bag(tum_seq, d / "rec.bag", depth_encoding="32FC1"),
        "ros1_bgr_mm": bag_write.write_bag(tum_seq, d / "bgr.bag", colour_encoding="bgr8"),
        "ros2_sqlite": bag_write.write_bag(tum_seq, d / "rec2", ros2=True, depth_encoding="32FC1"),
        "ros2_mcap_jpeg": bag_write.write_bag(tum_seq, d / "rec2mcap", ros2=True, storage="mcap", compressed=True,
                                        depth_encoding="32FC1"),
    }


@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["ros1", "ros1_bgr_mm", "ros2_sqlite", "ros2_mcap_jpeg"])
def test_bag_reads_like_the_folder(bags, tum_seq, kind):
    [seq] = open_scene(str(bags[kind]) + "?gt=/groundtruth")
    assert isinstance(seq, bag.BagSequence)
    assert len(seq) == len(tum_seq)
    np.testing.assert_allclose(seq.times(), tum_seq.times(), atol=1e-9)
    np.testing.assert_array_equal(seq.depth_times(), tum_seq.depth_times())  # the depth messages' own stamps, exactly
    assert seq.intrinsics == tum_seq.intrinsics
    np.testing.assert_allclose(seq.groundtruth(), tum_seq.groundtruth(), atol=1e-9)
    for k in (0, 1, 7, 3, 23):  # in order, then backwards (restarts the pass)
        rgb, depth = seq.rgb(k), seq.depth(k)
        if kind == "ros2_mcap_jpeg":  # re-encoded JPEG: close, not equal
            assert np.abs(rgb.astype(int) - tum_seq.rgb(k)).mean() < 3.0
        else:
            np.testing.assert_array_equal(rgb, tum_seq.rgb(k))
        tol = 5e-4 if kind == "ros1_bgr_mm" else 0.0  # millimetres vs TUM's 0.2 mm units
        np.testing.assert_allclose(depth, tum_seq.depth(k), atol=tol, rtol=0)
    # no ground truth unless a topic names it
    assert not open_scene(str(bags[kind]))[0].has_groundtruth


@pytest.mark.realdata
def test_frames_stream_with_bounded_buffer(bags):
    [seq] = open_scene(str(bags["ros1"]))
    for k in range(len(seq)):
        seq.rgb(k)
        seq.depth(k)
        assert len(seq._cursor.buf) <= 2 * bag.LOOKAHEAD
    assert len(seq._cursor.buf) == 0  # every message read once, none kept


@pytest.mark.realdata
def test_sequence_crosses_processes(bags):
    """Teacher worker processes get the sequence pickled: the open bag stays behind and the
    copy reopens it (also a view made by select)."""
    import pickle

    [seq] = open_scene(str(bags["ros1"]))
    seq.rgb(0)
    view = seq.select(4, 9)
    for s, k in ((seq, 5), (view, 1)):
        twin = pickle.loads(pickle.dumps(s))
        assert twin._cursor is None
        np.testing.assert_array_equal(twin.rgb(k), s.rgb(k))
        np.testing.assert_array_equal(twin.depth(k), s.depth(k))


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["ros1", "ros2_sqlite"])
def test_teacher_trajectory_from_bag_equals_folder(bags, tum_images, tmp_path, kind):
    """Same frames in, same labels out: raw colour and float metres are bit-exact, so the
    teacher's trajectory from the bag equals the folder's."""
    args = ["--gaps", "2", "--preset", "tiny", "--workers", "1"]
    assert teacher_cli.main(["generate", "--scene", str(tum_images), "--frames", FRAMES,
                             "--out", str(tmp_path / "folder"), *args]) == 0
    assert teacher_cli.main(["generate", "--scene", str(bags[kind]), "--out", str(tmp_path / "bag"),
                             "--gt-topic", "/groundtruth", *args]) == 0
    a, b = read_tum(tmp_path / "folder" / "trajectory.tum"), read_tum(tmp_path / "bag" / "trajectory.tum")
    np.testing.assert_allclose(b.timestamps, a.timestamps, atol=1e-6)
    np.testing.assert_allclose(b.poses, a.poses, atol=1e-9)
    assert (tmp_path / "bag" / "groundtruth.tum").is_file()
    assert (tmp_path / "folder" / "edges.g2o").read_text() == (tmp_path / "bag" / "edges.g2o").read_text()


@pytest.mark.slow
@pytest.mark.realdata
def test_teacher_on_compressed_colour_bag_is_close(bags, tum_images, tmp_path):
    """JPEG re-encoding changes pixels, not the motion: the trajectory stays within 3 mm."""
    args = ["--gaps", "2", "--preset", "tiny", "--workers", "1"]
    assert teacher_cli.main(["generate", "--scene", str(tum_images), "--frames", FRAMES,
                             "--out", str(tmp_path / "folder"), *args]) == 0
    assert teacher_cli.main(["generate", "--scene", str(bags["ros2_mcap_jpeg"]), "--out", str(tmp_path / "bag"),
                             *args]) == 0
    a, b = read_tum(tmp_path / "folder" / "trajectory.tum"), read_tum(tmp_path / "bag" / "trajectory.tum")
    # 3 mm: fr1 frames are undistorted (resampled) before the bag re-encodes them as JPEG
    assert np.abs(b.poses[:, :3, 3] - a.poses[:, :3, 3]).max() < 3e-3


def test_spec_round_trip_and_slug():
    spec = bag.with_topics("runs/x/rec.bag", bag.BagTopics(rgb="/cam/rgb", gt="/tf:world:kinect"))
    assert spec == "runs/x/rec.bag?rgb=/cam/rgb&gt=/tf:world:kinect"
    path, topics = bag.parse_spec(spec)
    assert path == Path("runs/x/rec.bag") and topics == bag.BagTopics(rgb="/cam/rgb", gt="/tf:world:kinect")
    assert bag.with_topics(spec, bag.BagTopics(rgb="/other")) == "runs/x/rec.bag?rgb=/other&gt=/tf:world:kinect"
    assert scene_slug(spec) == "rec"
    with pytest.raises(ConfigError, match="unknown bag option 'colour'"):
        bag.parse_spec("rec.bag?colour=/x")


# ----------------------------------------------------------------------------------
# topics, encodings and damaged bags, on small synthetic frames
# ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_seq():
    return open_scene("synthetic/tiny", frames="0:6")[0]


def _write(tmp_path, tiny_seq, name="r.bag", **kw) -> Path:
    return bag_write.write_bag(tiny_seq, tmp_path / name, **kw)


def test_camera_info_distortion_undistorts_the_frames(tmp_path, tiny_seq):
    """plumb_bob coefficients in the camera info: frames come out as the same remap of the
    recorded ones that data/undistort.py makes."""
    coeffs = (0.2, -0.3, 0.001, 0.002, 0.1)
    [seq] = open_scene(str(_write(tmp_path, tiny_seq, depth_encoding="32FC1", distortion=coeffs)))
    assert seq.undistortion is not None and seq.undistortion.coeffs == coeffs
    und = Undistortion(tiny_seq.intrinsics, coeffs)
    np.testing.assert_array_equal(seq.depth(1), und.depth(tiny_seq.depth(1)))
    np.testing.assert_array_equal(seq.rgb(1), und.rgb(tiny_seq.rgb(1)))
    assert not np.array_equal(seq.depth(1), tiny_seq.depth(1))


@pytest.mark.slow
def test_16uc1_millimetres_and_mono8(tmp_path, tiny_seq):
    p = _write(tmp_path, tiny_seq, colour_encoding="mono8")
    [seq] = open_scene(str(p))
    np.testing.assert_array_equal(seq.depth(2), tiny_seq.depth(2))  # 7-Scenes depth is whole mm
    rgb = seq.rgb(2)
    assert rgb.shape == tiny_seq.rgb(2).shape and (rgb[..., 0] == rgb[..., 1]).all()
    # a bag's sensor: colour registered, Kinect v1's readout, the depth encoding's units per metre
    assert seq.sensor == Sensor(None, KINECT_V1_READOUT_S, synchronous=False, depth_scale=1000.0)
    metres = open_scene(str(_write(tmp_path, tiny_seq, name="m.bag", depth_encoding="32FC1")))[0]
    assert metres.sensor == Sensor(None, KINECT_V1_READOUT_S, synchronous=False, depth_scale=1.0)


def _cli_error(capsys, argv) -> str:
    assert teacher_cli.main(["generate", *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.slow
def test_truncated_bags_give_one_line_errors(tmp_path, tiny_seq, capsys):
    p = _write(tmp_path, tiny_seq)
    data = p.read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])
    err = _cli_error(capsys, ["--scene", str(tmp_path / "cut.bag"), "--out", str(tmp_path / "o")])
    assert "cut.bag" in err
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    assert "junk.bag" in _cli_error(capsys, ["--scene", str(tmp_path / "junk.bag"), "--out", str(tmp_path / "o")])
    for storage in ("sqlite3", "mcap"):
        r2 = _write(tmp_path, tiny_seq, name=f"r2-{storage}", ros2=True, storage=storage)
        [f] = [x for x in r2.iterdir() if x.suffix in (".db3", ".mcap")]
        raw = f.read_bytes()
        f.write_bytes(raw[: len(raw) // 3])
        err = _cli_error(capsys, ["--scene", str(r2), "--out", str(tmp_path / "o")])
        assert f"r2-{storage}" in err


@pytest.mark.slow
def test_missing_and_ambiguous_topics(tmp_path, tiny_seq, capsys):
    p = _write(tmp_path, tiny_seq)
    out = ["--out", str(tmp_path / "o")]
    err = _cli_error(capsys, ["--scene", str(p), "--rgb-topic", "/nope", *out])
    assert "colour topic /nope is not in the bag" in err
    err = _cli_error(capsys, ["--scene", str(p), "--depth-topic", "/camera/rgb/camera_info", *out])
    assert "is sensor_msgs/msg/CameraInfo, expected sensor_msgs/msg/Image" in err
    err = _cli_error(capsys, ["--scene", str(p), "--gt-topic", "/camera/rgb/image_raw", *out])
    assert "ground-truth topic" in err
    err = _cli_error(capsys, ["--scene", "synthetic/tiny", "--rgb-topic", "/x", *out])
    assert "apply to a ROS bag scene" in err
    # two colour topics: auto-detection refuses and names them; --rgb-topic chooses
    two = tmp_path / "two"
    _merge(two, [_write(tmp_path, tiny_seq, name="a", ros2=True),
                 _write(tmp_path, tiny_seq, name="b", ros2=True, camera_ns="/cam2")])
    err = _cli_error(capsys, ["--scene", str(two), *out])
    assert "several colour image topics (/cam2/rgb/image_raw, /camera/rgb/image_raw); choose one with --rgb-topic" in err
    seq = open_scene(str(two) + "?rgb=/cam2/rgb/image_raw&depth=/cam2/depth/image_raw")[0]
    assert seq.topics.camera_info == "/cam2/rgb/camera_info" and len(seq) == len(tiny_seq)
    # no depth topic at all
    nodepth = tmp_path / "nodepth"
    _merge(nodepth, [_write(tmp_path, tiny_seq, name="c", ros2=True)], drop="/camera/depth/image_raw")
    assert "no depth image (16UC1 or 32FC1) topic" in _cli_error(capsys, ["--scene", str(nodepth), *out])


@pytest.mark.slow
def test_wrong_encodings(tmp_path, tiny_seq, capsys):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    p = tmp_path / "enc"
    with Writer(p, version=8) as w:
        c_rgb = w.add_connection("/rgb", bag.IMAGE, typestore=store)
        c_d = w.add_connection("/depth", bag.IMAGE, typestore=store)
        c_i = w.add_connection("/rgb/camera_info", bag.CAMERA_INFO, typestore=store)
        intr = tiny_seq.intrinsics
        for k in range(3):
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=k, nanosec=0), frame_id="c")
            img = T[bag.IMAGE](header=hdr, height=intr.height, width=intr.width, encoding="yuv422", is_bigendian=0,
                               step=2 * intr.width, data=np.zeros(2 * intr.width * intr.height, np.uint8))
            dep = T[bag.IMAGE](header=hdr, height=intr.height, width=intr.width, encoding="16UC1", is_bigendian=0,
                               step=2 * intr.width, data=np.zeros(2 * intr.width * intr.height, np.uint8))
            w.write(c_rgb, k * 10**9, store.serialize_cdr(img, bag.IMAGE))
            w.write(c_d, k * 10**9, store.serialize_cdr(dep, bag.IMAGE))
            if k == 0:
                w.write(c_i, 0, store.serialize_cdr(bag_write._camera_info(T, hdr, intr, True), bag.CAMERA_INFO))
    out = ["--out", str(tmp_path / "o")]
    # auto-detection does not take an unsupported encoding for colour
    assert "no colour image topic" in _cli_error(capsys, ["--scene", str(p), *out])
    err = _cli_error(capsys, ["--scene", str(p), "--rgb-topic", "/rgb", *out])
    assert "colour image encoding 'yuv422' is not supported" in err
    assert not (tmp_path / "o" / "report.json").exists()


def _merge(dst: Path, srcs: list[Path], drop: str = "") -> None:
    """One ROS2 bag with the topics of several (``drop``: a topic left out)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer

    with Writer(dst, version=8) as w:
        conns: dict[str, object] = {}
        for src in srcs:
            with AnyReader([src]) as r:
                for c in r.connections:
                    if c.topic != drop and c.topic not in conns:
                        conns[c.topic] = w.add_connection(c.topic, c.msgtype, typestore=r.typestore)
                for c, t, raw in r.messages():
                    if c.topic in conns and c.topic != drop:
                        w.write(conns[c.topic], t, raw)


@pytest.mark.slow
def test_posegraph_and_learner_clis_take_bag_scenes(tmp_path, tiny_seq, capsys):
    """The pose graph reads the bag's ground truth through --gt-topic; the learner CLI gives
    the topic options to its bag scenes only."""
    import argparse

    from ctcvo.data.scenes import add_topic_options, scenes_with_topics
    from ctcvo.posegraph import cli as pg_cli

    p = _write(tmp_path, tiny_seq)
    assert teacher_cli.main(["generate", "--scene", str(p), "--out", str(tmp_path / "t"), "--preset", "tiny",
                             "--workers", "1"]) == 0
    assert pg_cli.main(["optimize", "--scene", str(p), "--gt-topic", "/groundtruth", "--teacher", str(tmp_path / "t"),
                        "--out", str(tmp_path / "pg"), "--no-plots"]) == 0
    import json

    rep = json.loads((tmp_path / "pg" / "report.json").read_text())
    assert rep["has_groundtruth"] and rep["groundtruth_from"] == f"scene {p}?gt=/groundtruth"
    ap = argparse.ArgumentParser()
    add_topic_options(ap)
    args = ap.parse_args(["--rgb-topic", "/c"])
    assert scenes_with_topics([str(p), "synthetic/lab"], args) == [f"{p}?rgb=/c", "synthetic/lab"]
    with pytest.raises(ConfigError):
        scenes_with_topics(["synthetic/lab"], args)


def test_raw_topic_preferred_over_its_compressed_twin(tmp_path, tiny_seq):
    """image_transport records ``T`` and ``T/compressed``: one stream, the raw one is read."""
    both = tmp_path / "both"
    _merge(both, [_write(tmp_path, tiny_seq, name="raw", ros2=True),
                  _write(tmp_path, tiny_seq, name="jpg", ros2=True, compressed=True)])
    seq = open_scene(str(both))[0]
    assert seq.topics.rgb == "/camera/rgb/image_raw"
    np.testing.assert_array_equal(seq.rgb(1), tiny_seq.rgb(1))
