"""The own-video path end to end on a synthetic subject whose truth is known (docs/real-data.md).

    python -m benchmarks.own_video OUT [--preset default] [--resolution 512] [--frames 100] [--iterations 2000] [--fov DEG] [--split]
                                       [--cut ROWS] [--fitted-body] [--true-poses PART ...] [--true-masks]

1. `make-sample`'s turn-around of the preset (OUT/sample/train: exact poses, exact masks, white background);
   with `--cut ROWS` every frame keeps only its top ROWS pixel rows (OUT/sample/train-cut: the frame cuts the
   person off, `benchmarks/cut_frames.py`), and everything below uses those frames.
2. The same frames as a user's video: each person composited over a background that is not white (a
   gradient with a floor and a wall pattern), compressed to OUT/video.mp4.
3. `prepare` the video (its assumed field of view and anny's middle body, as for any video), then
   `train-initial` on the even frames (the body and the poses fitted to the masks, as for any prepared folder).
4. `evaluate --refine-poses` on the odd frames, against the true frames: OUT/truth-test holds the sample's
   images and masks with the prepared folder's camera and poses, so the score measures the avatar and not
   MediaPipe's masks.
5. Two references, each scored on the odd frames with the exact poses: the even frames as the video has them
   (OUT/video-exact: its decoded images and `prepare`'s masks, with the exact camera and poses) and as the
   sample has them, both on the subject's own body (`--body-shape exact`). The first differs from the own
   video only in what `prepare` and the fit estimate (poses, body, camera): it is the target. The second
   also shows what the video costs; `--split` adds the two between (only the images, only the masks the
   video's). `--fitted-body` trains the first reference's frames and exact poses once more on the body fitted
   to their masks (`--body-shape fit`) and scores both with the test poses refined too: what the fitted body
   costs, apart from the poses and the camera.
6. `--true-poses root limbs all` trains the prepared folder once per PART with that part of its poses replaced
   by the truth's, seen through `prepare`'s camera (root: the root orientation and the translation, so the
   body stands where the truth stands; limbs: every other joint's rotation; all: both), everything else as
   for the own video (the body and all poses still fitted to the masks and refined in training), and scores
   each on the odd frames whose poses carry the same replacement (OUT/truth-test-true-PART), and prints its
   training frames' PSNR at the poses it trained on: which of the estimates the gap to the reference comes from.
   `--true-masks` does the same with the prepared folder's masks replaced by the true ones (OUT/prepared-true-masks,
   scored on OUT/truth-test), and once more with only their errors beyond the trainer's mask band (3 px) put right
   (OUT/prepared-true-masks-beyond-band): what `prepare`'s masks cost once the poses are fitted and refined.

Prints one row per path: held-out IoU, PSNR and SSIM (given and refined poses), the Gaussian count and the
share of Gaussians longer than 3 cm; the comparison pictures are in each workspace's eval folder. Then how far
the training frames' joints land from the true ones in the image, with `prepare`'s poses and with the poses
the workspace trained on (fitted with the body and refined in training): the mean over joints and frames and
the worst frame, in pixels (the fitted body is not the subject's, so its joints need not meet the truth's
even at exact poses; `--fitted-body` prints how far they lie there); how the trained poses err about the
pelvis apart from what stays the same all clip long (`pose_drift`), across the image and along the viewing
direction; and the PSNR of the training frames at
the poses the avatar trained on, against the true frames (the mean, the first frame and the worst), beside the
same frames of the first reference at the exact poses. OUT/training_frames.png shows the first and the worst of
those frames: the truth, the own-video avatar, the reference.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from avatarperfect_cli.avatar.model import Avatar
from avatarperfect_cli.avatar.rendering import render_avatar
from avatarperfect_cli.body import forward_kinematics, load_body_template, posed_joints
from avatarperfect_cli.datasets import VideoDataset, load_people_snapshot, write_people_snapshot
from avatarperfect_cli.datasets.people_snapshot import FrameRange
from avatarperfect_cli.io.images import write_image
from avatarperfect_cli.io.video import frame_writer
from avatarperfect_cli.io.workspace import Workspace, open_workspace
from avatarperfect_cli.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from avatarperfect_cli.sample.generate import make_sample
from avatarperfect_cli.stages.workspace_data import body_template, load_video, transl_offset
from avatarperfect_cli.training import metrics
from avatarperfect_cli.training.losses import boundary_band
from avatarperfect_cli.training.silhouette import project
from avatarperfect_cli.training.trainer import TrainConfig
from benchmarks.cut_frames import cut_frames
from benchmarks.mask_error import long_shares

CLI = [sys.executable, "-m", "avatarperfect_cli"]


POSE_PARTS = ("root", "limbs", "all")
MASK_BAND = TrainConfig().mask_band  # pixels either side of a mask's edge where the trainer lets the frame decide


def with_true_poses(sample_train: Path, prepared: Path, out: Path, test_out: Path, part: str) -> None:
    """A copy of the prepared folder at `out` with the `part` of its poses (POSE_PARTS) replaced by the truth's
    in `prepare`'s camera frame, and at `test_out` the true frames with the same poses and `prepare`'s camera."""
    truth, video = load_people_snapshot(sample_train, with_images=False), load_people_snapshot(prepared, with_images=False)
    body_pose, transl = video.body_pose.clone(), video.transl.clone()
    if part in ("root", "all"):
        # truth world -> camera -> prepare's world; the body turns about its pelvis, which stays put
        change = torch.linalg.inv(video.camera.world_to_camera.double()) @ truth.camera.world_to_camera.double()
        rotation, shift = change[:3, :3], change[:3, 3]
        pelvis = load_body_template("anny", phenotype=truth.subject["phenotype"]).rest_joints[0].double()
        body_pose[:, 0] = matrix_to_axis_angle(rotation @ axis_angle_to_matrix(truth.body_pose[:, 0].double())).float()
        transl = ((pelvis + truth.transl.double()) @ rotation.T + shift - pelvis).float()
    if part in ("limbs", "all"):
        body_pose[:, 1:] = truth.body_pose[:, 1:]
    shutil.copytree(prepared, out, dirs_exist_ok=True)
    mixed_folder(sample_train, prepared, test_out, "truth", "truth", "video")
    for folder in (out, test_out):
        poses = dict(np.load(folder / "poses.npz"))
        poses["thetas"], poses["transl"] = body_pose.reshape(len(body_pose), -1).numpy(), transl.numpy()
        np.savez(folder / "poses.npz", **poses)


def with_true_masks(sample_train: Path, prepared: Path, out: Path, beyond_band: int | None = None) -> None:
    """A copy of the prepared folder at `out` (its frames as filmed, its camera and poses) with the sample's masks;
    with `beyond_band`, only the pixels where they differ more than that many pixels from the prepared mask's edge
    take the true value (the errors the trainer's mask band does not reach)."""
    truth, video = load_people_snapshot(sample_train, downscale=1), load_people_snapshot(prepared, downscale=1)
    shutil.copytree(prepared, out, dirs_exist_ok=True)
    for frame, true, mask in zip(truth.frame_ids.tolist(), truth.masks, video.masks):
        if beyond_band is not None:
            true = torch.where((true ^ mask) & ~boundary_band(mask, beyond_band), true, mask)
        np.save(out / "masks" / f"mask_{frame:04d}.npy", true.numpy().astype(np.uint8))


def mask_errors(sample_train: Path, prepared: Path, band: int = MASK_BAND) -> dict[str, float]:
    """How `prepare`'s masks differ from the true ones over all frames: the share of the true area they add
    ("added") and leave out ("left_out"); the 90th and 99th percentiles of the wrong pixels' distances from
    the true outline, pixels ("p90", "p99"); the share of the wrong pixels lying more than `band` pixels from
    the prepared mask's edge ("beyond_band": outside the trainer's mask band, where the mask alone decides)."""
    truth, video = load_people_snapshot(sample_train, downscale=1), load_people_snapshot(prepared, downscale=1)
    added = left_out = beyond = 0
    distances = []
    for true, mask in zip(truth.masks, video.masks):
        wrong, inside = (true ^ mask).numpy(), true.numpy().astype(np.uint8)
        added, left_out = added + int((mask & ~true).sum()), left_out + int((true & ~mask).sum())
        beyond += int((wrong & ~boundary_band(mask, band).numpy()).sum())
        outline = np.where(inside, cv2.distanceTransform(inside, cv2.DIST_L2, 5), cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5))
        distances.append(outline[wrong])
    area, wrong = int(truth.masks.sum()), added + left_out
    p90, p99 = np.percentile(np.concatenate(distances), [90, 99]) if wrong else (0.0, 0.0)
    return {"added": added / area, "left_out": left_out / area, "p90": float(p90), "p99": float(p99), "beyond_band": beyond / max(wrong, 1)}


