"""A People-Snapshot folder whose frames keep only their top rows: a person the frame cuts off, as phone
videos often lose the feet (docs/real-data.md, "A person the frame cuts off").

    python -m benchmarks.cut_frames SOURCE OUT --rows 420

The camera keeps its intrinsics (the image just ends at row ROWS); poses, betas and subject.json are copied.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from avatarperfect_cli.datasets import load_people_snapshot, write_people_snapshot
from avatarperfect_cli.render import Camera


def cut_frames(source: Path, out: Path, rows: int) -> None:
    """Write `out`: every frame of the People-Snapshot folder `source` cut to its top `rows` pixel rows."""
    video = load_people_snapshot(source, downscale=1)
    if not 0 < rows <= video.camera.height:
        raise SystemExit(f"--rows must be from 1 to the frames' height {video.camera.height}, got {rows}")
    camera = Camera(video.camera.K, video.camera.world_to_camera, video.camera.width, rows)
    frames = video.filmed if video.filmed is not None else (video.images * 255.0).round().to(torch.uint8)
    images = [frame[:rows].numpy() for frame in frames]
    write_people_snapshot(
        out, images, video.masks[:, :rows].numpy(), video.body_pose, video.transl, camera, betas=video.betas, subject=video.subject
    )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--rows", type=int, required=True, help="pixel rows kept from the top of every frame")
    args = parser.parse_args()
    cut_frames(args.source, args.out, args.rows)


if __name__ == "__main__":
    main()
