"""The avatar: canonical 3D Gaussians with skinning weights over SMPL's 24 joints."""

from avatarperfect_cli.avatar.model import Avatar

__all__ = ["Avatar"]
