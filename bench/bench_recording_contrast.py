"""One contrast threshold per recording against one per frame, on simulated recordings.

    python bench/bench_recording_contrast.py [--frames 8] [--images 6]

Each recording is one image moved along one camera path over ``--frames`` exposures by one
simulated sensor (clean sensors at c = 0.15, 0.2, 0.3, and the DAVIS-like default), as
`bench/bench_edi.py --quality` makes its frames. Per way of settling c — per frame
(``--contrast frame``) and once per recording from its 1, 2 or 3 busiest frames
(:func:`trmd_cli.deblur.recording_contrast`), the frames sharing out the energy's instants or
each measured at all of them — printed: the error of c
against the sensor's true mean threshold (|log(c / c_true)|, mean and worst), the PSNR of EDI's
middle frame lost against the one made with the true c (mean and worst over every frame), and
the time the threshold took per frame (wall clock: reading excluded, the search's evaluations
and the objectives' set-up included).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_edi import IMAGES, load, psnr


class Recording:
    """A simulated recording as a frame source: ``len`` and ``subset(positions)``."""

    def __init__(self, seq) -> None:
        from trmd_cli.read.base import Frame
        from trmd_cli.read.folders import FrameWindow

        self.items = [FrameWindow(Frame(seq.blurry[k], ex, k, f"{k:03d}"),
                                  seq.events.slice(ex.start_us, ex.end_us + 1))
                      for k, ex in enumerate(seq.exposures)]

    def __len__(self) -> int:
        return len(self.items)

    def subset(self, positions):
        return [self.items[p] for p in sorted(set(positions))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8, help="exposures per recording")
    ap.add_argument("--images", type=int, default=6, help="recordings per sensor")
    args = ap.parse_args()

    from trmd_cli.deblur import recording_contrast
    from trmd_cli.methods import window_model
    from trmd_cli.simulate import SensorConfig
    from trmd_cli.simulate.sample import make_sequence
    from trmd_cli.threshold import search_contrast

    rng = np.random.default_rng(11)
    # (frames, whether they share out the instants) of each way of settling c per recording
    settings = {"recording, 1 frame": (1, True), "recording, 2 frames": (2, True),
                "recording, 3 frames": (3, True), "recording, 2, all instants": (2, False),
                "recording, 3, all instants": (3, False)}
    ways = ["per frame", *settings]
    for label, sensors in (("clean", [SensorConfig.clean(c) for c in (0.15, 0.2, 0.3)]),
                           ("DAVIS-like", [SensorConfig()])):
        err = {w: [] for w in ways}
        lost = {w: [] for w in ways}
        spent = {w: 0.0 for w in ways}
        frames = 0
        for name in IMAGES[: args.images]:
            img = load(name)
            for sensor in sensors:
                seq = make_sequence(img, frames=args.frames, rng=rng, sensor=sensor)
                rec = Recording(seq)
                models = [window_model(it.events, it.frame.exposure, True)[0]
                          for it in rec.items]
                t = time.perf_counter()
                per_frame = [search_contrast(it.frame.image, m).contrast
                             for it, m in zip(rec.items, models, strict=True)]
                # the per-frame search's models are built by the method anyway: not counted
                spent["per frame"] += time.perf_counter() - t
                chosen = {"per frame": per_frame}
                for way, (k, share) in settings.items():
                    t = time.perf_counter()
                    r = recording_contrast(rec, frames=k, share_instants=share)
                    spent[way] += time.perf_counter() - t
                    chosen[way] = [r.contrast] * len(rec.items)
                for w in ways:
                    for j, (it, m) in enumerate(zip(rec.items, models, strict=True)):
                        c = chosen[w][j]

                        def mid(cc, m=m, it=it, j=j, seq=seq):
                            return psnr(m.latent(it.frame.image, np.array([0.5]), cc)[0],
                                        seq.sharp[j, 3])

                        err[w].append(abs(np.log(c / seq.contrast)))
                        lost[w].append(mid(seq.contrast) - mid(c))
                frames += len(rec.items)
        print(f"{label} sensors, {frames} frames in {frames // args.frames} recordings:")
        for w in ways:
            print(f"  {w:27s} |log c/c_true| mean {np.mean(err[w]):.3f} worst "
                  f"{max(err[w]):.3f}; PSNR lost mean {np.mean(lost[w]):.3f} dB, worst "
                  f"{max(lost[w]):.3f} dB; {1e3 * spent[w] / frames:.1f} ms per frame")


if __name__ == "__main__":
    main()
