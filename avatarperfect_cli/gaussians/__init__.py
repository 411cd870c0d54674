"""3D Gaussians: the container and spherical-harmonics colour."""

from avatarperfect_cli.gaussians.container import Gaussians, num_sh_bases, sh_degree_from_bases
from avatarperfect_cli.gaussians.sh import SH_C0, eval_sh, rgb_to_sh, sh_to_rgb

__all__ = [
    "Gaussians",
    "SH_C0",
    "eval_sh",
    "num_sh_bases",
    "rgb_to_sh",
    "sh_degree_from_bases",
    "sh_to_rgb",
]
