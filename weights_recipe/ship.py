"""Measure a trained candidate on the pinned validation set and ship it as the default weights.

    python weights_recipe/ship.py ../runs/s6-timing/final.safetensors \
        --valset ../runs/valset_kodak24.h5 [--dry-run]

Evaluates blurry, EDI given the true threshold, EDI with the automatic threshold and the
candidate (fp16, exactly as shipped) on every frame of the validation set, prints the table,
and writes ``src/trmd_cli/weights/trmd_default.safetensors`` with the figures in its metadata
and ``weights_recipe/figures.json`` beside this script. The validation file is recorded by its
name and SHA-256 (``relabel.py``), not by the path it had on the training machine.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from relabel import label_valset  # beside this script

HERE = Path(__file__).resolve().parent
TARGET = HERE.parent / "src" / "trmd_cli" / "weights" / "trmd_default.safetensors"
METHODS = ("blurry", "edi-true-c", "edi", "trmd")
FIGS = ("psnr_mid", "psnr_seq", "ssim_mid", "ssim_seq")


def measure(weights: Path, valset: Path, precision: str = "fp32") -> dict:
    from trmd_cli.evaluate import evaluate_dataset

    rep = evaluate_dataset(valset, METHODS, n=3, weights=weights, precision=precision)
    out = {m.method: {k: round(m.mean(k), 3) for k in FIGS} for m in rep.methods
           if not m.skipped}
    out["frames"] = rep.frames
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("candidate", type=Path)
    ap.add_argument("--valset", type=Path, required=True)
    ap.add_argument("--dry-run", action="store_true", help="measure only, ship nothing")
    ap.add_argument("--precision", default="fp32",
                    help="the network's arithmetic while measuring (default fp32; `trmd` itself "
                    "runs auto: bfloat16 on CPUs with AMX)")
    args = ap.parse_args()
    from trmd_cli.models.weights import load_weights, save_weights, weights_hash

    model, meta = load_weights(args.candidate)
    # what the model itself records (architecture, args, n …) is written again by save_weights
    own = {"format", "format_version", "architecture", "model_class", "dtype", "trmd_version",
           "n", "channels", "args"}
    meta = {k: v for k, v in meta.items() if k not in own}
    with tempfile.TemporaryDirectory() as d:
        half = Path(d) / "half.safetensors"
        save_weights(half, model, meta=meta, half=True)  # measure what ships: fp16
        figures = measure(half, args.valset, args.precision)
    figures["precision"] = args.precision
    t, e = figures["trmd"], figures["edi-true-c"]
    figures["margin_over_edi_true_c_db"] = {"mid": round(t["psnr_mid"] - e["psnr_mid"], 3),
                                            "seq": round(t["psnr_seq"] - e["psnr_seq"], 3)}
    print(f"{'method':<12}" + "".join(f"{k:>10}" for k in FIGS))
    for m in METHODS:
        if m in figures:
            print(f"{m:<12}" + "".join(f"{figures[m][k]:>10.3f}" for k in FIGS))
    print("TRMD − EDI(true c):", figures["margin_over_edi_true_c_db"])
    if args.dry_run:
        return
    meta = dict(meta)
    label_valset(meta.get("recipe"), meta.get("figures"), args.valset)
    meta["validation"] = {"set": "weights_recipe/make_valset.py (kodak24, 48 frames, 346x260)",
                          **figures}
    TARGET.parent.mkdir(exist_ok=True)
    save_weights(TARGET, model, meta=meta, half=True)
    (HERE / "figures.json").write_text(json.dumps(figures, indent=2) + "\n")
    print(f"shipped {TARGET} ({TARGET.stat().st_size / 2**20:.1f} MiB, sha {weights_hash(TARGET)})")


if __name__ == "__main__":
    main()
