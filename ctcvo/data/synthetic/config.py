"""Configuration of the synthetic RGB-D scenes: frozen dataclasses, presets as instances.

Change a preset with :func:`dataclasses.replace`, e.g.
``replace(PRESETS["office"], frames=100)`` or, for the sensor,
``replace(cfg, sensor=replace(cfg.sensor, noise_free=True))``.

Defaults of :class:`SensorConfig` model a Kinect v1 (the 7-Scenes sensor):

* depth noise in the disparity domain, ``sigma_z = depth_noise_coeff * z**2``
  (1.4 mm at 1 m, 23 mm at 4 m; Khoshelham & Oude Elberink 2012), half of it spatially
  correlated like block-matching errors;
* disparity quantisation: inverse depth in steps of ``disparity_step`` (1/m), which gives
  the 2.9 mm / 11 mm / 26 mm depth steps at 1 / 2 / 3 m seen in 7-Scenes depth PNGs;
* holes: projector shadows beside depth discontinuities (projector 7.5 cm to the right of
  the IR camera), a pixel band along discontinuities, grazing surfaces, random dropouts,
  and everything outside 0.5-4.5 m;
* colour: a separate, unregistered colour camera (10 % shorter focal length, a shift and a
  1.6 cm baseline, as fitted on 7-Scenes redkitchen), optical blur, motion blur, slow
  exposure changes, vignetting, read and shot noise, JPEG compression;
* dropped frames: a frame, or only its colour or only its depth image, repeats the previous
  one at the rates counted in the 7-Scenes redkitchen sample.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Bump when the renderer's output changes for the same config (invalidates caches).
RENDER_VERSION = 10


@dataclass(frozen=True)
class SensorConfig:
    """Kinect-v1-like sensor model applied to the exact rendering."""

    noise_free: bool = False
    """Write the exact rendering: exact depth (no noise, quantisation or holes; only the
    1 mm PNG rounding), clean colour (no blur, noise, exposure change or misregistration)."""
    depth_noise_coeff: float = 1.425e-3
    """Std of inverse depth noise in 1/m; equals ``sigma_z / z**2`` (m / m^2)."""
    depth_noise_correlated: float = 0.5
    """Fraction of the depth noise variance that is spatially correlated (0..1)."""
    depth_noise_corr_px: int = 6
    """Correlation length of the correlated depth noise, pixels."""
    depth_bias_coeff: float = 1.0e-3
    """Std of a fixed, smooth inverse-depth bias pattern in 1/m (Kinect v1 depth distortion,
    fixed in image coordinates: ~1 mm at 1 m, ~1 cm at 3 m). 0 = none."""
    depth_bias_px: int = 80
    """Correlation length of the depth bias pattern, pixels."""
    disparity_step: float = 2.85e-3
    """Quantisation step of inverse depth, 1/m (depth step ``~ step * z**2``); 0 = none."""
    depth_min_m: float = 0.5
    """Nearest measurable depth, metres; closer pixels are holes (0)."""
    depth_max_m: float = 4.5
    """Farthest measurable depth, metres; farther pixels are holes (0)."""
    projector_baseline_m: float = 0.075
    """IR projector offset along +x of the depth camera, metres; pixels the projector
    cannot see (shadows left of foreground objects) are holes. 0 = no shadows."""
    edge_jump_rel: float = 0.05
    """Relative depth jump between neighbouring pixels that counts as a discontinuity."""
    edge_hole_px: int = 1
    """Half-width in pixels of the hole band along depth discontinuities (0 = none)."""
    grazing_cos: float = 0.25
    """Below this |cos| between surface normal and viewing ray, pixels drop out with
    probability ``1 - cos / grazing_cos``."""
    dropout_prob: float = 0.003
    """Probability of an isolated random depth hole per pixel."""
    hole_blob_fraction: float = 0.03
    """Fraction of pixels lost in random blobs (dark or specular spots, missed speckle)."""
    hole_blob_px: int = 10
    """Typical size of the hole blobs, pixels."""
    invalid_right_cols: int = 8
    """Always-invalid columns at the right image border (Kinect v1; 7-Scenes shows 8)."""
    rolling_shutter_s: float = 0.027
    """Readout time from the top to the bottom row (colour and depth), seconds (Kinect v1's
    free-running 30 Hz sensors read out over most of the frame period); each row is
    seen from the pose at its own time, the ground truth is the pose at the middle row.
    0 = global shutter."""
    depth_time_offset_s: tuple[float, float] = (0.0, 0.0)
    """Colour-depth timing: each frame's depth image is taken this many seconds after its
    colour image (before, when negative), drawn per frame uniformly from ``[lo, hi]``; the
    frame's timestamp and pose are the colour image's, and the depth image's time is written
    (``seq-01/depth-offsets.txt``). TUM RGB-D's free-running Kinect streams, as associated
    (fr1/xyz, depth minus RGB timestamp: median -8.4 ms, 5-95 % -15.9 to -3.6 ms), are
    roughly ``(-0.0167, 0.0)``. (0, 0) = the same moment (7-Scenes, whose ground truth follows
    the depth). Not combined with repeated frames (their poses follow the depth)."""
    residual_distortion_k1: float = 0.015
    """Unmodelled radial distortion (division model ``x = x_d / (1 + k1 r_d^2)``, ~3 px at
    the corners) of the camera whose pinhole intrinsics are written. 0 = exact pinhole."""
    rgb_focal_scale: float = 0.91
    """Focal length of the colour camera relative to the written (depth-camera) intrinsics.
    7-Scenes colour frames are not registered to depth: the Kinect v1 RGB camera (~62 deg
    field of view, f ~ 532 px) sees ~10 % more than the IR camera (f = 585 px). Fitted on
    the redkitchen sample (colour edges against depth edges): 0.91. 1 = same camera."""
    rgb_shift_px: tuple[float, float] = (-3.5, -1.0)
    """Constant shift (x, y) of the colour image content against depth, pixels (redkitchen fit)."""
    rgb_baseline_m: float = 0.016
    """Offset of the colour camera from the depth camera along x, metres: content at depth z
    moves by another ``-rgb_focal_scale * fx * rgb_baseline_m / z`` pixels along x in the
    colour image (redkitchen fit: -11 px at ~1.1 m, -7 px at ~2.3 m, with the shift above)."""
    jpeg_quality: int = 80
    """JPEG compression of the colour image (quality 1-100, 4:2:0 chroma), as the 7-Scenes
    sample's colour frames (quality 80): written as ``.color.jpg``; 0 = none (``.color.png``)."""
    rgb_blur_sigma: float = 1.0
    """Optical blur of the colour camera (Gaussian sigma, pixels)."""
    motion_blur_exposure: float = 0.8
    """Exposure time as a fraction of the frame period for motion blur (0.8 = 27 ms, a
    Kinect v1 colour camera's auto-exposure indoors: redkitchen frames lose 14-21 % of their
    gradient energy above 22 deg/s); 0 = off."""
    exposure_log_sigma: float = 0.15
    """Std of the slowly varying log exposure gain (auto-exposure drift); 0 = off."""
    exposure_period_s: float = 5.0
    """Typical period of the exposure changes, seconds."""
    vignetting: float = 0.25
    """Relative brightness loss at the image corners."""
    read_noise_dn: float = 1.5
    """Colour read noise std in 8-bit digital numbers."""
    shot_noise_gain: float = 0.15
    """Shot noise: variance grows by ``shot_noise_gain * value`` (DN^2 per DN)."""
    frame_repeat_prob: float = 0.07
    """Probability that a frame repeats the previous one whole (colour, depth and pose): the
    recorder dropped a frame and wrote the last one again. 7-Scenes redkitchen seq-sample:
    42 of its 599 consecutive pairs have bit-identical colour *and* depth images, and there
    its ground truth (KinectFusion, which tracks the depth) moves by only 0.2-3 mm."""
    rgb_repeat_prob: float = 0.027
    """Probability that only the colour image repeats the previous frame's (depth and pose
    new): the colour shows no motion while the depth and the ground truth move (redkitchen:
    16 of 599 pairs, e.g. frames 312 -> 313)."""
    depth_repeat_prob: float = 0.028
    """Probability that only the depth image repeats, with the previous pose (the ground
    truth is the depth camera's pose) while the colour is new (redkitchen: 17 of 599 pairs).
    In redkitchen the repeats come in bursts (frames 222-413 and 453-595, every 4-5th frame);
    here they are independent per frame. 0 for all three = every frame new."""


