"""The training curve of the shipped weights, all six stages on one step axis.

    python weights_recipe/curve.py -o docs/images/training_curve.png

Reads the stages' logs in ``logs/`` beside this script (copies of the runs' ``log.csv``:
``STAGES``); each stage's steps are counted on from the last one of the stage before. Stages 3–6
validate with the true threshold and an average of the weights; the figures in README.md use the
estimated threshold.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: the stages' logs in order (stage 4 was taken at step 2,000: its log ends there)
STAGES = tuple(f"logs/stage{k}.csv" for k in range(1, 7))


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

    rows: list[dict] = []
    starts = []
    for name in STAGES:
        starts.append(rows[-1]["step"] if rows else 0)
        rows += read_log(HERE / name, offset=starts[-1])
    title = "shipped v6, stages from steps " + ", ".join(str(s) for s in starts[1:])
    write_curve(args.output, rows, title=title)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
