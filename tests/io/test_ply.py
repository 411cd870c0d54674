import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.lib import recfunctions
from plyfile import PlyData, PlyElement

from avatarperfect_cli.errors import InputFileError
from avatarperfect_cli.gaussians import Gaussians
from avatarperfect_cli.io.ply import read_gaussians, write_gaussians

STANDARD = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 4.0,
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g),
        extras={"skin_weights": torch.rand(n, 24, generator=g), "flag": torch.rand(n, 1, generator=g)},
        metadata={"body_model": "anny", "rest_joints": [[0.0, 0.9, 0.1]] * 3, "note": "é \"quoted\"\nline"},
    )


def plain_vertices(n: int, rest_count: int, dtypes: dict[str, object] | None = None) -> np.ndarray:
    """A standard 3DGS vertex array with random float32 values (and the given per-field dtypes)."""
    names = STANDARD + [f"f_rest_{j}" for j in range(rest_count)] + TAIL
    dtypes = dtypes or {}
    vertices = np.empty(n, dtype=[(name, dtypes.get(name, "<f4")) for name in names])
    rng = np.random.default_rng(1)
    for name in names:
        vertices[name] = rng.standard_normal(n)
    return vertices


def write_plain_element(path: Path, vertices: np.ndarray, element: str, comments: tuple[str, ...] = ()) -> Path:
    PlyData([PlyElement.describe(vertices, element)], byte_order="<", comments=list(comments)).write(str(path))
    return path


def write_plain(path: Path, vertices: np.ndarray, comments: tuple[str, ...] = ()) -> Path:
    return write_plain_element(path, vertices, "vertex", comments)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_exact(tmp_path: Path, degree: int) -> None:
    gaussians = random_gaussians(50, degree)
    write_gaussians(tmp_path / "a.ply", gaussians)
    loaded = read_gaussians(tmp_path / "a.ply")
    for name in ["means", "quats", "log_scales", "opacity_logits", "sh"]:
        assert getattr(loaded, name).dtype == torch.float32
        assert torch.equal(getattr(loaded, name), getattr(gaussians, name)), name
    assert loaded.extras.keys() == gaussians.extras.keys()
    for name, value in gaussians.extras.items():
        assert torch.equal(loaded.extras[name], value)
    assert loaded.metadata == gaussians.metadata
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply"]


def test_empty_avatar_round_trips(tmp_path: Path) -> None:
    write_gaussians(tmp_path / "a.ply", random_gaussians(0, 2))
    loaded = read_gaussians(tmp_path / "a.ply")
    assert len(loaded) == 0 and loaded.sh.shape == (0, 9, 3) and loaded.extras["skin_weights"].shape == (0, 24)


def test_f_rest_is_channel_major_when_reading(tmp_path: Path) -> None:
    n, bases = 4, 16
    vertices = plain_vertices(n, 3 * (bases - 1))
    expected = torch.zeros(n, bases, 3)
    for c in range(3):
        expected[:, 0, c] = torch.from_numpy(vertices[f"f_dc_{c}"].copy())
        for k in range(1, bases):
            expected[:, k, c] = torch.from_numpy(vertices[f"f_rest_{c * (bases - 1) + k - 1}"].copy())
    loaded = read_gaussians(write_plain(tmp_path / "a.ply", vertices))
    assert torch.equal(loaded.sh, expected)
    assert torch.equal(loaded.opacity_logits, torch.from_numpy(vertices["opacity"].copy()))
    assert torch.equal(loaded.quats[:, 0], torch.from_numpy(vertices["rot_0"].copy()))
    assert torch.equal(loaded.log_scales[:, 2], torch.from_numpy(vertices["scale_2"].copy()))


