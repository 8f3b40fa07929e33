"""Lens distortion: raw images remapped to pinhole ones (data/undistort.py), and the TUM
reader's published fr1/fr2 distortion and ``camera.txt`` coefficients."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from ctcvo.data.errors import DataError
from ctcvo.data.sequence import Intrinsics, read_rgb
from ctcvo.data.tum import TUM_DISTORTION, TUM_INTRINSICS, TumSequence, camera_for
from ctcvo.data.undistort import Undistortion, undistortion
from tests.test_readers import make_tum_seq

FR1 = TUM_INTRINSICS["fr1"]


def _raw_pixel(intr: Intrinsics, coeffs: tuple[float, ...], uv: tuple[float, float]) -> np.ndarray:
    """Where the raw (distorted) image shows what the pinhole pixel ``uv`` sees."""
    ray = np.array([[(uv[0] - intr.cx) / intr.fx, (uv[1] - intr.cy) / intr.fy, 1.0]])
    px, _ = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), intr.K, np.array(coeffs))
    return px.reshape(2)


@pytest.mark.parametrize("uv", [(60.0, 50.0), (600.0, 420.0), (320.0, 255.0), (100.0, 400.0)])
def test_a_raw_dot_lands_on_its_pinhole_pixel(uv: tuple[float, float]) -> None:
    coeffs = TUM_DISTORTION["fr1"]
    u_raw, v_raw = np.rint(_raw_pixel(FR1, coeffs, uv)).astype(int)
    depth = np.zeros((FR1.height, FR1.width), np.float32)
    depth[v_raw - 1: v_raw + 2, u_raw - 1: u_raw + 2] = 2.5
    rgb = np.zeros((FR1.height, FR1.width, 3), np.uint8)
    rgb[v_raw - 1: v_raw + 2, u_raw - 1: u_raw + 2] = 200
    und = Undistortion(FR1, coeffs)
    for img in (und.depth(depth), und.rgb(rgb)[..., 0].astype(np.float32)):
        ys, xs = np.nonzero(img > 0)
        assert len(xs) > 0
        w = img[ys, xs]
        centre = np.array([np.average(xs, weights=w), np.average(ys, weights=w)])
        np.testing.assert_allclose(centre, uv, atol=1.0)
    # away from the centre the distortion moves the dot by several pixels: the check has teeth
    if abs(uv[0] - FR1.cx) > 100:
        assert np.hypot(u_raw - uv[0], v_raw - uv[1]) > 3


def test_depth_is_never_blended_and_past_the_border_is_invalid() -> None:
    depth = np.where(np.arange(FR1.width)[None, :] < 320, 1.0, 3.0).astype(np.float32)
    depth = np.repeat(depth, FR1.height, 0)
    out = Undistortion(FR1, TUM_DISTORTION["fr1"]).depth(depth)
    assert set(np.unique(out)) <= {0.0, 1.0, 3.0}
    assert out[0, 0] == 0.0 and out[FR1.height // 2, FR1.width // 2] == 3.0


@pytest.mark.parametrize("coeffs", [TUM_DISTORTION["fr1"], TUM_DISTORTION["fr2"], (0.4, 0.2, 0.003, -0.002, 0.05)])
def test_depth_takes_the_pixels_opencvs_nearest_remap_takes(coeffs: tuple[float, ...]) -> None:
    """The depth's gather (:meth:`Undistortion.depth`) equals ``cv2.remap``'s nearest-pixel
    interpolation bit for bit, 0 past the border included, for the fr1 / fr2 lenses and a
    strong pincushion one whose corners look past the raw image."""
    und = Undistortion(FR1, coeffs)
    depth = np.random.default_rng(2).uniform(0.3, 6.0, (FR1.height, FR1.width)).astype(np.float32)
    want = cv2.remap(depth, *und._maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    got = und.depth(depth)
    assert got.dtype == np.float32 and got.shape == depth.shape
    np.testing.assert_array_equal(got, want)
    if coeffs[0] > 0.3:
        assert (got == 0).sum() > 1000  # the strong lens's corners are past the border
    with pytest.raises(DataError, match="depth image is"):
        und.depth(depth[:-1])


def test_no_distortion_is_none_and_bad_coefficients_are_errors() -> None:
    assert undistortion(FR1, ()) is None
    assert undistortion(FR1, (0.0, 0.0, 0.0, 0.0, 0.0)) is None
    with pytest.raises(DataError, match="4 or 5"):
        Undistortion(FR1, (0.1, 0.2))
    with pytest.raises(DataError, match="finite"):
        Undistortion(FR1, (0.1, np.nan, 0, 0))


def test_tum_cameras_by_name_and_camera_txt(tmp_path: Path) -> None:
    for name, coeffs in [("rgbd_dataset_freiburg1_xyz", TUM_DISTORTION["fr1"]),
                         ("rgbd_dataset_freiburg2_desk", TUM_DISTORTION["fr2"])]:
        (tmp_path / name).mkdir()
        intr, und = camera_for(tmp_path / name)
        assert und is not None and und.coeffs == coeffs and intr == und.intrinsics
    (tmp_path / "rgbd_dataset_freiburg3_teddy").mkdir()
    assert camera_for(tmp_path / "rgbd_dataset_freiburg3_teddy")[1] is None

    folder = make_tum_seq(tmp_path / "own", n=2, camera="10 11 4 3 8 6 0.1 -0.2 0.001 0.002")
    seq = TumSequence(folder)
    assert seq.intrinsics == Intrinsics(10, 11, 4, 3, 8, 6)
    assert seq.undistortion is not None and seq.undistortion.coeffs == (0.1, -0.2, 0.001, 0.002)
    assert seq.rgb(0).shape == (6, 8, 3) and seq.depth(0).shape == (6, 8)
    (folder / "camera.txt").write_text("10 11 4 3 8 6 0.1 -0.2 0.001 nan\n")
    with pytest.raises(DataError, match="non-finite"):
        TumSequence(folder)
    (folder / "camera.txt").write_text("10 11 4 3 8 6 0.1 -0.2 0.001 x\n")
    with pytest.raises(DataError, match="numbers"):
        TumSequence(folder)
    (folder / "camera.txt").write_text("10 11 4 3 8 6\n")
    assert TumSequence(folder).undistortion is None


def test_real_fr1_frames_are_undistorted(tum_images: Path) -> None:
    seq = TumSequence(tum_images)
    assert seq.undistortion is not None
    raw = read_rgb(tum_images / seq._rgb_files[0], seq.intrinsics)
    und = seq.rgb(0)
    assert und.shape == raw.shape
    # the centre barely moves, the corners by tens of pixels
    c = (slice(220, 260), slice(300, 340))
    assert np.abs(und[c].astype(int) - raw[c].astype(int)).mean() < np.abs(und.astype(int) - raw.astype(int)).mean()
    assert (seq.depth(0)[:5, :5] == 0).all()