@dataclass(frozen=True)
class SceneConfig:
    """A synthetic scene: layout, trajectory and camera; the sensor model in ``sensor``."""

    layout: str = "office"
    """Room layout generator: ``office``, ``kitchen`` or ``lab``."""
    seed: int = 0
    """Seed of the layout, textures, trajectory and sensor noise (same seed, same files)."""
    frames: int = 300
    """Number of frames (30 Hz)."""
    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    fx: float = 585.0
    """Focal length x, pixels (7-Scenes)."""
    fy: float = 585.0
    """Focal length y, pixels."""
    cx: float = 320.0
    """Principal point x, pixels."""
    cy: float = 240.0
    """Principal point y, pixels."""
    fps: float = 30.0
    """Frame rate, Hz."""
    mean_speed_mps: float = 0.22
    """Typical camera speed, m/s (7-Scenes redkitchen: ~7 mm per frame = 0.21 m/s)."""
    min_speed_mps: float = 0.08
    """Slowest desired speed where rotation does not limit it, m/s."""
    speed_variability: float = 0.5
    """Log-amplitude of the slow random variation of the desired speed (0 = constant)."""
    max_speed_mps: float = 0.47
    """Fastest camera speed of the smooth path, m/s (hand jitter adds a little)."""
    max_angular_dps: float = 26.5
    """Fastest rotation of the smooth path, deg/s (hand jitter adds a little)."""
    view_distance_m: tuple[float, float] = (0.9, 2.6)
    """Range of distances from the camera to the points it looks at, metres."""
    jitter_trans_m: float = 0.0015
    """Amplitude of hand tremor (1-4 Hz), metres."""
    jitter_rot_deg: float = 0.4
    """Amplitude of hand tremor in rotation, degrees."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """Sensor model."""
    texture_style: str = "default"
    """Surface textures (:func:`~data.synthetic.layout.restyle`): ``default`` (the layout's
    own), ``lowfreq`` (smooth low-frequency blobs), ``repetitive`` (one small motif tiled) or
    ``textureless`` (plain paint on all but the small objects), each keeping a material's mean
    colour."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def digest(self) -> str:
        """Short hash of the config and renderer version (names the cache folder). Fields
        added after RENDER_VERSION 10 count only when they differ from their default, so
        scenes rendered before they existed keep their cache folder."""
        cfg = self.to_dict()
        for name, default in _LATE_FIELDS.items():
            if cfg.get(name) == default:
                cfg.pop(name)
        for name, default in _LATE_SENSOR_FIELDS.items():
            if tuple(cfg["sensor"].get(name, ())) == default:
                cfg["sensor"].pop(name, None)
        blob = json.dumps({"v": RENDER_VERSION, "cfg": cfg}, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:8]