def mask_errors_picture(sample_train: Path, prepared: Path, frame: int) -> torch.Tensor:
    """(H, W, 3) the prepared frame `frame` at half brightness, red where `prepare`'s mask adds to the true one
    and blue where it leaves the person out, cropped to the person's box grown by 20 px."""
    span = FrameRange(frame, frame, 1)
    truth, video = load_people_snapshot(sample_train, span, downscale=1), load_people_snapshot(prepared, span, downscale=1)
    true, mask = truth.masks[0], video.masks[0]
    picture = video.filmed[0].float() / 255.0 * 0.5
    picture[mask & ~true] = torch.tensor([1.0, 0.0, 0.0])
    picture[true & ~mask] = torch.tensor([0.0, 0.3, 1.0])
    ys, xs = torch.nonzero(true | mask, as_tuple=True)
    height, width = true.shape
    return picture[max(int(ys.min()) - 20, 0) : min(int(ys.max()) + 21, height), max(int(xs.min()) - 20, 0) : min(int(xs.max()) + 21, width)]


def background(height: int, width: int) -> np.ndarray:
    """(H, W, 3) float in [0, 1]: a grey-blue wall with a faint tile pattern over a brown floor."""
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    wall = np.stack([0.55 + 0.1 * rows / height, 0.6 + 0.05 * cols / width, 0.7 * np.ones_like(rows)], axis=-1)
    tiles = ((rows // max(height // 12, 1) + cols // max(width // 12, 1)) % 2)[..., None]
    floor = np.array([0.45, 0.35, 0.25]) * (0.8 + 0.2 * cols[..., None] / width)
    picture = np.where((rows > 0.8 * height)[..., None], floor, wall - 0.05 * tiles)
    return np.clip(picture, 0.0, 1.0)


def write_video(train: Path, output: Path) -> None:
    """The training folder's people over `background`, as an .mp4 (lossy, like a phone's)."""
    video = load_people_snapshot(train, downscale=1)
    scene = torch.from_numpy(background(video.camera.height, video.camera.width)).float()
    with frame_writer(output, video.camera.width, video.camera.height, 30.0) as write:
        for image, mask in zip(video.images, video.masks):
            write(torch.where(mask[..., None], image, scene))


def mixed_folder(sample_train: Path, prepared: Path, out: Path, images_from: str, masks_from: str, poses_from: str) -> None:
    """A folder of the same frames with images, masks and camera + poses + subject each taken from the
    sample ("truth") or the prepared folder ("video"); refuses a prepared folder missing frames."""
    sources = {"truth": load_people_snapshot(sample_train, downscale=1), "video": load_people_snapshot(prepared, downscale=1)}
    if not torch.equal(sources["truth"].frame_ids, sources["video"].frame_ids):
        raise SystemExit(f"{prepared} has frames {sources['video'].frame_ids.tolist()}, the video {len(sources['truth'])}")
    images = (sources[images_from].images.numpy() * 255.0).round().astype(np.uint8)
    poses = sources[poses_from]
    write_people_snapshot(out, images, sources[masks_from].masks.numpy(), poses.body_pose, poses.transl, poses.camera, subject=poses.subject)


def decoded_psnr(sample_train: Path, prepared: Path, inset: int = 3) -> float:
    """PSNR (dB) of the prepared folder's decoded frames against the sample's, over the pixels both masks hold
    `inset` pixels inside their edges (the person, not the background or its boundary)."""
    truth = load_people_snapshot(sample_train, downscale=1)
    video = load_people_snapshot(prepared, downscale=1)
    both = (truth.masks & video.masks).float()[:, None]
    inside = -torch.nn.functional.max_pool2d(-both, 2 * inset + 1, 1, inset)[:, 0] > 0.5
    return float(-10.0 * torch.log10((video.images - truth.images)[inside].square().mean()))


def world_joints(video: VideoDataset, rest_joints: torch.Tensor) -> torch.Tensor:
    """(T, 24, 3) metres, world frame: the video's posed joints of the body whose rest joints are `rest_joints` (24, 3)."""
    rest_joints = rest_joints.float()
    return posed_joints(forward_kinematics(video.body_pose.float(), rest_joints, video.transl.float()), rest_joints)


def image_joints(video: VideoDataset, rest_joints: torch.Tensor) -> torch.Tensor:
    """(T, 24, 2) pixels: the video's posed joints of the body whose rest joints are `rest_joints` (24, 3), in its camera."""
    return project(world_joints(video, rest_joints).reshape(-1, 3), video.camera).reshape(len(video), -1, 2)


def given_poses(prepared: Path, workspace: Workspace, frames: FrameRange) -> VideoDataset:
    """The prepared folder's poses of `frames` (no images), moved by the workspace's translation offset as it trains them."""
    given = load_people_snapshot(prepared, frames, with_images=False)
    given.transl = given.transl + transl_offset(workspace)
    return given


def joint_errors(sample_train: Path, prepared: Path, workspace: Path, frames: FrameRange) -> dict[str, torch.Tensor]:
    """(T,) mean image distance (pixels) of the training frames' joints from the truth's, per frame: with
    `prepare`'s poses and with the workspace's (both on the workspace's fitted body and offset)."""
    truth = load_people_snapshot(sample_train, frames, with_images=False)
    subject = load_body_template("anny", phenotype=truth.subject["phenotype"]).rest_joints
    expected = image_joints(truth, subject)
    opened = open_workspace(workspace)
    fitted = body_template(opened, opened.manifest["body_model"])
    given = given_poses(prepared, opened, frames)
    trained = load_video(opened, with_images=False)
    return {
        name: (image_joints(video, fitted.rest_joints) - expected).norm(dim=-1).mean(dim=-1)
        for name, video in (("prepare's poses", given), ("the workspace's poses", trained))
    }


JOINT_GROUPS = {"all joints": list(range(24)), "hands and wrists": [20, 21, 22, 23], "ankles and feet": [7, 8, 10, 11]}


def camera_frame_joints(video: VideoDataset, rest_joints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The video's posed joints (T, 24, 3) metres in its camera's frame, and its root orientations there (T, 3, 3)."""
    world = world_joints(video, rest_joints)
    world_to_camera = torch.as_tensor(video.camera.world_to_camera).float()
    rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return world @ rotation.T + translation, rotation @ axis_angle_to_matrix(video.body_pose[:, 0].float())


def pose_drift(sample_train: Path, poses: VideoDataset, rest_joints: torch.Tensor, frames: FrameRange) -> dict[str, tuple[float, float]]:
    """How `poses` (the training frames', on the body whose rest joints are `rest_joints`) err about the pelvis, apart
    from what stays the same all clip long: each joint's offset from the pelvis against the truth's, in the true
    body's frame, less its mean over the frames (a fitted skeleton's own proportions), seen in the camera's axes.
    Per group of JOINT_GROUPS: the mean (across the image, along the viewing direction), cm."""
    truth = load_people_snapshot(sample_train, frames, with_images=False)
    true_joints, true_roots = camera_frame_joints(truth, load_body_template("anny", phenotype=truth.subject["phenotype"]).rest_joints)
    posed, _ = camera_frame_joints(poses, rest_joints)
    about_pelvis = (posed - posed[:, :1]) - (true_joints - true_joints[:, :1])
    in_body = torch.einsum("tji,tkj->tki", true_roots, about_pelvis)
    changing = torch.einsum("tij,tkj->tki", true_roots, in_body - in_body.mean(dim=0))
    return {
        name: (100 * changing[:, joints, :2].norm(dim=-1).mean().item(), 100 * changing[:, joints, 2].abs().mean().item())
        for name, joints in JOINT_GROUPS.items()
    }


def pose_drift_line(label: str, drift: dict[str, tuple[float, float]]) -> str:
    return f"| {label} | " + " | ".join(f"{across:.2f} / {along:.2f}" for across, along in drift.values()) + " |"


def training_psnr(workspace: Path, truth_test: Path, frames: FrameRange) -> torch.Tensor:
    """(T,) PSNR (dB) of the workspace's avatar in its training frames, at the poses it trained on, against the
    true frames (`truth_test`: the sample's images through the camera the workspace trained with: OUT/truth-test
    for the own video, the sample's folder for the references)."""
    opened = open_workspace(workspace)
    avatar, trained = Avatar.load(opened.require_avatar()), load_video(opened, with_images=False)
    truth = load_people_snapshot(truth_test, frames)
    with torch.no_grad():
        renders = [render_avatar(avatar, trained.body_pose[t], trained.transl[t], truth.camera, torch.ones(3)).image for t in range(len(truth))]
    return torch.tensor([metrics.psnr(render.clamp(0, 1), image) for render, image in zip(renders, truth.images)])


def training_frames_picture(out: Path, frames: FrameRange, shown: list[int]) -> torch.Tensor:
    """(H, W, 3) rows of training frames `shown` (indices into `frames`): the true frame, the own-video avatar
    at the poses it trained on (through `prepare`'s camera), and the video-frames reference at the exact poses,
    each row cropped to the person's box in the three."""
    own, reference = open_workspace(out / "ws-own"), open_workspace(out / "ws-video-exact")
    rows = []
    for index in shown:
        frame = FrameRange(frames.start + index * frames.step, frames.start + index * frames.step, 1)
        truth, seen = load_people_snapshot(out / "sample" / "train", frame), load_people_snapshot(out / "truth-test", frame)
        panels = [truth.images[0]]
        for workspace, camera in ((own, seen.camera), (reference, truth.camera)):
            avatar, trained = Avatar.load(workspace.require_avatar()), load_video(workspace, with_images=False)
            with torch.no_grad():
                out_image = render_avatar(avatar, trained.body_pose[index], trained.transl[index], camera, torch.ones(3)).image
            panels.append(out_image.clamp(0, 1))
        inked = torch.stack(panels).lt(0.98).any(dim=-1).any(dim=0)
        ys, xs = torch.nonzero(inked, as_tuple=True)
        rows.append(torch.cat([panel[int(ys.min()) : int(ys.max()) + 1, int(xs.min()) : int(xs.max()) + 1] for panel in panels], dim=1))
    width = max(row.shape[1] for row in rows)
    return torch.cat([torch.nn.functional.pad(row, (0, 0, 0, width - row.shape[1]), value=1.0) for row in rows], dim=0)


def scores(workspace: Path, test: Path) -> dict:
    """The latest metrics.json of `workspace` on `test`."""
    return json.loads((open_workspace(workspace).eval_dir() / test.name / "metrics.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--fov", type=float, help="prepare's field of view, degrees (default: prepare's assumed one)")
    parser.add_argument("--split", action="store_true", help="also the references with only the images or only the masks the video's")
    parser.add_argument("--cut", type=int, help="keep only the top CUT pixel rows of every frame (a person the frame cuts off)")
    parser.add_argument("--fitted-body", action="store_true", help="also the first reference on the body fitted to its masks")
    parser.add_argument("--true-poses", nargs="+", choices=POSE_PARTS, default=[], metavar="PART",
                        help=f"also the own video with this part of its poses the truth's ({', '.join(POSE_PARTS)})")
    parser.add_argument("--true-masks", action="store_true", help="also the own video with the true masks in place of prepare's")
    args = parser.parse_args()
    out, frames = args.out, args.frames
    train, even, odd = out / "sample" / "train", f"0:{frames - 1}:2", f"1:{frames - 1}:2"
    if not (train / "poses.npz").is_file():
        make_sample(out / "sample", args.preset, args.resolution, train_frames=frames, test_frames=1)
    if args.cut is not None:
        if not (out / "sample" / "train-cut" / "poses.npz").is_file():
            cut_frames(train, out / "sample" / "train-cut", args.cut)
        train = out / "sample" / "train-cut"
    if not (out / "video.mp4").is_file():
        write_video(train, out / "video.mp4")
    if not (out / "prepared" / "poses.npz").is_file():
        fov = () if args.fov is None else ("--fov", str(args.fov))
        subprocess.run([*CLI, "prepare", str(out / "video.mp4"), str(out / "prepared"), *fov], check=True)
    mixed_folder(train, out / "prepared", out / "truth-test", "truth", "truth", "video")  # the truth seen through prepare's camera and poses
    run = lambda *command: subprocess.run([*CLI, *map(str, command)], check=True)  # noqa: E731
    iterations = ("--iterations", args.iterations)
    run("train-initial", out / "prepared", out / "ws-own", "--frames", even, *iterations, "--force")
    run("evaluate", out / "ws-own", "--test", out / "truth-test", "--frames", odd, "--refine-poses")
    references = {"video-exact": ("the video's frames and masks", "video", "video")}
    if args.split:
        references |= {"video-images": ("the video's frames, exact masks", "video", "truth"),
                       "video-masks": ("the sample's frames, prepare's masks", "truth", "video")}  # fmt: skip
    for name, (_, images_from, masks_from) in references.items():
        mixed_folder(train, out / "prepared", out / name, images_from, masks_from, "truth")
    folders = [(out / name, out / f"ws-{name}") for name in references] + [(train, out / "ws-exact")]
    for folder, workspace in folders:
        run("train-initial", folder, workspace, "--frames", even, "--body-shape", "exact", *iterations, "--force")
        run("evaluate", workspace, "--test", train, "--frames", odd)
    fitted_body = out / "ws-video-exact-fitted-body"
    if args.fitted_body:
        run("train-initial", out / "video-exact", fitted_body, "--frames", even, "--body-shape", "fit", *iterations, "--force")
        for workspace in (fitted_body, out / "ws-video-exact"):
            run("evaluate", workspace, "--test", train, "--frames", odd, "--refine-poses")
    for part in args.true_poses:
        with_true_poses(train, out / "prepared", out / f"prepared-true-{part}", out / f"truth-test-true-{part}", part)
        run("train-initial", out / f"prepared-true-{part}", out / f"ws-true-{part}", "--frames", even, *iterations, "--force")
        run("evaluate", out / f"ws-true-{part}", "--test", out / f"truth-test-true-{part}", "--frames", odd, "--refine-poses")
    mask_variants = {"true-masks": None, "true-masks-beyond-band": MASK_BAND} if args.true_masks else {}
    for name, beyond_band in mask_variants.items():
        with_true_masks(train, out / "prepared", out / f"prepared-{name}", beyond_band)
        run("train-initial", out / f"prepared-{name}", out / f"ws-{name}", "--frames", even, *iterations, "--force")
        run("evaluate", out / f"ws-{name}", "--test", out / "truth-test", "--frames", odd, "--refine-poses")
    own = scores(out / "ws-own", out / "truth-test")
    rows = [
        ("own video, given poses", out / "ws-own", own["mean"]),
        ("own video, refined poses", out / "ws-own", own["refined_poses"]["mean"]),
        *[(f"{label}, exact poses and body", out / f"ws-{name}", scores(out / f"ws-{name}", train)["mean"])
          for name, (label, _, _) in references.items()],
        ("the sample's frames, exact poses and body", out / "ws-exact", scores(out / "ws-exact", train)["mean"]),
    ]  # fmt: skip
    rows += [(f"own video, {part} of the poses the truth's, test poses refined", out / f"ws-true-{part}",
              scores(out / f"ws-true-{part}", out / f"truth-test-true-{part}")["refined_poses"]["mean"]) for part in args.true_poses]
    labels = {"true-masks": "the true masks", "true-masks-beyond-band": f"prepare's masks true more than {MASK_BAND} px from their edge"}
    rows += [(f"own video, {labels[name]}, test poses refined", out / f"ws-{name}",
              scores(out / f"ws-{name}", out / "truth-test")["refined_poses"]["mean"]) for name in mask_variants]
    if args.fitted_body:
        fitted, exact = scores(fitted_body, train), scores(out / "ws-video-exact", train)
        rows += [
            ("the video's frames and masks, exact poses, fitted body", fitted_body, fitted["mean"]),
            ("the same, test poses refined", fitted_body, fitted["refined_poses"]["mean"]),
            ("the video's frames and masks, exact poses and body, test poses refined", out / "ws-video-exact", exact["refined_poses"]["mean"]),
        ]
    print("| path | IoU | PSNR (dB) | SSIM | Gaussians | > 3 cm |\n|---|---:|---:|---:|---:|---:|")
    for label, workspace, mean in rows:
        count, shares = long_shares(open_workspace(workspace).require_avatar())
        print(f"| {label} | {mean['iou']:.3f} | {mean['psnr']:.2f} | {mean['ssim']:.4f} | {count:,} | {100 * shares[0]:.2f} % |")
    print(f"the video's decoded frames inside the person: {decoded_psnr(train, out / 'prepared'):.2f} dB from the true ones")
    training = FrameRange(0, frames - 1, 2)
    for name, errors in joint_errors(train, out / "prepared", out / "ws-own", training).items():
        worst = int(errors.argmax())
        print(f"training frames' joints with {name}: {errors.mean():.2f} px from the truth on average, "
              f"{errors[worst]:.2f} px at frame {training.start + worst * training.step}")
    opened = open_workspace(out / "ws-own")
    trained = {"prepare's poses": (given_poses(out / "prepared", opened, training), opened), "the poses the own video trained on": (load_video(opened, with_images=False), opened)}
    for part in args.true_poses:
        variant = open_workspace(out / f"ws-true-{part}")
        trained[f"the same from {part} of the poses the truth's"] = (load_video(variant, with_images=False), variant)
    for name in mask_variants:
        variant = open_workspace(out / f"ws-{name}")
        trained[f"the same with {labels[name]}"] = (load_video(variant, with_images=False), variant)
    print("training poses' error about the pelvis that changes over the clip, across the image / along the view (cm)")
    print("| poses | " + " | ".join(JOINT_GROUPS) + " |\n|---|" + "---:|" * len(JOINT_GROUPS))
    for label, (poses, workspace) in trained.items():
        rest_joints = body_template(workspace, workspace.manifest["body_model"]).rest_joints
        print(pose_drift_line(label, pose_drift(train, poses, rest_joints, training)))
    psnrs = training_psnr(out / "ws-own", out / "truth-test", training)
    print(f"training frames at the poses the avatar trained on: {psnrs.mean():.2f} dB against the true frames, "
          f"{psnrs[0]:.2f} dB in the first, {psnrs.min():.2f} dB at frame {training.start + int(psnrs.argmin()) * training.step}")
    for part in args.true_poses:
        print(f"the same with {part} of the poses the truth's: "
              f"{training_psnr(out / f'ws-true-{part}', out / f'truth-test-true-{part}', training).mean():.2f} dB")
    for name in mask_variants:
        print(f"the same with {labels[name]}: {training_psnr(out / f'ws-{name}', out / 'truth-test', training).mean():.2f} dB")
    if args.true_masks:
        errors = mask_errors(train, out / "prepared")
        print(f"prepare's masks add {100 * errors['added']:.1f} % of the true area and leave out {100 * errors['left_out']:.1f} %; "
              f"of those pixels 90 % lie within {errors['p90']:.1f} px of the true outline and 99 % within {errors['p99']:.1f} px, "
              f"and {100 * errors['beyond_band']:.0f} % more than {MASK_BAND} px from the mask's edge")
        shown = training.start + int(psnrs.argmin()) * training.step
        write_image(out / "mask_errors.png", mask_errors_picture(train, out / "prepared", shown))
        print(f"wrote {out / 'mask_errors.png'}: frame {shown}, red where prepare's mask adds, blue where it leaves out")
    reference = training_psnr(out / "ws-video-exact", train, training)
    print(f"the same frames of the reference at the exact poses: {reference.mean():.2f} dB, {reference[0]:.2f} dB in the first, "
          f"{reference[int(psnrs.argmin())]:.2f} dB at the own video's worst")
    write_image(out / "training_frames.png", training_frames_picture(out, training, [0, int(psnrs.argmin())]))
    print(f"wrote {out / 'training_frames.png'}: the first and the worst training frame, truth, own video, reference")
    if args.fitted_body:
        errors = joint_errors(train, out / "prepared", fitted_body, training)["the workspace's poses"]
        print(f"training frames' joints on the fitted body at the exact poses: {errors.mean():.2f} px from the truth on average")


if __name__ == "__main__":
    main()
