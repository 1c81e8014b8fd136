"""`trmd simulate INPUT -o OUT.h5`: synthetic blurry frames, events and sharp ground truth."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from .boundary import err, guarded, progress_enabled, warn
from .options import N, Overwrite, parse_sensor

_NOISE = ("contrast_sigma", "refractory_us", "shot_noise_hz", "leak_hz", "hot_pixel_fraction")


def simulate(
    input: Annotated[Path, typer.Argument(
        help="A still image, a video file, or a folder of frames.", show_default=False,
            readable=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="Output .h5 (trmd layout).",
        readable=False)],
    count: Annotated[int, typer.Option(
        "--count", min=1, help="Samples per still image (each a new view, path and sensor).")] = 1,
    frames: Annotated[int | None, typer.Option(
        "--frames", min=1, help="Consecutive exposures per sample (still: default 1; video or "
        "frame folder: default as many as fit).")] = None,
    frame_interval_ms: Annotated[float | None, typer.Option(
        "--frame-interval-ms", help="Start-to-start time of consecutive exposures "
        "(default 1.2 × the exposure).")] = None,
    n: N = 3,
    exposure_ms: Annotated[float | None, typer.Option(
        "--exposure-ms", help="Exposure time (default: 20 ms for a still, 3 frame intervals "
        "for a video or frame folder).")] = None,
    size: Annotated[str | None, typer.Option(
        "--size", help="Output size WxH; the still or the frames are resized/cropped to it "
        "(default 346x260).")] = None,
    timestamps: Annotated[Path | None, typer.Option(
        "--timestamps", help="Frame folder or video: file with one time in seconds per frame.",
        readable=False)
    ] = None,
    fps: Annotated[float | None, typer.Option(
        "--fps", help="Frame folder or video: frames per second (video default: its own).")
    ] = None,
    motion_px: Annotated[float | None, typer.Option(
        "--motion-px", min=0, help="Still: largest camera translation per exposure, pixels "
        "(default 30; --training-set: 70, log-uniform).")] = None,
    rotation_deg: Annotated[float | None, typer.Option(
        "--rotation-deg", min=0, help="Still: largest rotation per exposure, degrees "
        "(default 2; --training-set: 3).")] = None,
    layers: Annotated[int | None, typer.Option(
        "--layers", min=0, help="Still: up to this many independently moving foreground "
        "layers (occlusion; default 0; --training-set: up to 2 in 30 % of samples).")] = None,
    contrast: Annotated[float | None, typer.Option(
        "--contrast", min=0.001, help="Mean contrast threshold, ON and OFF (default 0.25; "
        "0.2 with --clean).")] = None,
    contrast_sigma: Annotated[float | None, typer.Option(
        "--contrast-sigma", min=0, help="Per-pixel threshold mismatch σ (default 0.03).")] = None,
    shot_noise: Annotated[float | None, typer.Option(
        "--shot-noise", min=0, help="Shot-noise events per pixel per second (default 0.1).")
    ] = None,
    hot_pixels: Annotated[float | None, typer.Option(
        "--hot-pixels", min=0, max=1, help="Fraction of hot pixels (default 2e-5).")] = None,
    refractory_us: Annotated[float | None, typer.Option(
        "--refractory-us", min=0, help="Refractory period, µs (default 100).")] = None,
    leak: Annotated[float | None, typer.Option(
        "--leak", min=0, help="Leak events per pixel per second (default 0.05).")] = None,
    read_noise: Annotated[float | None, typer.Option(
        "--read-noise", min=0, help="σ of Gaussian noise on the blurry frames, [0, 1] units "
        "(default 0.005).")] = None,
    clean: Annotated[bool, typer.Option(
        "--clean", help="An ideal sensor: no mismatch, refractory period, noise or leak, no "
        "read noise (flags given explicitly still apply).")] = False,
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
    training_set: Annotated[bool, typer.Option(
        "--training-set", help="INPUT is an image or a folder of stills: write --count "
        "randomised crop×crop training samples (motion, sensor and noise drawn per sample; "
        "a sensor, noise, motion or exposure flag given fixes that value for every sample).")
    ] = False,
    crop: Annotated[int | None, typer.Option(
        "--crop", min=8, help="--training-set sample size (default 128).")] = None,
    workers: Annotated[int, typer.Option(
        "--workers", min=1, help="--training-set: simulating processes.")] = 1,
    overwrite: Overwrite = False,
) -> None:
    """Simulate an event camera over a still, a video or a frame folder; write blurry frames,
    events, exposure windows, sharp ground truth (2N+1 frames per exposure), the true
    contrast threshold and, for stills, the true camera path of each exposure to one HDF5 file
    that `info`, `voxelize`, `deblur` and `eval` read.

    8-bit images and videos are treated as linear intensity, as the GOPRO-based event datasets
    do. Videos and frame folders are upsampled in time with optical flow so that no point moves
    more than a pixel between simulation steps; the events cover the frames' whole time span."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from ..errors import InputError
    from ..read.frames import IMAGE_EXTENSIONS
    from ..write import check_output

    if output.suffix.lower() not in (".h5", ".hdf5"):
        raise typer.BadParameter("the output must end in .h5", param_hint="--output")
    if not input.exists():
        raise InputError("input not found", path=input, hint="check the path")
    from ..read.paths import check_input_path

    check_input_path(input)
    check_output(output, overwrite, inputs=[input, timestamps])
    if seed < 0:
        raise InputError(f"--seed must be 0 or more, got {seed}", hint="e.g. --seed 0")
    for flag, value, example in (("--read-noise", read_noise, "0.005 ([0, 1] intensity)"),
                                 ("--motion-px", motion_px, "30"),
                                 ("--rotation-deg", rotation_deg, "2")):
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise InputError(f"{flag} must be a finite number ≥ 0, got {value}",
                             hint=f"e.g. {flag} {example}")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive finite number, got {fps}",
                         hint="e.g. --fps 30")
    # what one kind of simulation takes and the other does not is said, not dropped unsaid
    for flag, given, kind in (("--size", size, True), ("--frames", frames, True),
                              ("--crop", crop, False)):
        if given is not None and kind == training_set:
            warn(f"{flag} is ignored: " + ("--training-set samples are --crop squares of one "
                                           "exposure" if training_set else
                                           "it sizes --training-set samples"))
    crop = 128 if crop is None else crop
    w, h = parse_sensor(size or "346x260", "--size")  # type: ignore[misc]
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        # below 16 px no threshold or motion can be measured on the result; above 8192 the
        # frames alone would fill the memory before a single event
        raise InputError(f"--size {w}x{h} lies outside 16x16 … 8192x8192",
                         hint="e.g. --size 346x260")
    progress = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn(
        "{task.percentage:>3.0f}%"), TimeRemainingColumn(), console=err,
        disable=not progress_enabled(), transient=True)

    if training_set:
        from ..simulate.pregen import pregenerate

        images = _still_images(input, IMAGE_EXTENSIONS)
        pinned = training_set_options(
            clean=clean, contrast=contrast, contrast_sigma=contrast_sigma,
            shot_noise=shot_noise, hot_pixels=hot_pixels, refractory_us=refractory_us,
            leak=leak, read_noise=read_noise, exposure_ms=exposure_ms, motion_px=motion_px,
            rotation_deg=rotation_deg, layers=layers)
        with progress:
            task = progress.add_task("simulating", total=count)
            # gzip: events dominate the size (≈2 MB/sample raw at 128×128, ≈0.8 MB packed)
            pregenerate(images, output, count, n=n, crop=crop, seed=seed, overwrite=overwrite,
                        workers=workers, compression="gzip",
                        progress=lambda d, t: progress.update(task, completed=d, total=t),
                        **pinned)
        typer.echo(f"wrote {output}: {count} training sample(s) of {crop}×{crop}, N={n}, "
                   f"from {len(images)} image(s)")
        return

    sensor = _sensor_config(clean, contrast, contrast_sigma, shot_noise, hot_pixels,
                            refractory_us, leak)
    motion_px = 30.0 if motion_px is None else motion_px
    rotation_deg = 2.0 if rotation_deg is None else rotation_deg
    layers = 0 if layers is None else layers
    rn = (0.0 if clean else 0.005) if read_noise is None else read_noise
    is_still = input.is_file() and input.suffix.lower() in IMAGE_EXTENSIONS
    settings = {"input": str(input), "n": n, "seed": seed, "sensor": sensor.to_dict(),
                "read_noise": rn, "size": [w, h]}
    if is_still:
        if timestamps is not None or fps is not None:
            warn("--timestamps and --fps apply to videos and frame folders; ignored for a still")
        _simulate_still(input, output, w, h, n, count, frames, frame_interval_ms, exposure_ms,
                        motion_px, rotation_deg, layers, sensor, rn, seed, settings, progress)
    else:
        if count != 1:
            warn("--count applies to still images; a video or frame folder gives one sequence")
        _simulate_frames(input, output, w, h, n, frames, frame_interval_ms, exposure_ms,
                         timestamps, fps, sensor, rn, seed, settings, progress)


