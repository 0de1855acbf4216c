"""SE(3)/quaternion maths and the device trajectory."""

from egobench.geometry.se3 import (
    check_pose, hat, make_pose, quat_conjugate, quat_multiply, quat_normalize, quat_to_rotmat,
    rotmat_to_quat, se3_exp, se3_interpolate, se3_inverse, se3_log, so3_exp, so3_log,
    transform_points,
)
from egobench.geometry.trajectory import Trajectory, TrajectoryVelocity

__all__ = [
    "check_pose", "hat", "make_pose", "quat_conjugate", "quat_multiply", "quat_normalize",
    "quat_to_rotmat", "rotmat_to_quat", "se3_exp", "se3_interpolate", "se3_inverse", "se3_log",
    "so3_exp", "so3_log", "transform_points", "Trajectory", "TrajectoryVelocity",
]
