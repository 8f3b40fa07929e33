"""Lens distortion of cameras whose images are recorded raw (TUM RGB-D's fr1 and fr2, a
camera self-calibrated by ``ctcvo teacher calibrate``).

A reader that knows a camera's distortion undistorts each frame before it leaves the
reader, so every stage (and ORB-SLAM3, fed through the same reader) sees pinhole frames
with the camera matrix the reader gives. The model is OpenCV's radial-tangential
(``plumb_bob``) one, coefficients ``k1 k2 p1 p2 [k3]``. The undistorted image keeps the
camera matrix; where it looks past the raw image's border (the corners, for fr1's
distortion), colour repeats the border and depth is 0 (invalid).

Depth needs no other correction: a depth image registered to the colour camera holds,
at each raw pixel, the z of the point that pixel sees, and z does not change when the
pixel moves (nearest-neighbour resampling, so depth values are never blended across
edges).

A camera file (``camera.json``, :func:`write_camera`) holds a camera matrix and its
distortion; :func:`with_camera` undistorts a sequence's frames with it (``--camera``).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import DataError
from ctcvo.data.io import write_json
from ctcvo.data.sensor import ColourCamera
from ctcvo.data.sequence import Intrinsics, Sequence

#: number of coefficients accepted: k1 k2 p1 p2, or k1 k2 p1 p2 k3
COEFF_COUNTS = (4, 5)


class Undistortion:
    """Remaps raw images of a camera with distortion ``coeffs`` to pinhole images of the
    same camera matrix ``intrinsics``. ``colour``: how colour pixels map onto the depth
    camera's (:class:`~data.sensor.ColourCamera`) when colour is not registered to depth;
    the distortion is the depth camera's, and the colour camera sees through the same lens
    model (the synthetic sensor's, :mod:`data.synthetic.renderer`), so a colour pixel is
    taken from where the raw colour image shows its depth-camera pixel's raw position."""

    def __init__(self, intrinsics: Intrinsics, coeffs: tuple[float, ...], colour: ColourCamera | None = None) -> None:
        coeffs = tuple(float(c) for c in coeffs)
        if len(coeffs) not in COEFF_COUNTS or not np.all(np.isfinite(coeffs)):
            raise DataError(f"distortion needs 4 or 5 finite coefficients (k1 k2 p1 p2 [k3]), got {coeffs}")
        self.intrinsics, self.coeffs, self.colour = intrinsics, coeffs, colour
        K = intrinsics.K
        self._maps = cv2.initUndistortRectifyMap(K, np.array(coeffs), None, K, (intrinsics.width, intrinsics.height),
                                                 cv2.CV_16SC2)
        self._colour_maps = self._maps if colour is None else _colour_maps(intrinsics, coeffs, colour)
        self._depth_source = _nearest_sources(self._maps, intrinsics.height, intrinsics.width)

    def rgb(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """(H, W, 3) raw colour -> undistorted (bilinear; the border repeats past the edge)."""
        return cv2.remap(img, *self._colour_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def depth(self, depth: NDArray[np.float32]) -> NDArray[np.float32]:
        """(H, W) raw depth, metres -> undistorted (nearest pixel; 0 past the edge): the
        pixels ``cv2.remap`` would take (:func:`_nearest_sources`), gathered 2.5 times faster."""
        h, w = self.intrinsics.height, self.intrinsics.width
        if depth.shape != (h, w):
            raise DataError(f"depth image is {depth.shape[::-1]} pixels, the camera's {(w, h)}")
        padded = np.empty(h * w + 1, depth.dtype)
        padded[:-1] = depth.reshape(-1)
        padded[-1] = 0  # what the border gives
        return padded.take(self._depth_source).reshape(h, w)

    def __repr__(self) -> str:
        return f"Undistortion({', '.join(f'{c:g}' for c in self.coeffs)})"


def _nearest_sources(maps: tuple[NDArray, NDArray], height: int, width: int) -> NDArray[np.intp]:
    """For each undistorted pixel (flattened), the flat index of the raw pixel that
    ``cv2.remap`` with nearest-pixel interpolation takes it from, ``height * width`` past the
    border: an image of the pixels' indices remapped once, so a gather through these indices
    gives what the remap gives, bit for bit."""
    index = np.arange(1, height * width + 1, dtype=np.float64).reshape(height, width)  # 0: past the border
    source = cv2.remap(index, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    source = source.astype(np.intp).reshape(-1) - 1
    source[source < 0] = height * width
    return source


def distort(x: NDArray, y: NDArray, coeffs: tuple[float, ...]) -> tuple[NDArray, NDArray]:
    """Normalised pinhole coordinates -> raw (distorted) ones, OpenCV's radial-tangential model."""
    k1, k2, p1, p2, k3 = (tuple(coeffs) + (0.0,))[:5]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def _colour_maps(intr: Intrinsics, coeffs: tuple[float, ...], colour: ColourCamera) -> tuple[NDArray, NDArray]:
    """Float maps of the colour image: colour pixel -> its depth-camera pixel (the colour
    camera's linear model, parallax left out: under 0.1 px of change here) -> that pixel's
    raw position -> the raw colour pixel showing it."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    s, (sx, sy) = colour.focal_scale, colour.shift_px
    x = (intr.cx + (u - intr.cx - sx) / s - intr.cx) / intr.fx
    y = (intr.cy + (v - intr.cy - sy) / s - intr.cy) / intr.fy
    xd, yd = distort(x, y, coeffs)
    return ((intr.cx + sx + s * intr.fx * xd).astype(np.float32), (intr.cy + sy + s * intr.fy * yd).astype(np.float32))


def undistortion(intrinsics: Intrinsics, coeffs: tuple[float, ...],
                 colour: ColourCamera | None = None) -> Undistortion | None:
    """An :class:`Undistortion`, or None for a camera without distortion (all zeros or none)."""
    if not coeffs or not np.any(np.asarray(coeffs, dtype=np.float64)):
        return None
    return Undistortion(intrinsics, coeffs, colour)


def with_camera(seq: Sequence, camera: Path) -> Sequence:
    """A view of ``seq`` whose frames are undistorted with the distortion of ``camera``
    (a camera file, :func:`read_camera`). The file's camera matrix must be the sequence's,
    and the sequence's reader must not undistort its frames already."""
    intr, coeffs = read_camera(camera)
    if intr != seq.intrinsics:
        raise DataError(f"{camera} is a camera of {_matrix(intr)}; {seq.name}'s is {_matrix(seq.intrinsics)}")
    if seq.undistortion is not None:
        raise DataError(f"{seq.name}: its reader already undistorts its frames ({seq.undistortion}); "
                        f"{camera} cannot be applied on top")
    view = copy.copy(seq)
    view.undistortion = undistortion(seq.intrinsics, coeffs, seq.sensor.colour)
    return view


def _matrix(intr: Intrinsics) -> str:
    return f"fx {intr.fx:g} fy {intr.fy:g} cx {intr.cx:g} cy {intr.cy:g}, {intr.width}x{intr.height}"


def write_camera(path: Path, intr: Intrinsics, coeffs: tuple[float, ...], about: dict) -> None:
    """A camera file (docs/formats.md, "camera.json"), written atomically."""
    body = {"intrinsics": dataclasses.asdict(intr), "model": "opencv", "distortion": [float(c) for c in coeffs],
            **about}
    write_json(Path(path), body)


def read_camera(path: Path) -> tuple[Intrinsics, tuple[float, ...]]:
    """Intrinsics and OpenCV distortion of a camera file; :class:`DataError` if malformed."""
    path = Path(path)
    try:
        body = json.loads(path.read_text())
        intr = Intrinsics(**{k: body["intrinsics"][k] for k in ("fx", "fy", "cx", "cy", "width", "height")})
        coeffs = tuple(float(c) for c in body["distortion"])
    except FileNotFoundError:
        raise DataError(f"camera file {path} not found") from None
    except (ValueError, KeyError, TypeError) as e:
        raise DataError(f"{path}: not a camera file ({type(e).__name__}: {e})") from None
    if body.get("model") != "opencv" or len(coeffs) not in COEFF_COUNTS or not np.all(np.isfinite(coeffs)):
        raise DataError(f"{path}: needs model 'opencv' and 4 or 5 finite distortion coefficients")
    return intr, coeffs
