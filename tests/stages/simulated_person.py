"""A simulated person at an image editor, started by `avatarperfect loop --editor` with the image to paint.

    python simulated_person.py SUBJECT MODES .../suggestions/NNN/suggested.png

SUBJECT: the make-sample folder; MODES: one comma-separated mode per suggestion number (the last repeats):
    paint       save painted.png beside the image, written whole in one go
    half-first  write the first half of painted.png's bytes, wait HALF_S (longer than the loop's settle time,
                so that only the decode check can tell), then the rest: a save still being written
    overwrite   save the painting over suggested.png itself
    unchanged   save an unchanged copy of the image as painted.png
The painting is simulate-user's (`sample.simulated_user.paint`) against the subject's exact render; it is
written after DELAY_S, as a person would take a while.
"""

from __future__ import annotations

import io
import sys
import time
from pathlib import Path

from PIL import Image

from avatarperfect_cli.io import read_image, read_pose
from avatarperfect_cli.sample.simulated_user import UserConfig, paint
from avatarperfect_cli.sample.subject import SyntheticSubject
from avatarperfect_cli.stages.simulate_user import subject_folder

DELAY_S = 0.5
HALF_S = 2.0


def painting(subject: Path, folder: Path) -> bytes:
    """PNG bytes of simulate-user's painting of the suggestion in `folder`."""
    pose = read_pose(folder / "pose.json")
    suggested = read_image(folder / "suggested.png", "RGB")
    alpha = read_image(folder / "suggested_alpha.png", "L")[..., 0]
    truth = SyntheticSubject.from_dataset(subject_folder(subject)).render(pose.body_pose, pose.transl, pose.camera)
    pixels = (paint(suggested, alpha, truth, UserConfig()).image.clamp(0, 1) * 255).round().byte().numpy()
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return buffer.getvalue()


def main(subject: Path, modes: list[str], image: Path) -> None:
    folder = image.parent
    mode = modes[min(int(folder.name), len(modes)) - 1]
    data = image.read_bytes() if mode == "unchanged" else painting(subject, folder)
    time.sleep(DELAY_S)
    target = image if mode == "overwrite" else folder / "painted.png"
    with open(target, "wb") as file:
        if mode == "half-first":
            file.write(data[: len(data) // 2])
            file.flush()
            time.sleep(HALF_S)
        file.write(data[len(data) // 2 :] if mode == "half-first" else data)


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2].split(","), Path(sys.argv[3]))
