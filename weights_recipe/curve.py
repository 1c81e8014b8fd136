"""The training curve of the shipped weights, all three stages on one step axis.

    python weights_recipe/curve.py -o docs/images/training_curve.png

Reads ``shipped-v2-stage1_log.csv``, ``shipped-v2_log.csv`` and ``shipped-v3_log.csv`` beside
this script (copies of the runs' ``log.csv``); each stage's steps are counted on from the last
one of the stage before. Stage 3 validates with the true threshold and an average of the
weights; the figures in README.md use the estimated threshold.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

HERE = Path(__file__).resolve().parent


def read_log(path: Path, offset: int = 0) -> list[dict]:
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            row: dict = {"step": int(r["step"]) + offset}
            for key in ("loss", "val_psnr_mid", "val_psnr_seq"):
                row[key] = float(r[key]) if r.get(key) else None
            rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, required=True)
    args = ap.parse_args()
    from trmd_cli.train.plots import write_curve

    stage1 = read_log(HERE / "shipped-v2-stage1_log.csv")
    stage2 = read_log(HERE / "shipped-v2_log.csv", offset=stage1[-1]["step"])
    stage3 = read_log(HERE / "shipped-v3_log.csv", offset=stage2[-1]["step"])
    write_curve(args.output, stage1 + stage2 + stage3,
                title=f"shipped-v3 (stage 2 from step {stage1[-1]['step']}, "
                      f"stage 3 from {stage2[-1]['step']})")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
