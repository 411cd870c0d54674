"""The 35 mm-equivalent focal length a phone records in a video's QuickTime metadata, read from box layouts
built here byte by byte, and the field of view it gives."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from avatarperfect_cli.io.video_metadata import FOCAL_LENGTH_KEY, field_of_view_degrees, recorded_focal_length


def box(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I4s", len(payload) + 8, kind) + payload


def large_box(kind: bytes, payload: bytes) -> bytes:
    """A box with a 64-bit size (size field 1)."""
    return struct.pack(">I4sQ", 1, kind, len(payload) + 16) + payload


def metadata(values: dict[str, tuple[int, bytes]], iso: bool = False) -> bytes:
    """A `meta` box with an 'mdta' handler, the keys in order and one `data` (type, value) per key; `iso`: with
    the version and flags of ISO's full box."""
    names = list(values)
    keys = struct.pack(">II", 0, len(names)) + b"".join(struct.pack(">I", len(name) + 8) + b"mdta" + name.encode() for name in names)
    items = b"".join(
        box(struct.pack(">I", index), box(b"data", struct.pack(">I", data_type) + b"\0\0\0\0" + value))
        for index, (data_type, value) in enumerate(values.values(), start=1)
    )
    handler = box(b"hdlr", bytes(8) + b"mdta" + bytes(13))
    return box(b"meta", (bytes(4) if iso else b"") + handler + box(b"keys", keys) + box(b"ilst", items))


def movie(moov_children: bytes, large_mdat: bool = False) -> bytes:
    mdat = (large_box if large_mdat else box)(b"mdat", bytes(64))
    return box(b"ftyp", b"qt  \0\0\0\0qt  ") + mdat + box(b"moov", box(b"mvhd", bytes(100)) + moov_children)


IPHONE_KEYS = {"com.apple.quicktime.make": (1, b"Apple"), FOCAL_LENGTH_KEY: (23, struct.pack(">f", 26.0))}


def test_the_focal_length_key_is_found_among_other_keys(tmp_path: Path) -> None:
    (tmp_path / "clip.mov").write_bytes(movie(metadata(IPHONE_KEYS)))
    assert recorded_focal_length(tmp_path / "clip.mov") == 26.0


@pytest.mark.parametrize(
    ("data_type", "value", "expected"),
    [(1, b"27", 27.0), (24, struct.pack(">d", 24.5), 24.5), (21, struct.pack(">h", 28), 28.0), (22, bytes([52]), 52.0),
     (67, struct.pack(">i", 77), 77.0)],
)  # fmt: skip
def test_each_number_encoding_is_read(tmp_path: Path, data_type: int, value: bytes, expected: float) -> None:
    (tmp_path / "clip.mov").write_bytes(movie(metadata({FOCAL_LENGTH_KEY: (data_type, value)})))
    assert recorded_focal_length(tmp_path / "clip.mov") == expected


def test_an_iso_meta_box_in_user_data_after_a_64_bit_media_box(tmp_path: Path) -> None:
    (tmp_path / "clip.mp4").write_bytes(movie(box(b"udta", metadata(IPHONE_KEYS, iso=True)), large_mdat=True))
    assert recorded_focal_length(tmp_path / "clip.mp4") == 26.0


def test_without_the_key_or_with_broken_boxes_no_focal_length_is_recorded(tmp_path: Path) -> None:
    cases = {
        "other keys": movie(metadata({"com.apple.quicktime.make": (1, b"Apple")})),
        "no metadata": movie(b""),
        "implausible": movie(metadata({FOCAL_LENGTH_KEY: (21, struct.pack(">b", -13))})),
        "text that is no number": movie(metadata({FOCAL_LENGTH_KEY: (1, b"wide")})),
        "cut short": movie(metadata(IPHONE_KEYS))[:-20],
        "noise": np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "empty": b"",
    }
    for name, content in cases.items():
        (tmp_path / "clip.mov").write_bytes(content)
        assert recorded_focal_length(tmp_path / "clip.mov") is None, name
    assert recorded_focal_length(tmp_path / "missing.mov") is None


def test_a_video_opencv_wrote_keeps_playing_with_the_metadata_added(tmp_path: Path) -> None:
    writer = cv2.VideoWriter(str(tmp_path / "clip.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (64, 48))
    for shade in range(5):
        writer.write(np.full((48, 64, 3), 40 * shade, np.uint8))
    writer.release()
    content = (tmp_path / "clip.mp4").read_bytes()
    moov_at = content.rindex(b"moov") - 4
    assert moov_at + struct.unpack(">I", content[moov_at : moov_at + 4])[0] == len(content)  # moov comes last
    assert recorded_focal_length(tmp_path / "clip.mp4") is None
    moov = content[moov_at + 8 :] + metadata(IPHONE_KEYS)
    (tmp_path / "clip.mp4").write_bytes(content[:moov_at] + box(b"moov", moov))

    assert recorded_focal_length(tmp_path / "clip.mp4") == 26.0
    capture = cv2.VideoCapture(str(tmp_path / "clip.mp4"))
    frames = []
    while (frame := capture.read())[0]:
        frames.append(frame[1])
    assert len(frames) == 5


def test_field_of_view_keeps_the_35mm_frames_diagonal_view() -> None:
    # a 3:2 frame is the 35 mm frame's shape: its longer side is 36 mm at any 35 mm-equivalent focal length
    assert field_of_view_degrees(18.0, 3000, 2000) == pytest.approx(90.0)
    assert field_of_view_degrees(36.0, 2000, 3000) == pytest.approx(math.degrees(2 * math.atan(0.5)))
    # a 4:3 frame with the same diagonal (43.27 mm) is 34.6 mm wide: a phone's 26 mm main camera sees 67.3°
    assert field_of_view_degrees(26.0, 4032, 3024) == pytest.approx(math.degrees(2 * math.atan(0.8 * math.hypot(18, 12) / 26.0)))
    # 16:9 video is wider for the same diagonal
    assert field_of_view_degrees(26.0, 1920, 1080) > field_of_view_degrees(26.0, 4032, 3024)
