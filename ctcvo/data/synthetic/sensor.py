"""Kinect-v1-like sensor model applied to an exact rendering (see :mod:`data.synthetic.config`).

Depth: disparity-domain noise (``sigma_z = c z^2``, partly spatially correlated), disparity
quantisation, projector shadows, holes along discontinuities, at grazing angles, random
dropouts and outside the working range. Colour: exposure gain, vignetting, motion blur,
optical blur, RGB-depth misregistration, read and shot noise, 8-bit quantisation.
All randomness comes from the generator passed in (one per frame), so output is
deterministic for a seed.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from ctcvo.data.synthetic.config import SensorConfig


class NoiseBank:
    """Pre-drawn standard normal and uniform numbers; each frame takes slices at random offsets.

    Drawing ~1.5 M random numbers per frame costs more than the rest of the sensor model;
    slicing a bank twice that size at offsets drawn from the frame's generator keeps frames
    deterministic and, in any one frame, the noise independent across pixels.
    """

    def __init__(self, seed: int, size: int) -> None:
        rng = np.random.default_rng([seed, 99])
        self._normal = rng.standard_normal(2 * size, dtype=np.float32)
        self._uniform = rng.random(2 * size, dtype=np.float32)
        self.size = size

    def _take(self, bank: NDArray[np.float32], shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float32]:
        n = int(np.prod(shape))
        if n > self.size:
            raise ValueError(f"noise bank of {self.size} too small for {shape}")
        off = int(rng.integers(0, len(bank) - n + 1))
        return bank[off: off + n].reshape(shape)

    def normal(self, shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float32]:
        """Standard normal samples of ``shape`` (read-only view)."""
        return self._take(self._normal, shape, rng)

    def uniform(self, shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float32]:
        """Uniform [0, 1) samples of ``shape`` (read-only view)."""
        return self._take(self._uniform, shape, rng)


def projector_shadow(z: NDArray[np.float32], fx: float, baseline_m: float) -> NDArray[np.bool_]:
    """Pixels the IR projector (``baseline_m`` along +x) cannot see, (H, W) bool.

    In projector image coordinates a pixel lands at ``u - fx * b / z``. Along a row this is
    increasing on a surface the projector sees; a pixel is shadowed when some pixel to its
    right lands at a smaller projector coordinate (a nearer surface blocks the light).
    Pixels with ``z == 0`` (misses) never block.
    """
    H, W = z.shape
    with np.errstate(divide="ignore"):
        up = np.arange(W, dtype=np.float32)[None, :] - np.float32(fx * baseline_m) / z
    up[~(z > 0)] = np.inf
    cm = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    shadow = np.zeros((H, W), bool)
    shadow[:, :-1] = up[:, :-1] > cm[:, 1:] + 1e-3
    return shadow


def discontinuity_mask(z: NDArray[np.float32], jump_rel: float, width_px: int) -> NDArray[np.bool_]:
    """Pixels within ``width_px`` of a relative depth jump larger than ``jump_rel``, (H, W) bool."""
    zz = np.where(z > 0, z, np.float32(100.0))
    mx = cv2.dilate(zz, np.ones((3, 3), np.uint8))
    mn = cv2.erode(zz, np.ones((3, 3), np.uint8))
    edge = ((mx - mn) > jump_rel * mn).astype(np.uint8)
    if width_px > 1:
        edge = cv2.dilate(edge, np.ones((2 * width_px - 1, 2 * width_px - 1), np.uint8))
    return edge.astype(bool)


def correlated_noise(rng: np.random.Generator, shape: tuple[int, int], scale_px: int) -> NDArray[np.float32]:
    """Smooth unit-variance Gaussian noise field with correlation length ``scale_px``, (H, W)."""
    H, W = shape
    low = rng.standard_normal((H // scale_px + 2, W // scale_px + 2), dtype=np.float32)
    up = cv2.resize(low, ((W // scale_px + 2) * scale_px, (H // scale_px + 2) * scale_px),
                    interpolation=cv2.INTER_LINEAR)[scale_px // 2: scale_px // 2 + H, scale_px // 2: scale_px // 2 + W]
    return up / max(float(up.std()), 1e-6)


def depth_bias_field(cfg: SensorConfig, shape: tuple[int, int], seed: int) -> NDArray[np.float32] | None:
    """The sensor's fixed inverse-depth bias pattern (H, W) in 1/m, or None when disabled."""
    if cfg.noise_free or cfg.depth_bias_coeff <= 0:
        return None
    rng = np.random.default_rng([seed, 5])
    return np.float32(cfg.depth_bias_coeff) * correlated_noise(rng, shape, cfg.depth_bias_px)


