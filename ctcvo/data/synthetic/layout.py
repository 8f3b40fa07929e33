"""Procedural indoor rooms: walls, furniture-like boxes and small objects, materials, lights.

World frame: z up, the room spans ``[0, W] x [0, D] x [0, H]`` metres. A :class:`Scene`
holds one flat triangle soup (every triangle with its material and per-vertex surface
coordinates in metres), the materials, point lights, the solid boxes the camera must not
enter, points worth looking at, and the rectangle the camera may move in.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

import ctcvo.data.synthetic.textures as tx
from ctcvo.data.synthetic.textures import Material


@dataclass(frozen=True)
class Obstacle:
    """A solid box: centre (3,), half sizes (3,), yaw about z (rad)."""

    center: NDArray[np.float64]
    half: NDArray[np.float64]
    yaw: float

    def distance(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance from points (N, 3) to the box (0 inside)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        d = np.atleast_2d(p) - self.center
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
        q = np.maximum(np.abs(local) - self.half, 0.0)
        return np.linalg.norm(q, axis=1)


@dataclass
class Scene:
    """Geometry and appearance of a room (see module docstring)."""

    size: NDArray[np.float64]  # (3,) W, D, H
    triangles: NDArray[np.float32]  # (T, 3, 3) vertices, world metres
    tri_uv: NDArray[np.float32]  # (T, 3, 2) surface coordinates of the vertices, metres
    tri_mat: NDArray[np.int64]  # (T,) material index
    materials: list[Material]
    lights: NDArray[np.float64]  # (L, 4) position xyz + intensity
    obstacles: list[Obstacle]
    interest: NDArray[np.float64]  # (P, 3) points worth looking at
    free_box: NDArray[np.float64]  # (2, 3) min/max corner of where the camera may be
    ambient: float = 0.35


class SceneBuilder:
    """Accumulates textured quads, boxes and cylinders into a :class:`Scene`."""

    def __init__(self, rng: np.random.Generator, size: tuple[float, float, float], photo_like: bool = False) -> None:
        """``photo_like``: pass every texture through :func:`~data.synthetic.textures.photo_like`
        (softened edges, grime, grain), as the built-in layouts do."""
        self.rng = rng
        self.photo_like = photo_like
        self.size = np.asarray(size, np.float64)
        self._tris: list[NDArray] = []
        self._uvs: list[NDArray] = []
        self._mats: list[NDArray] = []
        self.materials: list[Material] = []
        self._mat_index: dict[str, int] = {}
        self.obstacles: list[Obstacle] = []
        self.interest: list[NDArray] = []
        self.lights: list[tuple[float, float, float, float]] = []

    # -- materials
    def material(self, name: str, make: Callable[[np.random.Generator], NDArray], scale_m: float) -> int:
        """Index of material ``name``; created with ``make(rng)`` on first use."""
        if name not in self._mat_index:
            self._mat_index[name] = len(self.materials)
            tex = make(self.rng)
            if self.photo_like:
                tex = tx.photo_like(self.rng, tex)
            self.materials.append(Material(name, tex, scale_m))
        return self._mat_index[name]

    # -- primitives
    def quad(self, p0: NDArray, e1: NDArray, e2: NDArray, mat: int, uv0: NDArray | None = None) -> None:
        """Parallelogram ``p0, p0+e1, p0+e1+e2, p0+e2`` with surface coordinates in metres."""
        p0, e1, e2 = (np.asarray(a, np.float64) for a in (p0, e1, e2))
        l1, l2 = np.linalg.norm(e1), np.linalg.norm(e2)
        uv0 = self.rng.uniform(0, 10, 2) if uv0 is None else np.asarray(uv0)
        pts = [p0, p0 + e1, p0 + e1 + e2, p0 + e2]
        uvs = [uv0, uv0 + [l1, 0], uv0 + [l1, l2], uv0 + [0, l2]]
        self._tris.append(np.array([[pts[0], pts[1], pts[2]], [pts[0], pts[2], pts[3]]]))
        self._uvs.append(np.array([[uvs[0], uvs[1], uvs[2]], [uvs[0], uvs[2], uvs[3]]]))
        self._mats.append(np.array([mat, mat]))

    def box(self, center: NDArray, size: NDArray, yaw: float, mat: int, front: int | None = None,
            top: int | None = None, solid: bool = True, interesting: bool = True) -> None:
        """Box of ``size`` (w, d, h) at ``center``, rotated by ``yaw``; ``front`` is the +y face
        (local), ``top`` the +z face. Solid boxes are obstacles for the camera."""
        c = np.asarray(center, np.float64)
        h = np.asarray(size, np.float64) / 2
        cy, sy = np.cos(yaw), np.sin(yaw)
        R = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
        ax = [R[:, 0] * h[0], R[:, 1] * h[1], R[:, 2] * h[2]]
        fronts = {1: front, 2: top}
        for k in range(3):
            i, j = [a for a in range(3) if a != k]
            for sgn in (1, -1):
                m = fronts.get(k) if sgn == 1 else None
                m = mat if m is None else m
                p0 = c + sgn * ax[k] - ax[i] - ax[j]
                self.quad(p0, 2 * ax[i], 2 * ax[j], m)
        if solid:
            self.obstacles.append(Obstacle(c, h, yaw))
        if interesting:
            self.interest.append(c + ax[1] * 1.0)  # front face centre
            self.interest.append(c + ax[2] * 1.0)  # top centre

    def cylinder(self, center_bottom: NDArray, radius: float, height: float, mat: int, top: int | None = None,
                 segments: int = 20) -> None:
        """Vertical cylinder (side wrapped with ``mat``, caps with ``top`` or ``mat``)."""
        c = np.asarray(center_bottom, np.float64)
        ang = np.linspace(0, 2 * np.pi, segments + 1)
        ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1) * radius
        u0 = self.rng.uniform(0, 10)
        tris, uvs = [], []
        for k in range(segments):
            a, b = c + ring[k], c + ring[k + 1]
            up = np.array([0, 0, height])
            ua, ub = u0 + ang[k] * radius, u0 + ang[k + 1] * radius
            tris += [[a, b, b + up], [a, b + up, a + up]]
            uvs += [[[ua, 0], [ub, 0], [ub, height]], [[ua, 0], [ub, height], [ua, height]]]
        self._tris.append(np.array(tris))
        self._uvs.append(np.array(uvs))
        self._mats.append(np.full(len(tris), mat))
        capm = mat if top is None else top
        top_c = c + [0, 0, height]
        tris = [[top_c, top_c + ring[k], top_c + ring[k + 1]] for k in range(segments)]
        uvs = [[[0, 0], ring[k][:2], ring[k + 1][:2]] for k in range(segments)]
        self._tris.append(np.array(tris))
        self._uvs.append(np.array(uvs) + 5.0)
        self._mats.append(np.full(segments, capm))
        self.obstacles.append(Obstacle(c + [0, 0, height / 2], np.array([radius, radius, height / 2]), 0.0))
        self.interest.append(c + [0, 0, height * 0.6])

    # -- composite pieces
    def room(self, walls: list[int], floor: int, ceiling: int) -> None:
        """Floor, ceiling and four walls (materials of walls y=0, x=W, y=D, x=0)."""
        W, D, H = self.size
        self.quad([0, 0, 0], [W, 0, 0], [0, D, 0], floor)
        self.quad([0, 0, H], [W, 0, 0], [0, D, 0], ceiling)
        self.quad([0, 0, 0], [W, 0, 0], [0, 0, H], walls[0])
        self.quad([W, 0, 0], [0, D, 0], [0, 0, H], walls[1])
        self.quad([W, D, 0], [-W, 0, 0], [0, 0, H], walls[2])
        self.quad([0, D, 0], [0, -D, 0], [0, 0, H], walls[3])
        for _ in range(6):  # a few bare-wall views (some of them starve ORB on plain walls)
            wall = int(self.rng.integers(0, 4))
            s = self.rng.uniform(0.1, 0.9)
            z = self.rng.uniform(0.6, 2.0)
            self.interest.append(self.wall_point(wall, s, 0.0, z))

    def wall_point(self, wall: int, s: float, off: float, z: float) -> NDArray:
        """Point at fraction ``s`` along wall ``wall`` (0: y=0, 1: x=W, 2: y=D, 3: x=0),
        ``off`` metres into the room, height ``z``."""
        W, D, _ = self.size
        return np.array([
            [s * W, off, z], [W - off, s * D, z], [W - s * W, D - off, z], [off, D - s * D, z],
        ][wall], np.float64)

    @staticmethod
    def wall_yaw(wall: int) -> float:
        """Yaw that turns a box's local +y (front) into the room from wall ``wall``."""
        return [0.0, np.pi / 2, np.pi, -np.pi / 2][wall]

    def against_wall(self, wall: int, s: float, size: tuple[float, float, float], mat: int,
                     front: int | None = None, top: int | None = None, z0: float = 0.0,
                     gap: float = 0.01) -> NDArray:
        """Box standing against a wall (front facing the room); returns its centre."""
        w, d, h = size
        c = self.wall_point(wall, s, gap + d / 2, z0 + h / 2)
        self.box(c, size, self.wall_yaw(wall), mat, front=front, top=top)
        return c

    def poster(self, wall: int, s: float, z: float, w: float, h: float, mat: int) -> None:
        c = self.wall_point(wall, s, 0.006, z)
        self.box(c, (w, 0.01, h), self.wall_yaw(wall), mat, solid=False)

    def table(self, center: NDArray, size: tuple[float, float, float], yaw: float, top_mat: int, leg_mat: int) -> None:
        w, d, h = size
        c = np.asarray(center, np.float64)
        self.box(c + [0, 0, h - 0.02], (w, d, 0.04), yaw, top_mat, interesting=True)
        cy, sy = np.cos(yaw), np.sin(yaw)
        for a in (-1, 1):
            for b in (-1, 1):
                lx, ly = a * (w / 2 - 0.05), b * (d / 2 - 0.05)
                p = c + [cy * lx - sy * ly, sy * lx + cy * ly, (h - 0.04) / 2]
                self.box(p, (0.05, 0.05, h - 0.04), yaw, leg_mat, interesting=False)
        # the space under a table is solid for the camera
        self.obstacles.append(Obstacle(c + [0, 0, h / 2], np.array([w / 2, d / 2, h / 2]), yaw))

    def clutter_on(self, top_center: NDArray, area: tuple[float, float], yaw: float, n: int, mats: list[int]) -> None:
        """Small boxes and cylinders standing on a surface whose top centre is ``top_center``."""
        cy, sy = np.cos(yaw), np.sin(yaw)
        for _ in range(n):
            lx, ly = self.rng.uniform(-0.4, 0.4) * area[0], self.rng.uniform(-0.35, 0.35) * area[1]
            p = np.asarray(top_center) + [cy * lx - sy * ly, sy * lx + cy * ly, 0.0]
            m = mats[int(self.rng.integers(0, len(mats)))]
            if self.rng.random() < 0.5:
                sz = self.rng.uniform([0.08, 0.06, 0.06], [0.3, 0.25, 0.35])
                self.box(p + [0, 0, sz[2] / 2], sz, yaw + self.rng.uniform(-0.5, 0.5), m)
            else:
                self.cylinder(p, float(self.rng.uniform(0.03, 0.08)), float(self.rng.uniform(0.08, 0.3)), m)

    def build(self, free_margin: float) -> Scene:
        W, D, H = self.size
        free = np.array([[free_margin, free_margin, 1.0], [W - free_margin, D - free_margin, 1.75]])
        return Scene(
            size=self.size,
            triangles=np.concatenate(self._tris).astype(np.float32),
            tri_uv=np.concatenate(self._uvs).astype(np.float32),
            tri_mat=np.concatenate(self._mats).astype(np.int64),
            materials=self.materials,
            lights=np.array(self.lights, np.float64),
            obstacles=self.obstacles,
            interest=np.array(self.interest, np.float64),
            free_box=free,
        )