def test_written_file_has_standard_layout(tmp_path: Path) -> None:
    gaussians = random_gaussians(5, 2)
    write_gaussians(tmp_path / "a.ply", gaussians)
    ply = PlyData.read(str(tmp_path / "a.ply"))
    assert ply.byte_order == "<" and not ply.text
    vertex = ply["vertex"]
    rest = [f"f_rest_{j}" for j in range(24)]
    extras = [f"skin_weights_{j}" for j in range(24)] + ["flag_0"]
    assert [p.name for p in vertex.properties] == STANDARD + rest + TAIL + extras
    assert all(p.val_dtype == "f4" for p in vertex.properties)
    for c in range(3):
        for k in range(1, 9):
            assert np.array_equal(vertex[f"f_rest_{c * 8 + k - 1}"], gaussians.sh[:, k, c].numpy())
    assert np.array_equal(vertex["skin_weights_7"], gaussians.extras["skin_weights"][:, 7].numpy())
    assert not np.any(vertex["nx"]) and np.array_equal(vertex["rot_3"], gaussians.quats[:, 3].numpy())
    (comment,) = ply.comments
    assert comment.startswith("avatarperfect ")
    assert json.loads(comment.split(" ", 1)[1])["extras"] == {"skin_weights": 24, "flag": 1}


def test_plain_3dgs_file_from_another_tool_loads(tmp_path: Path) -> None:
    vertices = plain_vertices(6, 45)
    with_unknown = np.empty(6, dtype=vertices.dtype.descr + [("filter_3D", "<f4"), ("label", "u1")])
    for name in vertices.dtype.names:
        with_unknown[name] = vertices[name]
    with_unknown["filter_3D"], with_unknown["label"] = 0.5, 3
    loaded = read_gaussians(write_plain(tmp_path / "other.ply", with_unknown, comments=("made by another tool",)))
    assert loaded.sh_degree == 3 and len(loaded) == 6
    assert loaded.extras == {} and loaded.metadata == {}
    assert torch.equal(loaded.means[:, 1], torch.from_numpy(vertices["y"].copy()))


def test_double_precision_fields_are_accepted(tmp_path: Path) -> None:
    vertices = plain_vertices(3, 0, {"x": "<f8", "opacity": ">f8"})
    loaded = read_gaussians(write_plain(tmp_path / "a.ply", vertices))
    assert torch.equal(loaded.means[:, 0], torch.from_numpy(vertices["x"].astype(np.float32)))
    assert loaded.means.dtype == torch.float32


def test_invalid_extra_names_are_refused_on_write(tmp_path: Path) -> None:
    gaussians = random_gaussians(2, 1)
    gaussians.extras = {"f_rest": torch.zeros(2, 1)}
    with pytest.raises(ValueError, match="f_rest"):
        write_gaussians(tmp_path / "a.ply", gaussians)
    assert list(tmp_path.iterdir()) == []


def _comment(extras: dict[str, int], version: int = 1) -> str:
    return "avatarperfect " + json.dumps({"version": version, "extras": extras, "metadata": {}})


def _with_list_rot(path: Path) -> Path:
    vertices = plain_vertices(3, 0)
    descr = [(name, "O" if name == "rot_0" else "<f4") for name in vertices.dtype.names]
    listed = np.empty(3, dtype=descr)
    for name in vertices.dtype.names:
        listed[name] = [np.array([v], dtype="<f4") for v in vertices[name]] if name == "rot_0" else vertices[name]
    return write_plain(path, listed)


def _with_non_finite(path: Path) -> Path:
    vertices = plain_vertices(5, 9)
    vertices["opacity"][[1, 3]] = np.nan
    vertices["x"][0] = np.inf
    return write_plain(path, vertices)


def _without_field(path: Path, field: str, rest_count: int = 0) -> Path:
    vertices = plain_vertices(3, rest_count)
    kept = [name for name in vertices.dtype.names if name != field]
    return write_plain(path, recfunctions.repack_fields(vertices[kept]))


def _truncated(path: Path) -> Path:
    write_gaussians(path, random_gaussians(10, 1))
    path.write_bytes(path.read_bytes()[:-30])
    return path


def _missing_extra(path: Path) -> Path:
    vertices = plain_vertices(3, 0)
    extended = np.empty(3, dtype=vertices.dtype.descr + [(f"skin_weights_{j}", "<f4") for j in range(23)])
    for name in vertices.dtype.names:
        extended[name] = vertices[name]
    return write_plain(path, extended, (_comment({"skin_weights": 24}),))


def _declares_fewer(path: Path, text: bool = False) -> Path:
    """5 vertices in the body, a header that declares 3 (as a hand-edited or badly merged file would)."""
    PlyData([PlyElement.describe(plain_vertices(5, 0), "vertex")], text=text, byte_order="<").write(str(path))
    path.write_bytes(path.read_bytes().replace(b"element vertex 5", b"element vertex 3", 1))
    return path


