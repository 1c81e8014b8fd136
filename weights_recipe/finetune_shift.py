"""Fine-tuning under a simulated domain shift, scored with ground truth it never reads.

    python weights_recipe/finetune_shift.py DIR [--train 1-8] [--score 9-16]
        [--run "defaults"] [--run "lr=1e-3 anchor=0"] [--run "oracle loss.sequence=1"] …

Makes (once) the sets ``DIR/B_NN.h5`` from Kodak images (a sensor outside the training ranges:
c = 0.7, shot noise 0.2, a 40 ms exposure, up to 40 px of motion; the recipe of
docs/experiments.md), prepares the training sets' windows once, and for each ``--run``
fine-tunes the shipped weights on them and scores TRMD on the other sets (PSNR middle /
sequence, as ``trmd eval``). A run is ``KEY=VALUE`` words over :class:`FinetuneConfig`
(``steps``, ``lr``, ``anchor``, ``trainable=refine,head`` …); ``loss.NAME=W`` words replace
the default losses by those given; ``deconv_middle`` is the ``deconv`` term on the middle
frame only. ``oracle`` attaches the training windows' sharp frames and allows the supervised
losses (``loss.sequence``, ``loss.middle``): what ground truth would teach in the same run.
Each row also gives the fit on the training windows themselves (middle / sequence, against
their sharp frames), so fitting and learning can be told apart.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from trmd_cli.evaluate import evaluate
from trmd_cli.metrics import psnr
from trmd_cli.models.weights import load_weights, save_weights
from trmd_cli.read.dataset import open_dataset
from trmd_cli.train import finetune as ft
from trmd_cli.train.losses import _masked, register_loss

KODAK = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "kodak24"
SENSOR = ["--count", "1", "--frames", "4", "--size", "240x180", "--contrast", "0.7",
          "--read-noise", "0.005", "--shot-noise", "0.2", "--exposure-ms", "40",
          "--motion-px", "40"]
KEEP_META = ("recipe", "training_data", "description", "architecture")


@register_loss("deconv_middle")
def deconv_middle_loss(outputs: dict, batch: dict, recipe) -> torch.Tensor:
    """The ``deconv`` term on the middle frame only (experiments; needs no sharp frames)."""
    n = outputs["latent"].shape[1] // 2
    return _masked(outputs["latent"][:, n] - batch["deconv"][:, n],
                   batch["deconv_mask"][:, n], recipe)


def span(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def make_sets(folder: Path, images: list[int]) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in images:
        path = folder / f"B_{i:02d}.h5"
        if not path.exists():
            subprocess.run([sys.executable, "-m", "trmd_cli", "simulate",
                            str(KODAK / f"kodim{i:02d}.png"), "-o", str(path), *SENSOR,
                            "--seed", f"2{i:02d}"], check=True, stdout=subprocess.DEVNULL)
        paths.append(path)
    return paths


def with_truth(windows: list[ft.Window], paths: list[Path], n: int) -> list[ft.Window]:
    truth = {f"{p.name}:{fr.name}": fr.truth for p in paths
             for fr in open_dataset(p, n=n).frames()}
    return [replace(w, sharp=truth[w.name].astype(np.float32)) for w in windows]


def parse_run(words: str) -> tuple[dict, bool]:
    kw: dict = {}
    losses: dict[str, float] = {}
    oracle = False
    for word in words.split():
        if word in ("defaults", "oracle"):
            oracle = oracle or word == "oracle"
            continue
        key, _, value = word.partition("=")
        if key.startswith("loss."):
            losses[key[5:]] = float(value)
        elif key == "trainable":
            kw[key] = tuple(value.split(","))
        else:
            kw[key] = ast.literal_eval(value)
    if losses:
        kw["losses"] = losses
    return kw, oracle


def fit(model: torch.nn.Module, windows: list[ft.Window]) -> tuple[float, float]:
    mids, seqs = [], []
    with torch.inference_mode():
        for w in windows:
            lat = ft._outputs(model, ft.window_batch(w, 3))["latent"][0, :, 0]
            lat = lat.clamp(0, 1).numpy()
            mids.append(psnr(lat[w.n], w.sharp[w.n]))
            seqs.append(np.mean([psnr(lat[k], w.sharp[k]) for k in range(2 * w.n + 1)]))
    return float(np.mean(mids)), float(np.mean(seqs))


def pair(figures: tuple[float, float]) -> str:
    return f"{figures[0]:.2f} / {figures[1]:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--train", default="1-8", help="Kodak images fine-tuned on")
    ap.add_argument("--score", default="9-16", help="Kodak images scored")
    ap.add_argument("--run", action="append", default=None, help="a run (repeatable)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    train_sets = make_sets(args.folder, span(args.train))
    score_sets = make_sets(args.folder, span(args.score))
    model, meta = load_weights(None, device="cpu")
    t = time.perf_counter()
    windows, _ = ft.prepare_windows(ft.input_groups(train_sets), model.n,
                                    timing=model.needs.timing, config=ft.FinetuneConfig())
    windows = with_truth(windows, train_sets, model.n)
    print(f"{len(windows)} windows of {len(train_sets)} sets in "
          f"{time.perf_counter() - t:.0f} s", flush=True)

    def score(weights: Path | None) -> tuple[float, float]:
        o = evaluate(score_sets, "trmd", n=model.n, weights=weights).overall(True)["trmd"]
        return o["psnr_mid"], o["psnr_seq"]

    print("| run | scored (mid / seq) | fit on the training windows | s |")
    print("|---|---|---|---|")
    print(f"| shipped | {pair(score(None))} | {pair(fit(model, windows))} | |", flush=True)
    for words in args.run or ["defaults"]:
        kw, oracle = parse_run(words)
        config = ft.FinetuneConfig(**kw, oracle=oracle)
        net, _ = load_weights(None, device="cpu")
        train, _ = ft.split_windows(windows, config.holdout)
        # the GT-free runs must not see the sharp frames: only the oracle's batches carry them
        train = train if oracle else [replace(w, sharp=None) for w in train]
        t = time.perf_counter()
        ft.tune(net, train, config)
        dt = time.perf_counter() - t
        path = args.folder / f"run_{abs(hash(words)) % 10**8}.safetensors"
        save_weights(path, net, meta={k: v for k, v in meta.items() if k in KEEP_META})
        print(f"| {words} | {pair(score(path))} | {pair(fit(net, windows))} | {dt:.0f} |",
              flush=True)


if __name__ == "__main__":
    main()
