"""The standard 3DGS PLY (binary little-endian `vertex` element) <-> `Gaussians`.

Vertex properties, in file order: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..M-1, opacity (logit),
scale_0..2 (log), rot_0..3 (w x y z), then `{name}_{j}` for each extra. f_rest holds the SH coefficients of
degree >= 1 channel-major (all red, then green, then blue), as in the Inria and gsplat exporters; M is 0, 9,
24 or 45 for SH degree 0..3. Metadata, the extras' widths and the format version sit in one header comment
`avatarperfect {json}`; PLYs from other tools have none and load with empty extras and metadata.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch
from numpy.lib import recfunctions
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyListProperty, PlyParseError

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.gaussians import Gaussians, num_sh_bases
from avatarperfect_cli.io.atomic import atomic_path
from avatarperfect_cli.io.paths import require_file

FORMAT_VERSION = 1
COMMENT_PREFIX = "avatarperfect "
_REST_COUNTS = {3 * (num_sh_bases(degree) - 1) for degree in range(4)}  # 0, 9, 24, 45
_REST_NAME = re.compile(r"f_rest_\d+")
_EXTRA_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_STANDARD_GROUPS = ("f_dc", "f_rest", "scale", "rot")  # names whose `{group}_{j}` properties are standard
_TRAILING_PROBE = 4096  # bytes read past a binary body to tell trailing data from a final newline


def _names(prefix: str, count: int) -> list[str]:
    return [f"{prefix}_{j}" for j in range(count)]


def _is_valid_extra_name(name: str) -> bool:
    """A plain identifier whose `{name}_{j}` properties cannot collide with standard ones."""
    return bool(_EXTRA_NAME.fullmatch(name)) and name not in _STANDARD_GROUPS


def _ply_comment(gaussians: Gaussians) -> str:
    header = {
        "version": FORMAT_VERSION,
        "extras": {name: int(value.shape[1]) for name, value in gaussians.extras.items()},
        "metadata": gaussians.metadata,
    }
    return COMMENT_PREFIX + json.dumps(header, ensure_ascii=True, allow_nan=False, separators=(",", ":"))


def write_gaussians(path: Path | str, gaussians: Gaussians) -> None:
    """Write `gaussians` as a binary little-endian 3DGS PLY (float32 properties), atomically.

    Raises ValueError for an extra whose name is not a plain identifier or would collide with a standard
    property; json raises TypeError or ValueError for metadata that is not JSON-serialisable.
    """
    for name in gaussians.extras:
        if not _is_valid_extra_name(name):
            raise ValueError(f"extra name '{name}' is not a plain identifier or collides with a standard property")
    n = len(gaussians)
    rest = gaussians.sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (gaussians.sh.shape[1] - 1))  # channel-major
    columns = [
        gaussians.means,
        torch.zeros(n, 3),
        gaussians.sh[:, 0, :],
        rest,
        gaussians.opacity_logits[:, None],
        gaussians.log_scales,
        gaussians.quats,
        *gaussians.extras.values(),
    ]
    matrix = torch.cat([c.detach().to("cpu", torch.float32) for c in columns], dim=1).numpy()
    names = ["x", "y", "z", "nx", "ny", "nz", *_names("f_dc", 3), *_names("f_rest", rest.shape[1]), "opacity"]
    names += [*_names("scale", 3), *_names("rot", 4)]
    for name, value in gaussians.extras.items():
        names += _names(name, value.shape[1])
    vertices = matrix.view(np.dtype([(name, "<f4") for name in names])).reshape(n)
    element = PlyElement.describe(vertices, "vertex")
    ply = PlyData([element], text=False, byte_order="<", comments=[_ply_comment(gaussians)])
    with atomic_path(path) as temporary:
        ply.write(str(temporary))


def _read_ply(path: Path) -> PlyData:
    require_file(path)
    try:
        with open(path, "rb") as handle:
            ply = PlyData.read(handle)  # memory-mapped: binary bodies load without Python loops
            extra = _trailing_text_rows(path, ply) if ply.text else _trailing_binary_data(handle)
    except OSError as error:
        raise InputFileError(path, f"cannot read file: {error.strerror or error}") from None
    except UnicodeDecodeError:
        raise InputFileError(path, "not a PLY file (header is not ASCII text)") from None
    except PlyElementParseError as error:
        if error.message == "early end-of-file":
            name, count = error.element.name, error.element.count
            raise InputFileError(path, f"truncated: element '{name}' has {error.row} of {count} rows") from None
        raise InputFileError(path, f"malformed PLY body: {error}") from None
    except PlyParseError as error:
        raise InputFileError(path, f"not a PLY file ({error})") from None
    except (ValueError, MemoryError) as error:  # e.g. an element count too large for memory
        raise InputFileError(path, f"cannot load PLY body: {error}") from None
    if extra:
        declared = ", ".join(f"element {element.name} {element.count}" for element in ply.elements)
        problem = f"{extra} after the data its header declares ({declared}): a wrong count or trailing data"
        raise InputFileError(path, problem)
    return ply


def _trailing_binary_data(handle: BinaryIO) -> str | None:
    """What follows the body of a binary PLY that PlyData.read just read (it leaves `handle` right after the
    last element), e.g. "96 bytes"; None when nothing but whitespace follows."""
    rest = handle.read(_TRAILING_PROBE)
    if not rest.strip():
        return None
    return f"{os.fstat(handle.fileno()).st_size - handle.tell() + len(rest)} bytes"


def _trailing_text_rows(path: Path, ply: PlyData) -> str | None:
    """Non-blank rows of an ASCII PLY beyond those its header declares, e.g. "2 lines"; None when there are none."""
    with open(path, "rb") as handle:
        for line in handle:
            if line.strip() == b"end_header":
                break
        extra = sum(1 for line in handle if line.strip()) - sum(element.count for element in ply.elements)
    return f"{extra} lines" if extra > 0 else None


def _parse_comment(comments: list[str], path: Path) -> dict[str, Any]:
    """The avatarperfect header comment's {"extras": name -> width, "metadata": dict}; empty when absent."""
    ours = [c for c in comments if c.startswith(COMMENT_PREFIX)]
    if not ours:
        return {"extras": {}, "metadata": {}}
    if len(ours) > 1:
        raise InputFileError(path, f"{len(ours)} avatarperfect metadata comments; expected one")
    try:
        header = json.loads(ours[0][len(COMMENT_PREFIX) :])
    except json.JSONDecodeError as error:
        raise InputFileError(path, f"avatarperfect metadata comment is not valid JSON ({error})") from None
    if not isinstance(header, dict):
        raise InputFileError(path, "avatarperfect metadata comment is not a JSON object")
    version, extras, metadata = header.get("version"), header.get("extras", {}), header.get("metadata", {})
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputFileError(path, f"avatarperfect metadata comment has an invalid version {version!r}")
    if version > FORMAT_VERSION:
        raise InputFileError(path, f"format version {version} is newer than supported ({FORMAT_VERSION})")
    extras_ok = isinstance(extras, dict) and all(
        _is_valid_extra_name(name) and isinstance(width, int) and not isinstance(width, bool) and width >= 0
        for name, width in extras.items()
    )
    if not extras_ok:
        raise InputFileError(path, "avatarperfect metadata comment: 'extras' must map identifiers to widths >= 0")
    if not isinstance(metadata, dict):
        raise InputFileError(path, "avatarperfect metadata comment: 'metadata' must be a JSON object")
    return {"extras": extras, "metadata": metadata}


