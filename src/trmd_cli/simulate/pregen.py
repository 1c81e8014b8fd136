"""Pre-generate a simulated training set to one trmd HDF5 file, so that simulation does not
compete with training for the CPU. :class:`~trmd_cli.simulate.dataset.H5SampleDataset` reads it
back and yields exactly the items :class:`~trmd_cli.simulate.dataset.SimulatedDataset` would
have (same seed, same index).

Layout: the samples sit one after another on one timeline, sample ``i``'s exposure starting
``GAP_US`` after the previous one ends; ``frames/sharp`` holds the ground truth,
``frames/contrast`` each sample's true mean threshold, ``frames/motion`` its true camera path,
and the root attribute ``simulator`` the generator settings as JSON.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..events import EventStream
from ..write import H5Writer, check_output
from .sample import Sample

__all__ = ["pregenerate", "GAP_US"]

#: time between consecutive samples on the file's timeline, µs
GAP_US = 10_000

_WORKER_DS = None


def _init_worker(kwargs: dict) -> None:
    global _WORKER_DS
    from .dataset import SimulatedDataset

    _WORKER_DS = SimulatedDataset(**kwargs)


def _work(i: int) -> Sample:
    return _WORKER_DS.sample(i)  # type: ignore[union-attr]


def pregenerate(
    images: Sequence[Path | str | np.ndarray],
    out_path: str | Path,
    count: int,
    *,
    overwrite: bool = False,
    workers: int = 1,
    compression: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    **dataset_kwargs,
) -> Path:
    """Write ``count`` samples of ``SimulatedDataset(images, length=count, **dataset_kwargs)``.

    Args:
        images: still images (paths or arrays).
        out_path: the .h5 file (written atomically).
        count: number of samples.
        overwrite: replace an existing file.
        workers: processes simulating in parallel (samples are still written in order and are
            identical to a single-process run).
        compression: h5py compression for frames (``"gzip"``, ``"lzf"`` or None).
        progress: called as ``progress(done, total)`` after each sample — e.g.
            ``lambda d, t: bar.update(task, completed=d, total=t)`` with rich.progress.
        dataset_kwargs: ``n``, ``crop``, ``seed``, ``sensor_ranges``, ``motion``, … of
            :class:`~trmd_cli.simulate.dataset.SimulatedDataset`.

    Returns:
        ``out_path``.
    """
    from .dataset import SimulatedDataset

    if count < 1:
        raise InputError(f"count must be ≥ 1, got {count}")
    out_path = check_output(out_path, overwrite,
                            inputs=[i for i in images if isinstance(i, (str, Path))])
    kwargs = dict(dataset_kwargs, images=list(images), length=int(count))
    ds = SimulatedDataset(**kwargs)
    settings = {
        "generator": "trmd_cli.simulate.dataset.SimulatedDataset",
        "seed": ds.seed, "n": ds.n, "crop": ds.crop, "count": int(count),
        "sensor_ranges": asdict(ds.sensor_ranges), "motion": asdict(ds.motion),
        "exposure_ms": ds.exposure_ms, "gain": ds.gain, "read_noise": ds.read_noise,
        "zoom": ds.zoom, "max_px_per_step": ds.max_px_per_step,
        "images": [str(p) if not isinstance(p, np.ndarray) else "<array>" for p in images],
    }
    pool = None
    if workers > 1:
        import multiprocessing as mp

        # spawn, not fork: forking a process whose torch thread pool runs can deadlock
        pool = mp.get_context("spawn").Pool(workers, _init_worker, (kwargs,))
        samples = pool.imap(_work, range(count), chunksize=4)
    else:
        samples = (ds.sample(i) for i in range(count))
    try:
        with H5Writer(out_path, ds.crop, ds.crop, compression=compression,
                      attrs={"simulator": json.dumps(settings)}) as w:
            offset = 0
            for i, s in enumerate(samples):
                w.add_events(_shift(s.events, offset))
                w.add_frame(s.blurry, s.exposure.shifted(offset), sharp=s.sharp,
                            contrast=s.contrast, motion=s.motion)
                offset += s.exposure.end_us + GAP_US
                if progress is not None:
                    progress(i + 1, count)
    finally:
        if pool is not None:
            pool.terminate()
    return out_path


def _shift(events: EventStream, offset: int) -> EventStream:
    return EventStream(events.x, events.y, events.t + offset, events.p, events.width,
                       events.height)
