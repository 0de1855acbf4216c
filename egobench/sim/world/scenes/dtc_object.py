"""The object scene kind: a DTC-like object capture (a mug, a printed box, a ball on a table in a lab)."""

from __future__ import annotations

import numpy as np

from egobench.sim.textures import Texture
from egobench.sim.world.lighting import AmbientLight, Light, PointLight
from egobench.sim.world.primitives import Cylinder, Material, Primitive, Sphere, WalkRegion, axis_rect, yaw_box
from egobench.sim.world.scene import Scene
from egobench.sim.world.scenes.common import jitter, room_shell


def build(rng: np.random.Generator, seed: int, spread: float = 1.0) -> Scene:
    """A DTC-like object capture: a mug, a printed box and a ball on a table in an evenly lit lab."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731
    M = {
        "floor": Material(Texture("tiles", ((0.45, 0.45, 0.44), (0.20, 0.20, 0.20), (0.55, 0.55, 0.53)), 0.6, s(0))),
        "wall": Material(Texture("noise", ((0.62, 0.62, 0.60), (0.52, 0.52, 0.50)), 0.25, s(1))),
        "ceiling": Material(Texture("plain", ((0.8, 0.8, 0.8),), 1.0, s(2))),
        # A plain grey felt mat, as DTC's captures put objects on a plain backdrop. A 4 cm black-and-white
        # checkerboard here (2-3 px cells at 128 px, half of every view) made the scene near white noise
        # (spectral slope -0.26, one-pixel-shift PSNR 21.4 dB) and capped every model near 20 dB (issue 31).
        "mat": Material(Texture("plain", ((0.55, 0.55, 0.53),), 1.0, s(3))),
        "table": Material(Texture("noise", ((0.30, 0.30, 0.32), (0.40, 0.40, 0.42)), 0.05, s(4))),
        "mug": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.1), (0.80, 0.75, 0.65), (0.15, 0.35, 0.6), (0.7, 0.2, 0.15)), 0.012, s(5), edge_m=0.0007)),
        "package": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.9, 0.9, 0.85), (0.7, 0.15, 0.1), (0.9, 0.7, 0.1), (0.1, 0.3, 0.6)), 0.01, s(6), edge_m=0.0007)),
        "ball": Material(Texture("checker", ((0.85, 0.6, 0.1), (0.1, 0.2, 0.5)), 0.03, s(7), edge_m=0.0007)),
        "poster": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.05), (0.85, 0.8, 0.7), (0.3, 0.5, 0.3)), 0.04, s(8))),
        "lamp": Material(Texture("plain", ((0.8, 0.8, 0.8),), 1.0, s(9)), emission_cd_m2=3000.0),
    }
    size = (6.0, 6.0, 3.0)
    P: list[Primitive] = []
    room_shell(P, size, "floor", "wall", "ceiling")
    P.append(axis_rect((0.0, 2.99, 1.5), "-y", (1.5, 1.0), "poster"))
    P.append(axis_rect((-2.99, 0.0, 1.5), "+x", (1.5, 1.0), "poster"))
    table_top = 0.75
    P.append(yaw_box((0, 0, table_top - 0.02), (1.0, 0.8, 0.04), "table"))
    for dx in (-0.45, 0.45):
        for dy in (-0.35, 0.35):
            P.append(Cylinder((dx, dy, (table_top - 0.04) / 2), (0, 0, 1), 0.025, (table_top - 0.04) / 2, "table"))
    P.append(axis_rect((0, 0, table_top + 0.0005), "+z", (0.6, 0.45), "mat"))
    mx, my = 0.08 + jitter(rng, 0.02 * spread), 0.02 + jitter(rng, 0.02 * spread)
    P.append(Cylinder((mx, my, table_top + 0.05), (0, 0, 1), 0.042, 0.05, "mug"))
    P.append(yaw_box((mx + 0.055, my, table_top + 0.05), (0.018, 0.012, 0.06), "mug"))  # handle
    P.append(yaw_box((-0.12, 0.05, table_top + 0.09), (0.09, 0.05, 0.18), "package", yaw_deg=20 + jitter(rng, 15 * spread)))
    P.append(Sphere((0.03, -0.12, table_top + 0.045), 0.045, "ball"))
    lamp_xy = [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)]
    for (x, y) in lamp_xy:
        P.append(axis_rect((x, y, 2.99), "-z", (0.6, 0.6), "lamp"))
    lights: list[Light] = [AmbientLight(250.0)]
    lights += [PointLight((x, y, 2.9), 300.0, rgb=(1.0, 1.0, 1.0)) for (x, y) in lamp_xy]
    targets = np.array([[0.0, 0.0, table_top + 0.06]])
    # the objects: everything standing on the mat, 2 mm above it and up (the mat and the table are background)
    foreground = ((-0.3, -0.225, table_top + 0.002), (0.3, 0.225, table_top + 0.5))
    return Scene("object", P, M, lights, WalkRegion("ring", (0.0, 0.0), radius_min_m=1.1, radius_max_m=1.4,
                                                    eye_height_m=1.5), targets,
                 ((-3.0, -3.0, 0.0), (3.0, 3.0, 3.0)), seed, foreground_box=foreground)
