"""The indoor scene kind: a library-like room (shelves of books, posters, a table, a bright window)."""

from __future__ import annotations

import numpy as np

from egobench.sim.textures import Texture
from egobench.sim.world.lighting import AmbientLight, Light, PointLight
from egobench.sim.world.primitives import Cylinder, Material, Primitive, WalkRegion, axis_rect, yaw_box
from egobench.sim.world.scene import Scene
from egobench.sim.world.scenes.common import bookshelf, jitter, palette, room_shell


def build(rng: np.random.Generator, seed: int, spread: float = 1.0) -> Scene:
    """A library-like room: shelves of books, posters, a table, a bright window, ~150-300 lux."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731
    covers = palette(rng, 6, 0.08, 0.7)
    M = {
        "floor": Material(Texture("planks", ((0.40, 0.27, 0.16), (0.12, 0.08, 0.05), (0.52, 0.36, 0.22)), 0.14, s(0))),
        "wall": Material(Texture("noise", ((0.70, 0.68, 0.62), (0.60, 0.58, 0.52)), 0.2, s(1))),
        "ceiling": Material(Texture("grid", ((0.75, 0.75, 0.73), (0.45, 0.45, 0.45)), 0.6, s(2))),
        "shelf": Material(Texture("planks", ((0.35, 0.22, 0.12), (0.15, 0.09, 0.05), (0.45, 0.30, 0.18)), 0.1, s(3))),
        "books": Material(Texture("books", ((0.05, 0.04, 0.03), (0.85, 0.80, 0.65), *covers), 0.035, s(4))),
        "poster1": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.04, 0.04, 0.04), (0.85, 0.8, 0.7), (0.2, 0.4, 0.7), (0.8, 0.6, 0.2)), 0.03, s(5))),
        "poster2": Material(Texture("text", ((0.85, 0.84, 0.80), (0.05, 0.05, 0.05)), 0.025, s(6))),
        "board": Material(Texture("grid", ((0.80, 0.80, 0.78), (0.15, 0.25, 0.45)), 0.05, s(7))),
        "table": Material(Texture("planks", ((0.50, 0.35, 0.20), (0.20, 0.12, 0.06), (0.60, 0.45, 0.28)), 0.12, s(8))),
        "rug": Material(Texture("checker", ((0.45, 0.12, 0.10), (0.70, 0.62, 0.45)), 0.25, s(9))),
        "metal": Material(Texture("noise", ((0.25, 0.25, 0.26), (0.40, 0.40, 0.41)), 0.05, s(10))),
        "window": Material(Texture("plain", ((0.6, 0.6, 0.6),), 1.0, s(11)), emission_cd_m2=1000.0,
                           emission_rgb=(0.9, 1.0, 1.15),
                           emission_texture=Texture("window", ((0.95, 0.95, 0.95), (0.03, 0.03, 0.03)), 0.45, s(12))),
        "lamp": Material(Texture("plain", ((0.8, 0.8, 0.8),), 1.0, s(13)), emission_cd_m2=2500.0, emission_rgb=(1.0, 0.95, 0.85)),
    }
    size = (9.0, 7.0, 2.9)
    P: list[Primitive] = []
    room_shell(P, size, "floor", "wall", "ceiling")
    # shelves along the north and west walls
    for k in range(3):
        bookshelf(P, -3.0 + 2.2 * k + jitter(rng, 0.1 * spread), 3.48, 180.0, 2.0, "shelf", "books")
    bookshelf(P, -4.48, -1.2 + jitter(rng, 0.2 * spread), -90.0, 2.4, "shelf", "books")
    # posters and a notice board on the south wall; a window on the east wall
    P.append(axis_rect((-2.5, -3.49, 1.6), "+y", (0.8, 1.1), "poster1"))
    P.append(axis_rect((-1.2 + jitter(rng, 0.2 * spread), -3.49, 1.5), "+y", (0.7, 0.9), "poster2"))
    P.append(axis_rect((1.5, -3.49, 1.5), "+y", (1.8, 1.0), "board"))
    P.append(axis_rect((4.49, 0.3 + jitter(rng, 0.3 * spread), 1.55), "-x", (2.0, 1.4), "window"))
    # a reading table, chairs, a rug, ceiling lamps
    P.append(axis_rect((0.3, 0.2, 0.004), "+z", (3.0, 2.0), "rug"))
    P.append(yaw_box((2.6, -1.9, 0.74), (1.6, 0.8, 0.04), "table", yaw_deg=jitter(rng, 10 * spread)))
    for dx in (-0.7, 0.7):
        P.append(Cylinder((2.6 + dx, -1.9, 0.36), (0, 0, 1), 0.03, 0.36, "metal"))
        P.append(yaw_box((2.6 + dx, -1.2, 0.45), (0.45, 0.45, 0.05), "shelf", yaw_deg=jitter(rng, 20 * spread)))
    lamp_xy = [(-2.0, 0.0), (1.5, 0.0), (1.5, -2.0)]
    for (x, y) in lamp_xy:
        P.append(Cylinder((x, y, 2.86), (0, 0, 1), 0.25, 0.03, "lamp"))
    lights: list[Light] = [AmbientLight(110.0, (1.0, 0.98, 0.95))]
    lights += [PointLight((x, y, 2.8), 600.0, cast_shadows=False) for (x, y) in lamp_xy]
    lights.append(PointLight((3.6, 0.3, 1.8), 500.0, rgb=(0.9, 1.0, 1.15)))  # light from the window
    targets = np.array([[-3.0, 3.3, 1.2], [-0.8, 3.3, 1.0], [1.4, 3.3, 1.4], [-4.3, -1.2, 1.2], [-2.5, -3.4, 1.6],
                        [1.5, -3.4, 1.5], [4.4, 0.3, 1.5], [2.6, -1.9, 0.8]])
    return Scene("indoor", P, M, lights, WalkRegion("box", (0.0, 0.9), (3.2, 1.5)), targets,
                 ((-size[0] / 2, -size[1] / 2, 0.0), (size[0] / 2, size[1] / 2, size[2])), seed)