def _still_images(input: Path, exts) -> list[Path]:
    from ..errors import InputError

    if input.is_file():
        return [input]
    images = sorted(p for p in input.rglob("*") if p.is_file() and p.suffix.lower() in exts)
    if not images:
        raise InputError("no images in the folder", path=input, hint="use " + ", ".join(exts))
    return images


#: sensor noise fields (SensorConfig / SensorRanges) and the flags that set them, in the order
#: of _noise_given's arguments
_NOISE_FLAGS = {"contrast_sigma": "--contrast-sigma", "shot_noise_hz": "--shot-noise",
                "hot_pixel_fraction": "--hot-pixels", "refractory_us": "--refractory-us",
                "leak_hz": "--leak"}


def _noise_given(*values: float | None) -> dict[str, float]:
    """The noise flags given (not None), keyed by their sensor field."""
    return {k: float(v) for k, v in zip(_NOISE_FLAGS, values, strict=True) if v is not None}


def training_set_options(*, clean: bool = False, contrast: float | None = None,
                         contrast_sigma: float | None = None, shot_noise: float | None = None,
                         hot_pixels: float | None = None, refractory_us: float | None = None,
                         leak: float | None = None, read_noise: float | None = None,
                         exposure_ms: float | None = None, motion_px: float | None = None,
                         rotation_deg: float | None = None,
                         layers: int | None = None) -> dict:
    """``SimulatedDataset`` keywords for ``simulate --training-set``: a sensor, noise or exposure
    flag given pins its range to that one value; a motion flag sets the largest motion, drawn
    uniformly below it as for a still; flags left out keep the training ranges
    (``SensorRanges()``, ``DATASET_MOTION``). ``--clean`` makes every sample's sensor ideal
    (and read noise 0 unless ``--read-noise`` is given); noise flags cannot be combined with
    it."""
    from dataclasses import asdict, replace

    from ..errors import InputError
    from ..simulate.dataset import DATASET_MOTION, SensorRanges

    given = _noise_given(contrast_sigma, shot_noise, hot_pixels, refractory_us, leak)
    if clean and given:
        raise InputError(f"--clean with {', '.join(_NOISE_FLAGS[k] for k in given)}: a "
                         "training set's "
                         "clean samples have no noise at all",
                         hint="drop --clean to pin those noise values, or drop the noise flags")
    ranges = {k: (v, v) for k, v in given.items()}
    if contrast is not None:
        ranges["contrast"] = (float(contrast), float(contrast))
        ranges["on_off_ratio"] = (1.0, 1.0)
    if given:
        ranges["clean_prob"] = 0.0
    if clean:
        ranges["clean_prob"] = 1.0
    out: dict = {}
    if ranges:
        out["sensor_ranges"] = asdict(replace(SensorRanges(), **ranges))
    if read_noise is not None:
        out["read_noise"] = (float(read_noise), float(read_noise))
    elif clean:
        out["read_noise"] = (0.0, 0.0)
    if exposure_ms is not None:
        out["exposure_ms"] = (float(exposure_ms), float(exposure_ms))
    motion = {}
    if motion_px is not None:
        motion.update(translation_px=float(motion_px), log_magnitude=False)
    if rotation_deg is not None:
        motion["rotation_deg"] = float(rotation_deg)
    if layers is not None:
        motion.update(max_layers=int(layers), foreground_prob=1.0 if layers else 0.0)
    if motion:
        out["motion"] = asdict(replace(DATASET_MOTION, **motion))
    return out