# ---------------------------------------------------------------------------- colours

def _c(*rgb: float) -> NDArray[np.float32]:
    return np.array(rgb, np.float32)


def _ceiling_lights(b: SceneBuilder, n: int, power: float) -> None:
    W, D, H = b.size
    for k in range(n):
        b.lights.append((W * (k + 0.5) / n, D * b.rng.uniform(0.35, 0.65), H - 0.05, power))


# ---------------------------------------------------------------------------- layouts

def office(rng: np.random.Generator) -> Scene:
    b = SceneBuilder(rng, (6.0, 5.0, 2.7), photo_like=True)
    r = b.rng
    wall = b.material("wall", lambda g: tx.tex_plain(g, _c(0.85, 0.84, 0.8)), 2.0)
    wall2 = b.material("wall2", lambda g: tx.tex_plain(g, _c(0.6, 0.7, 0.8)), 2.0)
    paper = b.material("wallpaper", lambda g: tx.tex_noise(g, _c(0.55, 0.5, 0.42), _c(0.9, 0.86, 0.78)), 1.5)
    bricks = b.material("bricks", lambda g: tx.tex_bricks(g, _c(0.6, 0.3, 0.2), _c(0.75, 0.72, 0.7)), 1.2)
    carpet = b.material("carpet", lambda g: tx.tex_noise(g, _c(0.25, 0.28, 0.35), _c(0.5, 0.5, 0.55)), 1.0)
    ceil = b.material("ceiling", lambda g: tx.tex_plain(g, _c(0.9, 0.9, 0.9)), 3.0)
    wood = b.material("wood", lambda g: tx.tex_wood(g, _c(0.45, 0.3, 0.15), _c(0.7, 0.5, 0.3)), 1.0)
    metal = b.material("metal", lambda g: tx.tex_plain(g, _c(0.3, 0.3, 0.32)), 1.0)
    grey = b.material("cabinet", lambda g: tx.tex_plain(g, _c(0.7, 0.7, 0.68)), 1.0)
    books = b.material("books", lambda g: tx.tex_books(g), 0.7)
    screen = b.material("screen", lambda g: tx.tex_noise(g, _c(0.05, 0.05, 0.07), _c(0.15, 0.15, 0.2)), 0.5)
    whiteboard = b.material("whiteboard", lambda g: tx.tex_plain(g, _c(0.95, 0.95, 0.95)), 2.0)
    posters = [b.material(f"poster{k}", lambda g: tx.tex_clutter(g, _c(*g.uniform(0.5, 1, 3))), 0.8) for k in range(4)]
    small = [b.material(f"obj{k}", lambda g: tx.tex_clutter(g, _c(*g.uniform(0.2, 1, 3)), n_shapes=30), 0.3)
             for k in range(3)] + [wood, metal]
    b.room([paper, bricks, wall2, wall], carpet, ceil)
    # desks with monitors and clutter along wall 0 and wall 3
    for wall_i, ss in ((0, (0.25, 0.7)), (3, (0.3,))):
        for s in ss:
            c = b.wall_point(wall_i, s, 0.4, 0.0)
            yaw = b.wall_yaw(wall_i)
            b.table(c, (1.4, 0.75, 0.74), yaw, wood, metal)
            mon = b.wall_point(wall_i, s + r.uniform(-0.03, 0.03), 0.2, 0.74 + 0.22)
            b.box(mon, (0.55, 0.05, 0.34), yaw, metal, front=screen)
            b.clutter_on(b.wall_point(wall_i, s, 0.5, 0.74), (1.3, 0.5), yaw, 5, small)
    # bookshelves, a cabinet, a whiteboard, posters
    b.against_wall(2, 0.2, (1.0, 0.35, 1.9), wood, front=books)
    b.against_wall(2, 0.45, (1.0, 0.35, 1.9), wood, front=books)
    b.against_wall(2, 0.8, (0.9, 0.5, 1.1), grey, top=wood)
    b.clutter_on(b.wall_point(2, 0.8, 0.25, 1.1), (0.8, 0.4), np.pi, 4, small)
    b.poster(1, 0.5, 1.5, 1.6, 1.0, whiteboard)
    b.poster(3, 0.75, 1.5, 0.7, 0.9, posters[0])
    b.poster(0, 0.5, 1.6, 0.6, 0.8, posters[1])
    b.poster(1, 0.15, 1.4, 0.5, 0.7, posters[2])
    b.poster(2, 0.65, 1.9, 0.6, 0.5, posters[3])
    b.poster(3, 0.55, 1.6, 0.9, 0.6, posters[1])
    b.poster(3, 0.92, 1.3, 0.5, 0.7, posters[2])
    b.poster(3, 0.08, 1.5, 0.45, 0.6, posters[0])
    b.poster(0, 0.95, 1.4, 0.4, 0.5, posters[3])
    b.against_wall(1, 0.85, (0.6, 0.6, 1.3), grey, front=posters[3])
    b.against_wall(3, 0.6, (1.2, 0.4, 0.8), wood, front=books)
    b.clutter_on(b.wall_point(3, 0.6, 0.2, 0.8), (1.1, 0.3), b.wall_yaw(3), 3, small)
    _ceiling_lights(b, 2, 2.2)
    return b.build(free_margin=1.3)


