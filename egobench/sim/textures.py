"""Procedural high-frequency albedo textures: pure, seeded functions of surface coordinates.

Every texture maps surface coordinates ``uv`` in **metres** (``[N, 2]``, u along the surface's
first tangent, v along its second; on vertical surfaces v points up) to a linear albedo
``[N, 3]`` in [0, 1]. They are deterministic functions of (uv, parameters, seed): no global
random state, so a scene rendered twice, on two machines, gives the same numbers.

Detail is what makes the benchmark bite (rolling shutter, blur and calibration errors are
invisible on flat colour), so the kinds below are chosen for sharp edges at several scales:

============  ================================================================================
kind          what it looks like (``scale_m`` is the main feature size)
============  ================================================================================
``plain``     ``colors[0]`` with low-frequency noise (paint, plaster)
``noise``     fBm-modulated albedo between ``colors[0]`` and ``colors[1]`` (stone, fabric, foliage)
``checker``   checkerboard of period ``scale_m`` (calibration mats, floor tiles)
``grid``      thin lines of width ``0.06 * scale_m`` every ``scale_m`` (tiles, graph paper, fences)
``tiles``     paving: grid joints + per-tile colour variation + noise
``text``      rows of stroke glyphs (character height ``scale_m``): signs, posters, labels
``bricks``    running-bond bricks (``scale_m`` = brick length) with mortar joints
``planks``    wooden planks (``scale_m`` = plank width) with grain and seams
``books``     book spines on shelves (``scale_m`` = spine width), with title strokes
``poster``    blocks of colour with text rows on top
``window``    window panes with mullions (use as an emission pattern)
============  ================================================================================

Aliasing: every pattern is evaluated box-filtered over a footprint ``e`` (metres, per point):
``e = max(edge_m, footprint_m)``, where ``footprint_m`` is the size of the pixel on the surface
(given by the caller; `Scene.cast` computes it from the pixel angle, distance and incidence).
Steps become exact box-filtered ramps, thin lines and strokes exact 1D box-filtered bands,
checkers fade to their mean when the footprint exceeds a square, and noise octaves finer than
the footprint fade to their mean. So far-away bricks turn into their average colour instead of
moire. Add a kind: write ``_kind(uv, tex, e) -> [N, 3]`` (e: [N] footprint), register it in
``_KINDS``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Literal

import torch
from torch import Tensor

TextureKind = Literal[
    "plain", "noise", "checker", "grid", "tiles", "text", "bricks", "planks", "books", "poster", "window"
]
RGB = tuple[float, float, float]

_MASK32 = 0xFFFFFFFF


@dataclass(frozen=True)
class Texture:
    """A procedural albedo texture: a kind, its colours and its feature scale."""

    kind: TextureKind  # which pattern (see the module docstring table)
    colors: tuple[RGB, ...] = ((0.5, 0.5, 0.5), (0.1, 0.1, 0.1))  # linear albedo colours the pattern mixes, each in [0, 1]
    scale_m: float = 0.1  # main feature size in metres (period, brick length, character height...)
    seed: int = 0  # pattern seed (glyph shapes, per-tile colours, noise)
    grain: float = 0.15  # relative amplitude of the multiplicative fine noise on top of the pattern (0 = none)
    edge_m: float = 0.002  # width of the linear ramp that replaces hard edges (anti-aliasing), metres

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"Texture.kind: expected one of {sorted(_KINDS)}, got {self.kind!r}")
        if not (self.scale_m > 0 and math.isfinite(self.scale_m)):
            raise ValueError(f"Texture.scale_m: expected a positive finite length in metres, got {self.scale_m}")
        if len(self.colors) < 1 or any(len(c) != 3 for c in self.colors):
            raise ValueError(f"Texture.colors: expected a non-empty tuple of (r, g, b) triples, got {self.colors}")
        for c in self.colors:
            if not all(0.0 <= x <= 1.0 for x in c):
                raise ValueError(f"Texture.colors: albedo components must lie in [0, 1], got {c}")
        if not (self.edge_m >= 0 and self.grain >= 0):
            raise ValueError("Texture.edge_m and Texture.grain must be >= 0")

    def color(self, i: int) -> RGB:
        """The i-th colour, cycling when the texture has fewer."""
        return self.colors[i % len(self.colors)]


# ----------------------------------------------------------------------------------- hashing
def hash_u32(x: Tensor) -> Tensor:
    """Integer hash (int64 tensor holding 32-bit values) -> well mixed 32-bit values (int64)."""
    x = x & _MASK32
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _MASK32  # multipliers < 2^31 keep the int64 product exact
    x = x ^ (x >> 15)
    x = (x * 0x2C1B3C6D) & _MASK32
    x = x ^ (x >> 16)
    return x


def _hash_int(x: int) -> int:
    """The same 32-bit hash as `hash_u32`, on a Python int."""
    x &= _MASK32
    x ^= x >> 16
    x = (x * 0x7FEB352D) & _MASK32
    x ^= x >> 15
    x = (x * 0x2C1B3C6D) & _MASK32
    return x ^ (x >> 16)


def hash_cells(ix: Tensor, iy: Tensor, seed: int, salt: int = 0) -> Tensor:
    """Hash of integer lattice cells (int64 tensors, any sign) and a seed -> 32-bit int64."""
    s0 = _hash_int(_hash_int(seed) ^ (salt * 0x85EBCA77))
    return hash_u32(hash_u32((ix & _MASK32) ^ s0) ^ (iy & _MASK32))


def hash_float(ix: Tensor, iy: Tensor, seed: int, salt: int = 0, dtype: torch.dtype = torch.float32) -> Tensor:
    """Uniform [0, 1) value per lattice cell."""
    return hash_cells(ix, iy, seed, salt).to(dtype) / 4294967296.0


_TABLE_BITS = 16
_tables: dict[tuple[int, torch.dtype, torch.device], Tensor] = {}


def _lattice_table(seed: int, dtype: torch.dtype, device: torch.device | str = "cpu") -> Tensor:
    """2^16 uniform [0, 1) values for lattice noise, a pure function of the seed (cached per device)."""
    key = (seed, dtype, torch.device(device))
    if key not in _tables:
        ar = torch.arange(1 << _TABLE_BITS, dtype=torch.int64)
        table = (hash_cells(ar, torch.zeros_like(ar), seed, 1).to(torch.float64) / 4294967296.0).to(dtype)
        _tables[key] = table.to(device)
    return _tables[key]


# ---------------------------------------------------------------------------- noise helpers
def _smooth(x: Tensor) -> Tensor:
    return x * x * (3.0 - 2.0 * x)


def _compiled_noise_applies(uv: Tensor, e: Tensor | None) -> bool:
    """May `value_noise` run compiled: CPU float32 or float64 points [N, 2] (footprints [N], [1] or [] of their
    dtype), no autograd?"""
    points = uv.ndim == 2 and uv.shape[1] == 2 and uv.device.type == "cpu" and not uv.requires_grad
    same = e is None or (e.dtype == uv.dtype and e.device == uv.device and not e.requires_grad
                         and e.shape in ((), (1,), (uv.shape[0],)))
    return points and uv.dtype in (torch.float32, torch.float64) and same


def value_noise(uv: Tensor, scale_m: float, seed: int, e: Tensor | None = None) -> Tensor:
    """Smooth 2D value noise in [0, 1] with lattice spacing ``scale_m``. uv [N, 2] -> [N].

    With a footprint ``e`` [N] (metres) the noise fades to its mean 0.5 where e > scale_m / 2
    (gone at e >= 1.5 scale_m): a cheap low-pass filter against aliasing. Float32 and float64 CPU tensors
    without autograd go through `noise_kernel` (the same bits, compiled)."""
    if _compiled_noise_applies(uv, e):
        from egobench.sim import noise_kernel  # loads numba: after the thread set-up (host.setup_threads)

        return noise_kernel.value_noise(uv, scale_m, _lattice_table(seed, uv.dtype), e)
    p = uv / scale_m
    i = torch.floor(p)
    f = _smooth(p - i)
    ix, iy = i[:, 0].long(), i[:, 1].long()
    table = _lattice_table(seed, uv.dtype, uv.device)
    mask = (1 << _TABLE_BITS) - 1
    hx0, hx1 = ix * 0x2C9277B5, (ix + 1) * 0x2C9277B5  # multipliers < 2^31: |product| < 2^63 for |ix| < 2^32
    hy0, hy1 = iy * 0x1B873593, (iy + 1) * 0x1B873593
    a = table[(hx0 ^ hy0) & mask]
    b = table[(hx1 ^ hy0) & mask]
    c = table[(hx0 ^ hy1) & mask]
    d = table[(hx1 ^ hy1) & mask]
    fx, fy = f[:, 0], f[:, 1]
    n = (a + (b - a) * fx) * (1 - fy) + (c + (d - c) * fx) * fy
    if e is None:
        return n
    fade = torch.clamp(1.5 - e / scale_m, 0.0, 1.0)
    return 0.5 + fade * (n - 0.5)


def fbm(uv: Tensor, scale_m: float, seed: int, octaves: int = 4, e: Tensor | None = None) -> Tensor:
    """Fractal sum of value noise, normalised to [0, 1]. uv [N, 2] -> [N]."""
    total = torch.zeros(uv.shape[0], dtype=uv.dtype, device=uv.device)
    amp, norm, s = 1.0, 0.0, scale_m
    for o in range(octaves):
        total = total + amp * value_noise(uv, s, seed + 7919 * o, e)
        norm += amp
        amp *= 0.5
        s *= 0.5
    return total / norm


def _ramp(x: Tensor, e: Tensor | float) -> Tensor:
    """Box-filtered step (filter width ``e`` metres) of the signed distance x: 0 for x << 0, 1 for x >> 0."""
    if isinstance(e, float) and e <= 0:
        return (x > 0).to(x.dtype)
    return torch.clamp(x / e + 0.5, 0.0, 1.0)


def _band(d: Tensor, half_width: float | Tensor, e: Tensor) -> Tensor:
    """Box-filtered coverage of a band |x| <= half_width at distance d >= 0 from its centre line."""
    e = torch.clamp(e, min=1e-9)
    lo = torch.maximum(d - 0.5 * e, -half_width * torch.ones_like(d))
    hi = torch.minimum(d + 0.5 * e, half_width * torch.ones_like(d))
    return torch.clamp(hi - lo, min=0.0) / e


def _mix(c0: RGB, c1: RGB, w: Tensor) -> Tensor:
    a = torch.tensor(c0, dtype=w.dtype, device=w.device)
    b = torch.tensor(c1, dtype=w.dtype, device=w.device)
    return a + (b - a) * w[:, None]


def _palette(tex: Texture, idx: Tensor, dtype: torch.dtype) -> Tensor:
    pal = torch.tensor(tex.colors, dtype=dtype, device=idx.device)
    return pal[idx % len(tex.colors)]


def _line_mask(coord: Tensor, period: float, half_width: float, e: Tensor) -> Tensor:
    """Coverage of lines of half-width ``half_width`` centred on multiples of ``period``,
    box-filtered over ``e`` [N]; fades to the mean 2 hw / period as e approaches the period. coord [N] -> [N]."""
    d = torch.abs(coord - period * torch.round(coord / period))
    cover = _band(d, half_width, e)
    fade = torch.clamp(2.0 * e / period - 1.0, 0.0, 1.0)
    return cover + fade * (2.0 * half_width / period - cover)


# -------------------------------------------------------------------------------- the kinds
def _plain(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    n = fbm(uv, 1.0, tex.seed, 3, e=e)
    return _mix(tex.color(0), tex.color(0), n) * (0.85 + 0.3 * n)[:, None]  # colour 0 modulated


def _noise(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    n = fbm(uv, tex.scale_m, tex.seed, 5, e=e)
    w = torch.clamp((n - 0.5) * 2.5 + 0.5, 0.0, 1.0)
    return _mix(tex.color(0), tex.color(1), w)


def _checker(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    s = tex.scale_m
    # signed distance-like term per axis: positive in "even" half-periods
    fx = torch.remainder(uv[:, 0], s) - 0.5 * s
    fy = torch.remainder(uv[:, 1], s) - 0.5 * s
    ax = _ramp(torch.minimum(torch.abs(fx), 0.5 * s - torch.abs(fx)) * torch.sign(fx), e)
    ay = _ramp(torch.minimum(torch.abs(fy), 0.5 * s - torch.abs(fy)) * torch.sign(fy), e)
    w = ax + ay - 2 * ax * ay  # XOR of the two box-filtered square waves (exact for a separable box filter)
    w = w + torch.clamp(2.0 * e / s - 1.0, 0.0, 1.0) * (0.5 - w)  # footprint beyond a square: fade to the mean
    return _mix(tex.color(0), tex.color(1), w)


def _grid(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    s, hw = tex.scale_m, 0.03 * tex.scale_m
    m = torch.maximum(_line_mask(uv[:, 0], s, hw, e), _line_mask(uv[:, 1], s, hw, e))
    return _mix(tex.color(0), tex.color(1), m)


def _tiles(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    s = tex.scale_m
    cell = torch.floor(uv / s).long()
    var = hash_float(cell[:, 0], cell[:, 1], tex.seed, 3, uv.dtype)
    base = _mix(tex.color(0), tex.color(2) if len(tex.colors) > 2 else tex.color(0), var)
    base = base * (0.8 + 0.4 * fbm(uv, 0.05 * s + 0.01, tex.seed, 3, e=e))[:, None]
    joint = torch.maximum(_line_mask(uv[:, 0], s, 0.02 * s, e), _line_mask(uv[:, 1], s, 0.02 * s, e))
    joint_c = torch.tensor(tex.color(1), dtype=uv.dtype, device=uv.device)
    return base + (joint_c - base) * joint[:, None]


# Stroke glyphs: 16 segments on a 3x3 node grid of the glyph box [0, 1]^2 (x right, y up).
_SEGMENTS = torch.tensor(
    [
        [0, 0, 0.5, 0], [0.5, 0, 1, 0], [0, 0.5, 0.5, 0.5], [0.5, 0.5, 1, 0.5], [0, 1, 0.5, 1], [0.5, 1, 1, 1],
        [0, 0, 0, 0.5], [0, 0.5, 0, 1], [0.5, 0, 0.5, 0.5], [0.5, 0.5, 0.5, 1], [1, 0, 1, 0.5], [1, 0.5, 1, 1],
        [0, 0, 0.5, 0.5], [0.5, 0.5, 1, 1], [1, 0, 0.5, 0.5], [0.5, 0.5, 0, 1],
    ],
    dtype=torch.float64,
)  # [16, 4] (x0, y0, x1, y1)


def glyph_ink(uv: Tensor, char_height_m: float, seed: int, e: Tensor | float = 0.002,
              blank_prob: float = 0.2, line_gap: float = 0.7, stroke_frac: float = 0.14) -> Tensor:
    """Ink coverage in [0, 1] of rows of pseudo-random stroke characters. uv [N, 2] -> [N].

    Characters are ``char_height_m`` tall and ``0.5 * char_height_m`` wide, in cells of
    ``0.65 * char_height_m``; rows are separated by ``line_gap * char_height_m``. Each cell's
    glyph is a random subset of 16 strokes (hash of the cell and the seed); a fraction
    ``blank_prob`` of cells are spaces, which splits rows into words.
    """
    h = char_height_m
    cell_w, row_h, glyph_w = 0.65 * h, (1.0 + line_gap) * h, 0.5 * h
    cx = torch.floor(uv[:, 0] / cell_w)
    cy = torch.floor(uv[:, 1] / row_h)
    lx = uv[:, 0] - cx * cell_w  # metres inside the cell
    ly = uv[:, 1] - cy * row_h - line_gap * h  # glyph box starts above the gap
    bits = hash_cells(cx.long(), cy.long(), seed, 11)
    blank = hash_float(cx.long(), cy.long(), seed, 12, uv.dtype) < blank_prob
    seg = _SEGMENTS.to(device=uv.device, dtype=uv.dtype)
    x0, y0 = seg[:, 0] * glyph_w + 0.075 * h, seg[:, 1] * h
    x1, y1 = seg[:, 2] * glyph_w + 0.075 * h, seg[:, 3] * h
    dx, dy = x1 - x0, y1 - y0
    px = lx[:, None] - x0  # [N, 16]
    py = ly[:, None] - y0
    t = torch.clamp((px * dx + py * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    dist = torch.sqrt((px - t * dx) ** 2 + (py - t * dy) ** 2)
    on = ((bits[:, None] >> torch.arange(16, device=uv.device)) & 1).bool()
    e_t = torch.as_tensor(e, dtype=uv.dtype, device=uv.device).expand(uv.shape[0])
    cover = _band(dist, 0.5 * stroke_frac * h, e_t[:, None]) * on.to(uv.dtype)
    ink = cover.amax(dim=1)
    return torch.where(blank, torch.zeros_like(ink), ink)


def _text(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    ink = glyph_ink(uv, tex.scale_m, tex.seed, e)
    return _mix(tex.color(0), tex.color(1), ink)


def _bricks(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    bw, bh, mortar = tex.scale_m, 0.33 * tex.scale_m, 0.045 * tex.scale_m
    row = torch.floor(uv[:, 1] / bh)
    u_shift = uv[:, 0] + 0.5 * bw * torch.remainder(row, 2.0)
    col = torch.floor(u_shift / bw)
    var = hash_float(col.long(), row.long(), tex.seed, 21, uv.dtype)
    base = _mix(tex.color(0), tex.color(2) if len(tex.colors) > 2 else tex.color(0), var)
    base = base * (0.75 + 0.5 * fbm(uv, 0.03, tex.seed, 3, e=e))[:, None]
    ju = _line_mask(u_shift, bw, 0.5 * mortar, e)
    jv = _line_mask(uv[:, 1], bh, 0.5 * mortar, e)
    joint = torch.maximum(ju, jv)
    mortar_c = torch.tensor(tex.color(1), dtype=uv.dtype, device=uv.device)
    return base + (mortar_c - base) * joint[:, None]


def _planks(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    w = tex.scale_m
    length = 12.0 * w
    row = torch.floor(uv[:, 1] / w)
    offset = hash_float(row.long(), torch.zeros_like(row).long(), tex.seed, 31, uv.dtype) * length
    col = torch.floor((uv[:, 0] + offset) / length)
    var = hash_float(col.long(), row.long(), tex.seed, 32, uv.dtype)
    # grain: noise stretched along u
    grain_uv = torch.stack([uv[:, 0] * 0.08, uv[:, 1] + 13.0 * var], dim=1)
    g = fbm(grain_uv, 0.004, tex.seed + 1, 3, e=e)
    base = _mix(tex.color(0), tex.color(2) if len(tex.colors) > 2 else tex.color(0), var)
    base = base * (0.7 + 0.6 * g)[:, None]
    seam = torch.maximum(_line_mask(uv[:, 1], w, 0.004, e), _line_mask(uv[:, 0] + offset, length, 0.003, e))
    seam_c = torch.tensor(tex.color(1), dtype=uv.dtype, device=uv.device)
    return base + (seam_c - base) * seam[:, None]


def _books(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    w = tex.scale_m  # spine width
    shelf_h = 0.32  # books stand in rows of this height (v), the shelf board lies at v = k * shelf_h
    row = torch.floor(uv[:, 1] / shelf_h)
    col = torch.floor(uv[:, 0] / w)
    fv = uv[:, 1] - row * shelf_h
    height = (0.55 + 0.35 * hash_float(col.long(), row.long(), tex.seed, 41, uv.dtype)) * shelf_h
    pal_idx = hash_cells(col.long(), row.long(), tex.seed, 42) % 7
    spine = _palette(tex, pal_idx + 2, uv.dtype)  # colours 2.. are cover colours
    spine = spine * (0.8 + 0.4 * fbm(uv, 0.02, tex.seed, 2, e=e))[:, None]
    # title strokes along the spine: small glyphs in a rotated frame (v along the spine)
    title_uv = torch.stack([uv[:, 1] + 3.1 * col, uv[:, 0] - col * w - 0.3 * w], dim=1)
    ink = glyph_ink(title_uv, 0.35 * w, tex.seed + 5, e, blank_prob=0.35, line_gap=3.0)
    ink = ink * ((fv > 0.25 * shelf_h) & (fv < height - 0.05 * shelf_h)).to(uv.dtype)
    light = torch.tensor(tex.color(1), dtype=uv.dtype, device=uv.device)
    spine = spine + (light - spine) * ink[:, None]
    gap = _line_mask(uv[:, 0], w, 0.0025, e)
    back = torch.tensor(tex.color(0), dtype=uv.dtype, device=uv.device)  # shelf back / shadow
    book = _ramp(height - fv, e) * (1 - gap)
    return back + (spine - back) * book[:, None]


def _poster(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    s = tex.scale_m  # character height; colour blocks are 6x larger
    block = torch.floor(uv / (6 * s)).long()
    idx = hash_cells(block[:, 0], block[:, 1], tex.seed, 51) % max(1, len(tex.colors) - 2)
    base = _palette(tex, idx + 2, uv.dtype) if len(tex.colors) > 2 else _mix(tex.color(0), tex.color(0), uv[:, 0])
    n = fbm(uv, 2 * s, tex.seed, 3, e=e)
    base = base * (0.7 + 0.6 * n)[:, None]
    ink = glyph_ink(uv, s, tex.seed + 3, e, blank_prob=0.3, line_gap=1.2)
    ink_c = torch.tensor(tex.color(1), dtype=uv.dtype, device=uv.device)
    return base + (ink_c - base) * ink[:, None]


def _window(uv: Tensor, tex: Texture, e: Tensor) -> Tensor:
    s = tex.scale_m  # pane size
    bars = torch.maximum(_line_mask(uv[:, 0], s, 0.04 * s, e), _line_mask(uv[:, 1], s, 0.04 * s, e))
    # the view through the pane: brighter towards the top, with soft cloud-like variation
    n = fbm(uv, 4 * s, tex.seed, 3, e=e)
    pane = _mix(tex.color(0), tex.color(0), n) * (0.75 + 0.5 * n)[:, None]  # colour 0 modulated
    frame = torch.tensor(tex.color(1), dtype=uv.dtype, device=uv.device)
    return pane + (frame - pane) * bars[:, None]


_KINDS: dict[str, Callable[[Tensor, Texture], Tensor]] = {
    "plain": _plain, "noise": _noise, "checker": _checker, "grid": _grid, "tiles": _tiles, "text": _text,
    "bricks": _bricks, "planks": _planks, "books": _books, "poster": _poster, "window": _window,
}


def evaluate_texture(tex: Texture, uv: Tensor, footprint_m: Tensor | float | None = None) -> Tensor:
    """Albedo of ``tex`` at surface coordinates ``uv`` [N, 2] (metres) -> [N, 3] in [0, 1].

    ``footprint_m`` ([N] or scalar, metres): the pixel's size on the surface; patterns are
    box-filtered over max(edge_m, footprint_m). None: filtered over edge_m only.
    """
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"evaluate_texture: uv must have shape [N, 2] (metres), got {tuple(uv.shape)}")
    if not torch.is_floating_point(uv):
        raise ValueError(f"evaluate_texture: uv must be a floating tensor, got {uv.dtype}")
    if uv.shape[0] == 0:
        return uv.new_zeros((0, 3))
    e = torch.full((uv.shape[0],), float(tex.edge_m), dtype=uv.dtype, device=uv.device)
    if footprint_m is not None:
        fp = torch.as_tensor(footprint_m, dtype=uv.dtype, device=uv.device)
        if not bool(torch.isfinite(fp).all()) or bool((fp < 0).any()):
            raise ValueError("evaluate_texture: footprint_m must be finite and >= 0 (metres)")
        e = torch.maximum(e, fp.expand(uv.shape[0]))
    e = torch.clamp(e, min=1e-6)
    albedo = _KINDS[tex.kind](uv, tex, e)
    if tex.grain > 0:
        g = value_noise(uv, 0.004, tex.seed + 99991, e)  # ~4 mm grain: the fine detail a camera resolves up close
        albedo = albedo * (1.0 + tex.grain * (2.0 * g - 1.0))[:, None]
    return torch.clamp(albedo, 0.0, 1.0)