def _sensor_config(clean: bool, contrast, contrast_sigma, shot_noise, hot_pixels,
                   refractory_us, leak):
    from dataclasses import replace

    from ..simulate import SensorConfig

    base = SensorConfig.clean() if clean else SensorConfig()
    changes = _noise_given(contrast_sigma, shot_noise, hot_pixels, refractory_us, leak)
    if contrast is not None:
        changes["contrast_on"] = changes["contrast_off"] = float(contrast)
    return replace(base, **changes)


def _simulate_still(input, output, w, h, n, count, frames, frame_interval_ms, exposure_ms,
                    motion_px, rotation_deg, layers, sensor, read_noise, seed, settings,
                    progress) -> None:
    import json

    import numpy as np

    from ..read.frames import read_image
    from ..simulate import DEFAULT_EXPOSURE_US, MotionRanges, iter_sequence
    from ..write import H5Writer

    image = read_image(input)
    exposure_us = DEFAULT_EXPOSURE_US if exposure_ms is None else _ms_to_us(exposure_ms,
                                                                            "--exposure-ms")
    interval_us = None if frame_interval_ms is None else _ms_to_us(frame_interval_ms,
                                                                   "--frame-interval-ms")
    k = 1 if frames is None else frames
    motion = MotionRanges(translation_px=motion_px, rotation_deg=rotation_deg,
                          foreground_prob=1.0 if layers else 0.0, max_layers=layers)
    settings.update(kind="still", count=count, frames=k, exposure_us=exposure_us,
                    frame_interval_us=interval_us, motion=_asdict(motion))
    rng = np.random.default_rng(seed)
    total_frames = 0
    events_total = 0
    with progress, H5Writer(output, w, h, attrs={"simulator": json.dumps(settings)}) as writer:
        task = progress.add_task("simulating", total=count)
        t0 = 0
        for j in range(count):
            ev_sensor, exposures, it = iter_sequence(
                image, n=n, size=(w, h), exposure_us=exposure_us, frames=k,
                frame_interval_us=interval_us, rng=rng, sensor=sensor, motion=motion,
                read_noise=read_noise, zoom=None, random_view=count > 1, t0_us=t0)
            span_end = exposures[-1].end_us
            ev_count, fr_count = _write_items(it, writer, ev_sensor.mean_contrast)
            events_total += ev_count
            total_frames += fr_count
            t0 = span_end + 10_000
            progress.update(task, completed=j + 1)
    typer.echo(f"wrote {output}: {total_frames} frame(s) of {w}×{h} with {2 * n + 1} sharp "
               f"frames each, {events_total} events")