def _property_groups(vertex: PlyElement, extras: dict[str, int], path: Path) -> dict[str, list[str]]:
    """Property names per Gaussians field, checked to exist and to be float scalars."""
    rest_count = sum(1 for p in vertex.properties if _REST_NAME.fullmatch(p.name))
    if rest_count not in _REST_COUNTS:
        raise InputFileError(path, f"{rest_count} f_rest properties; expected 0, 9, 24 or 45 (SH degree 0..3)")
    groups = {
        "means": ["x", "y", "z"],
        "dc": _names("f_dc", 3),
        "rest": _names("f_rest", rest_count),
        "opacity": ["opacity"],
        "scale": _names("scale", 3),
        "rot": _names("rot", 4),
    }
    groups.update({f"extra:{name}": _names(name, width) for name, width in extras.items()})
    properties = {p.name: p for p in vertex.properties}
    for group, names in groups.items():
        for name in names:
            prop = properties.get(name)
            if prop is None:
                is_extra = group.startswith("extra:")
                origin = f" (extra '{group[6:]}' declared in the avatarperfect comment)" if is_extra else ""
                raise InputFileError(path, f"missing vertex property '{name}'{origin}")
            if isinstance(prop, PlyListProperty):
                raise InputFileError(path, f"vertex property '{name}' is a list; expected a float scalar")
            value_type = np.dtype(prop.val_dtype)
            if value_type.kind != "f":
                problem = f"vertex property '{name}' has type {value_type.name}; expected a float type"
                raise InputFileError(path, problem)
    return groups


def _check_finite(matrix: np.ndarray, names: list[str], path: Path) -> None:
    bad = (~np.isfinite(matrix)).sum(axis=0)
    if bad.any():
        listed = [f"{count} in '{name}'" for name, count in zip(names, bad.tolist()) if count]
        more = f" and {len(listed) - 3} more properties" if len(listed) > 3 else ""
        raise InputFileError(path, f"non-finite values (NaN or Inf): {', '.join(listed[:3])}{more}")


def read_gaussians(path: Path | str) -> Gaussians:
    """Load a 3DGS PLY into float32 CPU tensors; raises InputFileError naming the file and the problem."""
    path = Path(path)
    ply = _read_ply(path)
    if "vertex" not in ply:
        raise InputFileError(path, "no 'vertex' element")
    header = _parse_comment(ply.comments, path)
    groups = _property_groups(ply["vertex"], header["extras"], path)
    names = [name for group in groups.values() for name in group]
    data = ply["vertex"].data
    matrix = torch.from_numpy(np.array(recfunctions.structured_to_unstructured(data[names], dtype=np.float32)))
    _check_finite(matrix.numpy(), names, path)
    columns = dict(zip(groups, matrix.split([len(group) for group in groups.values()], dim=1)))
    n = matrix.shape[0]
    rest = columns["rest"].reshape(n, 3, len(groups["rest"]) // 3).transpose(1, 2)  # (N, K - 1, 3)
    return Gaussians(
        means=columns["means"].contiguous(),
        quats=columns["rot"].contiguous(),
        log_scales=columns["scale"].contiguous(),
        opacity_logits=columns["opacity"][:, 0].contiguous(),
        sh=torch.cat([columns["dc"][:, None, :], rest], dim=1),
        extras={name: columns[f"extra:{name}"].contiguous() for name in header["extras"]},
        metadata=header["metadata"],
    )
