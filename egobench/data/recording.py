"""In-memory form of a recording, shared by synthetic and real data.

A `Recording` is one rectified camera stream under one calibration (``online`` = VIBA, or
``factory``), as the authors' preprocessing produces it, plus the device trajectory and the
semi-dense points. Readers (`egobench.data.reader`) build it from disk; nothing here reads
files except `Recording.load_image`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
from torch import Tensor

from egobench.camera.pinhole import Pinhole

Calibration = Literal["online", "factory"]

#: Every HOLDOUT_EVERY-th frame (0, 8, 16, ... after sorting by time) is held out for testing.
HOLDOUT_EVERY = 8


@dataclass
class SparseDepth:
    """Semi-dense SLAM points visible in one frame (rectified pixel coordinates)."""

    uv: np.ndarray  # [P, 2] rectified pixel coordinates (u, v), pixel centres at integers
    z: np.ndarray  # [P] depth along the camera z axis, metres
    inv_dist_std: np.ndarray  # [P] inverse-distance standard deviation, 1/m
    dist_std: np.ndarray  # [P] distance standard deviation, m


@dataclass
class Frame:
    """One rectified image and its capture metadata (device clock, nanoseconds)."""

    index: int  # position in time order, 0-based
    image_path: Path
    timestamp_ns: int  # time of the centre-row pose `T_world_camera` (device clock)
    read_start_ns: int  # first raw row starts exposing (device clock, calibrated time offset applied)
    read_end_ns: int  # last raw row starts exposing
    exposure_s: float  # exposure duration, seconds
    gain: float  # analog gain (1 = base ISO)
    T_world_camera: Tensor  # [4, 4] float64, rectified camera to world at timestamp_ns
    T_device_camera: Tensor  # [4, 4] float64, rectified camera to device (extrinsics)
    sparse_depth: SparseDepth | None = None

    @property
    def readout_s(self) -> float:
        return (self.read_end_ns - self.read_start_ns) * 1e-9


@dataclass
class Recording:
    """One rectified camera stream of a recording under one calibration."""

    root: Path  # the folder holding transforms.json
    name: str
    calibration: Calibration
    camera: Pinhole  # rectified pinhole camera (same for every frame)
    camera_model: str  # "linear" (pinhole) as in the authors' transforms.json
    frames: list[Frame]  # sorted by timestamp_ns
    vignette: Tensor  # [H, W] float32 lens shading in the rectified image, 0..1
    mask: Tensor  # [H, W] bool, valid rectified pixels
    row_time_ratio: Tensor  # [H, W] float32 R(u): raw row / raw height, 0..1 (see camera.rectify)
    trajectory: "object"  # egobench.geometry.Trajectory of T_world_device (1 kHz)
    points_world: Tensor  # [P, 3] float32 semi-dense points (filtered), metres
    ground_truth: Path | None = None  # folder with clean radiance, depth, normals (synthetic only)
    meta: dict = field(default_factory=dict)  # free-form: scene kind, device profile, sim config

    @property
    def train_frames(self) -> list[Frame]:
        return [f for f in self.frames if f.index % HOLDOUT_EVERY != 0]

    @property
    def test_frames(self) -> list[Frame]:
        return [f for f in self.frames if f.index % HOLDOUT_EVERY == 0]

    def ground_truth_file(self, kind: str, frame: Frame) -> Path | None:
        """The frame's ground-truth map ``kind`` ("depth", "normal", "radiance"; .npy), or None if absent."""
        if self.ground_truth is None:
            return None
        path = Path(self.ground_truth) / kind / f"{frame.index:05d}.npy"
        return path if path.is_file() else None

    def load_image(self, frame: Frame) -> Tensor:
        """The frame's image as float32 [H, W, 3] in 0..1 (gamma-encoded, as captured)."""
        img = cv2.imread(str(frame.image_path), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"{frame.image_path}: image of frame {frame.index} is missing or unreadable")
        expected = (self.camera.height, self.camera.width)
        if img.shape[:2] != expected:
            raise ValueError(
                f"{frame.image_path}: frame {frame.index} is {img.shape[1]}x{img.shape[0]}, "
                f"the calibration says {expected[1]}x{expected[0]}"
            )
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        return torch.from_numpy(img).float().div_(255.0)
