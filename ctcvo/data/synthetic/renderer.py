"""Ray-cast rendering of a :class:`~data.synthetic.layout.Scene` with Open3D (CPU, headless).

All triangles live in one ``open3d.t.geometry.RaycastingScene``. Camera rays are cast with
direction ``R @ K^-1 [u, v, 1]`` (unnormalised, z = 1 in the camera), so the returned
``t_hit`` *is* the z-depth. Colour: per-triangle material and surface coordinates
interpolated with the hit's barycentric coordinates, a bilinear, mip-mapped texture lookup,
Lambert shading from point lights plus ambient light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ctcvo.data.open3d_import import o3d
from ctcvo.data.synthetic.layout import Scene
from ctcvo.data.synthetic.textures import TextureAtlas


@dataclass(frozen=True)
class ExactFrame:
    """Noise-free rendering of one view.

    ``colour`` (H, W, 3) float32 linear in [0, ~1]; ``depth`` (H, W) float32 z-depth in metres
    (0 where no surface was hit); ``cos_incidence`` (H, W) float32 |cos| between viewing ray
    and surface normal; ``triangle`` (H, W) int64 hit triangle (-1 for none).
    """

    colour: NDArray[np.float32]
    depth: NDArray[np.float32]
    cos_incidence: NDArray[np.float32]
    triangle: NDArray[np.int64]

    def crop(self, px: int, py: int) -> ExactFrame:
        """The frame without ``px`` columns left and right and ``py`` rows above and below."""
        if px == 0 and py == 0:
            return self
        sl = (slice(py, self.depth.shape[0] - py), slice(px, self.depth.shape[1] - px))
        return ExactFrame(self.colour[sl], self.depth[sl], self.cos_incidence[sl], self.triangle[sl])


class Renderer:
    """Renders ``scene`` through a pinhole camera (fx, fy, cx, cy, width x height)."""

    def __init__(self, scene: Scene, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                 nthreads: int = 0, distortion_k1: float = 0.0, pad: tuple[int, int] = (0, 0)) -> None:
        """``pad`` (px, py): render ``px`` extra columns left and right and ``py`` extra rows
        above and below the image (same camera, extended grid), so a second camera with a
        wider field of view can be resampled from the rendering; outputs are then
        (H + 2 py, W + 2 px)."""
        self.scene = scene
        self.pad = (int(pad[0]), int(pad[1]))
        width, height = width + 2 * self.pad[0], height + 2 * self.pad[1]
        cx, cy = cx + self.pad[0], cy + self.pad[1]
        self.width, self.height, self.fx = width, height, fx
        self.nthreads = nthreads
        tris = scene.triangles.reshape(-1, 3)
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(o3d.core.Tensor(tris.astype(np.float32)),
                               o3d.core.Tensor(np.arange(len(tris), dtype=np.uint32).reshape(-1, 3)))
        self.atlas = TextureAtlas(scene.materials)
        # per triangle: surface coordinates of vertex 0 and the edge deltas, in texture tiles
        inv_scale = (1.0 / self.atlas.scale_m[scene.tri_mat])[:, None]
        uv = scene.tri_uv.astype(np.float64)
        self._tri_tex = np.concatenate([uv[:, 0], uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], 1) * inv_scale
        self._tri_tex = self._tri_tex.astype(np.float32)  # (T, 6): u0 v0 du1 dv1 du2 dv2
        self._tri_texel = (self.atlas.scale_m[scene.tri_mat] / self.atlas.size).astype(np.float32)
        self._tri_mat = scene.tri_mat.astype(np.int32)
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        xd, yd = (u - cx) / fx, (v - cy) / fy
        f = 1.0 / (1.0 + distortion_k1 * (xd ** 2 + yd ** 2))  # division model, 1 when k1 = 0
        self._xc = (xd * f).astype(np.float32)  # (H, W) camera ray x at z = 1
        self._yc = (yd * f).astype(np.float32)
        self._inv_norm = (1.0 / np.sqrt(1.0 + self._xc ** 2 + self._yc ** 2)).astype(np.float32)
        self._lights = scene.lights.astype(np.float32)

    def render(self, T_world_cam: NDArray[np.float64]) -> ExactFrame:
        """Exact rendering of the view ``T_world_cam``: (4, 4), or (H, 4, 4) one pose per
        image row (rolling shutter; H counts the padded rows)."""
        H, W = self.height, self.width
        T = np.asarray(T_world_cam, np.float32)
        if T.ndim == 3:  # per-row poses: coefficients broadcast as (H, 1)
            R = T[:, :3, :3, None]
            o = [T[:, i, 3, None] for i in range(3)]
            Rij = lambda i, j: R[:, i, j]  # noqa: E731
        else:
            o = [T[i, 3] for i in range(3)]
            Rij = lambda i, j: T[i, j]  # noqa: E731
        xc, yc = self._xc, self._yc
        d = [Rij(i, 0) * xc + Rij(i, 1) * yc + Rij(i, 2) for i in range(3)]  # world ray directions, (H, W) each
        rays = np.empty((H, W, 6), np.float32)
        rays[..., 0], rays[..., 1], rays[..., 2] = o
        rays[..., 3], rays[..., 4], rays[..., 5] = d
        ans = self._rc.cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)), nthreads=self.nthreads)
        t = ans["t_hit"].numpy().reshape(H, W)
        hit = np.isfinite(t)
        prim = ans["primitive_ids"].numpy().reshape(H, W).astype(np.int64)
        prim[~hit] = 0
        t = np.where(hit, t, np.float32(0.0))
        bary = ans["primitive_uvs"].numpy().reshape(H, W, 2)
        n = ans["primitive_normals"].numpy().reshape(H, W, 3)
        a, b = bary[..., 0], bary[..., 1]
        g = self._tri_tex[prim]  # (H, W, 6)
        u = g[..., 0] + a * g[..., 2] + b * g[..., 4]
        v = g[..., 1] + a * g[..., 3] + b * g[..., 5]
        nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
        nd = nx * d[0] + ny * d[1] + nz * d[2]
        sgn = np.where(nd > 0, np.float32(-1.0), np.float32(1.0))
        nx, ny, nz = nx * sgn, ny * sgn, nz * sgn
        cos = np.abs(nd) * self._inv_norm
        # pixel footprint on the surface: z * cos(off-axis angle) / fx, stretched by 1/cos(incidence)
        footprint = t * self._inv_norm / (np.float32(self.fx) * np.maximum(cos, np.float32(0.3)))
        albedo = self.atlas.sample(self._tri_mat[prim], u, v, footprint / self._tri_texel[prim])
        X = [o[i] + t * d[i] for i in range(3)]
        shade = np.full((H, W), self.scene.ambient, np.float32)
        for lx, ly, lz, power in self._lights:
            vx, vy, vz = lx - X[0], ly - X[1], lz - X[2]
            d2 = vx * vx + vy * vy + vz * vz
            lam = np.maximum(nx * vx + ny * vy + nz * vz, np.float32(0.0)) / np.sqrt(d2)
            shade += lam * (power / (np.float32(0.5) + d2))
        shade[~hit] = 0.0
        colour = albedo.astype(np.float32) * (shade * np.float32(1 / 255.0))[..., None]
        prim[~hit] = -1
        cos[~hit] = 0.0
        return ExactFrame(colour, t, cos, prim)
