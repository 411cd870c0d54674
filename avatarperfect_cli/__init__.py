"""avatarperfect: repair 3D Gaussian Splatting human avatars by painting 2D images."""

__version__ = "0.1.0"
