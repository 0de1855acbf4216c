"""Helpers the scene builders share: jitter, palettes, a room shell, a bookshelf."""

from __future__ import annotations

import numpy as np

from egobench.sim.world.primitives import RGB, Box, Primitive, axis_rect, rot_z


def jitter(rng: np.random.Generator, scale: float) -> float:
    return float(rng.uniform(-scale, scale))


def palette(rng: np.random.Generator, n: int, lo: float = 0.08, hi: float = 0.75) -> tuple[RGB, ...]:
    return tuple(tuple(float(x) for x in rng.uniform(lo, hi, 3)) for _ in range(n))


def room_shell(P: list[Primitive], size: tuple[float, float, float], floor: str, wall: str, ceiling: str) -> None:
    """Floor, ceiling and four walls of a closed room centred on (0, 0), facing inwards."""
    sx, sy, sz = size
    P.append(axis_rect((0, 0, 0), "+z", (sx, sy), floor))
    P.append(axis_rect((0, 0, sz), "-z", (sx, sy), ceiling))
    P.append(axis_rect((-sx / 2, 0, sz / 2), "+x", (sy, sz), wall))
    P.append(axis_rect((sx / 2, 0, sz / 2), "-x", (sy, sz), wall))
    P.append(axis_rect((0, -sy / 2, sz / 2), "+y", (sx, sz), wall))
    P.append(axis_rect((0, sy / 2, sz / 2), "-y", (sx, sz), wall))


def bookshelf(P: list[Primitive], x: float, y: float, yaw_deg: float, width: float, material_frame: str,
               material_books: str, height: float = 2.0, depth: float = 0.32) -> None:
    """A shelf unit: a frame box with a row of books (textured box front) per shelf."""
    R = rot_z(yaw_deg)
    fwd = R[:, 1]  # the shelf faces +y of its frame
    P.append(Box((x, y, height / 2), (width / 2, 0.02, height / 2), material_frame, tuple(map(tuple, R))))  # back
    for k in range(5):
        z = 0.05 + k * 0.4
        c = np.array([x, y, z]) + fwd * depth / 2
        P.append(Box(tuple(c), (width / 2, depth / 2, 0.015), material_frame, tuple(map(tuple, R))))
        if k < 4:
            bc = np.array([x, y, z + 0.16]) + fwd * (depth / 2 - 0.02)
            P.append(Box(tuple(bc), (width / 2 - 0.02, depth / 2 - 0.04, 0.145), material_books, tuple(map(tuple, R))))