def depth_sensor(z: NDArray[np.float32], cos_incidence: NDArray[np.float32], fx: float,
                 cfg: SensorConfig, rng: np.random.Generator, bank: NoiseBank | None = None,
                 bias: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """Measured depth (H, W) float32 metres (0 = hole) from exact z-depth ``z`` (0 = miss)
    and |cos| of the viewing ray against the surface normal (H, W); ``bias`` (H, W) is the
    fixed inverse-depth bias of :func:`depth_bias_field`."""
    if cfg.noise_free:
        return z.copy()
    valid = z > 0
    if cfg.projector_baseline_m > 0:
        valid &= ~projector_shadow(z, fx, cfg.projector_baseline_m)
    if cfg.edge_hole_px > 0:
        valid &= ~discontinuity_mask(z, cfg.edge_jump_rel, cfg.edge_hole_px)
    bank = bank or NoiseBank(int(rng.integers(1 << 31)), z.size)
    if cfg.grazing_cos > 0:
        valid &= cos_incidence > np.float32(cfg.grazing_cos) * bank.uniform(z.shape, rng)
    if cfg.dropout_prob > 0:
        valid &= bank.uniform(z.shape, rng) >= np.float32(cfg.dropout_prob)
    if cfg.hole_blob_fraction > 0:
        from scipy.special import ndtri

        field = correlated_noise(rng, z.shape, cfg.hole_blob_px)
        valid &= field < np.float32(ndtri(1.0 - cfg.hole_blob_fraction))
    if cfg.invalid_right_cols > 0:
        valid[:, -cfg.invalid_right_cols:] = False
    with np.errstate(divide="ignore"):
        inv = np.where(valid, 1.0 / np.maximum(z, 1e-6), 0).astype(np.float32)
    if bias is not None:
        inv = inv + bias
    if cfg.depth_noise_coeff > 0:
        a = np.float32(np.sqrt(cfg.depth_noise_correlated))
        b = np.float32(np.sqrt(1.0 - cfg.depth_noise_correlated))
        n = b * bank.normal(z.shape, rng)
        if a > 0:
            n += a * correlated_noise(rng, z.shape, cfg.depth_noise_corr_px)
        inv = inv + np.float32(cfg.depth_noise_coeff) * n
    if cfg.disparity_step > 0:
        step = np.float32(cfg.disparity_step)
        inv = np.rint(inv / step) * step
    with np.errstate(divide="ignore"):
        out = np.where(valid & (inv > 0), 1.0 / inv, 0).astype(np.float32)
    out[(out < cfg.depth_min_m) | (out > cfg.depth_max_m)] = 0.0
    return out


def exposure_gains(cfg: SensorConfig, times: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float32]:
    """Slowly varying exposure gain per frame (N,), log-normal around 1."""
    if cfg.noise_free or cfg.exposure_log_sigma <= 0:
        return np.ones(len(times), np.float32)
    f0 = 1.0 / cfg.exposure_period_s
    out = np.zeros(len(times))
    for _ in range(3):
        out += np.sin(2 * np.pi * rng.uniform(0.5 * f0, 2 * f0) * times + rng.uniform(0, 2 * np.pi))
    return np.exp(cfg.exposure_log_sigma * out * np.sqrt(2 / 3)).astype(np.float32)


def motion_kernel(flow: NDArray[np.float64], exposure: float) -> NDArray[np.float32] | None:
    """Linear blur kernel for image motion ``flow`` (2,) pixels per frame; None if < 0.5 px."""
    vec = np.asarray(flow, np.float64) * exposure
    length = float(np.linalg.norm(vec))
    if length < 0.5:
        return None
    half = int(np.ceil(length / 2)) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    for s in np.linspace(-0.5, 0.5, max(3, int(4 * length))):
        x, y = half + s * vec[0], half + s * vec[1]
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx_, fy_ = x - x0, y - y0
        k[y0, x0] += (1 - fx_) * (1 - fy_)
        k[y0, x0 + 1] += fx_ * (1 - fy_)
        k[y0 + 1, x0] += (1 - fx_) * fy_
        k[y0 + 1, x0 + 1] += fx_ * fy_
    return k / k.sum()


def shifted_gaussian(sigma: float, shift: float) -> NDArray[np.float32]:
    """1-D correlation kernel that blurs by ``sigma`` and moves content by ``+shift`` pixels."""
    half = int(np.ceil(abs(shift) + 3 * max(sigma, 0.3))) + 1
    x = np.arange(-half, half + 1, dtype=np.float64)
    if sigma > 0:
        k = np.exp(-0.5 * ((x + shift) / sigma) ** 2)
    else:  # pure sub-pixel shift: linear interpolation
        k = np.maximum(1 - np.abs(x + shift), 0)
    return (k / k.sum()).astype(np.float32)


def colour_camera_pad(cfg: SensorConfig, width: int, height: int, fx: float) -> tuple[int, int]:
    """Extra columns and rows (px, py) the depth camera's rendering needs on each side so the
    colour camera (wider field of view, shifted, parallax down to 0.4 m) can be resampled
    from it; (0, 0) for the noise-free (registered) mode."""
    if cfg.noise_free:
        return 0, 0
    s = cfg.rgb_focal_scale
    parallax = fx * abs(cfg.rgb_baseline_m) / 0.4
    px = (width / 2) * max(1 / s - 1, 0) + abs(cfg.rgb_shift_px[0]) / s + parallax + 2
    py = (height / 2) * max(1 / s - 1, 0) + abs(cfg.rgb_shift_px[1]) / s + 2
    return int(np.ceil(px)), int(np.ceil(py))


class ColourSensor:
    """Turns a linear rendering (He, We, 3) float32 of the depth camera, padded by
    :func:`colour_camera_pad`, into the colour camera's 8-bit RGB image (H, W, 3)."""

    def __init__(self, cfg: SensorConfig, width: int, height: int, cx: float, cy: float, fx: float = 585.0) -> None:
        self.cfg = cfg
        self.pad = colour_camera_pad(cfg, width, height, fx)
        self.fx = fx
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (cx ** 2 + cy ** 2)
        self.vignette = (1.0 - cfg.vignetting * r2)[..., None].astype(np.float32)
        self.k = shifted_gaussian(cfg.rgb_blur_sigma, 0.0)
        self.bank = NoiseBank(0, width * height * 3)
        # colour pixel (u, v) sees the depth camera's (padded) pixel (mx + parallax, my)
        s = cfg.rgb_focal_scale
        self._mx = (cx + (xx - cx - cfg.rgb_shift_px[0]) / s + self.pad[0]).astype(np.float32)
        self._my = (cy + (yy - cy - cfg.rgb_shift_px[1]) / s + self.pad[1]).astype(np.float32)

    def __call__(self, img: NDArray[np.float32], gain: float, flow: NDArray[np.float64],
                 rng: np.random.Generator, depth: NDArray[np.float32] | None = None) -> NDArray[np.uint8]:
        """8-bit RGB (H, W, 3) from the padded linear rendering ``img`` (He, We, 3); ``depth``
        (He, We) exact z drives the parallax; ``flow`` (2,) is the image motion per frame in
        depth-camera pixels (motion blur)."""
        return self.encoded(img, gain, flow, rng, depth)[0]

    def encoded(self, img: NDArray[np.float32], gain: float, flow: NDArray[np.float64],
                rng: np.random.Generator, depth: NDArray[np.float32] | None = None
                ) -> tuple[NDArray[np.uint8], bytes | None]:
        """As :meth:`__call__`, with the JPEG file whose decoding the image is (None when
        ``jpeg_quality`` is 0 or the sensor is noise-free)."""
        cfg = self.cfg
        if cfg.noise_free:
            return np.clip(np.rint(img * 255), 0, 255).astype(np.uint8), None
        mx = self._mx
        if cfg.rgb_baseline_m and depth is not None:
            He, We = depth.shape
            zi = np.clip(np.rint(self._my).astype(np.int32), 0, He - 1)
            zj = np.clip(np.rint(mx).astype(np.int32), 0, We - 1)
            z = depth[zi, zj]
            mx = mx + np.where(z > 0, np.float32(self.fx * cfg.rgb_baseline_m) / np.maximum(z, np.float32(0.4)), 0)
        img = cv2.remap(img, mx, self._my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img = img * (np.float32(gain) * self.vignette)
        if cfg.motion_blur_exposure > 0:
            k = motion_kernel(np.asarray(flow) * cfg.rgb_focal_scale, cfg.motion_blur_exposure)
            if k is not None:
                img = cv2.filter2D(img, -1, k, borderType=cv2.BORDER_REFLECT)
        img = cv2.sepFilter2D(img, -1, self.k, self.k, borderType=cv2.BORDER_REFLECT)
        dn = np.clip(img, 0, 1) * np.float32(255)
        sd = np.sqrt(np.float32(cfg.read_noise_dn ** 2) + np.float32(cfg.shot_noise_gain) * dn)
        dn += sd * self.bank.normal(dn.shape, rng)
        out = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
        if cfg.jpeg_quality <= 0:
            return out, None
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
        if not ok:
            raise RuntimeError("JPEG encoding of a synthetic colour image failed")
        return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB), buf.tobytes()
