"""How well and how cheaply the contrast search finds the minimum of its energy.

    python bench/bench_threshold_search.py

The same energy (:class:`trmd_cli.threshold.ContrastObjective`) minimised three ways on 32
simulated frames with a known threshold (8 images × clean sensors at c = 0.15, 0.2, 0.3 and a
DAVIS-like one, as `bench/bench_edi.py --quality`) and on the 8 real esl-cups frames:

* ``search``: :func:`trmd_cli.threshold.search_contrast` as shipped;
* ``13-point``: the earlier search (a coarse grid of 8, five points on a finer grid around its
  best, a parabola), written out here for comparison;
* ``dense``: a 49-point grid and a parabola, the reference minimum.

Printed per method: energy evaluations per frame, the distance of its c from the reference
minimum (|log(c / c_dense)|, mean and worst), and on the simulated frames the PSNR lost by the
middle EDI frame against the one made with the true c; then the esl-cups c of each frame.
"""

from __future__ import annotations

import numpy as np
from bench_edi import IMAGES, SHARED, load, psnr


class Counted:
    """The energy on log c, each point evaluated once."""

    def __init__(self, obj) -> None:
        self.obj, self.cache = obj, {}

    def __call__(self, x: float) -> float:
        if x not in self.cache:
            self.cache[x] = self.obj(float(np.exp(x)))
        return self.cache[x]


def _parabola(xs, fs) -> float:
    order = np.argsort(xs)
    xs, fs = np.asarray(xs)[order], np.asarray(fs)[order]
    k = int(np.argmin(fs))
    if 0 < k < len(xs) - 1:
        (x0, x1, x2), (f0, f1, f2) = xs[k - 1: k + 2], fs[k - 1: k + 2]
        den = (x1 - x0) * (f1 - f2) - (x1 - x2) * (f1 - f0)
        if den != 0:
            x = x1 - 0.5 * ((x1 - x0) ** 2 * (f1 - f2) - (x1 - x2) ** 2 * (f1 - f0)) / den
            if x0 < x < x2:
                return float(x)
    return float(xs[k])


def thirteen_point(f, lo: float, hi: float) -> float:
    coarse = np.linspace(lo, hi, 8)
    i = int(np.argmin([f(g) for g in coarse]))
    fine = np.linspace(coarse[max(i - 1, 0)], coarse[min(i + 1, 7)], 7)[1:-1]
    xs = np.concatenate([coarse, fine])
    return _parabola(xs, [f(x) for x in xs])


def dense(f, lo: float, hi: float) -> float:
    xs = np.linspace(lo, hi, 49)
    return _parabola(xs, [f(x) for x in xs])


def frames():
    from trmd_cli.edi import EdiEvents, check_blurry, hot_pixel_mask
    from trmd_cli.read import ReadOptions
    from trmd_cli.read.inputs import open_inputs
    from trmd_cli.simulate import SensorConfig, make_sample

    rng = np.random.default_rng(7)
    for name in IMAGES:
        img = load(name)
        for sensor in [SensorConfig.clean(c) for c in (0.15, 0.2, 0.3)] + [SensorConfig()]:
            s = make_sample(img, rng=rng, sensor=sensor)
            yield f"{name} c={s.contrast:.2f}", s.blurry, EdiEvents.build(s.events, s.exposure), s
    cups = SHARED / "real" / "esl-cups"
    if not cups.exists():
        return
    with open_inputs([cups / "images", cups / "mat"], ReadOptions()) as ins:
        for item in ins.source:
            ev, ex = item.events, item.frame.exposure
            b = check_blurry(item.frame.image, ev.width, ev.height)
            yield (f"esl-cups {item.frame.name}", b,
                   EdiEvents.build(ev, ex, hot_pixel_mask(ev, ex)), None)


def main() -> None:
    from trmd_cli.threshold import CONTRAST_BOUNDS, ContrastObjective, search_contrast

    lo, hi = np.log(CONTRAST_BOUNDS[0]), np.log(CONTRAST_BOUNDS[1])
    names = ("search", "13-point", "dense")
    evals = {k: [] for k in names}
    dist = {k: [] for k in names}
    loss = {k: [] for k in names}
    real = []
    for label, blurry, prep, sample in frames():
        found = {}
        est = search_contrast(blurry, prep)
        found["search"] = est.contrast
        evals["search"].append(est.evaluations)
        for key, method in (("13-point", thirteen_point), ("dense", dense)):
            f = Counted(ContrastObjective.from_events(prep, blurry))
            found[key] = float(np.exp(method(f, lo, hi)))
            evals[key].append(len(f.cache))
        for key in names:
            dist[key].append(abs(np.log(found[key] / found["dense"])))
        if sample is None:
            real.append((label, found))
            continue
        ref = psnr(prep.latent(blurry, np.array([0.5]), sample.contrast)[0], sample.sharp[3])
        for key in names:
            got = psnr(prep.latent(blurry, np.array([0.5]), found[key])[0], sample.sharp[3])
            loss[key].append(ref - got)
    print(f"{len(dist['search'])} frames ({len(loss['search'])} simulated, {len(real)} real)")
    for key in names:
        d, lo_ = np.array(dist[key]), np.array(loss[key])
        print(f"  {key:9s} {np.mean(evals[key]):4.1f} evaluations; |log(c / c_dense)| mean "
              f"{d.mean():.4f}, worst {d.max():.4f}; simulated: PSNR lost to the true c mean "
              f"{lo_.mean():+.3f} dB, worst {lo_.max():+.2f} dB")
    for label, found in real:
        print(f"  {label}: c = " + ", ".join(f"{k} {found[k]:.4f}" for k in names))


if __name__ == "__main__":
    main()
