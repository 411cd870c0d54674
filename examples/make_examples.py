"""Rebuild the committed examples and the sample's documentation figures.

    python examples/make_examples.py motions   # examples/motions/{walk,raise_arms,squat}.npz
    python examples/make_examples.py sample    # examples/sample/{train,test}: 256 px, 60 + 20 frames
    python examples/make_examples.py report    # full 512 px sample in out/sample: timing, hidden-region
                                               # fractions and docs/images/sample_contact_sheet.png
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from avatarperfect_cli.sample.generate import make_sample, write_example_motions

ROOT = Path(__file__).resolve().parents[1]
SHEET_CELL = 224  # pixels per contact-sheet cell


def contact_sheet(sample: Path, out: Path, train_ids: list[int], test_ids: list[int]) -> None:
    """Write two labelled rows of frames from `sample` (training on top, test below) to `out`."""
    rows = []
    for split, ids in (("train", train_ids), ("test", test_ids)):
        cells = []
        for frame in ids:
            image = Image.open(sample / split / "images" / f"image_{frame:04d}.png").convert("RGB")
            side = image.width  # keep the middle three quarters of each square frame's width
            cell = image.crop((side // 8, 0, side - side // 8, side))
            cell = cell.resize((SHEET_CELL * 3 // 4, SHEET_CELL), Image.LANCZOS)
            ImageDraw.Draw(cell).text((4, 4), f"{split} {frame}", fill=(0, 0, 0))
            cells.append(np.asarray(cell))
        rows.append(np.concatenate(cells, axis=1))
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(out, optimize=True)


def main(task: str) -> None:
    if task == "motions":
        for path in write_example_motions(ROOT / "examples" / "motions"):
            print(path.relative_to(ROOT))
    elif task == "sample":
        make_sample(ROOT / "examples" / "sample", resolution=256, seed=0, train_frames=60, test_frames=20)
    elif task == "report":
        out = ROOT / "out" / "sample"
        start = time.perf_counter()
        make_sample(out)
        print(f"make_sample 512 px, 100 + 30 frames: {time.perf_counter() - start:.1f} s")
        for split in ("train", "test"):
            fractions = json.loads((out / split / "subject.json").read_text())["hidden_region_fraction"]
            print(split, json.dumps({key: round(value, 4) for key, value in fractions.items()}))
        sheet = ROOT / "docs" / "images" / "sample_contact_sheet.png"
        contact_sheet(out, sheet, train_ids=[0, 13, 25, 38, 50, 75], test_ids=[3, 11, 16, 20, 24, 28])
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "")
