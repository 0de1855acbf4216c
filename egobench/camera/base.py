"""The protocol every egobench camera model follows (pixel centres at integer coordinates)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor


@runtime_checkable
class CameraModel(Protocol):
    """A central camera: ``project`` maps camera-frame points (OpenCV axes, metres) to pixels.

    Pixel (column i, row j) has its centre at (u, v) = (i, j) (see ``camera/pinhole.py``).
    """

    width: int
    height: int

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """points_cam [..., 3] -> (pixels [..., 2], valid [...] bool)."""
        ...

    def unproject(self, pixels: Tensor) -> Tensor:
        """pixels [..., 2] -> rays [..., 3] (unit length for fisheye models, z = 1 for Pinhole)."""
        ...

    def scaled(self, factor: float) -> "CameraModel":
        """The same camera at ``factor`` times the resolution."""
        ...


def check_points(points_cam: Tensor, who: str) -> None:
    """ValueError unless points_cam is a [..., 3] tensor."""
    if not isinstance(points_cam, Tensor) or points_cam.ndim < 1 or points_cam.shape[-1] != 3:
        shape = tuple(points_cam.shape) if isinstance(points_cam, Tensor) else type(points_cam).__name__
        raise ValueError(f"{who}: points_cam must be a tensor of shape [..., 3], got {shape}")


def check_pixels(pixels: Tensor, who: str) -> None:
    """ValueError unless pixels is a [..., 2] tensor."""
    if not isinstance(pixels, Tensor) or pixels.ndim < 1 or pixels.shape[-1] != 2:
        shape = tuple(pixels.shape) if isinstance(pixels, Tensor) else type(pixels).__name__
        raise ValueError(f"{who}: pixels must be a tensor of shape [..., 2], got {shape}")


def scaled_size(width: int, height: int, factor: float, who: str) -> tuple[int, int, float, float]:
    """New (width, height) = round(size * factor) and the exact per-axis scales."""
    if not (factor > 0 and factor < float("inf")):
        raise ValueError(f"{who}.scaled(factor): expected a positive finite factor, got {factor}")
    w, h = round(width * factor), round(height * factor)
    if w < 1 or h < 1:
        raise ValueError(f"{who}.scaled(factor): factor {factor} gives an empty image ({w}x{h})")
    return w, h, w / width, h / height
