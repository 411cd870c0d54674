"""Reading and validating the small JSON files (camera, pose): every problem is an InputFileError one-liner."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.io.atomic import atomic_write_text
from avatarperfect_cli.io.paths import require_file


def read_json_object(path: Path, file_format: str, version: int) -> dict[str, Any]:
    """The top-level object of a JSON file whose optional "format"/"version" keys must match (version <= ours)."""
    require_file(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise InputFileError(path, f"cannot read file: {error.strerror or error}") from None
    except UnicodeDecodeError:
        raise InputFileError(path, "not a UTF-8 text file") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise InputFileError(path, f"invalid JSON at line {error.lineno}, column {error.colno}: {error.msg}") from None
    if not isinstance(data, dict):
        raise InputFileError(path, f"expected a JSON object at the top level, got {_json_type(data)}")
    if data.get("format", file_format) != file_format:
        raise InputFileError(path, f"'format' is {data['format']!r}, expected {file_format!r}")
    found_version = data.get("version", version)
    if not _is_int(found_version) or found_version < 1:
        raise InputFileError(path, f"'version' must be a positive integer, got {found_version!r}")
    if found_version > version:
        raise InputFileError(path, f"format version {found_version} is newer than supported ({version})")
    return data


def write_json_object(path: Path | str, data: dict[str, Any]) -> None:
    """Write `data` as indented JSON, atomically."""
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def tensor_to_json(tensor: torch.Tensor) -> list[Any]:
    """Nested lists of the float32 values, each written with the fewest digits that read back exactly."""
    return tensor.detach().cpu().float().numpy().astype(str).astype(np.float64).tolist()


def get_key(data: dict[str, Any], key: str, path: Path, where: str = "") -> Any:
    """data[key]; a missing key is an InputFileError naming `{where}{key}`."""
    if key not in data:
        raise InputFileError(path, f"missing key '{where}{key}'")
    return data[key]


def get_array(data: dict[str, Any], key: str, shape: tuple[int, ...], path: Path, where: str = "") -> torch.Tensor:
    """data[key] as a float64 tensor of `shape`; it must be nested lists of finite numbers."""
    label = f"{where}{key}"
    value = get_key(data, key, path, where)
    problem = _nesting_problem(value, shape, label)
    if problem is not None:
        shape_text = "x".join(map(str, shape))
        raise InputFileError(path, f"'{label}' must be a {shape_text} array of finite numbers: {problem}")
    return torch.tensor(value, dtype=torch.float64).reshape(shape)


def get_positive_int(data: dict[str, Any], key: str, path: Path, where: str = "") -> int:
    value = get_key(data, key, path, where)
    if not _is_int(value) or value < 1:
        raise InputFileError(path, f"'{where}{key}' must be a positive integer, got {value!r}")
    return value


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _json_type(value: Any) -> str:
    names = {dict: "an object", list: "an array", str: "a string", bool: "a boolean", type(None): "null"}
    return names.get(type(value), "a number")


def _nesting_problem(value: Any, shape: tuple[int, ...], label: str) -> str | None:
    """Why `value` is not nested lists of finite numbers with `shape`, or None when it is."""
    if not shape:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{label} is {_json_type(value)}"
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer beyond the float range
            finite = False
        return None if finite else f"{label} is not finite"
    if not isinstance(value, list):
        return f"{label} is {_json_type(value)}, not an array of {shape[0]}"
    if len(value) != shape[0]:
        return f"{label} has {len(value)} entries, not {shape[0]}"
    for index, item in enumerate(value):
        problem = _nesting_problem(item, shape[1:], f"{label}[{index}]")
        if problem is not None:
            return problem
    return None
