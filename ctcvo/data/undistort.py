"""Lens distortion of cameras whose images are recorded raw (TUM RGB-D's fr1 and fr2).

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
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.errors import DataError
from ctcvo.data.sequence import Intrinsics

#: number of coefficients accepted: k1 k2 p1 p2, or k1 k2 p1 p2 k3
COEFF_COUNTS = (4, 5)


class Undistortion:
    """Remaps raw images of a camera with distortion ``coeffs`` to pinhole images of the
    same camera matrix ``intrinsics``."""

    def __init__(self, intrinsics: Intrinsics, coeffs: tuple[float, ...]) -> None:
        coeffs = tuple(float(c) for c in coeffs)
        if len(coeffs) not in COEFF_COUNTS or not np.all(np.isfinite(coeffs)):
            raise DataError(f"distortion needs 4 or 5 finite coefficients (k1 k2 p1 p2 [k3]), got {coeffs}")
        self.intrinsics, self.coeffs = intrinsics, coeffs
        K = intrinsics.K
        self._maps = cv2.initUndistortRectifyMap(K, np.array(coeffs), None, K, (intrinsics.width, intrinsics.height),
                                                 cv2.CV_16SC2)

    def rgb(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """(H, W, 3) raw colour -> undistorted (bilinear; the border repeats past the edge)."""
        return cv2.remap(img, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def depth(self, depth: NDArray[np.float32]) -> NDArray[np.float32]:
        """(H, W) raw depth, metres -> undistorted (nearest pixel; 0 past the edge)."""
        return cv2.remap(depth, *self._maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)

    def __repr__(self) -> str:
        return f"Undistortion({', '.join(f'{c:g}' for c in self.coeffs)})"


def undistortion(intrinsics: Intrinsics, coeffs: tuple[float, ...]) -> Undistortion | None:
    """An :class:`Undistortion`, or None for a camera without distortion (all zeros or none)."""
    if not coeffs or not np.any(np.asarray(coeffs, dtype=np.float64)):
        return None
    return Undistortion(intrinsics, coeffs)