def kitchen(rng: np.random.Generator) -> Scene:
    b = SceneBuilder(rng, (5.0, 4.4, 2.6), photo_like=True)
    r = b.rng
    paint = b.material("paint", lambda g: tx.tex_plain(g, _c(0.9, 0.85, 0.65)), 2.0)
    backsplash = b.material("backsplash", lambda g: tx.tex_tiles(g, _c(0.55, 0.7, 0.8), _c(0.9, 0.9, 0.9), 8), 0.8)
    floor = b.material("floor", lambda g: tx.tex_tiles(g, _c(0.6, 0.55, 0.5), _c(0.3, 0.3, 0.3), 4), 1.2)
    ceil = b.material("ceiling", lambda g: tx.tex_plain(g, _c(0.92, 0.92, 0.9)), 3.0)
    cab = b.material("cabinet", lambda g: tx.tex_wood(g, _c(0.6, 0.15, 0.1), _c(0.8, 0.3, 0.2)), 0.8)
    counter = b.material("counter", lambda g: tx.tex_noise(g, _c(0.15, 0.15, 0.15), _c(0.7, 0.68, 0.65)), 0.6)
    white = b.material("appliance", lambda g: tx.tex_plain(g, _c(0.93, 0.93, 0.93)), 2.0)
    steel = b.material("steel", lambda g: tx.tex_plain(g, _c(0.55, 0.56, 0.58)), 1.0)
    tabletop = b.material("tabletop", lambda g: tx.tex_wood(g, _c(0.55, 0.4, 0.25), _c(0.8, 0.65, 0.45)), 1.2)
    labels = [b.material(f"label{k}", lambda g: tx.tex_clutter(g, _c(*g.uniform(0.3, 1, 3)), n_shapes=40), 0.25)
              for k in range(4)]
    calendar = b.material("calendar", lambda g: tx.tex_clutter(g, _c(0.95, 0.95, 0.9), n_shapes=80), 0.6)
    b.room([backsplash, paint, paint, backsplash], floor, ceil)
    # counters along wall 0 and wall 3 with upper cabinets
    for wall_i, ss in ((0, (0.2, 0.4, 0.6, 0.8)), (3, (0.35, 0.6))):
        for s in ss:
            b.against_wall(wall_i, s, (0.9 if wall_i == 0 else 0.85, 0.6, 0.88), steel, front=cab)
            top = b.wall_point(wall_i, s, 0.31, 0.88)
            b.box(top + [0, 0, 0.02], (0.92 if wall_i == 0 else 0.87, 0.62, 0.04), b.wall_yaw(wall_i), counter)
            b.clutter_on(top + [0, 0, 0.04], (0.8, 0.5), b.wall_yaw(wall_i), int(r.integers(1, 4)), labels)
            if r.random() < 0.7:
                b.against_wall(wall_i, s, (0.85, 0.35, 0.7), cab, z0=1.5)
    b.against_wall(1, 0.3, (0.8, 0.7, 1.9), white)  # fridge: plain, starves ORB
    b.poster(1, 0.55, 1.5, 0.5, 0.7, calendar)
    b.poster(2, 0.4, 1.5, 0.9, 0.6, labels[0])
    b.against_wall(2, 0.75, (1.0, 0.4, 1.0), cab, top=counter)
    b.clutter_on(b.wall_point(2, 0.75, 0.2, 1.0), (0.9, 0.35), np.pi, 3, labels)
    # table in the middle
    tc = np.array([b.size[0] * 0.55, b.size[1] * 0.55, 0.0])
    b.table(tc, (1.1, 0.8, 0.75), float(r.uniform(-0.3, 0.3)), tabletop, steel)
    b.clutter_on(tc + [0, 0, 0.75], (0.9, 0.6), 0.0, 4, labels)
    _ceiling_lights(b, 2, 2.0)
    return b.build(free_margin=1.0)


