"""Built-in synthetic RGB-D scenes: procedural rooms ray-cast with Open3D, Kinect-v1 sensor model.

``--scene synthetic/NAME`` (NAME one of :data:`~data.synthetic.config.PRESETS`, or
``NAME-clean`` for the noise-free rendering) is rendered on first use into
``$VO_CACHE_DIR/synthetic/NAME-<config hash>/`` (default cache ``~/.cache/ctcvo``) in the
7-Scenes layout and read back with :class:`~data.sevenscenes.SevenScenesSequence`:

* ``camera-intrinsics.txt`` (3x3 matrix; ``fx fy cx cy w h`` when not 640x480),
  ``config.json`` (resolved config, git revision, motion statistics);
* ``seq-01/frame-NNNNNN.color.jpg`` (8-bit RGB, the sensor model's JPEG itself;
  ``.color.png`` without JPEG compression, e.g. the noise-free variants), ``.depth.png``
  (uint16 mm, 0 = hole), ``.pose.txt`` (exact 4x4 ``T_world_cam``).

The scene is rendered into a temporary sibling folder that is renamed at the end, so a
killed render never leaves a half scene; the hash in the folder name changes with the
config (and :data:`~data.synthetic.config.RENDER_VERSION`), so a changed config re-renders.
See docs/formats.md ("Synthetic scenes").
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
import shutil
import sys
import time
import uuid
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.geometry import relative_pose, se3_log
from ctcvo.data.io import ensure_dir, git_revision, write_json, write_text
from ctcvo.data.sequence import Sequence
from ctcvo.data.sevenscenes import SevenScenesSequence
from ctcvo.data.synthetic.config import (
    PRESETS,
    RENDER_VERSION,
    SceneConfig,
    SensorConfig,
    corpus_names,
    known_names,
    resolve_preset,
)
from ctcvo.data.synthetic.layout import LAYOUTS, TEXTURE_STYLES, Scene, restyle
from ctcvo.data.synthetic.renderer import ExactFrame, Renderer
from ctcvo.data.synthetic.sensor import (
    ColourSensor,
    NoiseBank,
    colour_camera_pad,
    depth_bias_field,
    depth_sensor,
    exposure_gains,
)
from ctcvo.data.synthetic.trajectory import make_trajectory, motion_stats

__all__ = [
    "PRESETS", "SceneConfig", "SensorConfig", "synthetic_sequence", "synthetic_sequences", "render_scene", "build",
    "default_cache_dir", "scene_dir", "known_names", "FrameRenderer",
]

log = logging.getLogger(__name__)


def default_cache_dir() -> Path:
    """``$VO_CACHE_DIR`` or ``~/.cache/ctcvo``."""
    env = os.environ.get("VO_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "ctcvo"


def scene_dir(name: str, config: SceneConfig, cache_dir: Path | None = None) -> Path:
    """Cache folder of scene ``name`` rendered with ``config``."""
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return root / "synthetic" / f"{name}-{config.digest()}"


def _check(config: SceneConfig) -> None:
    if config.layout not in LAYOUTS:
        raise ConfigError(f"unknown synthetic layout {config.layout!r} (known: {', '.join(sorted(LAYOUTS))})")
    if config.texture_style not in TEXTURE_STYLES:
        raise ConfigError(f"unknown texture style {config.texture_style!r} (known: {', '.join(TEXTURE_STYLES)})")
    if config.frames < 2:
        raise ConfigError(f"a synthetic scene needs at least 2 frames, got {config.frames}")
    if config.width < 16 or config.height < 16:
        raise ConfigError(f"image size {config.width}x{config.height} too small")


def synthetic_sequence(name: str, cache_dir: Path | None = None, config: SceneConfig | None = None) -> Sequence:
    """The sequence of synthetic scene ``name``, rendered into the cache on first use.

    ``config`` overrides the preset's config (the cache folder is still named after ``name``
    plus the config hash). Unknown names raise :class:`DataError` listing the known ones.
    """
    if config is None:
        try:
            config = resolve_preset(name)
        except KeyError:
            raise DataError(
                f"unknown synthetic scene {name!r}; known: {', '.join(known_names())} "
                "(append -clean for the noise-free rendering, e.g. synthetic/office-clean)"
            ) from None
    _check(config)
    folder = scene_dir(name, config, cache_dir)
    if not (folder / "seq-01").is_dir():
        render_scene(config, folder)
    return SevenScenesSequence(folder / "seq-01", name=f"synthetic-{name}")


def synthetic_sequences(name: str, cache_dir: Path | None = None) -> list[Sequence]:
    """The sequences of ``name``: the rooms of a corpus spec ``corpus-<COUNT>[x<FRAMES>]``
    (see :func:`~data.synthetic.config.corpus_names`), rendered one after the other on first
    use, or the one scene ``name``."""
    try:
        names = corpus_names(name)
    except KeyError:
        names = [name]
    return [synthetic_sequence(n, cache_dir) for n in names]


def build(config: SceneConfig) -> tuple[Scene, NDArray[np.float64]]:
    """The room and the poses ``T_world_cam`` (N, 4, 4) of ``config`` (deterministic)."""
    _check(config)
    scene = LAYOUTS[config.layout](np.random.default_rng([config.seed, 0]))
    scene = restyle(scene, config.texture_style, np.random.default_rng([config.seed, 6]))
    poses = make_trajectory(config, scene, np.random.default_rng([config.seed, 1]))
    return scene, poses


class FrameRenderer:
    """Renders frames of a scene and trajectory with the sensor model of ``config``."""

    def __init__(self, config: SceneConfig, scene: Scene, poses: NDArray[np.float64], nthreads: int = 0) -> None:
        self.config = config
        self.poses = poses
        c = config
        k1 = 0.0 if c.sensor.noise_free else c.sensor.residual_distortion_k1
        self.pad = colour_camera_pad(c.sensor, c.width, c.height, c.fx)
        self.renderer = Renderer(scene, c.fx, c.fy, c.cx, c.cy, c.width, c.height, nthreads=nthreads,
                                 distortion_k1=k1, pad=self.pad)
        self.colour_sensor = ColourSensor(c.sensor, c.width, c.height, c.cx, c.cy, c.fx)
        self.bank = NoiseBank(c.seed, c.width * c.height)
        self.depth_bias = depth_bias_field(c.sensor, (c.height, c.width), c.seed)
        self.gains = exposure_gains(c.sensor, np.arange(len(poses)) / c.fps, np.random.default_rng([c.seed, 2]))
        self.depth_offsets = depth_time_offsets(c, len(poses))
        gv, gu = np.mgrid[c.height // 12: c.height: c.height // 6, c.width // 16: c.width: c.width // 8]
        self._grid = np.stack([gu.ravel(), gv.ravel()], 1)
        self.K = np.array([[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1.0]])

    def image_flow(self, k: int, exact: ExactFrame) -> NDArray[np.float64]:
        """Mean image motion (2,) in pixels per frame around frame ``k`` (for motion blur)."""
        n = len(self.poses)
        if n < 2:
            return np.zeros(2)
        z = exact.depth[self._grid[:, 1], self._grid[:, 0]]
        ok = z > 0
        if not ok.any():
            return np.zeros(2)
        pix = self._grid[ok].astype(np.float64)
        Xc = np.linalg.inv(self.K) @ np.vstack([pix.T, np.ones(ok.sum())]) * z[ok]
        Xw = self.poses[k][:3, :3] @ Xc + self.poses[k][:3, 3:4]
        a, b = max(k - 1, 0), min(k + 1, n - 1)
        proj = []
        for j in (a, b):
            Tinv = np.linalg.inv(self.poses[j])
            Xj = Tinv[:3, :3] @ Xw + Tinv[:3, 3:4]
            uv = (self.K @ Xj)[:2] / np.maximum(Xj[2], 1e-3)
            proj.append(uv.T)
        return ((proj[1] - proj[0]) / max(b - a, 1)).mean(0)

    def row_poses(self, k: int, offset_s: float = 0.0) -> NDArray[np.float64]:
        """Rolling shutter: pose of every rendered row (H + 2 py, 4, 4) of frame ``k`` (rows
        of the padding, see :attr:`pad`, included), from the camera's velocity (central
        difference of the neighbouring poses); the middle row has the frame's pose, or the
        pose ``offset_s`` seconds later (an image taken then: the depth of a frame with a
        colour-depth time offset, ``depth_time_offset_s``)."""
        c, n = self.config, len(self.poses)
        a, b = max(k - 1, 0), min(k + 1, n - 1)
        xi = se3_log(relative_pose(self.poses[a], self.poses[b])) / max(b - a, 1)  # (v, w) per frame
        py = self.pad[1]
        s = ((np.arange(c.height + 2 * py) - py) / max(c.height - 1, 1) - 0.5) * c.sensor.rolling_shutter_s * c.fps
        s = s + offset_s * c.fps
        Tk = self.poses[k]
        out = np.repeat(Tk[None], len(s), 0)
        # first order in the (tiny) per-row motion: R_k exp(w s), t_k + R_k v s
        out[:, :3, :3] = Tk[:3, :3] @ Rotation.from_rotvec(np.outer(s, xi[3:])).as_matrix()
        out[:, :3, 3] += np.outer(s, Tk[:3, :3] @ xi[:3])
        return out

    def frame(self, k: int) -> tuple[NDArray[np.uint8], NDArray[np.float32], ExactFrame]:
        """Frame ``k``: RGB (H, W, 3) uint8, measured depth (H, W) float32 m, exact rendering
        of the depth camera (H, W)."""
        rgb, _, depth, exact = self.frame_encoded(k)
        return rgb, depth, exact

    def frame_encoded(self, k: int) -> tuple[NDArray[np.uint8], bytes | None, NDArray[np.float32], ExactFrame]:
        """As :meth:`frame`, with the colour image's JPEG file (None without JPEG compression)."""
        c = self.config
        rolling = c.sensor.rolling_shutter_s > 0 and not c.sensor.noise_free and len(self.poses) > 1
        padded = self.renderer.render(self.row_poses(k) if rolling else self.poses[k])
        exact = padded.crop(*self.pad)
        if self.depth_offsets[k] != 0.0:  # the depth image is taken at another moment: rendered again
            exact = self.renderer.render(self.row_poses(k, float(self.depth_offsets[k]))).crop(*self.pad)
        rng = np.random.default_rng([c.seed, 3, k])
        depth = depth_sensor(exact.depth, exact.cos_incidence, c.fx, c.sensor, rng, self.bank, self.depth_bias)
        flow = self.image_flow(k, exact) if (c.sensor.motion_blur_exposure > 0 and not c.sensor.noise_free) else np.zeros(2)
        rgb, jpeg = self.colour_sensor.encoded(padded.colour, float(self.gains[k]), flow, rng, padded.depth)
        return rgb, jpeg, depth, exact


