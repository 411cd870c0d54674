"""The camera's focal length as a phone records it in a video: the 35 mm-equivalent focal length of QuickTime's
metadata keys (`moov/meta` with an 'mdta' handler, a `keys` table and an `ilst` of values), which iPhones write
into every .mov and .mp4 they record (AVFoundation's AVMetadataQuickTimeMetadataKeyCameraFocalLength35mmEquivalent).

Only the boxes on the way are read: the top-level boxes' headers, then `moov` (at most `MAX_MOOV_BYTES`).
A file without the key, or with boxes that do not parse, has no recorded focal length.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

FOCAL_LENGTH_KEY = "com.apple.quicktime.camera.focal_length.35mm_equivalent"
MAX_MOOV_BYTES = 64 * 2**20  # a phone's moov is a few hundred kB per minute
# 35 mm-equivalent focal lengths outside this range (mm) are taken for a misread value
PLAUSIBLE_FOCAL_MM = (4.0, 2000.0)
# the 35 mm frame's half diagonal, mm: a 35 mm-equivalent focal length keeps the diagonal field of view
HALF_DIAGONAL_MM = 0.5 * math.hypot(36.0, 24.0)


class _Malformed(Exception):
    """A box that does not parse."""


def recorded_focal_length(path: Path | str) -> float | None:
    """The 35 mm-equivalent focal length (mm) the video at `path` records, or None."""
    try:
        with open(path, "rb") as file:
            moov = _top_level_box(file, b"moov")
        value = None if moov is None else _metadata_value(moov, FOCAL_LENGTH_KEY)
    except (OSError, _Malformed, struct.error, UnicodeDecodeError, ValueError):
        return None
    if value is None or not math.isfinite(value) or not PLAUSIBLE_FOCAL_MM[0] <= value <= PLAUSIBLE_FOCAL_MM[1]:
        return None
    return value


def field_of_view_degrees(focal_35mm: float, width: int, height: int) -> float:
    """The field of view across the longer side of a width x height frame (degrees) of a lens whose 35 mm-equivalent
    focal length is `focal_35mm` (mm): the frame's diagonal sees what a 36 x 24 mm frame's does at that focal length."""
    half_longer = HALF_DIAGONAL_MM * max(width, height) / math.hypot(width, height)
    return math.degrees(2.0 * math.atan(half_longer / focal_35mm))


def _top_level_box(file, kind: bytes) -> bytes | None:
    """The payload of the first top-level box of type `kind` in the open file, or None."""
    file.seek(0, 2)
    end = file.tell()
    position = 0
    while position + 8 <= end:
        file.seek(position)
        size, box_type = struct.unpack(">I4s", file.read(8))
        header = 8
        if size == 1:
            size, header = struct.unpack(">Q", file.read(8))[0], 16
        elif size == 0:
            size = end - position
        if size < header or position + size > end:
            raise _Malformed(f"box {box_type!r} at {position}")
        if box_type == kind:
            if size - header > MAX_MOOV_BYTES:
                raise _Malformed(f"{kind!r} of {size} bytes")
            return file.read(size - header)
        position += size
    return None


def _children(payload: bytes) -> list[tuple[bytes, bytes]]:
    """The (type, payload) of the boxes that fill `payload`."""
    boxes, position = [], 0
    while position + 8 <= len(payload):
        size, box_type = struct.unpack_from(">I4s", payload, position)
        header = 8
        if size == 1:
            size, header = struct.unpack_from(">Q", payload, position + 8)[0], 16
        elif size == 0:
            size = len(payload) - position
        if size < header or position + size > len(payload):
            raise _Malformed(f"box {box_type!r}")
        boxes.append((box_type, payload[position + header : position + size]))
        position += size
    return boxes


def _meta_boxes(moov: bytes) -> list[bytes]:
    """The payloads of `moov/meta` and `moov/udta/meta`, each as a list of child boxes' bytes (QuickTime's meta
    has no version and flags; ISO's full box has four zero bytes before its first child)."""
    found = []
    for box_type, payload in _children(moov):
        if box_type == b"udta":
            found += [child for child_type, child in _children(payload) if child_type == b"meta"]
        elif box_type == b"meta":
            found.append(payload)
    return [payload[4:] if payload[:4] == b"\0\0\0\0" else payload for payload in found]


def _metadata_value(moov: bytes, key: str) -> float | None:
    """The numeric value of metadata key `key` in `moov`'s keys and ilst, or None."""
    for meta in _meta_boxes(moov):
        boxes = dict(_children(meta))
        if b"keys" not in boxes or b"ilst" not in boxes:
            continue
        index = _key_index(boxes[b"keys"], key)
        if index is None:
            continue
        for item_type, item in _children(boxes[b"ilst"]):
            if struct.unpack(">I", item_type)[0] == index:
                for data_type, data in _children(item):
                    if data_type == b"data" and len(data) >= 8:
                        return _number(struct.unpack(">I", data[:4])[0] & 0xFFFFFF, data[8:])
    return None


def _key_index(keys: bytes, key: str) -> int | None:
    """The 1-based index of `key` in a `keys` box's payload (version and flags, a count, then size-prefixed
    namespace + name entries)."""
    count = struct.unpack_from(">I", keys, 4)[0]
    position = 8
    for index in range(1, count + 1):
        size = struct.unpack_from(">I", keys, position)[0]
        if size < 8 or position + size > len(keys):
            raise _Malformed("keys entry")
        if keys[position + 4 : position + 8] == b"mdta" and keys[position + 8 : position + size].decode("utf-8") == key:
            return index
        position += size
    return None


# well-known data types of QuickTime metadata values: struct formats of the numbers
_NUMBER_FORMATS = {23: ">f", 24: ">d", 65: ">b", 66: ">h", 67: ">i", 74: ">q", 75: ">B", 76: ">H", 77: ">I", 78: ">Q"}


def _number(data_type: int, value: bytes) -> float | None:
    """A metadata value as a number: UTF-8 text (type 1), big-endian integers of 1 to 8 bytes (21 signed, 22
    unsigned), or the fixed-size numbers of `_NUMBER_FORMATS`; None for other types."""
    if data_type == 1:
        return float(value.decode("utf-8").strip())
    if data_type in (21, 22) and 1 <= len(value) <= 8:
        return float(int.from_bytes(value, "big", signed=data_type == 21))
    if data_type in _NUMBER_FORMATS:
        return float(struct.unpack(_NUMBER_FORMATS[data_type], value[: struct.calcsize(_NUMBER_FORMATS[data_type])])[0])
    return None
