"""Input videos: the People-Snapshot layout (InstantAvatar / GART preprocessing)."""

from avatarperfect_cli.datasets.people_snapshot import (
    FrameRange,
    VideoDataset,
    load_people_snapshot,
    read_dataset_camera,
    write_people_snapshot,
)

__all__ = ["FrameRange", "VideoDataset", "load_people_snapshot", "read_dataset_camera", "write_people_snapshot"]
