"""Two study runs on the same initial avatars, compared run by run (B minus A).

    python -m benchmarks.compare_studies A/study.json B/study.json [--a-condition ap-exact] [--b-condition ap-exact]

The loop is chaotic after its first round: the same code with kernels that differ by float32 rounding moved
a nine-run mean by 0.08 dB held out and single runs by up to 0.76 dB in the hidden regions (docs/study.md,
"Reading a difference"). A trial is worth keeping only where the paired differences clear that band, so this
prints each run's difference and how many runs went each way, not only the means.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

METRICS = (
    ("psnr", "PSNR"), ("psnr_hidden", "PSNR hidden"), ("psnr_armpit", "PSNR armpit"),
    ("worst_training_change", "worst train dPSNR"), ("seconds_per_round", "s/round"),
)  # fmt: skip


def paired_runs(a: dict, b: dict, a_condition: str, b_condition: str) -> list[tuple[str, dict, dict]]:
    """(label, A's row, B's row) for every subject and seed both studies ran with their conditions."""
    runs = []
    for preset in sorted(set(a) & set(b)):
        for seed in sorted(set(a[preset]) & set(b[preset]), key=int):
            if a_condition in a[preset][seed] and b_condition in b[preset][seed]:
                runs.append((f"{preset} seed {seed}", a[preset][seed][a_condition], b[preset][seed][b_condition]))
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--a-condition", default="ap-exact")
    parser.add_argument("--b-condition", default="ap-exact")
    args = parser.parse_args()
    runs = paired_runs(json.loads(args.a.read_text()), json.loads(args.b.read_text()), args.a_condition, args.b_condition)
    if not runs:
        raise SystemExit("the two studies share no subject and seed with those conditions")
    names = [name for name, _ in METRICS]
    print(f"B ({args.b_condition}, {args.b}) minus A ({args.a_condition}, {args.a}), {len(runs)} runs\n")
    print("| run | " + " | ".join(label for _, label in METRICS) + " |")
    print("|---|" + "---|" * len(METRICS))
    differences = {name: [] for name in names}
    for label, row_a, row_b in runs:
        cells = []
        for name in names:
            if name in row_a and name in row_b:
                differences[name].append(row_b[name] - row_a[name])
                cells.append(f"{differences[name][-1]:+.2f}")
            else:
                cells.append("—")
        print(f"| {label} | " + " | ".join(cells) + " |")
    summary = []
    for name in names:
        values = differences[name]
        summary.append(
            f"{statistics.fmean(values):+.2f} ({sum(v > 0 for v in values)} up, {sum(v < 0 for v in values)} down)" if values else "—"
        )
    print("| **mean** | " + " | ".join(summary) + " |")


if __name__ == "__main__":
    main()
