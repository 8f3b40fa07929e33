"""Teacher configuration: a frozen dataclass, presets are instances (change with
``dataclasses.replace``). Tuned values are named constants of the modules that use them."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

from ctcvo.data.errors import ConfigError
from ctcvo.data.sensor import KINECT_V1_COLOUR, ColourCamera, Sensor

DENSE_METHODS = ("auto", "hybrid", "point-to-plane")
COLOUR_CAMERAS = ("auto", "registered", "kinect-v1")
COVARIANCES = ("calibrated", "raw")


@dataclass(frozen=True)
class TeacherConfig:
    """Settings of the ORB + PnP-RANSAC RGB-D odometry teacher."""

    gaps: int = 5
    """Edges are estimated for every frame pair (i, i+g), g = 1..gaps (the paper's 1-5)."""
    n_features: int = 1000
    """ORB features per frame."""
    refine: bool = True
    """Refine the PnP-RANSAC pose with the robust two-way Newton solve (reprojection both ways
    and a 3-D depth term); False keeps OpenCV's least-squares pose on the RANSAC inliers."""
    dense: bool = True
    """Refine each good edge with a dense depth alignment (not a gap-1 edge of a registered
    colour camera without photometric maps, TUM RGB-D: :mod:`teacher.odometry`, step 4), and
    run the dense fallbacks when no sparse estimate passes."""
    dense_method: str = "auto"
    """Dense step: ``point-to-plane`` (depth alone), ``hybrid`` (then a photometric + depth stage
    on gap-1 edges) or ``auto`` (hybrid for a sensor that exposes colour and depth together)."""
    colour_camera: str = "auto"
    """How colour pixels map onto the depth camera's: ``registered``, ``kinect-v1`` (7-Scenes'
    unregistered colour camera) or ``auto`` (from the sequence's sensor)."""
    rolling_shutter_s: float | None = None
    """Row readout time of the sensor (s); 0: global shutter, None: from the sequence's sensor.
    Edges longer than one frame move each frame's points to its middle row's moment."""
    depth_time_compensation: bool = True
    """Where a frame's depth was taken at another moment than its colour, the dense steps align
    the depth moments and move the result back to the colour moments."""
    dense_on_stale: bool = True
    """Take the dense estimate whole for an edge with a frame whose colour and depth were taken at
    different times (one stream repeated); turn off when the ground truth follows the colour."""
    max_speed: float = 1.5
    """Translations faster than this (m/s) are ``implausible_motion``."""
    max_angular_speed_deg: float = 180.0
    """Rotations faster than this (deg/s) are ``implausible_motion``."""
    workers: int = 2
    """Worker processes, each taking chunks of consecutive frames; 1: all in the calling process."""
    threads: int = 1
    """OpenMP and BLAS threads of each teacher thread; the labels depend on it (Open3D's
    reductions), so it is part of the outputs' fingerprint."""
    chunk_frames: int = 75
    """Frames per chunk of a worker; it shapes the edges through the chunk bounds. A sequence
    shorter than two chunks runs in one process. 75 against 150 on the validation ranges:
    the same graph ATE, 1 s and gap-1 RPE within 0.03 mm, and fr3/teddy 0:200 and
    synthetic/lab 0:200 cut in two instead of one (wall 9 -> 7 s and 10 -> 8 s). The count
    is a multiple of the workers (:func:`teacher.generate._chunks`)."""
    keyframes: bool = True
    """Also estimate edges between keyframes reaching back seconds, and verified loop edges
    (:mod:`teacher.keyframes`): on every validation range they lower the pose graph's ATE and
    1 s RPE at the same gap-1 RPE (bench/README.md, keyframes). Code that reads labels by gap
    tells the kinds apart by edges.csv's ``kind``."""

    covariance: str = "calibrated"
    """``calibrated``: each edge's covariance times the per-gap scale fitted against ground truth
    for the sequence's sensor (:mod:`teacher.covariance_model`); ``raw``: the estimator's own,
    far too small on real data."""

    def __post_init__(self) -> None:
        for name in ("gaps", "n_features", "workers", "threads", "chunk_frames"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.dense_method not in DENSE_METHODS:
            raise ConfigError(f"dense_method must be auto, hybrid or point-to-plane, got {self.dense_method!r}")
        if self.colour_camera not in COLOUR_CAMERAS:
            raise ConfigError(f"colour_camera must be auto, registered or kinect-v1, got {self.colour_camera!r}")
        if self.covariance not in COVARIANCES:
            raise ConfigError(f"covariance must be calibrated or raw, got {self.covariance!r}")
        r = self.rolling_shutter_s
        if r is not None and not (math.isfinite(r) and 0.0 <= r < 1.0):
            raise ConfigError(f"rolling_shutter_s must be in [0, 1) s, got {r!r}")
        if not (self.max_speed > 0 and self.max_angular_speed_deg > 0):
            raise ConfigError(f"max_speed and max_angular_speed_deg must be > 0, got {self.max_speed!r}, "
                              f"{self.max_angular_speed_deg!r}")

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT = TeacherConfig()
#: a fast preset for tests: fewer features and gaps
TINY = TeacherConfig(gaps=2, n_features=800)
#: The paper's kind of teacher: frame-to-frame ORB + PnP-RANSAC as ORB-SLAM's tracking does it,
#: without the robust refinement, the dense step and the rolling shutter correction.
PAPER = replace(DEFAULT, refine=False, dense=False, rolling_shutter_s=0.0)
PRESETS = {"default": DEFAULT, "tiny": TINY, "paper": PAPER}


def dense_method(cfg: TeacherConfig, colour: ColourCamera | None) -> str:
    """``cfg.dense_method`` resolved for a colour camera model: ``auto`` is ``hybrid`` for a
    synchronous one (:attr:`ColourCamera.synchronous`), else ``point-to-plane``."""
    if cfg.dense_method != "auto":
        return cfg.dense_method
    return "hybrid" if colour is not None and colour.synchronous else "point-to-plane"


def colour_camera_for(sensor: Sensor, cfg: TeacherConfig) -> ColourCamera | None:
    """The colour camera model ``cfg.colour_camera`` names (None: registered); ``auto``: the
    sensor's own (``Sequence.sensor``, set by its reader)."""
    if cfg.colour_camera == "registered":
        return None
    if cfg.colour_camera == "kinect-v1":
        return KINECT_V1_COLOUR
    return sensor.colour


def dense_method_for(sensor: Sensor, cfg: TeacherConfig) -> str:
    """The dense step's method: ``cfg.dense_method``, with ``auto`` resolved by the colour
    camera model ``colour_camera_for`` picks (:func:`teacher.config.dense_method`):
    ``hybrid`` for a synthetic scene's sensor model (colour and depth exposed at the same
    instant), ``point-to-plane`` otherwise (real Kinect v1 recordings: 7-Scenes, whose
    ground truth follows the depth while the colour is exposed at other times, TUM RGB-D;
    noise-free synthetic scenes, whose colour needs no model)."""
    return dense_method(cfg, colour_camera_for(sensor, cfg))
