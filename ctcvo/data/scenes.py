"""Resolve a ``--scene`` argument to sequences, the same way in every CLI.

``--scene`` accepts:
* ``synthetic/NAME`` - a built-in synthetic scene, rendered on first use and cached
  (see :mod:`data.synthetic`); ``synthetic/corpus-<COUNT>[x<FRAMES>]`` is the rooms
  ``room-0 .. room-<COUNT-1>`` of the training corpus, one sequence each;
* a 7-Scenes sequence folder (``.../seq-XX``) or any folder in that layout;
* a 7-Scenes scene folder (``.../redkitchen``) together with ``split`` (train/test/all);
* a TUM RGB-D sequence folder (``rgb.txt``, ``depth.txt``);
* a ROS1 ``.bag`` file or a ROS2 bag folder (``metadata.yaml``; sqlite3 or mcap), with
  its topics optionally appended as ``?rgb=/t&depth=/t&camera_info=/t&gt=/t`` (what the
  CLIs' ``--rgb-topic`` etc. write, see :func:`add_topic_options`; :mod:`data.bag`).

``frames`` (``START:STOP[:STEP]``) selects part of every sequence.
"""

from __future__ import annotations

from pathlib import Path

from ctcvo.data import bag, sevenscenes, synthetic, tum
from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.runs import SYNTHETIC_PREFIX, scene_slug  # noqa: F401 - scene_slug lives with the run layout
from ctcvo.data.sequence import Sequence, parse_frame_range


def open_scene(spec: str, split: str = "all", frames: str | None = None,
               cache_dir: Path | None = None) -> list[Sequence]:
    """Open the sequences named by ``spec`` (see module docstring)."""
    start, stop, step = parse_frame_range(frames)
    seqs = _open(spec, split, cache_dir)
    if frames:
        seqs = [s.select(start, stop, step) for s in seqs]
    return seqs


def _open(spec: str, split: str, cache_dir: Path | None) -> list[Sequence]:
    if spec.startswith(SYNTHETIC_PREFIX):
        return synthetic.synthetic_sequences(spec[len(SYNTHETIC_PREFIX):], cache_dir=cache_dir)
    path = Path(spec.partition(bag.SPEC_SEP)[0])
    if bag.is_bag(path) or bag.SPEC_SEP in spec:
        bag_path, topics = bag.parse_spec(spec)
        if not bag_path.exists():
            raise DataError(f"ROS bag {bag_path} not found")
        if not bag.is_bag(bag_path):
            raise DataError(f"{bag_path} is not a ROS bag (a .bag file or a ROS2 bag folder with metadata.yaml), "
                            "but the scene names bag topics")
        if split != "all":
            raise DataError(f"--split applies to a 7-Scenes scene folder; {bag_path} is a single recording")
        return [bag.BagSequence(bag_path, topics)]
    if not path.exists():
        raise DataError(f"scene {spec!r} not found (give a sequence or scene folder, or synthetic/NAME)")
    if not path.is_dir():
        raise DataError(f"scene {spec!r} is not a folder")
    if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
        if split != "all":
            raise DataError(f"--split applies to a 7-Scenes scene folder; {spec} is a single TUM sequence")
        return [tum.TumSequence(path)]
    if sevenscenes.is_sequence_folder(path):
        if split != "all":
            raise DataError(f"--split applies to a scene folder; {spec} is a single sequence")
        return [sevenscenes.SevenScenesSequence(path)]
    if any(path.glob("seq-*")) or (path / "TrainSplit.txt").is_file():
        return sevenscenes.open_scene_folder(path, split)
    raise DataError(f"{spec} is neither a 7-Scenes sequence/scene folder nor a TUM sequence (no rgb.txt/depth.txt)")


def add_topic_options(parser) -> None:
    """Add ``--rgb-topic``, ``--depth-topic``, ``--camera-info-topic`` and ``--gt-topic``
    (ROS bag scenes) to an argparse parser; :func:`scene_with_topics` applies them."""
    g = parser.add_argument_group("ROS bag topics (a --scene that is a .bag file or a ROS2 bag folder; "
                                  "detected when unambiguous)")
    g.add_argument("--rgb-topic", help="colour topic (sensor_msgs/Image rgb8/bgr8/mono8 or CompressedImage; "
                                       "default: the bag's one such topic)")
    g.add_argument("--depth-topic", help="depth topic (sensor_msgs/Image 16UC1 mm or 32FC1 m; default: the bag's "
                                         "one such topic)")
    g.add_argument("--camera-info-topic", help="sensor_msgs/CameraInfo topic with the intrinsics (default: the "
                                               "bag's one such topic)")
    g.add_argument("--gt-topic", help="ground truth: a PoseStamped or TransformStamped topic, or TOPIC:PARENT:CHILD "
                                      "of a tf topic (default: none)")


def scene_with_topics(spec: str | None, args) -> str | None:
    """``spec`` with the topic options of :func:`add_topic_options` appended (unchanged when
    none is given; a ConfigError when some are given but ``spec`` is not a bag)."""
    topics = bag.BagTopics(getattr(args, "rgb_topic", None), getattr(args, "depth_topic", None),
                           getattr(args, "camera_info_topic", None), getattr(args, "gt_topic", None))
    if spec is None or topics == bag.BagTopics():
        return spec
    if spec.startswith(SYNTHETIC_PREFIX) or not bag.is_bag(Path(spec.partition(bag.SPEC_SEP)[0])):
        raise ConfigError(f"--rgb-topic/--depth-topic/--camera-info-topic/--gt-topic apply to a ROS bag scene, "
                          f"not to {spec}")
    return bag.with_topics(spec, topics)


def scenes_with_topics(specs: list[str], args) -> list[str]:
    """:func:`scene_with_topics` over several scenes: the topic options go to the bag scenes
    among them (a ConfigError when they are given and none is a bag)."""
    is_bag = [not s.startswith(SYNTHETIC_PREFIX) and bag.is_bag(Path(s.partition(bag.SPEC_SEP)[0])) for s in specs]
    if not any(is_bag):
        return [scene_with_topics(s, args) for s in specs[:1]] + list(specs[1:])  # errors if options given
    return [scene_with_topics(s, args) if b else s for s, b in zip(specs, is_bag)]
