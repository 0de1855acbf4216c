"""The Quest 3 scene kind: a living room (sofa, coffee table, TV, rug, bookshelf, window, lamps)."""

from __future__ import annotations

import numpy as np

from egobench.sim.textures import Texture
from egobench.sim.world.lighting import AmbientLight, Light, PointLight
from egobench.sim.world.primitives import Cylinder, Material, Primitive, WalkRegion, axis_rect, yaw_box
from egobench.sim.world.scene import Scene
from egobench.sim.world.scenes.common import bookshelf, jitter, palette, room_shell


def build(rng: np.random.Generator, seed: int, spread: float = 1.0) -> Scene:
    """A living room (Quest 3 captures): sofa, coffee table, TV, rug, bookshelf, window, lamps."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731
    covers = palette(rng, 5, 0.1, 0.7)
    M = {
        "floor": Material(Texture("planks", ((0.55, 0.40, 0.25), (0.15, 0.10, 0.06), (0.62, 0.48, 0.30)), 0.18, s(0))),
        "wall": Material(Texture("noise", ((0.72, 0.70, 0.64), (0.64, 0.62, 0.56)), 0.3, s(1))),
        "ceiling": Material(Texture("plain", ((0.8, 0.8, 0.78),), 1.0, s(2))),
        "fabric": Material(Texture("noise", ((0.20, 0.28, 0.38), (0.30, 0.38, 0.48)), 0.01, s(3))),
        "cushion": Material(Texture("checker", ((0.70, 0.60, 0.30), (0.25, 0.20, 0.15)), 0.08, s(4))),
        "wood": Material(Texture("planks", ((0.45, 0.30, 0.18), (0.15, 0.10, 0.06), (0.55, 0.38, 0.22)), 0.1, s(5))),
        "rug": Material(Texture("grid", ((0.60, 0.55, 0.45), (0.30, 0.10, 0.08)), 0.15, s(6))),
        "tv": Material(Texture("noise", ((0.03, 0.03, 0.03), (0.06, 0.06, 0.06)), 0.05, s(7))),
        "screen": Material(Texture("plain", ((0.02, 0.02, 0.02),), 1.0, s(8)), emission_cd_m2=120.0,
                           emission_texture=Texture("poster", ((0.5, 0.5, 0.5), (0.95, 0.95, 0.95), (0.3, 0.5, 0.8), (0.8, 0.4, 0.2)), 0.05, s(9))),
        "books": Material(Texture("books", ((0.05, 0.04, 0.03), (0.85, 0.80, 0.65), *covers), 0.04, s(10))),
        "art": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.05), (0.8, 0.7, 0.5), (0.2, 0.5, 0.4)), 0.04, s(11))),
        "magazine": Material(Texture("text", ((0.9, 0.88, 0.85), (0.05, 0.05, 0.05)), 0.012, s(12), edge_m=0.0008)),
        "window": Material(Texture("plain", ((0.6, 0.6, 0.6),), 1.0, s(13)), emission_cd_m2=1000.0, emission_rgb=(0.9, 1.0, 1.15),
                           emission_texture=Texture("window", ((0.95, 0.95, 0.95), (0.05, 0.05, 0.05)), 0.5, s(14))),
        "shade": Material(Texture("noise", ((0.9, 0.85, 0.7), (0.8, 0.75, 0.6)), 0.05, s(15)), emission_cd_m2=600.0,
                          emission_rgb=(1.0, 0.9, 0.75)),
        "metal": Material(Texture("noise", ((0.2, 0.2, 0.2), (0.35, 0.35, 0.35)), 0.05, s(16))),
    }
    size = (7.0, 5.5, 2.6)
    P: list[Primitive] = []
    room_shell(P, size, "floor", "wall", "ceiling")
    # sofa against the south wall, coffee table and rug in front, TV on the north wall
    P.append(yaw_box((0.0, -2.3, 0.22), (2.2, 0.9, 0.44), "fabric"))
    P.append(yaw_box((0.0, -2.65, 0.65), (2.2, 0.2, 0.5), "fabric"))
    for dx in (-0.6, 0.6):
        P.append(yaw_box((dx + jitter(rng, 0.1 * spread), -2.35, 0.52), (0.5, 0.5, 0.16), "cushion", yaw_deg=jitter(rng, 8 * spread)))
    P.append(axis_rect((0.0, -0.9, 0.004), "+z", (2.6, 1.8), "rug"))
    P.append(yaw_box((0.0, -1.0, 0.42), (1.1, 0.6, 0.04), "wood"))
    P.append(yaw_box((0.0, -1.0, 0.2), (1.0, 0.5, 0.02), "wood"))
    P.append(yaw_box((0.15, -1.0, 0.445), (0.28, 0.21, 0.01), "magazine", yaw_deg=15 + jitter(rng, 10 * spread)))
    P.append(yaw_box((0.0, 2.7, 1.3), (1.4, 0.06, 0.8), "tv"))
    P.append(axis_rect((0.0, 2.665, 1.3), "-y", (1.3, 0.72), "screen"))
    P.append(yaw_box((0.0, 2.5, 0.3), (2.0, 0.45, 0.6), "wood"))
    bookshelf(P, -3.48, 1.0, -90.0, 1.6, "wood", "books", height=1.8)
    P.append(axis_rect((3.49, 0.0, 1.45), "-x", (1.8, 1.3), "window"))
    P.append(axis_rect((-3.49, -1.6, 1.5), "+x", (1.0, 0.7), "art"))
    # floor lamp
    P.append(Cylinder((2.8, -2.2, 0.8), (0, 0, 1), 0.02, 0.8, "metal"))
    P.append(Cylinder((2.8, -2.2, 1.7), (0, 0, 1), 0.2, 0.14, "shade"))
    lights: list[Light] = [AmbientLight(110.0), PointLight((2.8, -2.2, 1.7), 150.0, rgb=(1.0, 0.9, 0.75)),
                           PointLight((0.0, 0.0, 2.5), 450.0), PointLight((3.0, 0.0, 1.6), 300.0, rgb=(0.9, 1.0, 1.15))]
    targets = np.array([[0.0, 2.66, 1.3], [0.0, -1.0, 0.45], [0.0, -2.3, 0.6], [-3.3, 1.0, 1.0], [3.45, 0.0, 1.45],
                        [-3.45, -1.6, 1.5]])
    return Scene("quest3", P, M, lights, WalkRegion("box", (0.2, 0.9), (1.8, 0.9)), targets,
                 ((-size[0] / 2, -size[1] / 2, 0.0), (size[0] / 2, size[1] / 2, size[2])), seed)
