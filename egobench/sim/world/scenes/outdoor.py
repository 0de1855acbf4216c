"""The outdoor scene kind: a sunlit street corner or patio (facades, shop signs, poles, tables, an awning)."""

from __future__ import annotations

import math

import numpy as np

from egobench.sim.textures import Texture
from egobench.sim.world.lighting import Light, SkyDome, Sun
from egobench.sim.world.primitives import Cylinder, Material, Primitive, Rect, Sphere, WalkRegion, axis_rect, yaw_box
from egobench.sim.world.scene import Scene
from egobench.sim.world.scenes.common import jitter


def build(rng: np.random.Generator, seed: int, spread: float = 1.0) -> Scene:
    """A sunlit street corner / patio: brick and plaster facades, shop signs, poles, tables, awning."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731 - texture seeds
    M = {
        "pavement": Material(Texture("tiles", ((0.32, 0.30, 0.28), (0.12, 0.12, 0.12), (0.45, 0.42, 0.38)), 0.4, s(0))),
        "asphalt": Material(Texture("noise", ((0.10, 0.10, 0.10), (0.22, 0.21, 0.20)), 0.08, s(1))),
        "bricks": Material(Texture("bricks", ((0.45, 0.20, 0.12), (0.55, 0.52, 0.48), (0.30, 0.13, 0.09)), 0.24, s(2))),
        "plaster": Material(Texture("noise", ((0.62, 0.58, 0.50), (0.48, 0.44, 0.38)), 0.3, s(3))),
        "shopfront": Material(Texture("grid", ((0.05, 0.06, 0.07), (0.50, 0.50, 0.50)), 0.6, s(4))),
        "sign1": Material(Texture("text", ((0.80, 0.78, 0.70), (0.05, 0.05, 0.08)), 0.12, s(5))),
        "sign2": Material(Texture("text", ((0.08, 0.20, 0.45), (0.85, 0.85, 0.85)), 0.09, s(6))),
        "menu": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.05), (0.8, 0.75, 0.6), (0.7, 0.3, 0.2), (0.85, 0.8, 0.7)), 0.035, s(7))),
        "metal": Material(Texture("noise", ((0.18, 0.18, 0.19), (0.35, 0.35, 0.36)), 0.05, s(8))),
        "wood": Material(Texture("planks", ((0.42, 0.26, 0.14), (0.10, 0.06, 0.04), (0.55, 0.36, 0.20)), 0.09, s(9))),
        "awning": Material(Texture("checker", ((0.65, 0.08, 0.06), (0.80, 0.78, 0.72)), 0.5, s(10), edge_m=0.004)),
        "planter": Material(Texture("noise", ((0.08, 0.22, 0.05), (0.25, 0.40, 0.10)), 0.04, s(11))),
        "stone": Material(Texture("noise", ((0.50, 0.50, 0.48), (0.30, 0.30, 0.29)), 0.06, s(12))),
    }
    P: list[Primitive] = []
    P.append(axis_rect((0, 0, 0), "+z", (60.0, 60.0), "pavement"))
    P.append(axis_rect((0, -9.0, 0.002), "+z", (60.0, 6.0), "asphalt"))
    # north facade (bricks) with a shop front and signs; west facade (plaster); a south-west building
    P.append(yaw_box((0, 7.5, 5.0), (24.0, 1.0, 10.0), "bricks"))
    P.append(axis_rect((jitter(rng, 1.0 * spread) - 2.0, 6.99, 1.5), "-y", (5.0, 2.6), "shopfront"))
    P.append(axis_rect((-2.0, 6.96, 3.4), "-y", (4.0, 0.7), "sign1"))
    P.append(axis_rect((4.5 + jitter(rng, 0.5 * spread), 6.98, 2.6), "-y", (2.2, 1.4), "menu"))
    P.append(yaw_box((-9.5, 0.0, 4.0), (1.0, 16.0, 8.0), "plaster"))
    P.append(axis_rect((-8.99, -1.0 + jitter(rng, 0.5 * spread), 2.8), "+x", (3.0, 0.6), "sign2"))
    P.append(axis_rect((-8.99, 2.5, 1.4), "+x", (1.2, 1.6), "menu"))
    P.append(yaw_box((-3.0, -12.5, 6.0), (14.0, 1.0, 12.0), "bricks"))
    # awning over the shop front (casts a shadow band)
    P.append(Rect((-2.0, 5.9, 3.0), (1.0, 0.0, 0.0), (0.0, 0.8, 0.6), 3.0, 1.1, "awning"))
    # poles with signs
    for k, (x, y) in enumerate([(3.5, -3.2), (-5.5, 3.8), (6.5, 3.0)]):
        x, y = x + jitter(rng, 0.3 * spread), y + jitter(rng, 0.3 * spread)
        P.append(Cylinder((x, y, 1.5), (0, 0, 1), 0.045, 1.5, "metal"))
        P.append(Rect((x, y, 2.55 + 0.1 * k), (1.0, 0.3 * (k - 1), 0.0), (0, 0, 1), 0.45, 0.3, "sign1" if k % 2 else "sign2"))
    # bistro tables with chairs, and planters
    for (x, y) in [(2.0, 4.0), (-1.5, 4.3), (5.0, 5.2), (-6.0, -4.0)]:
        x, y = x + jitter(rng, 0.3 * spread), y + jitter(rng, 0.3 * spread)
        P.append(Cylinder((x, y, 0.74), (0, 0, 1), 0.4, 0.02, "wood"))
        P.append(Cylinder((x, y, 0.37), (0, 0, 1), 0.04, 0.36, "metal"))
        P.append(yaw_box((x + 0.65, y, 0.45), (0.42, 0.42, 0.06), "wood", yaw_deg=jitter(rng, 30 * spread)))
        P.append(yaw_box((x - 0.65, y, 0.45), (0.42, 0.42, 0.06), "wood", yaw_deg=jitter(rng, 30 * spread)))
    for (x, y) in [(-7.5, -2.5), (-7.5, 1.0), (7.0, -2.0)]:
        P.append(yaw_box((x, y, 0.35), (0.9, 0.9, 0.7), "stone"))
        P.append(Sphere((x, y, 0.9), 0.45, "planter"))
    for x in (-3.0, -1.0, 1.0, 3.0):
        P.append(Sphere((x, -5.5, 0.35), 0.25, "stone"))
    # sun from the south-west, 50 deg elevation: facades and the awning cast long shadows
    az, el = math.radians(225.0 + jitter(rng, 10.0 * spread)), math.radians(50.0)
    lights: list[Light] = [
        Sun((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)), 60000.0),
        SkyDome(4000.0, ground_albedo=0.25),
    ]
    targets = np.array([[-2.0, 6.9, 3.4], [4.5, 6.9, 2.6], [-8.9, -1.0, 2.8], [2.0, 4.0, 0.8], [-6.0, -4.0, 0.8],
                        [3.5, -3.2, 2.5], [-7.5, -2.5, 0.9]])
    return Scene("outdoor", P, M, lights, WalkRegion("box", (0.0, 0.0), (4.0, 2.0)), targets,
                 ((-30.0, -30.0, 0.0), (30.0, 30.0, 12.0)), seed)