def lab(rng: np.random.Generator) -> Scene:
    b = SceneBuilder(rng, (7.0, 5.5, 3.0), photo_like=True)
    r = b.rng
    bricks = b.material("bricks", lambda g: tx.tex_bricks(g, _c(0.75, 0.7, 0.6), _c(0.4, 0.4, 0.4)), 1.5)
    paint = b.material("paint", lambda g: tx.tex_plain(g, _c(0.75, 0.78, 0.75)), 2.0)
    concrete = b.material("concrete", lambda g: tx.tex_noise(g, _c(0.4, 0.4, 0.38), _c(0.65, 0.63, 0.6)), 2.0)
    ceil = b.material("ceiling", lambda g: tx.tex_tiles(g, _c(0.9, 0.9, 0.88), _c(0.6, 0.6, 0.6), 2), 1.2)
    bench_top = b.material("benchtop", lambda g: tx.tex_noise(g, _c(0.1, 0.1, 0.12), _c(0.3, 0.3, 0.3)), 0.8)
    bench = b.material("bench", lambda g: tx.tex_plain(g, _c(0.6, 0.62, 0.65)), 1.0)
    cardboard = b.material("cardboard", lambda g: tx.tex_noise(g, _c(0.55, 0.4, 0.25), _c(0.7, 0.55, 0.35)), 0.6)
    whiteboard = b.material("whiteboard", lambda g: tx.tex_plain(g, _c(0.96, 0.96, 0.96)), 2.0)
    board = b.material("noticeboard", lambda g: tx.tex_clutter(g, _c(0.7, 0.55, 0.35), n_shapes=120), 1.2)
    panels = [b.material(f"panel{k}", lambda g: tx.tex_panel(g, _c(*g.uniform(0.5, 0.9, 3))), 0.5) for k in range(3)]
    boxes = [cardboard] + [b.material(f"box{k}", lambda g: tx.tex_clutter(g, _c(*g.uniform(0.3, 1, 3)), n_shapes=40), 0.4)
                           for k in range(3)]
    b.room([bricks, paint, bricks, paint], concrete, ceil)
    # benches with equipment along walls 0 and 2
    for wall_i in (0, 2):
        for s in (0.2, 0.45, 0.7):
            b.against_wall(wall_i, s, (1.5, 0.75, 0.9), bench, top=bench_top)
            yaw = b.wall_yaw(wall_i)
            for _ in range(int(r.integers(1, 3))):
                sz = r.uniform([0.25, 0.25, 0.15], [0.55, 0.45, 0.45])
                p = b.wall_point(wall_i, s + r.uniform(-0.07, 0.07), 0.1 + sz[1] / 2, 0.9 + sz[2] / 2)
                b.box(p, sz, yaw, bench, front=panels[int(r.integers(0, 3))])
            b.clutter_on(b.wall_point(wall_i, s, 0.5, 0.9), (1.2, 0.3), yaw, 2, boxes)
    # shelves with boxes on wall 1, whiteboard and notice board on wall 3
    for s in (0.3, 0.7):
        b.against_wall(1, s, (1.2, 0.45, 2.0), bench)
        for z in (0.5, 1.1, 1.65):
            for k in range(3):
                sz = r.uniform([0.25, 0.3, 0.2], [0.35, 0.4, 0.35])
                p = b.wall_point(1, s + (k - 1) * 0.06, 0.5 + sz[1] / 2 - 0.05, z + sz[2] / 2)
                b.box(p, sz, b.wall_yaw(1) + r.uniform(-0.2, 0.2), boxes[int(r.integers(0, 4))])
    b.poster(3, 0.3, 1.5, 1.8, 1.1, whiteboard)
    b.poster(3, 0.75, 1.5, 1.2, 0.9, board)
    # an island bench in the middle
    ic = np.array([b.size[0] * 0.5, b.size[1] * 0.5, 0.45])
    b.box(ic, (1.6, 0.8, 0.9), 0.0, bench, top=bench_top)
    b.clutter_on(ic + [0, 0, 0.45], (1.4, 0.7), 0.0, 4, boxes + panels)
    _ceiling_lights(b, 3, 3.0)
    return b.build(free_margin=1.2)


