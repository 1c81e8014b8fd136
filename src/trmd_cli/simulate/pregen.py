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
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..errors import InputError, TrmdError
from ..events import EventStream
from ..signals import raise_if_received
from ..write import H5Writer, check_output
from .sample import Sample

__all__ = ["pregenerate", "GAP_US"]

#: time between consecutive samples on the file's timeline, µs
GAP_US = 10_000


def _worker(kwargs: dict, first: int, step: int, count: int, conn) -> None:
    """A simulating process: samples ``first, first + step, …`` sent in order down ``conn``
    (an exception in place of the sample that raised it)."""
    import signal

    # Ctrl-C is the parent's to handle (a terminal sends it to the whole group); it stops
    # the workers. First, before the seconds of importing torch.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from .dataset import SimulatedDataset

    ds = SimulatedDataset(**kwargs)
    for i in range(first, count, step):
        try:
            item = ds.sample(i)
        except Exception as e:  # noqa: BLE001 - raised again in the parent
            conn.send(e)
            return
        conn.send(item)


class _Workers:
    """``workers`` processes simulating the samples in turn, each with a pipe of its own.

    Not a ``multiprocessing.Pool``: its workers share the queues' locks and one results pipe,
    so one killed while it sent a sample (a ``kill`` of the whole group) left a lock held or
    half a message in the pipe, and the pool's own shutdown then waited for ever. Here a
    worker's death is one pipe's EOF, and stopping is SIGKILL."""

    def __init__(self, kwargs: dict, workers: int, count: int) -> None:
        import multiprocessing as mp

        # spawn, not fork: forking a process whose torch thread pool runs can deadlock
        ctx = mp.get_context("spawn")
        self.count, self._procs, self._conns = count, [], []
        for k in range(workers):
            recv, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_worker, args=(kwargs, k, workers, count, send),
                               daemon=True)
            proc.start()
            send.close()  # the worker's end: its death is then this pipe's EOF
            self._procs.append(proc)
            self._conns.append(recv)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(self.count):
            k = i % len(self._conns)
            conn = self._conns[k]
            # while the HDF5 writer is open a signal is only recorded
            # (:func:`~trmd_cli.signals.recorded_only`): raised here within half a second
            while not conn.poll(0.5):
                raise_if_received()
            try:
                item = conn.recv()
            except (EOFError, OSError):  # (OSError: it died in the middle of a sample)
                raise_if_received()
                self._procs[k].join(5)
                raise TrmdError(f"simulating worker {k + 1} ended without its sample "
                                f"(exit code {self._procs[k].exitcode})",
                                hint="out of memory? try fewer --workers") from None
            if isinstance(item, BaseException):
                raise item
            yield item

    def stop(self) -> None:
        for proc in self._procs:
            proc.kill()
        for proc, conn in zip(self._procs, self._conns, strict=True):
            proc.join()
            conn.close()


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
    pool = _Workers(kwargs, workers, count) if workers > 1 else None
    samples = iter(pool) if pool is not None else (ds.sample(i) for i in range(count))
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
            pool.stop()
    return out_path


def _shift(events: EventStream, offset: int) -> EventStream:
    return EventStream(events.x, events.y, events.t + offset, events.p, events.width,
                       events.height)
