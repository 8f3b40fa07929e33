"""Per-frame maps of the dense alignments: Open3D vertex, normal and photometric maps."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.open3d_import import o3d

# 'the validation ranges': redkitchen 350:450 and synthetic/lab 0:150 (bench/README.md, seventh session)
DEPTH_MIN = 0.3  # m; the Kinect's range, by hand (fa44eca); 0.2 and 0.5 change no label on the validation ranges
DEPTH_MAX = 4.5  # m; the Kinect's range, by hand (fa44eca); 3.5 and 6 change no label on the validation ranges
DENSE_SCALE = 4  # every 4th depth pixel moved; by hand (b8ac45d); 3 better but 1.8x slower, 5 worse on the validation ranges
DENSE_TARGET_SCALE = 2  # surface sampled every 2nd pixel; by hand (b8ac45d); 3 mixed on the validation ranges
DENSE_NORMAL_KERNEL = 7  # smoothing before normals; by hand (b8ac45d); 5 worse on redkitchen 350:450
PHOTO_WEIGHT = 0.5  # photometric against depth residual; chosen on the stress scenes, office and lab (issue 13)
PHOTO_BLUR_PX = 2.0  # grey blur sigma; stress-far and synthetic/lab 0:100 (12b33f0)

@dataclass
class DenseMaps:
    """Open3D tensors of one frame for the dense depth alignment (float32, NaN where invalid).

    ``points`` (h4, w4, 3): vertex map of every ``DENSE_SCALE``-th pixel, used when the
    frame is the one moved (j); ``vertex`` and ``normal`` (h2, w2, 3): vertex and normal maps
    of every ``DENSE_TARGET_SCALE``-th pixel, used when the frame is the one aligned to
    (i), with ``K`` (3x3 float64) their camera matrix.
    """

    points: o3d.core.Tensor
    vertex: o3d.core.Tensor | None
    normal: o3d.core.Tensor | None
    K: o3d.core.Tensor
    photo: PhotoMaps | None = None
    _cache: dict = field(default_factory=dict, repr=False)
    """What the covariances of :func:`point_to_plane_covariance` take from this frame on
    every edge it is part of, computed on its first edge (:meth:`moved_points`,
    :meth:`surface`)."""

    def moved_points(self, stride: int) -> NDArray[np.float64]:
        """(N, 3) the finite points of ``points``, every ``stride``-th in both axes, float64
        (the frame as the one moved, j; the same for all its edges)."""
        key = ("points", stride)
        if key not in self._cache:
            q = self.points.numpy()[::stride, ::stride].reshape(-1, 3)
            self._cache[key] = np.compress(np.isfinite(q).all(axis=1), q, axis=0).astype(np.float64)
        return self._cache[key]

    def surface(self) -> tuple[NDArray[np.float32], NDArray[np.float32], int, int, NDArray[np.float64]]:
        """The frame as the one aligned to (i): (h * w, 3) vertex and normal of each pixel of
        ``vertex`` / ``normal`` (row-major views of Open3D's float32 maps, NaN where
        invalid), h, w and the camera matrix. An edge gathers the rows of the pixels it
        hits and tests and converts those alone: cheaper than one (h * w, 6) float64 table
        and its finiteness per frame (3.7 ms, more than the ~5 edges' gathers)."""
        if "surface" not in self._cache:
            vert, nrm = self.vertex.numpy(), self.normal.numpy()
            h, w = vert.shape[:2]
            self._cache["surface"] = (vert.reshape(-1, 3), nrm.reshape(-1, 3), h, w, self.K.numpy())
        return self._cache["surface"]


@dataclass
class PhotoMaps:
    """Open3D tensors of one frame for the hybrid (photometric + depth) alignment of
    :func:`hybrid_align` (float32, (rows, cols, 1) unless noted, NaN depth where invalid).

    As the frame moved (j): ``src_depth`` and ``src_intensity`` at the pixels of
    ``DenseMaps.points`` (every ``DENSE_SCALE``-th). As the frame aligned to (i), at
    full resolution: ``depth``, ``intensity`` (grey in [0, 1], registered to the depth
    camera), their unnormalised 3x3 Sobel derivatives ``depth_dx`` ... ``intensity_dy``, and
    ``K`` (3x3 float64). Full resolution on that side is what makes the alignment precise:
    Open3D's kernel pairs each point with the nearest target pixel, and at half resolution
    the gap-1 error on synthetic/stress-far doubled (2.1-2.5 against 0.9-1.3 mm)."""

    src_depth: o3d.core.Tensor
    src_intensity: o3d.core.Tensor
    depth: o3d.core.Tensor
    intensity: o3d.core.Tensor
    depth_dx: o3d.core.Tensor
    depth_dy: o3d.core.Tensor
    intensity_dx: o3d.core.Tensor
    intensity_dy: o3d.core.Tensor
    K: o3d.core.Tensor
    levels: dict = field(default_factory=dict)
    """Coarser levels for :func:`pyramid_align`, built on first use: scale -> (depth,
    intensity, depth_dx, depth_dy, intensity_dx, intensity_dy, vertex map, K) at that scale."""
    grey: bool = True
    """False: the intensity maps are zeros (:meth:`depth_only`), so the kernel's photometric
    term is void and only its depth term acts."""
    _depth_only: PhotoMaps | None = field(default=None, repr=False)

    def depth_only(self) -> PhotoMaps:
        """These maps with every intensity map zero (``grey`` False; built once, kept): for
        a frame whose colour shows another moment than its depth, and for the frame it is
        paired with, so Open3D's hybrid kernel aligns the depth alone (the projective depth
        term, coarse to fine in :func:`pyramid_align`)."""
        if not self.grey:
            return self
        if self._depth_only is None:
            z_src = o3d.core.Tensor(np.zeros(tuple(self.src_intensity.shape), np.float32))
            z = o3d.core.Tensor(np.zeros(tuple(self.intensity.shape), np.float32))
            self._depth_only = PhotoMaps(self.src_depth, z_src, self.depth, z, self.depth_dx, self.depth_dy, z, z,
                                         self.K, grey=False)
        return self._depth_only

    def level(self, s: int) -> tuple:
        """The maps of every ``s``-th pixel (intensity averaged over ``s x s`` blocks, depth
        subsampled), both as source and as target of the kernel."""
        if s not in self.levels:
            d = self.depth.numpy()[::s, ::s, 0].copy()
            full = self.intensity.numpy()[..., 0]
            inten = cv2.resize(full, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_AREA)
            K = self.K.numpy().copy()
            K[:2] /= s
            Kt = o3d.core.Tensor(K)
            maps = _kernel_maps(d, inten)
            vertex = o3d.t.geometry.Image(maps[0]).create_vertex_map(Kt, float("nan")).as_tensor()
            self.levels[s] = (*maps, vertex, Kt)
        return self.levels[s]


def _image_tensor(a: NDArray) -> o3d.core.Tensor:
    """(H, W) array -> (H, W, 1) float32 Open3D tensor, as the odometry kernels take images."""
    return o3d.core.Tensor(np.ascontiguousarray(a[..., None], dtype=np.float32))


def _kernel_maps(depth: NDArray[np.float32], inten: NDArray[np.float32]) -> tuple[o3d.core.Tensor, ...]:
    """What Open3D's hybrid kernel takes of a frame as its target: depth, intensity and
    their unnormalised 3x3 Sobel derivatives (depth_dx, depth_dy, intensity_dx,
    intensity_dy), each an (H, W, 1) float32 tensor."""
    return (_image_tensor(depth), _image_tensor(inten),
            *(_image_tensor(cv2.Sobel(a, cv2.CV_32F, dx, 1 - dx, ksize=3)) for a in (depth, inten) for dx in (1, 0)))


def _subsampled(depth: NDArray[np.float32], K: NDArray, s: int) -> tuple[o3d.t.geometry.Image, o3d.core.Tensor]:
    """Every ``s``-th pixel of ``depth`` (NaN outside ``[depth_min, depth_max]``) as an Open3D
    image, with its camera matrix ``K / s`` (pixel centres stay on the grid)."""
    d = np.array(depth[::s, ::s], dtype=np.float32)
    d[~((d >= DEPTH_MIN) & (d <= DEPTH_MAX))] = np.nan
    Ks = np.array(K, dtype=np.float64)
    Ks[:2] /= s
    return o3d.t.geometry.Image(o3d.core.Tensor(d)), o3d.core.Tensor(Ks)


def dense_maps(depth: NDArray[np.float32], K: NDArray,
               gray: NDArray[np.uint8] | None = None, surface: bool = True) -> DenseMaps:
    """The maps of :class:`DenseMaps` for one depth image (metres, 0 = invalid).

    The points moved are sparse (every 4th pixel: the cost of an iteration is proportional
    to their number), the surface they are aligned to is denser (every 2nd pixel): at 1/4
    resolution on both sides the alignment of noise-free frames was biased by ~1.5 mm
    (edges and curved surfaces are coarsely sampled), at 2 / 4 it is ~0.2 mm. Normals come
    from a Gaussian-smoothed copy of the depth (``filter_bilateral`` with a 5 m value sigma,
    which skips holes), as in Open3D's own point-to-plane odometry; Kinect noise makes
    unsmoothed normals useless.

    ``surface`` False leaves ``vertex`` and ``normal`` (the frame as the one aligned to, i:
    about two thirds of the time here) to :func:`add_surface`: a frame is i only in the
    edges of the frames after it, so ``vo-online`` builds them after handing the frame over.
    """
    img, Kt = _subsampled(depth, K, DENSE_SCALE)
    points = img.create_vertex_map(Kt, float("nan")).as_tensor()
    img, Kt = _subsampled(depth, K, DENSE_TARGET_SCALE)
    maps = DenseMaps(points, None, None, Kt, photo_maps(gray, depth, K) if gray is not None else None)
    if surface:
        _fill_surface(maps, img)
    return maps


def add_surface(maps: DenseMaps, depth: NDArray[np.float32], K: NDArray) -> None:
    """Fill ``maps.vertex`` and ``maps.normal`` (see :func:`dense_maps`) when they are missing."""
    if maps.vertex is None:
        _fill_surface(maps, _subsampled(depth, K, DENSE_TARGET_SCALE)[0])


def _fill_surface(maps: DenseMaps, img: o3d.t.geometry.Image) -> None:
    smooth = img.filter_bilateral(DENSE_NORMAL_KERNEL, 5.0, 10.0)
    maps.vertex = img.create_vertex_map(maps.K, float("nan")).as_tensor()
    maps.normal = smooth.create_vertex_map(maps.K, float("nan")).create_normal_map(float("nan")).as_tensor()


def photo_maps(gray: NDArray[np.uint8], depth: NDArray[np.float32], K: NDArray) -> PhotoMaps:
    """The maps of :class:`PhotoMaps` for one frame: ``gray`` (H, W) uint8, registered to the
    depth camera (:meth:`ColourCamera.to_depth_image`), ``depth`` (H, W) metres."""
    d = np.array(depth, dtype=np.float32)
    d[~((d >= DEPTH_MIN) & (d <= DEPTH_MAX))] = np.nan
    inten = gray.astype(np.float32) * np.float32(1 / 255)
    # undo the auto-exposure gain: a dark frame's contrast counts as a bright one's
    inten *= np.float32(0.5 / max(float(inten[::4, ::4].mean()), 1e-3))
    inten = cv2.GaussianBlur(inten, (0, 0), PHOTO_BLUR_PX)
    inten *= np.float32(np.sqrt(PHOTO_WEIGHT))  # the kernel weighs both residuals alike: scale the grey instead
    s = DENSE_SCALE
    return PhotoMaps(_image_tensor(d[::s, ::s]), _image_tensor(inten[::s, ::s]), *_kernel_maps(d, inten),
                     o3d.core.Tensor(np.asarray(K, dtype=np.float64)))

