"""Input videos: the People-Snapshot layout (InstantAvatar / GART preprocessing)."""

from avatarperfect_cli.datasets.people_snapshot import (
    FrameRange,
    VideoDataset,
    VideoFingerprint,
    load_people_snapshot,
    read_dataset_camera,
    video_fingerprint,
    write_people_snapshot,
)

__all__ = [
    "FrameRange", "VideoDataset", "VideoFingerprint", "load_people_snapshot", "read_dataset_camera", "video_fingerprint",
    "write_people_snapshot",
]  # fmt: skip
