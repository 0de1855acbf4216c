"""Head motion: a 1 kHz ``T_world_device`` trajectory of a person walking and looking around.

Frames (read this before composing cameras)
-------------------------------------------
The trajectory moves a **look frame**: OpenCV axes, +z = where the head looks (forward),
+x = right, +y = down, origin at the eyes (about 1.6 m above the floor). A camera with
``T_device_camera = I`` looks where the head looks; `egobench.sim.capture.device_trajectory`
re-expresses it as the device frame of a real device profile (whose RGB camera is rotated
against the device frame). World: metres, z up, gravity -z (`egobench.sim.world`).

Model (every term is a documented field of `HeadMotionConfig`)
---------------------------------------------------------------
- Walking (``normal``/``fast``): a centripetal Catmull-Rom spline through random waypoints of
  the scene's walk region (a box, or a ring around an object), travelled at a speed that
  varies slowly around ``walk_speed_m_s`` and pulses at the step frequency.
- Gait: vertical head bob (``bob_amplitude_m`` at the step frequency), lateral sway and head
  yaw/roll at the stride frequency (half the step frequency), head pitch at the step frequency.
- Gaze: mostly along the walking direction, pitched down by ``gaze_pitch_deg``; every
  ``attention_interval_s`` on average attention shifts to a look target of the scene (or back
  to the path), with minimum-jerk transitions. Ring regions (object captures) always look at the
  first look target. Small-amplitude look-around: band-limited Gaussian noise on yaw and pitch.
- ``fast``: in addition, saccade-like head turns (minimum-jerk yaw out by 30-90 deg and back
  after a short dwell), whose peak angular speed is ``turn_rate_deg_s``.
- ``static``: standing at one point (postural sway of a few mm), slow gaze shifts, small
  look-around.
Deterministic from the seed: `numpy.random.default_rng([seed, ...])` only.

The ``normal`` defaults are fitted to the real 11.4 s Aria walk in
``aria_mps_sample/closed_loop_trajectory.csv`` (angular speed p25/p50/p75/p90/p99 =
14.5/27.0/39.6/50.6/76.7 deg/s, linear speed p50 0.75 m/s): see `egobench motion-stats`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import pandas as pd
import torch

from egobench import portable_math as pm
from egobench.geometry import Trajectory

if TYPE_CHECKING:  # pragma: no cover
    from egobench.sim.world import Scene, WalkRegion

MotionSetting = Literal["normal", "fast", "static"]
MOTION_SETTINGS: tuple[str, ...] = ("normal", "fast", "static")

#: Optical axis of the Aria RGB camera in the Aria device frame (third column of R_device_camera of
#: the camera-rgb entry in aria_mps_sample/online_calibration.jsonl, rounded). Used by
#: `replay_trajectory` to find where a real wearer was looking.
ARIA_RGB_AXIS_DEVICE: tuple[float, float, float] = (0.0922, -0.6250, 0.7752)


@dataclass
class HeadMotionConfig:
    """Parameters of the head-motion model (units in the names; sources in the comments)."""

    duration_s: float = 15.0  # trajectory length, seconds
    setting: MotionSetting = "normal"  # normal walk, fast (quick head turns) or static (standing)
    rate_hz: float = 1000.0  # sampling rate; MPS closed-loop trajectories are 1 kHz (docs/paper-notes.md §4)
    start_ns: int = 0  # device-clock time of the first sample, ns
    walk_speed_m_s: float = 0.75  # mean walking speed: median of the real sample (0.75 m/s); slow indoor walking
    speed_variation: float = 0.2  # relative std of slow speed changes (sample: p25/p75 = 0.44/0.89 m/s)
    step_frequency_hz: float = 1.9  # cadence ~114 steps/min (Hirasaki et al. 1999, Exp Brain Res 127: 1.4-2.5 Hz)
    bob_amplitude_m: float = 0.015  # vertical head bob amplitude (3 cm peak-to-peak; Hirasaki et al. 1999: 2-6 cm)
    sway_amplitude_m: float = 0.02  # lateral head sway at the stride frequency (half the step frequency), metres
    gait_pitch_deg: float = 1.0  # head pitch oscillation at the step frequency (Pozzo et al. 1990, Exp Brain Res 82: a few deg)
    gait_yaw_deg: float = 1.5  # head yaw oscillation at the stride frequency (Grossman et al. 1988, Exp Brain Res 70)
    gait_roll_deg: float = 1.5  # head roll oscillation at the stride frequency (Grossman et al. 1988)
    gaze_pitch_deg: float = -10.0  # mean gaze pitch while walking (negative = down, towards the path ahead)
    attention_interval_s: float = 3.0  # mean time between attention shifts to a look target or back to the path
    attention_probability: float = 0.6  # chance that an attention shift goes to a look target (else: straight ahead)
    attention_shift_s: float = 2.5  # duration of a minimum-jerk gaze shift, s (fitted: sample p99 77 deg/s)
    attention_max_deg: float = 45.0  # largest yaw offset of the gaze from the walking direction, deg
    max_turn_rate_deg_s: float = 30.0  # walkers slow down in bends so that the path turns at most this fast (fitted)
    look_around_deg: float = 4.0  # std of the band-limited look-around noise on yaw (pitch: 0.6x), deg (fitted)
    look_around_rate_hz: float = 1.0  # bandwidth (Gaussian spectrum sigma) of the look-around noise, Hz (fitted)
    turn_rate_deg_s: float = 400.0  # fast: peak speed of quick head turns ("several hundred deg/s", paper; Zangemeister & Stark 1981)
    turns_per_s: float = 0.5  # fast: rate of quick head turns (each goes out and back), 1/s
    turn_amplitude_deg: tuple[float, float] = (30.0, 90.0)  # fast: range of head-turn amplitudes, deg
    turn_dwell_s: tuple[float, float] = (0.3, 1.0)  # fast: time spent looking aside before turning back, s

    def validate(self) -> None:
        """ValueError naming the field and the expected form."""
        if self.setting not in MOTION_SETTINGS:
            raise ValueError(f"HeadMotionConfig.setting: expected one of {list(MOTION_SETTINGS)}, got {self.setting!r}")
        positive = ("duration_s", "rate_hz", "walk_speed_m_s", "step_frequency_hz", "attention_interval_s",
                    "attention_shift_s", "attention_max_deg", "max_turn_rate_deg_s", "look_around_rate_hz",
                    "turn_rate_deg_s")
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"HeadMotionConfig.{name}: expected a positive finite number, got {v!r}")
        non_negative = ("speed_variation", "bob_amplitude_m", "sway_amplitude_m", "gait_pitch_deg", "gait_yaw_deg",
                        "gait_roll_deg", "look_around_deg", "turns_per_s")
        for name in non_negative:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"HeadMotionConfig.{name}: expected a finite number >= 0, got {v!r}")
        if not 0 <= self.attention_probability <= 1:
            raise ValueError(f"HeadMotionConfig.attention_probability: expected a value in [0, 1], got {self.attention_probability}")
        for name in ("turn_amplitude_deg", "turn_dwell_s"):
            lo, hi = getattr(self, name)
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise ValueError(f"HeadMotionConfig.{name}: expected (low, high) with 0 < low <= high, got {(lo, hi)}")
        if self.duration_s * self.rate_hz < 2:
            raise ValueError("HeadMotionConfig: duration_s * rate_hz must give at least 2 samples")
        if int(self.start_ns) != self.start_ns:
            raise ValueError(f"HeadMotionConfig.start_ns: expected an integer (ns), got {self.start_ns!r}")

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]


# ----------------------------------------------------------------------------- helpers
def min_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk profile 10 t^3 - 15 t^4 + 6 t^5 on [0, 1] (clamped outside); peak slope 1.875."""
    x = np.clip(tau, 0.0, 1.0)
    return x ** 3 * (10.0 - 15.0 * x + 6.0 * x * x)