def _with_trailing_garbage(path: Path) -> Path:
    write_gaussians(path, random_gaussians(10, 1))
    path.write_bytes(path.read_bytes() + b"junk")
    return path


def with_bytes(content: bytes) -> Callable[[Path], Path]:
    def make(path: Path) -> Path:
        path.write_bytes(content)
        return path

    return make


def _directory(path: Path) -> Path:
    path.mkdir()
    return path


def _without_vertex(path: Path) -> Path:
    return write_plain_element(path, np.zeros(2, dtype=[("x", "<f4")]), "point")


MALFORMED = {
    "missing": (lambda p: p, "file not found"),
    "directory": (_directory, "not a regular file"),
    "text": (with_bytes(b"hello, world\n"), "not a PLY file"),
    "empty": (with_bytes(b""), "not a PLY file"),
    "binary header": (with_bytes(b"ply\nformat binary_little_endian 1.0\ncomment \xff\n"), "header is not ASCII"),
    "no vertex": (_without_vertex, "no 'vertex' element"),
    "missing opacity": (lambda p: _without_field(p, "opacity"), "missing vertex property 'opacity'"),
    "missing rot_2": (lambda p: _without_field(p, "rot_2"), "missing vertex property 'rot_2'"),
    "list property": (_with_list_rot, "'rot_0' is a list"),
    "integer field": (
        lambda p: write_plain(p, plain_vertices(3, 0, {"scale_1": "<i4"})),
        "'scale_1' has type int32; expected a float type",
    ),
    "non-finite": (_with_non_finite, "non-finite values (NaN or Inf): 1 in 'x', 2 in 'opacity'"),
    "truncated": (_truncated, "truncated: element 'vertex' has 9 of 10 rows"),
    "f_rest count": (lambda p: write_plain(p, plain_vertices(3, 10)), "10 f_rest properties"),
    "f_rest gap": (lambda p: _without_field(p, "f_rest_4", rest_count=10), "missing vertex property 'f_rest_4'"),
    "bad json": (lambda p: write_plain(p, plain_vertices(3, 0), ("avatarperfect {not json",)), "not valid JSON"),
    "newer version": (lambda p: write_plain(p, plain_vertices(3, 0), (_comment({}, version=2),)), "newer"),
    "bad extras table": (lambda p: write_plain(p, plain_vertices(3, 0), (_comment({"w": -1}),)), "'extras'"),
    "missing extra": (_missing_extra, "'skin_weights_23' (extra 'skin_weights' declared"),
    "huge count": (
        with_bytes(b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty list uchar float x\nend_header\n"),
        "cannot load PLY body",
    ),
    "two comments": (lambda p: write_plain(p, plain_vertices(3, 0), (_comment({}), _comment({}))), "2 avatarperfect"),
    # 2 rows of 17 float32 properties left over after the 3 declared vertices
    "fewer declared (binary)": (_declares_fewer, f"{2 * 17 * 4} bytes after the data its header declares (element vertex 3)"),
    "fewer declared (ascii)": (lambda p: _declares_fewer(p, text=True), "2 lines after the data its header declares"),
    "trailing garbage": (_with_trailing_garbage, "4 bytes after the data its header declares (element vertex 10)"),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_file_gives_one_line_input_file_error(tmp_path: Path, case: str) -> None:
    make, problem = MALFORMED[case]
    path = make(tmp_path / "broken_avatar.ply")
    with pytest.raises(InputFileError) as caught:
        read_gaussians(path)
    message = str(caught.value)
    assert "broken_avatar.ply" in message
    assert problem in message
    assert "\n" not in message


@pytest.mark.parametrize("text", [False, True])
def test_a_final_newline_after_the_body_is_accepted(tmp_path: Path, text: bool) -> None:
    vertices = plain_vertices(4, 0)
    path = tmp_path / "a.ply"
    PlyData([PlyElement.describe(vertices, "vertex")], text=text, byte_order="<").write(str(path))
    path.write_bytes(path.read_bytes() + b"\n")
    np.testing.assert_allclose(read_gaussians(path).means.numpy(), recfunctions.structured_to_unstructured(vertices[["x", "y", "z"]]), rtol=1e-6)
