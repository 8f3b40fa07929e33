"""Synthetic scenes: known-answer depth, sensor statistics, trajectories, cache and reader."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import ctcvo.data.synthetic as syn
from ctcvo.data.errors import ConfigError, DataError
from ctcvo.data.geometry import is_rigid
from ctcvo.data.scenes import open_scene
from ctcvo.data.synthetic.config import PRESETS, SensorConfig
from ctcvo.data.synthetic.layout import SceneBuilder
from ctcvo.data.synthetic.renderer import Renderer
from ctcvo.data.synthetic.sensor import ColourSensor, colour_camera_pad, depth_sensor, projector_shadow
from ctcvo.data.synthetic.textures import tex_plain
from ctcvo.data.synthetic.trajectory import motion_stats

FX, CX, CY, W, H = 585.0, 320.0, 240.0, 640, 480


def _plane_scene(point: np.ndarray, normal: np.ndarray, half: float = 20.0):
    """A single large square plane through ``point`` with ``normal`` (world = camera frame)."""
    b = SceneBuilder(np.random.default_rng(0), (1.0, 1.0, 1.0))
    m = b.material("grey", lambda g: tex_plain(g, np.array([0.5, 0.5, 0.5], np.float32)), 1.0)
    n = normal / np.linalg.norm(normal)
    e1 = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    b.quad(point - half * e1 - half * e2, 2 * half * e1, 2 * half * e2, m)
    b.lights.append((0.0, 0.0, 0.0, 1.0))
    return b.build(free_margin=0.1)


def _plane_z(point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Analytic z-depth (H, W) of the plane n.X = n.point seen by the camera at the origin."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - CX) / FX, (v - CY) / FX, np.ones_like(u)], -1)
    return float(normal @ point) / (d @ normal)


@pytest.mark.parametrize("dist,normal", [(1.5, [0.0, 0.0, -1.0]), (2.0, [0.3, -0.2, -1.0])])
def test_noise_free_depth_is_exact_z(dist, normal):
    point, normal = np.array([0.0, 0.0, dist]), np.array(normal)
    r = Renderer(_plane_scene(point, normal), FX, FX, CX, CY, W, H)
    frame = r.render(np.eye(4))
    expected = _plane_z(point, normal / np.linalg.norm(normal))
    assert (frame.triangle >= 0).all()
    np.testing.assert_allclose(frame.depth, expected, rtol=2e-6, atol=2e-6)
    clean = depth_sensor(frame.depth, frame.cos_incidence, FX, SensorConfig(noise_free=True), np.random.default_rng(0))
    np.testing.assert_array_equal(clean, frame.depth)
    mm = syn.depth_to_png_mm(clean)
    assert np.abs(mm / 1000.0 - expected).max() <= 0.0005 + 1e-6


def test_shading_is_lambertian_on_a_plane():
    # light at the camera centre, grey albedo 0.5: colour = 0.5 * (ambient + cos / (0.5 + r^2))
    point, normal = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    scene = _plane_scene(point, normal)
    frame = Renderer(scene, FX, FX, CX, CY, W, H).render(np.eye(4))
    centre = frame.colour[240, 320]
    expected = 0.5 * (scene.ambient + 1.0 / (0.5 + 1.0))
    np.testing.assert_allclose(centre, expected, rtol=0.03)


def _wall_errors(z: float, seed: int = 0) -> np.ndarray:
    zz = np.full((H, W), z, np.float32)
    out = depth_sensor(zz, np.ones_like(zz), FX, SensorConfig(), np.random.default_rng(seed))
    inner = out[20:-20, 20:-20]
    return inner[inner > 0] - z


def test_depth_noise_follows_kinect_z_squared_law():
    e1, e3, e4 = _wall_errors(1.0), _wall_errors(3.0), _wall_errors(4.0)
    s1, s3, s4 = e1.std(), e3.std(), e4.std()
    assert 1.0e-3 < s1 < 2.5e-3, s1  # ~1.5 mm at 1 m
    assert 10e-3 < s3 < 22e-3, s3  # cm-level at 3 m
    assert 20e-3 < s4 < 33e-3, s4  # 2-3 cm at 4 m
    assert 11 < s4 / s1 < 21  # ~ z^2
    assert abs(e1.mean()) < 0.3e-3
    # disparity quantisation: few distinct depth values at 1 m, steps ~2.85 mm
    vals = np.unique(np.round(e1 + 1.0, 6))
    steps = np.diff(vals)
    assert 2.0e-3 < np.median(steps) < 3.5e-3


def test_depth_holes_outside_working_range():
    zz = np.tile(np.linspace(0.3, 6.0, W, dtype=np.float32), (H, 1))
    out = depth_sensor(zz, np.ones_like(zz), FX, SensorConfig(), np.random.default_rng(1))
    assert (out[zz < 0.47] == 0).all()
    assert (out[zz > 4.9] == 0).all()
    assert ((out > 0) & ((out < 0.5) | (out > 4.5))).sum() == 0
    mid = (zz > 0.7) & (zz < 4.0)
    assert 0.93 < (out[mid] > 0).mean() < 0.99  # blobs, dropouts and the invalid right band
    assert (out[:, -8:] == 0).all()


def test_projector_shadow_width_matches_geometry():
    zz = np.full((H, W), 2.0, np.float32)
    zz[:, 300:400] = 1.0  # a 1 m foreground bar in front of a 2 m wall
    shadow = projector_shadow(zz, FX, 0.075)
    cols = np.flatnonzero(shadow[100])
    expected = FX * 0.075 * (1 / 1.0 - 1 / 2.0)  # 21.9 px left of the bar
    assert cols.max() == 299
    assert abs(len(cols) - expected) <= 1.0
    assert not shadow[:, 300:].any()


def test_presets_are_distinct_and_sized():
    names = [n for n in PRESETS if n != "tiny"]
    assert len(names) >= 3
    assert len({PRESETS[n].layout for n in names}) >= 3
    assert all(300 <= PRESETS[n].frames <= 600 for n in names)
    assert PRESETS["tiny"].frames <= 30
    digests = {PRESETS[n].digest() for n in PRESETS}
    assert len(digests) == len(PRESETS)
    clean = syn.config.resolve_preset("office-clean")
    assert clean.sensor.noise_free and clean.digest() != PRESETS["office"].digest()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["office", "kitchen", "lab"])
def test_trajectories_are_hand_held_speeds(name):
    cfg = PRESETS[name]
    scene, poses = syn.build(cfg)
    assert poses.shape == (cfg.frames, 4, 4)
    assert all(is_rigid(T, atol=1e-9) for T in poses)
    st = motion_stats(poses, cfg.fps)
    assert 0.1 <= st["mean_speed_mps"] <= 0.4, st
    assert st["max_speed_mps"] <= 0.55, st  # redkitchen: 99th percentile 17.7 mm/frame = 0.53 m/s
    # redkitchen's per-frame rotation speed: median 12.6, 99th percentile 31, peak 43 deg/s
    rot = np.degrees([np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))
                      for a, b in zip(poses[:-1], poses[1:])]) * cfg.fps
    assert 8.0 <= np.median(rot) <= 16.0 and 25.0 <= np.percentile(rot, 99) <= 40.0, np.percentile(rot, [50, 99])
    assert 30.0 <= st["max_angular_dps"] <= 40.0, st
    assert 3.0 <= st["mean_step_mm"] <= 15.0, st
    pos = poses[:, :3, 3]
    assert (pos > 0.3).all() and (pos < scene.size - 0.3).all()
    clearance = np.min([ob.distance(pos) for ob in scene.obstacles], axis=0)
    assert clearance.min() > 0.2


@pytest.mark.slow
def test_rendering_is_deterministic_for_a_seed():
    cfg = dataclasses.replace(PRESETS["tiny"], frames=4)
    a = syn.FrameRenderer(cfg, *syn.build(cfg))
    b = syn.FrameRenderer(cfg, *syn.build(cfg))
    np.testing.assert_array_equal(a.poses, b.poses)
    rgb_a, d_a, _ = a.frame(2)
    rgb_b, d_b, _ = b.frame(2)
    np.testing.assert_array_equal(rgb_a, rgb_b)
    np.testing.assert_array_equal(d_a, d_b)
    other = dataclasses.replace(cfg, seed=cfg.seed + 1)
    assert not np.allclose(syn.build(other)[1], a.poses)
    # noise is on: the measured depth differs from the exact one, with holes
    exact = a.renderer.render(a.poses[2]).crop(*a.pad).depth
    valid = d_a > 0
    assert 0.6 < valid.mean() < 0.995
    assert np.abs(d_a[valid] - exact[valid]).max() > 1e-3


@pytest.mark.slow
def test_open_scene_round_trip_and_cache(tmp_path: Path):
    seqs = open_scene("synthetic/tiny", cache_dir=tmp_path)
    assert len(seqs) == 1
    seq = seqs[0]
    cfg = PRESETS["tiny"]
    assert len(seq) == cfg.frames and seq.name == "synthetic-tiny"
    assert seq.intrinsics.K.tolist() == [[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]]
    folder = syn.scene_dir("tiny", cfg, tmp_path)
    assert folder.name.endswith(cfg.digest()) and (folder / "seq-01" / "frame-000000.color.jpg").is_file()
    scene, poses = syn.build(cfg)
    plan = syn.repeat_plan(cfg.sensor, len(poses), cfg.seed)
    new = np.flatnonzero(plan == syn.NEW)
    np.testing.assert_allclose(seq.groundtruth()[new], poses[new], atol=1e-8)
    fr = syn.FrameRenderer(cfg, scene, poses)
    k = int(new[new >= 2][0])
    rgb, depth, exact = fr.frame(k)
    np.testing.assert_array_equal(seq.rgb(k), rgb)
    np.testing.assert_allclose(seq.depth(k), np.rint(depth * 1000) / 1000, atol=1e-6)
    # the camera looks at the room contents from typical 7-Scenes distances
    assert 0.7 < np.median(exact.depth[exact.depth > 0]) < 3.0
    # second open: cached, nothing re-rendered
    mtime = (folder / "config.json").stat().st_mtime_ns
    open_scene("synthetic/tiny", cache_dir=tmp_path)
    assert (folder / "config.json").stat().st_mtime_ns == mtime
    assert not list(folder.parent.glob(".tmp-*"))


@pytest.mark.slow
def test_killed_render_leaves_no_scene(tmp_path: Path, monkeypatch):
    calls = {"n": 0}
    real = syn._write_frame

    def failing(*args):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(syn, "_write_frame", failing)
    cfg = dataclasses.replace(PRESETS["tiny"], frames=6, width=160, height=120, fx=146.25, fy=146.25, cx=80, cy=60)
    with pytest.raises(KeyboardInterrupt):
        syn.synthetic_sequence("small", cache_dir=tmp_path, config=cfg)
    root = tmp_path / "synthetic"
    assert not any(root.iterdir())
    monkeypatch.setattr(syn, "_write_frame", real)
    seq = syn.synthetic_sequence("small", cache_dir=tmp_path, config=cfg)
    assert len(seq) == 6 and seq.rgb(0).shape == (120, 160, 3) and seq.intrinsics.width == 160


def test_unknown_name_lists_known_names(tmp_path: Path):
    with pytest.raises(DataError) as err:
        open_scene("synthetic/attic", cache_dir=tmp_path)
    msg = str(err.value)
    assert "attic" in msg and all(n in msg for n in ("office", "kitchen", "lab", "tiny"))


def test_cache_dir_from_environment(monkeypatch, tmp_path: Path):
    monkeypatch.setenv("VO_CACHE_DIR", str(tmp_path / "c"))
    assert syn.default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("VO_CACHE_DIR")
    assert syn.default_cache_dir() == Path.home() / ".cache" / "ctcvo"
    cfg = PRESETS["office"]
    changed = dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, depth_noise_coeff=2e-3))
    assert syn.scene_dir("office", cfg, tmp_path) != syn.scene_dir("office", changed, tmp_path)


def test_open3d_barycentric_convention():
    # the renderer interpolates surface coordinates as (1-a-b) uv0 + a uv1 + b uv2
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32), np.array([[0, 1, 2]], np.uint32))
    ans = rc.cast_rays(np.array([[0.2, 0.3, 0, 0, 0, 1]], np.float32))
    np.testing.assert_allclose(ans["primitive_uvs"].numpy()[0], [0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(ans["t_hit"].numpy()[0], 1.0, atol=1e-6)


@pytest.mark.slow
def test_rolling_shutter_row_poses():
    cfg = dataclasses.replace(PRESETS["tiny"], frames=6)
    fr = syn.FrameRenderer(cfg, *syn.build(cfg))
    py = fr.pad[1]
    all_rows = fr.row_poses(3)
    assert all_rows.shape == (cfg.height + 2 * py, 4, 4) and all(is_rigid(T, atol=1e-9) for T in all_rows[::60])
    rows = all_rows[py: py + cfg.height]  # the image rows, without the colour camera's padding
    mid = (rows[239] + rows[240]) / 2
    np.testing.assert_allclose(mid[:3, 3], fr.poses[3][:3, 3], atol=1e-6)
    # the top-to-bottom motion is the readout time times the camera speed
    speed = np.linalg.norm(fr.poses[4][:3, 3] - fr.poses[2][:3, 3]) / 2 * cfg.fps
    travel = np.linalg.norm(rows[-1][:3, 3] - rows[0][:3, 3])
    np.testing.assert_allclose(travel, speed * cfg.sensor.rolling_shutter_s, rtol=0.05)
    # the noise-free mode renders an exact pinhole, global-shutter image
    clean = dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, noise_free=True))
    fc = syn.FrameRenderer(clean, *syn.build(clean))
    _, depth, exact = fc.frame(3)
    np.testing.assert_array_equal(depth, fc.renderer.render(fc.poses[3]).depth)


@pytest.mark.parametrize("z", [0.8, 2.5])
def test_colour_camera_is_unregistered_like_kinect(z):
    # a dot at depth-camera pixel (u, v) on a fronto-parallel wall at z appears in the colour
    # image at c + s (u - c) + shift - s fx b / z (wider field of view, shift, parallax)
    cfg = SensorConfig(rgb_blur_sigma=0.0, motion_blur_exposure=0.0, vignetting=0.0, read_noise_dn=0.0,
                       shot_noise_gain=0.0, jpeg_quality=0)
    px, py = colour_camera_pad(cfg, W, H, FX)
    assert px > W / 2 * (1 / cfg.rgb_focal_scale - 1) + FX * cfg.rgb_baseline_m / 0.4 and py > 20
    sensor = ColourSensor(cfg, W, H, CX, CY, FX)
    img = np.zeros((H + 2 * py, W + 2 * px, 3), np.float32)
    u, v = 150, 400
    img[v + py - 1: v + py + 2, u + px - 1: u + px + 2] = 1.0
    out = sensor(img, 1.0, np.zeros(2), np.random.default_rng(0), np.full(img.shape[:2], z, np.float32))
    s, (sx, sy) = cfg.rgb_focal_scale, cfg.rgb_shift_px
    w = out[..., 0].astype(np.float64)
    yy, xx = np.mgrid[0:H, 0:W]
    found = np.array([(w * xx).sum(), (w * yy).sum()]) / w.sum()
    expected = [CX + s * (u - CX) + sx - s * FX * cfg.rgb_baseline_m / z, CY + s * (v - CY) + sy]
    np.testing.assert_allclose(found, expected, atol=0.15)


@pytest.mark.slow
def test_dropped_frames_repeat_the_previous_files(tmp_path: Path):
    """The sensor model's dropped frames: a repeated frame has the previous frame's colour,
    depth and pose; a colour repeat only its colour; a depth repeat its depth and pose. The
    rates follow the config, and the noise-free mode has none."""
    plan = syn.repeat_plan(PRESETS["office"].sensor, 20000, 0)
    rates = np.bincount(plan, minlength=4) / len(plan)
    s = PRESETS["office"].sensor
    np.testing.assert_allclose(rates[1:], [s.frame_repeat_prob, s.rgb_repeat_prob, s.depth_repeat_prob], atol=0.005)
    assert not syn.repeat_plan(dataclasses.replace(s, noise_free=True), 100, 0).any()
    assert plan[0] == syn.NEW

    cfg = dataclasses.replace(PRESETS["tiny"], frames=40, sensor=dataclasses.replace(
        PRESETS["tiny"].sensor, frame_repeat_prob=0.2, rgb_repeat_prob=0.2, depth_repeat_prob=0.2))
    plan = syn.repeat_plan(cfg.sensor, cfg.frames, cfg.seed)
    assert {1, 2, 3} <= set(plan.tolist())
    seq_dir = syn.render_scene(cfg, tmp_path / "scene", workers=2) / "seq-01"
    read = lambda k, suffix: (seq_dir / f"frame-{k:06d}{suffix}").read_bytes()  # noqa: E731
    for k in range(1, cfg.frames):
        same = {suffix: read(k, suffix) == read(k - 1, suffix) for suffix in (".color.jpg", ".depth.png", ".pose.txt")}
        if plan[k] == syn.REPEAT_FRAME:
            assert all(same.values()), k
        elif plan[k] == syn.REPEAT_RGB:
            assert same[".color.jpg"] and not same[".depth.png"] and not same[".pose.txt"], k
        elif plan[k] == syn.REPEAT_DEPTH:
            assert same[".depth.png"] and same[".pose.txt"] and not same[".color.jpg"], k
        else:
            assert not any(same.values()), k


@pytest.mark.slow
def test_colour_files_are_the_sensor_jpeg(tmp_path) -> None:
    """The colour files are the sensor model's JPEG itself (as the 7-Scenes sample's): read
    back, they equal the rendered image exactly; the noise-free variant stays lossless PNG."""
    from ctcvo.data.sequence import read_rgb

    cfg = dataclasses.replace(PRESETS["tiny"], frames=3, sensor=dataclasses.replace(
        PRESETS["tiny"].sensor, frame_repeat_prob=0, rgb_repeat_prob=0, depth_repeat_prob=0))
    seq_dir = syn.render_scene(cfg, tmp_path / "noisy", workers=1) / "seq-01"
    fr = syn.FrameRenderer(cfg, *syn.build(cfg))
    for k in range(cfg.frames):
        assert not (seq_dir / f"frame-{k:06d}.color.png").exists()
        np.testing.assert_array_equal(read_rgb(seq_dir / f"frame-{k:06d}.color.jpg"), fr.frame(k)[0])
    clean = dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, noise_free=True))
    seq_dir = syn.render_scene(clean, tmp_path / "clean", workers=1) / "seq-01"
    fc = syn.FrameRenderer(clean, *syn.build(clean))
    np.testing.assert_array_equal(read_rgb(seq_dir / "frame-000001.color.png"), fc.frame(1)[0])
    assert syn.colour_suffix(cfg.sensor) == ".color.jpg" and syn.colour_suffix(clean.sensor) == ".color.png"


@pytest.mark.slow
def test_training_corpus_rooms(tmp_path: Path):
    """``synthetic/room-<N>``: rooms of the three layouts in turn, each from its own seed
    (never a named scene's) with its own trajectory statistics; ``-clean`` works for them
    too, unknown forms are refused, and a room renders."""
    from ctcvo.data.synthetic.config import CORPUS_SEED0, resolve_preset

    rooms = [resolve_preset(f"room-{k}") for k in range(6)]
    assert [r.layout for r in rooms] == ["office", "kitchen", "lab"] * 2
    assert [r.seed for r in rooms] == list(range(CORPUS_SEED0, CORPUS_SEED0 + 6))
    assert len({r.mean_speed_mps for r in rooms}) == 6 and all(0.12 <= r.mean_speed_mps <= 0.40 for r in rooms)
    assert not {r.seed for r in rooms} & {c.seed for c in syn.config.PRESETS.values()}
    assert resolve_preset("room-4-clean").sensor.noise_free and resolve_preset("room-4") == rooms[4]
    for bad in ("room-", "room-x", "room--1"):
        with pytest.raises(DataError):
            open_scene(f"synthetic/{bad}", cache_dir=tmp_path)
    cfg = dataclasses.replace(rooms[1], frames=3, width=160, height=120, fx=146.25, fy=146.25, cx=80.0, cy=60.0)
    seq = syn.synthetic_sequence("room-1", cache_dir=tmp_path, config=cfg)
    assert len(seq) == 3 and seq.rgb(0).shape == (120, 160, 3) and seq.groundtruth().shape == (3, 4, 4)


def test_corpus_spec(tmp_path: Path, monkeypatch):
    """``synthetic/corpus-<COUNT>[x<FRAMES>]`` opens rooms 0..COUNT-1 as separate sequences;
    ``room-<N>x<FRAMES>`` is room N (same room, same trajectory statistics) with another
    number of frames; malformed specs are refused with the list of known names."""
    from ctcvo.data.synthetic.config import corpus_names, resolve_preset

    assert corpus_names("corpus-3") == ["room-0", "room-1", "room-2"]
    assert corpus_names("corpus-2x40") == ["room-0x40", "room-1x40"]
    short, full = resolve_preset("room-2x40"), resolve_preset("room-2")
    assert short.frames == 40 and full.frames == 300 and dataclasses.replace(short, frames=300) == full
    for bad in ("corpus-0", "corpus-", "corpus-2x1", "corpus-2x", "room-2x1", "room-2x"):
        with pytest.raises(DataError):
            open_scene(f"synthetic/{bad}", cache_dir=tmp_path)
    # each room is one sequence, rendered (here: stood in for) one after the other
    opened = []
    monkeypatch.setattr(syn, "synthetic_sequence", lambda name, cache_dir=None: opened.append(name) or name)
    assert open_scene("synthetic/corpus-2x3", cache_dir=tmp_path) == ["room-0x3", "room-1x3"] == opened


@pytest.mark.slow
def test_depth_time_offsets_are_drawn_written_and_read_back(tmp_path: Path):
    """``depth_time_offset_s``: per-frame offsets uniform in the range, deterministic for the
    seed, written as ``depth-offsets.txt`` and read back as the depth timestamps; the depth
    image of a frame is rendered from the pose at its own moment (the frame's pose, and
    timestamp, are the colour's). Bad ranges and offsets with repeated frames are refused."""
    base = PRESETS["tiny"]
    sensor = dataclasses.replace(base.sensor, frame_repeat_prob=0.0, rgb_repeat_prob=0.0, depth_repeat_prob=0.0,
                                 depth_time_offset_s=(-0.0167, -0.002))
    cfg = dataclasses.replace(base, frames=4, sensor=sensor)
    assert cfg.digest() != dataclasses.replace(cfg, sensor=dataclasses.replace(sensor, depth_time_offset_s=(0.0, 0.0))).digest()
    assert base.digest() == "6864bae2"  # the new field leaves the cache folders of the scenes without it
    off = syn.depth_time_offsets(cfg, 200)
    assert off.min() >= -0.0167 and off.max() <= -0.002 and np.ptp(off) > 0.01
    np.testing.assert_array_equal(off, syn.depth_time_offsets(cfg, 200))
    assert not syn.depth_time_offsets(base, 5).any()
    fr = syn.FrameRenderer(cfg, *syn.build(cfg))
    _, depth, exact = fr.frame(2)
    shifted = fr.renderer.render(fr.row_poses(2, float(fr.depth_offsets[2]))).crop(*fr.pad)
    np.testing.assert_array_equal(exact.depth, shifted.depth)
    assert not np.array_equal(exact.depth, fr.renderer.render(fr.row_poses(2)).crop(*fr.pad).depth)
    seq = syn.synthetic_sequence("tiny", cache_dir=tmp_path, config=cfg)
    np.testing.assert_allclose(seq.depth_offsets(), syn.depth_time_offsets(cfg, 4), atol=1e-9)
    np.testing.assert_allclose(seq.times(), np.arange(4) / 30)
    with pytest.raises(ConfigError, match="repeated frames"):
        syn.depth_time_offsets(dataclasses.replace(base, sensor=dataclasses.replace(
            base.sensor, depth_time_offset_s=(-0.01, 0.0))), 4)
    with pytest.raises(ConfigError, match="within one frame"):
        syn.depth_time_offsets(dataclasses.replace(cfg, sensor=dataclasses.replace(sensor, depth_time_offset_s=(0.01, -0.01))), 4)


@pytest.fixture(scope="module")
def _module_scoped_cache() -> Path:
    return syn.default_cache_dir()


def test_tests_never_use_the_users_cache(_module_scoped_cache) -> None:
    """Every fixture scope and every subprocess sees the session's temporary cache."""
    import subprocess
    import sys

    user = Path.home() / ".cache" / "ctcvo"
    code = "from ctcvo.data.synthetic import default_cache_dir; print(default_cache_dir())"
    child = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           cwd=Path(__file__).resolve().parents[1]).stdout.strip()
    assert _module_scoped_cache == syn.default_cache_dir() == Path(child) != user
    assert "ctcvo-test-cache-" in str(child)