PRESETS: dict[str, SceneConfig] = {
    "office": SceneConfig(layout="office", seed=11, frames=300),
    "kitchen": SceneConfig(layout="kitchen", seed=25, frames=300, mean_speed_mps=0.31),
    "lab": SceneConfig(layout="lab", seed=33, frames=300, mean_speed_mps=0.25),
    "tiny": SceneConfig(layout="office", seed=44, frames=20),
    # stress scenes (issue 13): conditions that starve feature matching; the team's own
    # scenes for checking the teacher never gets stranded, not a hold-out
    "stress-lowfreq": SceneConfig(layout="office", seed=51, frames=300, texture_style="lowfreq"),
    "stress-repetitive": SceneConfig(layout="office", seed=52, frames=300, texture_style="repetitive"),
    "stress-far": SceneConfig(layout="lab", seed=53, frames=300, view_distance_m=(3.6, 5.0)),
    "stress-fast": SceneConfig(layout="kitchen", seed=54, frames=300, mean_speed_mps=0.45, max_speed_mps=0.9,
                               max_angular_dps=120.0, jitter_rot_deg=2.5, view_distance_m=(0.8, 1.8)),
    "stress-blur": SceneConfig(layout="office", seed=55, frames=300, mean_speed_mps=0.4, max_speed_mps=0.7,
                               max_angular_dps=60.0, sensor=SensorConfig(motion_blur_exposure=1.0)),
    "stress-textureless": SceneConfig(layout="office", seed=56, frames=300, texture_style="textureless"),
}
"""Named scenes for ``--scene synthetic/NAME``; ``NAME-clean`` is the noise-free variant."""

