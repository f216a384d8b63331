"""Batched torch geometry: quaternions, SE(3) and Euler angles."""

from src.geometry.quaternion import (
    matrix_to_quat,
    quat_canonical,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
)
from src.geometry.se3 import (
    EULER_SEQUENCES,
    euler_to_matrix,
    matrix_to_euler,
    rotation_angle,
    se3_apply,
    se3_compose,
    se3_from_quat,
    se3_from_rt,
    se3_identity,
    se3_inverse,
)

__all__ = [
    "EULER_SEQUENCES", "euler_to_matrix", "matrix_to_euler", "matrix_to_quat", "quat_canonical",
    "quat_conjugate", "quat_multiply", "quat_normalize", "quat_rotate", "quat_to_matrix",
    "rotation_angle", "se3_apply", "se3_compose", "se3_from_quat", "se3_from_rt", "se3_identity",
    "se3_inverse",
]
