"""File I/O: atomic writes, 3DGS PLY, camera and pose JSON, images. Bad user files raise InputFileError."""

from avatarperfect_cli.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from avatarperfect_cli.io.camera_json import read_camera, write_camera
from avatarperfect_cli.io.images import read_image, write_image
from avatarperfect_cli.io.ply import read_gaussians, write_gaussians
from avatarperfect_cli.io.pose_json import PoseFile, read_pose, write_pose

__all__ = [
    "PoseFile",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "read_camera",
    "read_gaussians",
    "read_image",
    "read_pose",
    "write_camera",
    "write_gaussians",
    "write_image",
    "write_pose",
]
