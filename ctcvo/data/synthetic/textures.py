"""Procedural, tileable textures (numpy + OpenCV drawing), deterministic for a generator.

Every generator returns an (S, S, 3) float32 albedo in [0, 1] that tiles seamlessly
(except ``poster``, meant to be mapped once). Kinds:

* rich: ``noise`` (carpet, granite, concrete), ``wood``, ``tiles``, ``bricks``,
  ``clutter`` (shapes and text, like posters or a notice board), ``books``, ``panel``;
* plain (few ORB corners): ``plain`` - a flat colour with faint large-scale shading;
* hard for feature matching (the stress scenes): ``blobs`` (smooth low-frequency shapes),
  ``repeat`` (one small motif tiled).

:class:`TextureAtlas` stacks the mip pyramids of all materials into one flat array and
samples it bilinearly by (material, level, u, v) with numpy gathers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

TEX_SIZE = 512


def periodic_noise(rng: np.random.Generator, size: int, cells: int) -> NDArray[np.float32]:
    """Tileable smooth value noise in [0, 1], (size, size), ``cells`` features per side."""
    grid = rng.random((cells, cells)).astype(np.float32)
    pad = 2
    big = np.pad(grid, pad, mode="wrap")
    step = size // cells
    up = cv2.resize(big, ((cells + 2 * pad) * step,) * 2, interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(up[pad * step: pad * step + size, pad * step: pad * step + size])


def fbm(rng: np.random.Generator, size: int, base: int = 4, octaves: int = 6, gain: float = 0.55) -> NDArray[np.float32]:
    """Fractal sum of :func:`periodic_noise`, normalised to [0, 1]."""
    out = np.zeros((size, size), np.float32)
    amp, cells = 1.0, base
    for _ in range(octaves):
        if cells > size // 2:
            break
        out += amp * periodic_noise(rng, size, cells)
        amp *= gain
        cells *= 2
    out -= out.min()
    return out / max(float(out.max()), 1e-6)


def _mix(a: NDArray, c0: NDArray, c1: NDArray) -> NDArray[np.float32]:
    return (c0[None, None, :] * (1 - a[..., None]) + c1[None, None, :] * a[..., None]).astype(np.float32)


def _rand_color(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9) -> NDArray[np.float32]:
    return rng.uniform(lo, hi, 3).astype(np.float32)


def tex_plain(rng: np.random.Generator, color: NDArray, size: int = TEX_SIZE) -> NDArray[np.float32]:
    shade = 1.0 + 0.04 * (fbm(rng, size, base=2, octaves=2) - 0.5)
    return np.clip(color[None, None, :] * shade[..., None], 0, 1).astype(np.float32)


def tex_noise(rng: np.random.Generator, c0: NDArray, c1: NDArray, size: int = TEX_SIZE) -> NDArray[np.float32]:
    a = fbm(rng, size, base=8, octaves=7, gain=0.7)
    speck = (rng.random((size, size)) < 0.02).astype(np.float32)
    speck = cv2.GaussianBlur(speck, (0, 0), 1.0) * 3
    return np.clip(_mix(np.clip(a + 0.3 * speck, 0, 1), c0, c1), 0, 1)


def tex_wood(rng: np.random.Generator, c0: NDArray, c1: NDArray, size: int = TEX_SIZE) -> NDArray[np.float32]:
    y = np.arange(size, dtype=np.float32)[:, None] / size
    warp = fbm(rng, size, base=4, octaves=4)
    rings = int(rng.integers(10, 20))
    a = 0.5 + 0.5 * np.sin(2 * np.pi * (rings * y + 2.5 * warp))
    a = 0.7 * a + 0.3 * fbm(rng, size, base=32, octaves=3)
    return _mix(a, c0, c1)


def tex_tiles(rng: np.random.Generator, c0: NDArray, grout: NDArray, n: int, size: int = TEX_SIZE) -> NDArray[np.float32]:
    step = size // n
    img = np.empty((size, size, 3), np.float32)
    for i in range(n):
        for j in range(n):
            jit = rng.uniform(0.85, 1.15, 3).astype(np.float32)
            img[i * step:(i + 1) * step, j * step:(j + 1) * step] = np.clip(c0 * jit, 0, 1)
    img *= (0.9 + 0.2 * fbm(rng, size, base=16, octaves=4))[..., None]
    lines = np.zeros((size, size), np.float32)
    w = max(2, step // 16)
    for k in range(n):
        lines[k * step: k * step + w, :] = 1
        lines[:, k * step: k * step + w] = 1
    return np.where(lines[..., None] > 0, grout[None, None, :], img).astype(np.float32)


def tex_bricks(rng: np.random.Generator, c0: NDArray, mortar: NDArray, size: int = TEX_SIZE) -> NDArray[np.float32]:
    rows, cols = 16, 4
    bh, bw = size // rows, size // cols
    img = np.empty((size, size, 3), np.float32)
    for r in range(rows):
        off = (bw // 2) * (r % 2)
        for c in range(cols + 1):
            x0 = c * bw - off
            col = np.clip(c0 * rng.uniform(0.75, 1.25, 3), 0, 1)
            xs = np.arange(x0, x0 + bw) % size
            img[r * bh:(r + 1) * bh][:, xs] = col
    img *= (0.8 + 0.4 * fbm(rng, size, base=32, octaves=4))[..., None]
    img[np.arange(size) % bh < 3] = mortar
    for r in range(rows):
        off = (bw // 2) * (r % 2)
        for c in range(cols + 1):
            x = (c * bw - off) % size
            img[r * bh:(r + 1) * bh, x: x + 3] = mortar
    return np.clip(img, 0, 1).astype(np.float32)


_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"


def _text(rng: np.random.Generator, n: int) -> str:
    return "".join(_LETTERS[i] for i in rng.integers(0, len(_LETTERS), n))


def tex_clutter(rng: np.random.Generator, bg: NDArray, size: int = TEX_SIZE, n_shapes: int = 60) -> NDArray[np.float32]:
    """Rectangles, circles, lines and text on a background (posters, notice boards)."""
    img = np.ascontiguousarray(np.tile(bg, (size, size, 1)) * 255).astype(np.uint8)
    for _ in range(n_shapes):
        col = tuple(int(v) for v in rng.integers(0, 256, 3))
        kind = rng.integers(0, 4)
        x, y = (int(v) for v in rng.integers(0, size, 2))
        if kind == 0:
            w, h = (int(v) for v in rng.integers(10, size // 4, 2))
            cv2.rectangle(img, (x, y), (x + w, y + h), col, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), int(rng.integers(5, size // 10)), col, -1, cv2.LINE_AA)
        elif kind == 2:
            x2, y2 = (int(v) for v in rng.integers(0, size, 2))
            cv2.line(img, (x, y), (x2, y2), col, int(rng.integers(1, 6)), cv2.LINE_AA)
        else:
            cv2.putText(img, _text(rng, int(rng.integers(3, 9))), (x, y), cv2.FONT_HERSHEY_SIMPLEX,
                        float(rng.uniform(0.5, 1.6)), col, int(rng.integers(1, 4)), cv2.LINE_AA)
    return img.astype(np.float32) / 255.0


def tex_books(rng: np.random.Generator, size: int = TEX_SIZE) -> NDArray[np.float32]:
    """Book spines: vertical strips of varied width and colour with titles."""
    img = np.zeros((size, size, 3), np.uint8)
    x = 0
    while x < size:
        w = int(rng.integers(12, 40))
        col = rng.integers(20, 235, 3)
        img[:, x: min(x + w, size)] = col
        top = int(rng.integers(0, size // 5))
        img[:top, x: min(x + w, size)] = 15
        for yy in range(int(rng.integers(size // 4, size // 2)), size - 20, int(rng.integers(60, 140))):
            tc = tuple(int(255 - v) for v in col)
            cv2.putText(img, _text(rng, 2), (x + 2, yy), cv2.FONT_HERSHEY_PLAIN, max(0.6, w / 30), tc, 1, cv2.LINE_AA)
        x += w + int(rng.integers(0, 3))
    return img.astype(np.float32) / 255.0


def tex_panel(rng: np.random.Generator, bg: NDArray, size: int = TEX_SIZE) -> NDArray[np.float32]:
    """Equipment front panel: knobs, displays, labels."""
    img = np.ascontiguousarray(np.tile(bg, (size, size, 1)) * 255).astype(np.uint8)
    for _ in range(25):
        x, y = (int(v) for v in rng.integers(20, size - 20, 2))
        k = rng.integers(0, 3)
        if k == 0:
            cv2.circle(img, (x, y), int(rng.integers(6, 20)), (30, 30, 30), -1, cv2.LINE_AA)
            cv2.circle(img, (x, y), 3, (200, 200, 200), -1)
        elif k == 1:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(30, 90)), y + int(rng.integers(15, 40))),
                          tuple(int(v) for v in rng.integers(0, 120, 3)), -1)
        else:
            cv2.putText(img, _text(rng, 4), (x, y), cv2.FONT_HERSHEY_PLAIN, 1.0, (10, 10, 10), 1, cv2.LINE_AA)
    return img.astype(np.float32) / 255.0


def tex_blobs(rng: np.random.Generator, c0: NDArray, c1: NDArray, size: int = TEX_SIZE) -> NDArray[np.float32]:
    """Smooth low-frequency blobs (2-3 per tile side, soft edges) between two colours: shapes
    a few decimetres across and no fine detail, so ORB finds few, poorly localised corners."""
    a = 0.75 * periodic_noise(rng, size, 3) + 0.25 * periodic_noise(rng, size, 6)
    a = (a - a.min()) / max(float(a.max() - a.min()), 1e-6)
    a = a * a * (3 - 2 * a)  # smoothstep: broad areas of each colour
    return _mix(a.astype(np.float32), c0, c1)


def tex_repeat(rng: np.random.Generator, c0: NDArray, c1: NDArray, size: int = TEX_SIZE,
               period: int = 8) -> NDArray[np.float32]:
    """One small motif (a few shapes in a ``size / period`` cell) repeated ``period`` times
    per side, as on wallpaper or tiles: every corner has many identical twins, so a
    descriptor's best and second-best matches are equally good."""
    cell = size // period
    img = np.ascontiguousarray(np.tile(c0, (cell, cell, 1)) * 255).astype(np.uint8)
    col = tuple(int(v) for v in np.asarray(c1) * 255)
    for _ in range(3):
        x, y = (int(v) for v in rng.integers(cell // 6, cell - cell // 6, 2))
        if rng.random() < 0.5:
            w, h = (int(v) for v in rng.integers(cell // 8, cell // 3, 2))
            cv2.rectangle(img, (x - w // 2, y - h // 2), (x + w // 2, y + h // 2), col, -1, cv2.LINE_AA)
        else:
            cv2.circle(img, (x, y), int(rng.integers(cell // 10, cell // 5)), col, -1, cv2.LINE_AA)
    return np.tile(img.astype(np.float32) / 255.0, (period, period, 1))


def _blur_wrap(img: NDArray[np.float32], sigma: float) -> NDArray[np.float32]:
    """Gaussian blur of a tileable image (S, S[, C]) with wrap-around borders."""
    p = int(np.ceil(4 * sigma)) + 1
    pad = ((p, p), (p, p)) + ((0, 0),) * (img.ndim - 2)
    out = cv2.GaussianBlur(np.pad(img, pad, mode="wrap"), (0, 0), sigma)
    return np.ascontiguousarray(out[p:-p, p:-p])


def photo_like(rng: np.random.Generator, tex: NDArray[np.float32], soften_px: float = 1.2,
               grime: float = 0.12, grain: float = 0.04) -> NDArray[np.float32]:
    """A procedural texture (S, S, 3) made to look photographed: drawn edges softened by a
    Gaussian of ``soften_px`` texels, multiplicative multi-scale shading/grime of relative
    amplitude ``grime`` (fractal noise over 4 octaves, slightly coloured), and fine grain of
    relative amplitude ``grain``. Real surfaces are never flat colour and real prints have
    no pixel-sharp edges; keypoints on them are less precise than on clean drawings.
    Keeps the texture tileable."""
    S = tex.shape[0]
    out = _blur_wrap(tex, soften_px) if soften_px > 0 else tex.copy()
    shade = np.stack([fbm(rng, S, base=4, octaves=4, gain=0.6) for _ in range(2)], -1)
    lum = 1.0 + grime * 2 * (shade[..., 0] - 0.5)
    tint = 1.0 + 0.3 * grime * (shade[..., 1:2] - 0.5) * np.array([1.0, 0.0, -1.0], np.float32)
    fine = _blur_wrap(rng.standard_normal((S, S)).astype(np.float32), 0.7)
    fine /= max(float(fine.std()), 1e-6)
    out = out * (lum[..., None] * tint) * (1.0 + grain * fine[..., None])
    return np.clip(out, 0, 1).astype(np.float32)


@dataclass(frozen=True)
class Material:
    """A texture and its physical size: one texture tile covers ``scale_m`` metres."""

    name: str
    texture: NDArray[np.float32]  # (S, S, 3) albedo in [0, 1]
    scale_m: float


class TextureAtlas:
    """All materials' mip pyramids packed into one padded uint8 image, sampled with ``cv2.remap``.

    Material ``m`` occupies a column of width ``S + 2``; its mip level ``l`` (size ``S >> l``)
    sits at row offset ``sum_{j<l} (S >> j) + 2``, with a one-texel border copied from the
    opposite edge so bilinear lookups wrap around (textures tile).
    """

    def __init__(self, materials: list[Material]) -> None:
        sizes = {m.texture.shape[0] for m in materials}
        if len(sizes) != 1:
            raise ValueError("all textures must have the same size")
        S = self.size = sizes.pop()
        self.levels = int(np.log2(S)) - 2  # down to 8x8
        self.level_size = np.array([S >> lv for lv in range(self.levels)], np.float32)
        self.yoff = np.concatenate([[0], np.cumsum(self.level_size + 2)[:-1]]).astype(np.float32)
        self.xoff = (np.arange(len(materials)) * (S + 2)).astype(np.float32)
        self.image = np.zeros((int(self.yoff[-1] + self.level_size[-1] + 2), len(materials) * (S + 2), 3), np.uint8)
        for mi, m in enumerate(materials):
            img = m.texture.astype(np.float32)
            for lv in range(self.levels):
                pad = np.pad(np.clip(np.rint(img * 255), 0, 255).astype(np.uint8), ((1, 1), (1, 1), (0, 0)), mode="wrap")
                y0, x0 = int(self.yoff[lv]), int(self.xoff[mi])
                self.image[y0: y0 + pad.shape[0], x0: x0 + pad.shape[1]] = pad
                img = cv2.pyrDown(img, borderType=cv2.BORDER_WRAP)
        self.scale_m = np.array([m.scale_m for m in materials], np.float32)
        self.names = [m.name for m in materials]

    def sample(self, mat: NDArray[np.int64], u: NDArray[np.float32], v: NDArray[np.float32],
               footprint_texels: NDArray[np.float32]) -> NDArray[np.uint8]:
        """Albedo (H, W, 3) uint8 at texture coordinates ``u, v`` (H, W) in tiles of material
        ``mat`` (H, W); ``footprint_texels`` (H, W), the size of a pixel in level-0 texels,
        picks the mip level."""
        level = np.rint(np.log2(np.maximum(footprint_texels, np.float32(1.0)))).astype(np.int32)
        np.clip(level, 0, self.levels - 1, out=level)
        sz = self.level_size[level]
        mx = self.xoff[mat] + np.float32(1.0) + np.mod(u * sz - np.float32(0.5), sz)
        my = self.yoff[level] + np.float32(1.0) + np.mod(v * sz - np.float32(0.5), sz)
        return cv2.remap(self.image, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