CLEAN_SUFFIX = "-clean"

#: SceneConfig fields added after RENDER_VERSION 10, with their defaults (see SceneConfig.digest)
_LATE_FIELDS = {"texture_style": "default"}
#: SensorConfig fields added after RENDER_VERSION 10, with their defaults (as dataclasses.asdict writes them)
_LATE_SENSOR_FIELDS = {"depth_time_offset_s": (0.0, 0.0)}


#: first seed of the training corpus rooms (the named scenes use seeds below 100)
CORPUS_SEED0 = 1000
CORPUS_PREFIX = "room-"
#: frames of a corpus room unless its name asks for others (``room-<N>x<FRAMES>``)
CORPUS_FRAMES = 300
_ROOM = re.compile(r"room-(\d+)(?:x(\d+))?")


def corpus_room(index: int, frames: int = CORPUS_FRAMES) -> SceneConfig:
    """Room ``index`` of the synthetic training corpus (``synthetic/room-<index>``, or
    ``synthetic/room-<index>x<frames>`` for a shorter or longer walk through the same room):
    a new room of one of the three layout generators in turn (its own furniture placement,
    materials, textures and lights from seed ``CORPUS_SEED0 + index``, never one of the
    named scenes' seeds), and a trajectory of its own speed (0.12-0.40 m/s mean), top
    rotation rate (15-45 deg/s) and viewing distances, drawn from the same seed."""
    if index < 0 or frames < 2:
        raise KeyError(f"{CORPUS_PREFIX}{index}x{frames}")
    rng = np.random.default_rng([CORPUS_SEED0, index])
    near = float(rng.uniform(0.6, 1.2))
    return SceneConfig(layout=("office", "kitchen", "lab")[index % 3], seed=CORPUS_SEED0 + index, frames=frames,
                       mean_speed_mps=float(rng.uniform(0.12, 0.40)), max_angular_dps=float(rng.uniform(15.0, 45.0)),
                       max_speed_mps=0.6, view_distance_m=(near, float(near + rng.uniform(1.2, 2.4))))


def corpus_names(spec: str) -> list[str]:
    """The room names of a corpus spec ``corpus-<COUNT>[x<FRAMES>]``: rooms ``0..COUNT-1``
    (``room-<N>`` or ``room-<N>x<FRAMES>``); KeyError if ``spec`` is not one."""
    m = re.fullmatch(r"corpus-(\d+)(?:x(\d+))?", spec)
    if not m or int(m.group(1)) < 1 or (m.group(2) and int(m.group(2)) < 2):
        raise KeyError(spec)
    suffix = f"x{int(m.group(2))}" if m.group(2) else ""
    return [f"{CORPUS_PREFIX}{k}{suffix}" for k in range(int(m.group(1)))]


def _base(name: str) -> SceneConfig:
    if name in PRESETS:
        return PRESETS[name]
    m = _ROOM.fullmatch(name)
    if m:
        return corpus_room(int(m.group(1)), int(m.group(2)) if m.group(2) else CORPUS_FRAMES)
    raise KeyError(name)


def resolve_preset(name: str) -> SceneConfig:
    """Config of a scene name (``office``, ``office-clean``, ``room-7``, ...); KeyError if unknown."""
    if name.endswith(CLEAN_SUFFIX):
        cfg = _base(name[: -len(CLEAN_SUFFIX)])
        return dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, noise_free=True))
    return _base(name)


def known_names() -> list[str]:
    return sorted(PRESETS) + [f"{CORPUS_PREFIX}<N>[x<FRAMES>] (a training-corpus room)",
                              "corpus-<COUNT>[x<FRAMES>] (rooms 0..COUNT-1)"]