def depth_to_png_mm(depth: NDArray[np.float32]) -> NDArray[np.uint16]:
    """Metres (H, W) -> uint16 millimetres, 0 stays 0 (hole); values beyond 65.534 m -> 0."""
    mm = np.rint(depth.astype(np.float64) * 1000.0)
    mm[(mm < 0) | (mm > 65534)] = 0
    return mm.astype(np.uint16)


# fast settings: zlib level 1, RLE strategy, "up" filter (~3x faster than the defaults)
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
               cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]


def colour_suffix(sensor: SensorConfig) -> str:
    """File suffix of the colour images: ``.color.jpg`` when the sensor compresses them
    (the file is the compressed image itself), else ``.color.png``."""
    return ".color.jpg" if sensor.jpeg_quality > 0 and not sensor.noise_free else ".color.png"


def _write_frame(seq_dir: Path, k: int, rgb: NDArray[np.uint8], jpeg: bytes | None, depth: NDArray[np.float32],
                 T: NDArray) -> None:
    stem = seq_dir / f"frame-{k:06d}"
    if jpeg is None:
        ok1, col = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), PNG_PARAMS)
        colour, suffix = col.tobytes(), ".color.png"
    else:
        ok1, colour, suffix = True, jpeg, ".color.jpg"
    ok2, dep = cv2.imencode(".png", depth_to_png_mm(depth), PNG_PARAMS)
    if not (ok1 and ok2):
        raise DataError(f"could not encode frame {k}")
    Path(f"{stem}{suffix}").write_bytes(colour)
    Path(f"{stem}.depth.png").write_bytes(dep.tobytes())
    Path(f"{stem}.pose.txt").write_text("\n".join(" ".join(f"{v:.9e}" for v in row) for row in T) + "\n")


