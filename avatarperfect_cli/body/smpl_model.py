"""SMPL as a template provider, through the `smplx` package, from model files the user supplies.

The licensed SMPL files are never shipped and never downloaded: pass the folder that holds
SMPL_{NEUTRAL,MALE,FEMALE}.pkl (or .npz), directly or in a `smpl/` subfolder.
"""

from __future__ import annotations

import contextlib
import io
import pickle
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.body.base import NUM_JOINTS, SMPL_PARENTS, BodyTemplate
from avatarperfect_cli.errors import AvatarPerfectError, InputFileError

GENDERS = ("neutral", "male", "female")


def find_smpl_file(model_dir: Path, gender: str) -> Path:
    """The SMPL model file for `gender` in `model_dir` or `model_dir/smpl`; InputFileError if there is none."""
    if gender not in GENDERS:
        raise AvatarPerfectError(f"unknown SMPL gender {gender!r}; choose one of {', '.join(GENDERS)}")
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise InputFileError(model_dir, "SMPL model folder not found")
    names = [f"SMPL_{gender.upper()}.{ext}" for ext in ("pkl", "npz")]
    for folder in (model_dir, model_dir / "smpl"):
        for name in names:
            if (folder / name).is_file():
                return folder / name
    raise InputFileError(model_dir, f"no {' or '.join(names)} in this folder or its smpl/ subfolder")


def _read_model_data(path: Path) -> dict:
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=True) as data:
                return {key: data[key] for key in data.files}
        with path.open("rb") as file:
            return pickle.load(file, encoding="latin1")
    except ModuleNotFoundError as error:
        raise InputFileError(path, f"needs the Python module {error.name!r} to unpickle") from error
    except (OSError, EOFError, ValueError, pickle.UnpicklingError, zipfile.BadZipFile) as error:
        raise InputFileError(path, f"not a readable SMPL model file ({error})") from error


def load_smpl_template(model_dir: Path, gender: str = "neutral", betas: Sequence[float] | None = None) -> BodyTemplate:
    """The SMPL body with shape `betas` (default all 0) in its zero pose (T-pose), float32, metres.

    vertices = v_template + shapedirs . betas; rest joints from J_regressor; weights and faces as stored.
    """
    try:
        import smplx
        from smplx.lbs import blend_shapes, vertices2joints
        from smplx.utils import Struct
    except ImportError as error:
        raise AvatarPerfectError("the SMPL body needs the smplx package: pip install 'avatarperfect-cli[smpl]'") from error
    path = find_smpl_file(model_dir, gender)
    data = _read_model_data(path)
    missing = sorted({"v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f"} - set(data))
    if missing:
        raise InputFileError(path, f"not an SMPL model: missing {', '.join(missing)}")
    num_betas = 0 if betas is None else len(betas)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # smplx prints a note about the shape space size
            model = smplx.SMPL(
                str(path), data_struct=Struct(**data), gender=gender, num_betas=max(num_betas, 1), dtype=torch.float64
            )
    except (ValueError, IndexError, TypeError, AttributeError) as error:
        raise InputFileError(path, f"not a usable SMPL model ({error})") from error
    if tuple(model.parents.tolist()) != SMPL_PARENTS or model.lbs_weights.shape[1] != NUM_JOINTS:
        raise InputFileError(path, "the kinematic tree is not SMPL's 24-joint tree")
    if num_betas > model.num_betas:
        raise AvatarPerfectError(f"{path}: the model has {model.num_betas} shape coefficients, {num_betas} given")
    shape = torch.zeros(1, model.num_betas, dtype=torch.float64)
    shape[0, :num_betas] = torch.as_tensor(list(betas or []), dtype=torch.float64)
    vertices = model.v_template[None] + blend_shapes(shape, model.shapedirs)
    joints = vertices2joints(model.J_regressor, vertices)
    weights = model.lbs_weights
    return BodyTemplate(
        vertices=vertices[0].float(),
        faces=model.faces_tensor.long(),
        weights=(weights / weights.sum(1, keepdim=True)).float(),
        rest_joints=joints[0].float(),
    )
