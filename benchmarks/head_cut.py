"""`prepare` on a video whose frames cut the person's head off (docs/real-data.md, "A person the frame cuts off").

    python -m benchmarks.head_cut OUT [--rows 60] [--every 2]

OUT is a folder of `benchmarks/own_video.py` (it needs OUT/video.mp4 and OUT/sample/train). Every EVERY-th
frame of the video loses its top ROWS pixel rows (the head above the frame) into OUT/head-cut.mp4, which
`prepare` reads twice: with the frames whose torso turns from the clip's upright left out (the default), and
with them kept. For each it prints the frames kept, the torso turns and mask areas of the frames left out, and
how far the fitted joints of anny's middle body lie from the subject's true joints in the image (pixels, the
mean over the 24 joints): over the frames each kept, and over the frames both kept.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import torch

from avatarperfect_cli.body import load_body_template
from avatarperfect_cli.datasets import load_people_snapshot
from avatarperfect_cli.io.video import frame_writer
from avatarperfect_cli.stages import prepare as prepare_stage
from benchmarks.own_video import image_joints


def write_head_cut(video: Path, output: Path, rows: int, every: int) -> None:
    """Every `every`-th frame of `video` without its top `rows` pixel rows, as an .mp4."""
    frames, _ = prepare_stage.read_video_frames(video, every)
    height, width = frames[0].shape[:2]
    with frame_writer(output, width, height - rows, 30.0) as write:
        for frame in frames:
            write(torch.from_numpy(frame[rows:].astype(np.float32) / 255.0))


def joint_errors(prepared: Path, sample_train: Path, rows: int, every: int) -> dict[int, float]:
    """{cut video frame: mean image distance (pixels) of the prepared poses' joints on anny's middle body from
    the subject's true joints}, for every frame `prepared` kept."""
    truth = load_people_snapshot(sample_train, with_images=False)
    expected = image_joints(truth, load_body_template("anny", phenotype=truth.subject["phenotype"]).rest_joints)
    expected[..., 1] -= rows  # the cut frames start `rows` pixel rows lower
    video = load_people_snapshot(prepared, with_images=False)
    kept = json.loads((prepared / "subject.json").read_text())["source_frames"]
    errors = (image_joints(video, load_body_template("anny").rest_joints) - expected[[every * frame for frame in kept]]).norm(dim=-1)
    return dict(zip(kept, errors.mean(dim=-1).tolist()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--rows", type=int, default=60, help="pixel rows cut from the top of every frame")
    parser.add_argument("--every", type=int, default=2, help="keep every N-th frame of the video")
    args = parser.parse_args()
    cut = args.out / "head-cut.mp4"
    write_head_cut(args.out / "video.mp4", cut, args.rows, args.every)
    landmarks, found = prepare_stage.detect_landmarks(prepare_stage._pose_solution(), prepare_stage.read_video_frames(cut, 1)[0], progress=False)
    turned = prepare_stage.turned_torsos(landmarks)
    torso = prepare_stage.torsos(landmarks)
    turns = np.degrees(np.arctan2(np.abs(torso[:, 0]), -torso[:, 1]))
    areas = landmarks.masks.reshape(len(landmarks.masks), -1).sum(axis=1)
    areas = areas / np.median(areas)
    print(f"MediaPipe found the person in {int(found.sum())} of {len(found)} frames; torso turns from image up "
          f"{turns[~turned].min():.0f}-{turns[~turned].max():.0f}° in the frames kept; left out (turn, mask area against the "
          f"median): {', '.join(f'{turn:.0f}° {area:.2f}' for turn, area in zip(turns[turned], areas[turned])) or 'none'}")
    errors = {}
    for label, limit in {"turned torsos left out": prepare_stage.MAX_TORSO_TURN_DEGREES, "every frame kept": 180.0}.items():
        folder = args.out / f"head-cut-{limit:g}"
        shutil.rmtree(folder, ignore_errors=True)
        prepare_stage.MAX_TORSO_TURN_DEGREES = limit
        prepare_stage.prepare(cut, folder, progress=False)
        errors[label] = joint_errors(folder, args.out / "sample" / "train", args.rows, args.every)
        values = np.array(list(errors[label].values()))
        print(f"{label}: {len(values)} frames, joints {values.mean():.2f} px from the truth on average")
    both = sorted(set.intersection(*(set(kept) for kept in errors.values())))
    for label, by_frame in errors.items():
        values = np.array([by_frame[frame] for frame in both])
        print(f"{label}, the {len(both)} frames both kept: joints {values.mean():.2f} px on average, first of them {values[0]:.2f} px")


if __name__ == "__main__":
    main()