def intrinsics_text(config: SceneConfig) -> str:
    c = config
    if (c.width, c.height) == (640, 480):
        return f"{c.fx:.6f} 0 {c.cx:.6f}\n0 {c.fy:.6f} {c.cy:.6f}\n0 0 1\n"
    return f"{c.fx:.6f} {c.fy:.6f} {c.cx:.6f} {c.cy:.6f} {c.width} {c.height}\n"


#: :func:`repeat_plan` codes: new frame, whole frame repeated, colour only, depth (and pose) only
NEW, REPEAT_FRAME, REPEAT_RGB, REPEAT_DEPTH = 0, 1, 2, 3


def depth_time_offsets(config: SceneConfig, n: int) -> NDArray[np.float64]:
    """Depth minus colour time of each of ``n`` frames, seconds (n,): uniform in the sensor's
    ``depth_time_offset_s`` range, deterministic for the seed; zeros when the range is (0, 0)
    or the sensor is noise-free. A ConfigError for a reversed range, an offset of a frame
    period or more, or offsets together with repeated frames (whose poses follow the depth)."""
    s = config.sensor
    lo, hi = (float(v) for v in s.depth_time_offset_s)
    if s.noise_free or (lo == 0.0 and hi == 0.0):
        return np.zeros(n)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi and max(abs(lo), abs(hi)) < 1.0 / config.fps):
        raise ConfigError(f"depth_time_offset_s {s.depth_time_offset_s} must be a range lo <= hi within one frame "
                          f"period ({1.0 / config.fps:.4f} s)")
    if s.frame_repeat_prob or s.rgb_repeat_prob or s.depth_repeat_prob:
        raise ConfigError("depth_time_offset_s cannot be combined with repeated frames (frame_repeat_prob, "
                          "rgb_repeat_prob, depth_repeat_prob must be 0): a repeated depth image's pose is the depth's")
    return np.random.default_rng([config.seed, 7]).uniform(lo, hi, n)


