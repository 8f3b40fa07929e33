"""Writing a :class:`~data.sequence.Sequence` as a ROS1 bag or a ROS2 bag folder (tests,
benchmarks, converting a folder to a bag); :mod:`data.bag` reads them."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ctcvo.data import geometry as geo
from ctcvo.data.bag import CAMERA_INFO, COMPRESSED, DEPTH_SCALE_16U, IMAGE, POSE_STAMPED
from ctcvo.data.sequence import Intrinsics, Sequence


def write_bag(seq: Sequence, path: Path, *, ros2: bool = False, storage: str = "sqlite3",
              compressed: bool = False, depth_encoding: str = "16UC1", colour_encoding: str = "rgb8",
              gt: bool = True, camera_ns: str = "/camera", distortion: tuple[float, ...] = ()) -> Path:
    """Write ``seq`` as a ROS1 bag (``path`` ending in ``.bag``) or a ROS2 bag folder
    (``ros2``, ``storage`` sqlite3 or mcap): ``{ns}/rgb/image_raw`` (or ``.../compressed``,
    JPEG quality 95), ``{ns}/depth/image_raw`` (``16UC1`` mm or ``32FC1`` m, stamped with the
    frame's depth timestamp, ``seq.depth_times()``: the colour image's where the sequence has
    none), ``{ns}/rgb/camera_info`` and, with ``gt`` and ground truth, a
    ``/groundtruth`` PoseStamped per frame. Frames are streamed one at a time. The camera
    info's ``plumb_bob`` coefficients are ``distortion`` (none: zeros, the frames being the
    reader's pinhole ones)."""
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = store.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    intr = seq.intrinsics
    if ros2:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
        ser = store.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        ser = store.serialize_ros1
    gt_poses = seq.groundtruth() if gt else None
    with writer:
        rgb_topic = f"{camera_ns}/rgb/image_raw" + ("/compressed" if compressed else "")
        c_rgb = writer.add_connection(rgb_topic, COMPRESSED if compressed else IMAGE, typestore=store)
        c_depth = writer.add_connection(f"{camera_ns}/depth/image_raw", IMAGE, typestore=store)
        c_info = writer.add_connection(f"{camera_ns}/rgb/camera_info", CAMERA_INFO, typestore=store)
        c_gt = writer.add_connection("/groundtruth", POSE_STAMPED, typestore=store) if gt_poses is not None else None
        depth_times = seq.depth_times()
        for k in range(len(seq)):
            t = float(seq.times()[k])
            ns = _nanoseconds(t)
            hdr = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="camera_rgb_optical_frame",
                         **({} if ros2 else {"seq": k}))
            rgb, depth = seq.rgb(k), seq.depth(k)
            h, w = depth.shape
            if compressed:
                ok, enc = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
                msg = T[COMPRESSED](header=hdr, format="jpeg", data=enc.reshape(-1))
            else:
                px = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)}[colour_encoding]
                px = np.ascontiguousarray(px)
                ch = 1 if px.ndim == 2 else 3
                msg = T[IMAGE](header=hdr, height=h, width=w, encoding=colour_encoding, is_bigendian=0,
                               step=w * ch, data=px.reshape(-1))
            writer.write(c_rgb, ns, ser(msg, c_rgb.msgtype))
            if depth_encoding == "16UC1":
                raw = np.round(depth * DEPTH_SCALE_16U).astype("<u2")
            else:
                raw = depth.astype("<f4")
            dns = _nanoseconds(float(depth_times[k]))
            dhdr = Header(stamp=Time(sec=dns // 10**9, nanosec=dns % 10**9), frame_id="camera_rgb_optical_frame",
                          **({} if ros2 else {"seq": k}))
            dmsg = T[IMAGE](header=dhdr, height=h, width=w, encoding=depth_encoding, is_bigendian=0,
                            step=w * raw.itemsize, data=raw.view(np.uint8).reshape(-1))
            writer.write(c_depth, ns, ser(dmsg, IMAGE))
            if k == 0:
                writer.write(c_info, ns, ser(_camera_info(T, hdr, intr, ros2, distortion), CAMERA_INFO))
            if c_gt is not None:
                P = gt_poses[k]
                q = geo.R_to_quat_xyzw(P[:3, :3])
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=P[0, 3], y=P[1, 3], z=P[2, 3]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                ghdr = Header(stamp=hdr.stamp, frame_id="world", **({} if ros2 else {"seq": k}))
                writer.write(c_gt, ns, ser(T[POSE_STAMPED](header=ghdr, pose=pose), POSE_STAMPED))
    return path


def _nanoseconds(t: float) -> int:
    """Seconds -> integer nanoseconds, exactly enough that reading the stamp back
    (``sec + 1e-9 nanosec``) gives ``t`` again: ``t * 1e9`` of a time since 1970 is only
    good to ~128 ns in float64, the fraction of a second alone to far below 1 ns."""
    sec = int(np.floor(t))
    return sec * 10**9 + int(round((t - sec) * 1e9))


def _camera_info(T, hdr, intr: Intrinsics, ros2: bool, distortion: tuple[float, ...] = ()):
    K = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], dtype=np.float64)
    P = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    R = np.eye(3).reshape(-1)
    D = np.zeros(5)
    D[:len(distortion)] = distortion
    names = ("d", "k", "r", "p") if ros2 else ("D", "K", "R", "P")
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T[CAMERA_INFO](header=hdr, height=intr.height, width=intr.width, distortion_model="plumb_bob",
                          **dict(zip(names, (D, K, R, P))), binning_x=0, binning_y=0, roi=roi)
