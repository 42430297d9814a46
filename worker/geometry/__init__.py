"""Rigid and similarity transforms, quaternions (wxyz), the pinhole camera and Umeyama alignment."""

from .align import fit_similarity, nearest_rotation, umeyama, umeyama_sim3
from .camera import Intrinsics, pixel_grid, project_points, unproject_depth
from .quaternion import (
    quat_align_sign,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
)
from .transforms import (
    make_sim3,
    nearest_sim3,
    relative_transform,
    se3_exp,
    se3_part,
    sim3_apply,
    sim3_blend,
    sim3_compose,
    sim3_decompose,
    sim3_from_quat,
    sim3_inverse,
    sim3_scale,
    sim3_to_quat,
    so3_exp,
    so3_log,
)

__all__ = [
    "Intrinsics", "fit_similarity", "make_sim3", "nearest_rotation", "pixel_grid", "project_points",
    "quat_align_sign", "quat_conjugate",
    "quat_multiply", "quat_normalize", "quat_to_rotmat", "relative_transform", "rotmat_to_quat", "se3_exp", "se3_part",
    "nearest_sim3", "sim3_apply", "sim3_blend", "sim3_compose", "sim3_decompose", "sim3_from_quat", "sim3_inverse",
    "sim3_scale",
    "sim3_to_quat", "so3_exp", "so3_log", "umeyama", "umeyama_sim3", "unproject_depth",
]