LAYOUTS: dict[str, Callable[[np.random.Generator], Scene]] = {"office": office, "kitchen": kitchen, "lab": lab}

#: texture styles of :func:`restyle` (``SceneConfig.texture_style``)
TEXTURE_STYLES = ("default", "lowfreq", "repetitive", "textureless")


def restyle(scene: Scene, style: str, rng: np.random.Generator) -> Scene:
    """``scene`` with every material's texture replaced, keeping its mean colour:

    * ``default``: unchanged;
    * ``lowfreq``: smooth low-frequency blobs (:func:`~data.synthetic.textures.tex_blobs`);
    * ``repetitive``: one small motif tiled (:func:`~data.synthetic.textures.tex_repeat`);
    * ``textureless``: plain paint (:func:`~data.synthetic.textures.tex_plain`) on every
      surface but the small objects (materials ``obj*``): views of walls, floor and
      furniture are stretches without texture, only shading and outlines.
    """
    if style == "default":
        return scene
    if style not in TEXTURE_STYLES:
        raise ValueError(f"unknown texture style {style!r} (known: {', '.join(TEXTURE_STYLES)})")
    mats = []
    for m in scene.materials:
        c = m.texture.reshape(-1, 3).mean(0).astype(np.float32)
        dark, light = (0.55 * c).astype(np.float32), np.minimum(1.3 * c + 0.1, 1.0).astype(np.float32)
        if style == "lowfreq":
            tex = tx.tex_blobs(rng, dark, light)
        elif style == "repetitive":
            tex = tx.tex_repeat(rng, light, dark)
        elif m.name.startswith("obj"):
            tex = m.texture
        else:
            tex = tx.tex_plain(rng, c)
        mats.append(Material(m.name, tex, m.scale_m))
    return dataclasses.replace(scene, materials=mats)