def write_depth_offsets(seq_dir: Path, offsets: NDArray[np.float64]) -> None:
    """``depth-offsets.txt``: ``frame_id offset_s`` per frame (depth minus colour time), read
    back by :class:`~data.sevenscenes.SevenScenesSequence` as the frames' depth timestamps."""
    rows = "".join(f"{k} {v:.9f}\n" for k, v in enumerate(offsets))
    write_text(seq_dir / "depth-offsets.txt", "# frame_id depth_minus_colour_time_s\n" + rows)


def repeat_plan(sensor: SensorConfig, n: int, seed: int) -> NDArray[np.int8]:
    """Dropped frames of the sensor model, (n,) codes: :data:`NEW`, :data:`REPEAT_FRAME`
    (colour, depth and pose of the previous frame), :data:`REPEAT_RGB` (its colour image),
    :data:`REPEAT_DEPTH` (its depth image and pose). Frame 0 is new; none repeat in the
    noise-free mode. Deterministic for a seed."""
    plan = np.zeros(n, np.int8)
    if sensor.noise_free or n < 2:
        return plan
    p = np.array([sensor.frame_repeat_prob, sensor.rgb_repeat_prob, sensor.depth_repeat_prob])
    if np.any(p < 0) or p.sum() >= 1:
        raise ConfigError(f"repeat probabilities {p.tolist()} must be >= 0 and sum to < 1")
    if p.sum() == 0:
        return plan
    u = np.random.default_rng([seed, 5]).random(n - 1)
    plan[1:] = np.searchsorted(np.cumsum(p), u, side="right") + 1
    plan[1:][u >= p.sum()] = NEW
    return plan