def _simulate_frames(input, output, w, h, n, frames, frame_interval_ms, exposure_ms,
                     timestamps, fps, sensor, read_noise, seed, settings, progress) -> None:
    import json

    import numpy as np

    from ..errors import InputError
    from ..simulate.video import (
        VIDEO_EXTENSIONS,
        FolderFrames,
        VideoFrames,
        iter_video,
        list_frames,
        read_timestamps,
        video_exposures,
    )
    from ..write import H5Writer

    if input.is_dir():
        paths = list_frames(input)
        if timestamps is not None:
            times = read_timestamps(timestamps, len(paths))
        elif fps is not None:
            if fps <= 0:
                raise InputError(f"--fps must be positive, got {fps}")
            times = np.rint(np.arange(len(paths)) * (1e6 / fps)).astype(np.int64)
        else:
            raise InputError("a frame folder needs its frame times", path=input,
                             hint="pass --fps or --timestamps FILE")
        source = FolderFrames(paths, times, (w, h))
        kind = "frame_folder"
    elif input.is_file():
        if input.suffix.lower() not in VIDEO_EXTENSIONS:
            import cv2

            cap = cv2.VideoCapture(str(input))
            ok = cap.isOpened() and cap.read()[0]
            cap.release()
            if not ok:
                raise InputError("not an image, video or folder of frames", path=input,
                                 hint="use .png/.jpg stills, .mp4/.avi videos or a folder")
        source = VideoFrames(input, (w, h), fps=fps)
        if timestamps is not None:
            source.times_us = read_timestamps(timestamps, len(source.times_us))
        kind = "video"
    else:
        raise InputError("not a file or folder", path=input)
    exposure_us = None if exposure_ms is None else _ms_to_us(exposure_ms, "--exposure-ms")
    interval_us = None if frame_interval_ms is None else _ms_to_us(frame_interval_ms,
                                                                   "--frame-interval-ms")
    exposures = video_exposures(source.times_us, exposure_us, interval_us, frames)
    if frames is not None and len(exposures) < frames:
        warn(f"--frames {frames}: only {len(exposures)} exposure(s) of "
             f"{exposures[0].duration_us / 1000:g} ms fit in the "
             f"{(source.times_us[-1] - source.times_us[0]) / 1000:g} ms the source spans")
    settings.update(kind=kind, frames=len(exposures), source_frames=len(source),
                    exposure_us=exposures[0].duration_us,
                    frame_interval_us=(exposures[1].start_us - exposures[0].start_us
                                       if len(exposures) > 1 else None))
    rng = np.random.default_rng(seed)
    with progress, H5Writer(output, w, h, attrs={"simulator": json.dumps(settings)}) as writer:
        task = progress.add_task("simulating", total=len(source) - 1)
        ev_sensor, it = iter_video(source, exposures, n=n, sensor=sensor, rng=rng,
                                   read_noise=read_noise,
                                   on_interval=lambda i, t: progress.update(task, completed=i))
        events_total, done = _write_items(it, writer, ev_sensor.mean_contrast)
    if done < len(exposures):
        warn(f"only {done} of {len(exposures)} exposures were complete (the video was shorter "
             "than it said)")
    span = (source.times_us[-1] - source.times_us[0]) / 1e6
    typer.echo(f"wrote {output}: {done} frame(s) of {w}×{h} with {2 * n + 1} sharp frames "
               f"each, {events_total} events over {span:.3f} s")


def _ms_to_us(ms: float, name: str) -> int:
    from ..errors import InputError

    if not (math.isfinite(ms) and ms * 1000 < 2.0**62):
        raise InputError(f"{name} must be a finite number of milliseconds, got {ms}",
                         hint=f"e.g. {name} 20")
    us = int(round(ms * 1000))
    if not ms > 0 or us < 2:
        raise InputError(f"{name} must be at least 0.002 ms (2 µs), got {ms}",
                         hint=f"e.g. {name} 20")
    return us


def _asdict(obj) -> dict:
    from dataclasses import asdict

    return asdict(obj)


def _write_items(items, writer, contrast: float) -> tuple[int, int]:
    """Write a simulator's event blocks and finished exposures as they come (bounded memory);
    returns (events, frames) written."""
    from ..events import EventStream

    events = frames = 0
    for item in items:
        if isinstance(item, EventStream):
            writer.add_events(item)
            events += len(item)
        else:
            writer.add_frame(item.blurry, item.exposure, sharp=item.sharp, contrast=contrast,
                             motion=item.motion)
            frames += 1
    return events, frames


def register(app: typer.Typer) -> None:
    app.command(name="simulate")(guarded(simulate))
