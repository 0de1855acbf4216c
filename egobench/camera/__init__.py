"""Camera models (pixel centres at integer coordinates) and fisheye -> pinhole rectification."""

from egobench.camera.base import CameraModel
from egobench.camera.equidistant import Equidistant
from egobench.camera.fisheye624 import Fisheye624
from egobench.camera.pinhole import Pinhole
from egobench.camera.rectify import Rectification, default_pinhole_for

__all__ = ["CameraModel", "Equidistant", "Fisheye624", "Pinhole", "Rectification", "default_pinhole_for"]