def band_limited_noise(rng: np.random.Generator, n: int, rate_hz: float, sigma_hz: float) -> np.ndarray:
    """Zero-mean, unit-std Gaussian noise [n] with a Gaussian power spectrum of width sigma_hz."""
    white = rng.standard_normal(n)
    spec = np.fft.rfft(white)
    f = np.fft.rfftfreq(n, d=1.0 / rate_hz)
    spec *= pm.exp(-0.5 * (f / sigma_hz) ** 2)
    spec[0] = 0.0
    x = np.fft.irfft(spec, n)
    std = float(x.std())
    return x / std if std > 0 else x


def rotation_from_yaw_pitch_roll(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R_world_look [M, 3, 3] (radians, z-up world): look frame +z = forward, +x = right, +y = down.

    yaw: heading about world z (0 = looking along world +x), pitch: up positive, roll: about the
    viewing axis. R = Rz(yaw) @ R0 @ Rx(pitch) @ Rz(roll), R0 = level look along +x.
    """
    R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    M = len(yaw)
    Rz = np.zeros((M, 3, 3)); Rz[:, 0, 0] = cy; Rz[:, 0, 1] = -sy; Rz[:, 1, 0] = sy; Rz[:, 1, 1] = cy; Rz[:, 2, 2] = 1
    # pitch up = rotation about the look frame's x (right) axis by +pitch (its +z tilts towards -y = up)
    Rx = np.zeros((M, 3, 3)); Rx[:, 0, 0] = 1; Rx[:, 1, 1] = cp; Rx[:, 1, 2] = -sp; Rx[:, 2, 1] = sp; Rx[:, 2, 2] = cp
    Rr = np.zeros((M, 3, 3)); Rr[:, 0, 0] = cr; Rr[:, 0, 1] = -sr; Rr[:, 1, 0] = sr; Rr[:, 1, 1] = cr; Rr[:, 2, 2] = 1
    return pm.matmul(pm.matmul(pm.matmul(Rz, R0), Rx), Rr)


def _catmull_rom(points: np.ndarray, samples_per_segment: int = 200) -> np.ndarray:
    """Centripetal Catmull-Rom spline through points [K, 2] (K >= 2) -> dense polyline [S, 2]."""
    P = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    out = []
    u = np.linspace(0.0, 1.0, samples_per_segment, endpoint=False)[:, None]
    for i in range(1, len(P) - 2):
        p0, p1, p2, p3 = P[i - 1], P[i], P[i + 1], P[i + 2]
        t0 = 0.0
        t1 = t0 + max(math.hypot(*(p1 - p0)), 1e-6) ** 0.5
        t2 = t1 + max(math.hypot(*(p2 - p1)), 1e-6) ** 0.5
        t3 = t2 + max(math.hypot(*(p3 - p2)), 1e-6) ** 0.5
        t = t1 + u * (t2 - t1)
        a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
        a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
        a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
        b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
        b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
        out.append((t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2)
    out.append(points[-1:])
    return np.concatenate(out)


def _waypoints(region: "WalkRegion", rng: np.random.Generator, length_m: float) -> np.ndarray:
    """Waypoints [K, 2] inside the region whose polyline is at least length_m long."""
    if region.kind == "ring":
        r_mid = 0.5 * (region.radius_min_m + region.radius_max_m)
        step = 0.6  # rad between waypoints: ~0.7 m at 1.25 m radius
        k = max(3, int(math.ceil(length_m * 1.3 / (step * r_mid))) + 2)
        ang = rng.uniform(0, 2 * np.pi) + step * np.arange(k) * (1 if rng.uniform() < 0.5 else -1)
        ang = ang + rng.uniform(-0.1, 0.1, k)
        rad = rng.uniform(region.radius_min_m, region.radius_max_m, k)
        return np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1) + np.asarray(region.center_xy)
    pts = [region.sample_xy(rng, 1)[0]]
    heading = rng.uniform(0, 2 * np.pi)
    total = 0.0
    diag = float(np.hypot(*region.half_size_xy))
    while total < length_m * 1.3 + 2.0:
        cand = region.sample_xy(rng, 24)
        vec = cand - pts[-1]
        dist = np.linalg.norm(vec, axis=1)
        turn = np.abs(_wrap(pm.arctan2(vec[:, 1], vec[:, 0]) - heading))
        score = -np.abs(dist - min(2.5, diag)) - 3.0 * turn
        j = int(np.argmax(score))
        if dist[j] < 1e-3:
            continue
        heading = math.atan2(float(vec[j, 1]), float(vec[j, 0]))
        total += float(dist[j])
        pts.append(cand[j])
    return np.asarray(pts)


def _slew_limit(x: np.ndarray, max_step: float) -> np.ndarray:
    """Follow x [M] with steps of at most max_step per sample (sequential, O(M))."""
    out = np.empty_like(x)
    cur = float(x[0])
    for i, target in enumerate(x.tolist()):
        cur += min(max(target - cur, -max_step), max_step)
        out[i] = cur
    return out


def _unwrap_angle(a: np.ndarray) -> np.ndarray:
    return np.unwrap(a)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


# ----------------------------------------------------------------------------- simulation
_DEG = np.pi / 180.0  # radians per degree


def _gaussian_smooth(x: np.ndarray, window_s: float, rate: float) -> np.ndarray:
    """x [M] convolved with a Gaussian kernel spanning +-2 sigma over window_s seconds (edges padded)."""
    k = int(window_s * rate) | 1
    kern = pm.exp(-0.5 * (np.linspace(-2, 2, k)) ** 2)
    kern /= kern.sum()
    return pm.convolve_valid(np.pad(x, k // 2, mode="edge"), kern)


def _standing_path(config: HeadMotionConfig, region: "WalkRegion", targets: np.ndarray, rng: np.random.Generator,
                   t: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """static: eye position [M, 3] (m) at one point with a few mm of postural sway, and the body
    heading [M] (rad, about world z) towards the first look target (random without targets)."""
    M = len(t)
    base = region.sample_xy(rng, 1)[0] if region.kind == "box" else region.center_point[:2]
    xy = base + 0.004 * np.stack([band_limited_noise(rng, M, rate, 0.3), band_limited_noise(rng, M, rate, 0.3)], 1)
    z = region.eye_height_m + 0.002 * band_limited_noise(rng, M, rate, 0.3)
    heading = np.full(M, rng.uniform(0, 2 * np.pi))
    if len(targets):  # face the scene: the first target
        d0 = targets[0, :2] - base
        heading[:] = math.atan2(d0[1], d0[0])
    return np.concatenate([xy, z[:, None]], 1), heading


def _walking_effort(config: HeadMotionConfig, rng: np.random.Generator, t: np.ndarray, rate: float,
                    step_phase: float) -> np.ndarray:
    """Arc length [M] (m) walked by time t [M] at full speed: slow speed changes, a 1 s start-up
    ramp and a pulse at the step frequency (bends slow this down: `_bend_slowed_arc_length`)."""
    M = len(t)
    ramp = 0.5 + 0.5 * min_jerk(t / 1.0)
    slow = 1.0 + config.speed_variation * band_limited_noise(rng, M, rate, 0.15)
    v = (config.walk_speed_m_s * np.clip(slow, 0.3, 2.0) * ramp
         * (1.0 + 0.12 * np.sin(2 * np.pi * config.step_frequency_hz * t + step_phase)))
    return np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / rate)])


def _bend_slowed_arc_length(config: HeadMotionConfig, poly: np.ndarray,
                            effort: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the walker is on the path polyline poly [S, 2] at each time -> (s [M] arc length, m;
    arc [S] arc length of the polyline vertices, m; tang [S-1] segment directions, rad).

    Walkers slow down in bends: speed factor g(s) = min(1, omega_max / (v0 kappa(s))); with
    ds/dt = v(t) g(s), the arc length reached at time t solves A(s) = effort(t), A = int ds / g.
    """
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    tang = pm.arctan2(np.diff(poly[:, 1]), np.diff(poly[:, 0]))
    kappa = np.abs(_wrap(np.diff(tang))) / np.maximum(0.5 * (seg[1:] + seg[:-1]), 1e-9)
    kappa = np.concatenate([[kappa[0]], kappa, [kappa[-1]]])  # per polyline vertex
    ks = max(1, int(0.3 / max(float(np.median(seg)), 1e-6)))  # smooth curvature over ~0.3 m
    kappa = pm.convolve_valid(np.pad(kappa, ks, mode="edge"), np.ones(2 * ks + 1) / (2 * ks + 1))
    g = np.clip(config.max_turn_rate_deg_s * _DEG / (config.walk_speed_m_s * np.maximum(kappa, 1e-9)), 0.1, 1.0)
    A = np.concatenate([[0.0], np.cumsum(seg / (0.5 * (g[1:] + g[:-1])))])
    return np.interp(effort, A, arc), arc, tang


def _walking_heading(config: HeadMotionConfig, s: np.ndarray, arc: np.ndarray, tang: np.ndarray,
                     rate: float) -> np.ndarray:
    """Body heading [M] (rad, about world z) at arc lengths s [M] of the path (vertex arc lengths
    arc [S], segment directions tang [S-1])."""
    # the path tangent at s (its rate is v kappa, bounded by the bend slow-down), smoothed over
    # ~1 s of time (a symmetric window: the head anticipates turns)
    tang_v = _unwrap_angle(np.concatenate([tang, tang[-1:]]))  # per polyline vertex
    heading = _gaussian_smooth(np.interp(s, arc, tang_v), 1.0, rate)
    # sharp corners (walk-region edges) would still turn the head faster than people turn
    # while walking: slew-rate limit, then smooth the corners of the limited signal (0.1 s)
    heading = _slew_limit(heading, config.max_turn_rate_deg_s * _DEG / rate)
    return _gaussian_smooth(heading, 0.4, rate)


def _walking_path(config: HeadMotionConfig, region: "WalkRegion", rng: np.random.Generator, t: np.ndarray,
                  rate: float, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """normal/fast: eye position [M, 3] (m) along a spline through random waypoints of the walk
    region, with head bob and lateral sway, and the body heading [M] (rad, about world z)."""
    f_step = config.step_frequency_hz
    effort = _walking_effort(config, rng, t, rate, phase[0])
    poly = _catmull_rom(_waypoints(region, rng, float(effort[-1])))
    s, arc, tang = _bend_slowed_arc_length(config, poly, effort)
    centre = np.stack([np.interp(s, arc, poly[:, 0]), np.interp(s, arc, poly[:, 1])], 1)
    heading = _walking_heading(config, s, arc, tang, rate)
    lateral = np.stack([-np.sin(heading), np.cos(heading)], 1)
    xy = centre + config.sway_amplitude_m * np.sin(np.pi * f_step * t + phase[1])[:, None] * lateral
    z = region.eye_height_m + config.bob_amplitude_m * np.cos(2 * np.pi * f_step * t + phase[2])
    return np.concatenate([xy, z[:, None]], 1), heading


def _attention(config: HeadMotionConfig, region: "WalkRegion", n_targets: int, rng: np.random.Generator,
               t: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Attention weight w [M] in [0, 1] (0 = along the path, 1 = at a look target) and the index
    [M] of the target attended to. Ring regions (object captures) always look at target 0."""
    M = len(t)
    target_of_t = np.zeros(M, dtype=np.int64)
    if region.kind == "ring" and n_targets:
        return np.ones(M), target_of_t
    w = np.zeros(M)
    tt = rng.exponential(config.attention_interval_s) * 0.5
    cur_w, cur_target = 0.0, 0
    shift = config.attention_shift_s
    while tt < t[-1]:
        go_target = n_targets > 0 and rng.uniform() < config.attention_probability
        new_w = 1.0 if go_target else 0.0
        i0 = int(tt * rate)
        if go_target and cur_w == 0.0:
            cur_target = int(rng.integers(n_targets))
            target_of_t[i0:] = cur_target
        elif go_target:  # from one target to another: go through "ahead"
            new_w = 0.0
        prof = cur_w + (new_w - cur_w) * min_jerk((t[i0:] - tt) / shift)
        w[i0:] = prof
        cur_w = new_w
        tt += shift + rng.exponential(config.attention_interval_s)
    return w, target_of_t


def _gaze_angles(config: HeadMotionConfig, region: "WalkRegion", targets: np.ndarray, pos: np.ndarray,
                 heading: np.ndarray, w: np.ndarray, target_of_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gaze (yaw [M], pitch [M]) in radians: the heading pitched by gaze_pitch_deg, blended with
    weight w [M] towards look target target_of_t [M] seen from the eye positions pos [M, 3]."""
    to_t = targets[target_of_t] - pos if len(targets) else np.zeros_like(pos)
    yaw_t = pm.arctan2(to_t[:, 1], to_t[:, 0])
    pitch_t = pm.arctan2(to_t[:, 2], np.hypot(to_t[:, 0], to_t[:, 1]))
    off = _wrap(yaw_t - heading)
    # targets behind the walker are not looked at (fades out between 100 and 150 deg), which
    # also hides the +-180 deg wrap of `off`; the head turns at most 80 deg from the path
    w = w * np.clip((150 * _DEG - np.abs(off)) / (50 * _DEG), 0.0, 1.0) if region.kind != "ring" else w
    off = (np.clip(off, -config.attention_max_deg * _DEG, config.attention_max_deg * _DEG)
           if region.kind != "ring" else off)
    yaw = heading + w * off
    pitch = (1 - w) * (config.gaze_pitch_deg * _DEG) + w * pitch_t
    return yaw, pitch


def _add_gait_and_look_around(config: HeadMotionConfig, rng: np.random.Generator, t: np.ndarray, rate: float,
                              phase: np.ndarray, walking: float, yaw: np.ndarray,
                              pitch: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(yaw, pitch, roll) [M] in radians: gaze plus band-limited look-around noise and, when
    walking (1.0; 0.0 standing), the gait's head oscillations at the step and stride frequencies."""
    M = len(t)
    f_step = config.step_frequency_hz
    la = config.look_around_deg * _DEG * (0.5 if config.setting == "static" else 1.0)
    yaw = yaw + la * band_limited_noise(rng, M, rate, config.look_around_rate_hz)
    pitch = pitch + 0.6 * la * band_limited_noise(rng, M, rate, config.look_around_rate_hz)
    roll = 0.3 * la * band_limited_noise(rng, M, rate, config.look_around_rate_hz)
    yaw = yaw + walking * config.gait_yaw_deg * _DEG * np.sin(np.pi * f_step * t + phase[1] + 0.5)
    roll = roll + walking * config.gait_roll_deg * _DEG * np.sin(np.pi * f_step * t + phase[3])
    pitch = pitch + walking * config.gait_pitch_deg * _DEG * np.sin(2 * np.pi * f_step * t + phase[2] + 1.0)
    return yaw, pitch, roll


def _add_quick_turns(config: HeadMotionConfig, rng: np.random.Generator, t: np.ndarray, yaw: np.ndarray,
                     pitch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """fast: (yaw, pitch) [M] (rad) plus minimum-jerk head turns out and back, peak speed turn_rate_deg_s."""
    tt = rng.exponential(1.0 / config.turns_per_s) * 0.5
    while tt < t[-1]:
        amp = rng.uniform(*config.turn_amplitude_deg) * _DEG * (1 if rng.uniform() < 0.5 else -1)
        dur = 1.875 * abs(amp) / (config.turn_rate_deg_s * _DEG)  # min-jerk peak speed = 1.875 A / T
        dwell = rng.uniform(*config.turn_dwell_s)
        back = tt + dur + dwell
        yaw = yaw + amp * (min_jerk((t - tt) / dur) - min_jerk((t - back) / dur))
        pitch = pitch + 0.15 * amp * (min_jerk((t - tt) / dur) - min_jerk((t - back) / dur))
        tt = back + dur + rng.exponential(1.0 / config.turns_per_s)
    return yaw, pitch


def _pose_matrices(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """T_world_look [M, 4, 4] from gaze angles [M] (rad; pitch clamped to +-80 deg) and eye positions [M, 3]."""
    R = rotation_from_yaw_pitch_roll(yaw, np.clip(pitch, -80 * _DEG, 80 * _DEG), roll)
    T = np.zeros((len(yaw), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = pos
    T[:, 3, 3] = 1.0
    return T


def head_motion_arrays(config: HeadMotionConfig, scene: "Scene", seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The motion model without the Trajectory wrapper -> (t_ns int64 [M], T_world_look float64 [M, 4, 4])."""
    config.validate()
    rng = np.random.default_rng([int(seed), 4242, MOTION_SETTINGS.index(config.setting)])
    region = scene.walk_region
    rate = float(config.rate_hz)
    M = int(round(config.duration_s * rate)) + 1
    t = np.arange(M) / rate
    t_ns = int(config.start_ns) + np.round(np.arange(M) * (1e9 / rate)).astype(np.int64)
    phase = rng.uniform(0, 2 * np.pi, 4)
    targets = np.asarray(scene.look_targets, dtype=np.float64).reshape(-1, 3)
    # every step draws from rng in this order: position, attention, look-around, quick turns
    if config.setting == "static":
        pos, heading = _standing_path(config, region, targets, rng, t, rate)
        walking = 0.0
    else:
        pos, heading = _walking_path(config, region, rng, t, rate, phase)
        walking = 1.0
    w, target_of_t = _attention(config, region, len(targets), rng, t, rate)
    yaw, pitch = _gaze_angles(config, region, targets, pos, heading, w, target_of_t)
    yaw, pitch, roll = _add_gait_and_look_around(config, rng, t, rate, phase, walking, yaw, pitch)
    if config.setting == "fast" and config.turns_per_s > 0:
        yaw, pitch = _add_quick_turns(config, rng, t, yaw, pitch)
    return t_ns, _pose_matrices(yaw, pitch, roll, pos)


def simulate_head_motion(config: HeadMotionConfig, scene: "Scene", seed: int) -> "Trajectory":
    """A 1 kHz (config.rate_hz) trajectory of the look frame (+z = gaze) in ``scene``'s world."""
    t_ns, T = head_motion_arrays(config, scene, seed)
    return Trajectory(torch.from_numpy(t_ns), torch.from_numpy(T))


# ----------------------------------------------------------------------------- replay
def _gravity_alignment(gravity_world: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking the measured gravity direction to -z."""
    g = gravity_world / np.linalg.norm(gravity_world)
    target = np.array([0.0, 0.0, -1.0])
    v = np.cross(g, target)
    c = float(g @ target)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def _read_gravity(path: Path) -> np.ndarray:
    """Mean gravity_{x,y,z}_world of an MPS csv; (0, 0, -9.81) when the columns are absent."""
    cols = ["gravity_x_world", "gravity_y_world", "gravity_z_world"]
    header = pd.read_csv(path, nrows=0).columns
    if not all(c in header for c in cols):
        return np.array([0.0, 0.0, -9.81])
    g = pd.read_csv(path, usecols=cols).to_numpy(dtype=np.float64).mean(0)
    if not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-6:
        raise ValueError(f"{path}: gravity_{{x,y,z}}_world columns must hold a finite non-zero vector, got {g}")
    return g


def replay_trajectory(path_csv: str | Path, scene: "Scene", rgb_axis_device: tuple[float, float, float] = ARIA_RGB_AXIS_DEVICE,
                      yaw_candidates: int = 72) -> "Trajectory":
    """Replay a real MPS closed_loop_trajectory.csv in ``scene`` (look frame, like simulate_head_motion).

    1. Gravity-align: the mean ``gravity_*_world`` of the file is rotated onto world -z.
    2. Look frame: T_world_look = T_world_device @ [R_device_look | 0], a constant rotation whose
       +z is the RGB optical axis in the device frame (``rgb_axis_device``) and whose +y is the
       mean gravity direction in the device frame projected orthogonally (image "down").
       Right-multiplying by a constant rotation with zero translation keeps the angular speed and
       the linear speed of the origin exactly.
    3. Re-centre: a rotation about z and a translation put the first sample at eye height inside
       the walk region; among ``yaw_candidates`` yaws x a grid of start points the one keeping
       most of the path inside the walk region is used. Timestamps are kept.
    """
    path = Path(path_csv)
    real = Trajectory.from_mps_csv(path)
    T = real.T_world_device.numpy().copy()
    R_align = _gravity_alignment(_read_gravity(path))
    T[:, :3, :3] = R_align @ T[:, :3, :3]
    T[:, :3, 3] = T[:, :3, 3] @ R_align.T
    # constant device -> look rotation
    z_l = np.asarray(rgb_axis_device, dtype=np.float64)
    if z_l.shape != (3,) or not np.isfinite(z_l).all() or np.linalg.norm(z_l) < 1e-9:
        raise ValueError(f"replay_trajectory(rgb_axis_device): expected a non-zero 3-vector, got {rgb_axis_device}")
    z_l = z_l / np.linalg.norm(z_l)
    down_dev = (T[:, :3, :3].transpose(0, 2, 1) @ np.array([0.0, 0.0, -1.0])).mean(0)
    y_l = down_dev - (down_dev @ z_l) * z_l
    if np.linalg.norm(y_l) < 1e-6:
        raise ValueError(f"{path}: the RGB axis is parallel to gravity on average; cannot define 'down'")
    y_l /= np.linalg.norm(y_l)
    R_device_look = np.stack([np.cross(y_l, z_l), y_l, z_l], 1)
    T[:, :3, :3] = T[:, :3, :3] @ R_device_look
    # re-centre in the walk region
    region = scene.walk_region
    p = T[:, :3, 3]
    rel = p[:: max(1, len(p) // 400), :2] - p[0, :2]  # subsampled path relative to the start
    if region.kind == "box":
        gx = np.linspace(-1, 1, 9) * region.half_size_xy[0] + region.center_xy[0]
        gy = np.linspace(-1, 1, 9) * region.half_size_xy[1] + region.center_xy[1]
        starts = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    else:
        r_mid = 0.5 * (region.radius_min_m + region.radius_max_m)
        a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        starts = np.stack([r_mid * np.cos(a), r_mid * np.sin(a)], 1) + np.asarray(region.center_xy)
    yaws = np.linspace(0, 2 * np.pi, yaw_candidates, endpoint=False)
    c, s = np.cos(yaws), np.sin(yaws)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # [Y, 2, 2]
    moved = np.einsum("yij,nj->yni", rot, rel)  # [Y, n, 2]
    cand = starts[None, :, None, :] + moved[:, None]  # [Y, S, n, 2]
    cand3 = np.concatenate([cand, np.full(cand.shape[:-1] + (1,), region.eye_height_m)], -1)
    score = region.contains(cand3).mean(-1)  # [Y, S]
    # prefer starts near the region centre on ties (deterministic)
    score = score - 1e-6 * np.linalg.norm(starts - np.asarray(region.center_xy), axis=1)[None]
    yi, si = np.unravel_index(int(np.argmax(score)), score.shape)
    Rz = np.array([[c[yi], -s[yi], 0.0], [s[yi], c[yi], 0.0], [0.0, 0.0, 1.0]])
    offset = np.array([*starts[si], region.eye_height_m]) - Rz @ p[0]
    T_new = np.eye(4)
    T_new[:3, :3] = Rz
    T_new[:3, 3] = offset
    return Trajectory(real.t_ns, torch.from_numpy(T_new @ T))