def _apply_repeats(seq_dir: Path, plan: NDArray[np.int8], colour: str) -> None:
    """Overwrite the repeated parts of each frame with the previous frame's files, in frame
    order (so a chain of repeats copies the first frame of the chain); ``colour`` is the
    colour images' suffix."""
    suffixes = {REPEAT_FRAME: (colour, ".depth.png", ".pose.txt"), REPEAT_RGB: (colour,),
                REPEAT_DEPTH: (".depth.png", ".pose.txt")}
    for k in np.flatnonzero(plan):
        for suffix in suffixes[int(plan[k])]:
            shutil.copyfile(seq_dir / f"frame-{k - 1:06d}{suffix}", seq_dir / f"frame-{k:06d}{suffix}")


def _render_frames(fr: FrameRenderer, seq_dir: Path, workers: int, desc: str, plan: NDArray[np.int8]) -> None:
    """Render and write every frame, ``workers`` frames at a time in threads (the heavy
    parts - ray casting, OpenCV, image encoding, large numpy operations - release the GIL),
    then the repeats of ``plan`` (whole repeated frames are not rendered)."""
    n = len(fr.poses)

    def job(k: int) -> None:
        if plan[k] == REPEAT_FRAME:
            return
        rgb, jpeg, depth, _ = fr.frame_encoded(k)
        _write_frame(seq_dir, k, rgb, jpeg, depth, fr.poses[k])

    with cf.ThreadPoolExecutor(max_workers=max(1, workers)) as pool, \
            tqdm(total=n, desc=desc, unit="frame", disable=not sys.stderr.isatty()) as bar:
        pending: list[cf.Future] = []
        for k in range(n):
            pending.append(pool.submit(job, k))
            while len(pending) > 2 * workers:
                pending.pop(0).result()
                bar.update()
        for f in pending:
            f.result()
            bar.update()
    _apply_repeats(seq_dir, plan, colour_suffix(fr.config.sensor))


def render_scene(config: SceneConfig, out_dir: Path, workers: int | None = None) -> Path:
    """Render ``config`` into ``out_dir`` (7-Scenes layout, see module docstring); returns it.

    ``workers`` threads render frames in parallel (default: the number of cores, at most 4).
    Rendered into a temporary sibling folder first and renamed at the end. If ``out_dir``
    appears meanwhile (another process rendered it), the temporary folder is discarded.
    """
    out_dir = Path(out_dir)
    workers = workers or min(os.cpu_count() or 1, 4)
    ensure_dir(out_dir.parent)
    tmp = out_dir.parent / f".tmp-{out_dir.name}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    seq_dir = tmp / "seq-01"
    t0 = time.perf_counter()
    try:
        ensure_dir(seq_dir)
        scene, poses = build(config)
        fr = FrameRenderer(config, scene, poses, nthreads=1)
        write_text(tmp / "camera-intrinsics.txt", intrinsics_text(config))
        log.info("rendering synthetic scene %s (%d frames, %d triangles) into %s",
                 out_dir.name, config.frames, len(scene.triangles), out_dir)
        plan = repeat_plan(config.sensor, len(poses), config.seed)
        if fr.depth_offsets.any():
            write_depth_offsets(seq_dir, fr.depth_offsets)
        _render_frames(fr, seq_dir, workers, desc=f"render {out_dir.name}", plan=plan)
        seconds = time.perf_counter() - t0
        write_json(tmp / "config.json", {
            "render_version": RENDER_VERSION, "config": config.to_dict(), "git_revision": git_revision(),
            "triangles": int(len(scene.triangles)), "materials": [m.name for m in scene.materials],
            "motion": motion_stats(poses, config.fps), "render_seconds": round(seconds, 2),
            "repeated_frames": {name: int(np.sum(plan == code)) for name, code in
                                (("frame", REPEAT_FRAME), ("rgb", REPEAT_RGB), ("depth", REPEAT_DEPTH))},
        })
        try:
            os.rename(tmp, out_dir)
        except OSError:
            if not (out_dir / "seq-01").is_dir():
                raise
            log.info("%s was rendered by another process meanwhile; keeping that one", out_dir)
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("rendered %s in %.1f s (%.1f frames/s)", out_dir.name, seconds, config.frames / seconds)
    return out_dir
