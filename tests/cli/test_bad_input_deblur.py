"""The bad-input matrix, second part: `trmd deblur`, `trmd hfr` and `trmd eval`.

Blurry images that do not fit the sensor or cannot be read, windows outside the events, empty
or foreign event files, weights that are damaged, pickled, or for another N, bad options and
bad output paths. Each case is run through every command it applies to (hfr into an .mp4, a
.gif and a folder in turn; with no previous output, and with one and ``--overwrite``). Every
run must end with exit code 2, one ``error:`` line on stderr naming the file or option with a
hint (``— how to fix``), no traceback, and the output path absent — or byte-identical when it
existed — with no temporary file beside it. Some cases fail only after several frames were
written (a damaged frame in the middle, events unsorted deep inside a lazily read file): the
half-built output must vanish too.
"""

from __future__ import annotations

import json
import pickle
import struct
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from trmd_cli.cli.app import app
from trmd_cli.events import Exposure, make_stream
from trmd_cli.write import write_events_npz, write_h5, write_image

W, H = 64, 48
K = 4  # frames in the recordings and folders
EXPOSURES = [Exposure(10_000 + k * 50_000, 30_000 + k * 50_000) for k in range(K)]
PREVIOUS = b"the user's previous output"
runner = CliRunner()


# -- inputs that work (the starting points for damage) --------------------------------------------


def stream(n: int = 8000, seed: int = 3, t_max: int = 200_000):
    rng = np.random.default_rng(seed)
    return make_stream(rng.integers(0, W, n), rng.integers(0, H, n),
                       np.sort(rng.integers(0, t_max, n)), rng.integers(0, 2, n), W, H)


def frames(k: int = K, w: int = W, h: int = H) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    base = (0.2 + 0.6 * (((xx // 8) + (yy // 8)) % 2)).astype(np.float32)
    return np.stack([np.roll(base, i, axis=1) for i in range(k)])


@dataclass(frozen=True)
class Good:
    """Valid inputs shared by every case (never modified: cases copy what they damage)."""

    image: Path  # one blurry frame
    events: Path  # npz with one stored window (the image's)
    folder: Path  # K frames
    folder_events: Path  # npz with K stored windows
    recording: Path  # trmd HDF5 with K frames and their windows
    weights: Path  # test_trmd, N = 3, gray


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Good:
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights

    d = tmp_path_factory.mktemp("good")
    s = stream()
    write_image(d / "blurry.png", frames(1)[0])
    write_events_npz(d / "events.npz", s, [EXPOSURES[0]])
    (d / "frames").mkdir()
    for k, img in enumerate(frames()):
        write_image(d / "frames" / f"{k:06d}.png", img)
    write_events_npz(d / "frames_events.npz", s, EXPOSURES)
    write_h5(d / "rec.h5", s, blurry=frames(), exposures=EXPOSURES)
    save_weights(d / "w3.safetensors", create_model("test_trmd", n=3), meta={})
    return Good(d / "blurry.png", d / "events.npz", d / "frames", d / "frames_events.npz",
                d / "rec.h5", d / "w3.safetensors")


# -- builders of damaged inputs -------------------------------------------------------------------


def _w(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _noise(n: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def _png(path: Path, img: np.ndarray) -> Path:
    write_image(path, img)
    return path


def _folder_with(d: Path, g: Good, k: int, data: bytes | None = None,
                 img: np.ndarray | None = None) -> Path:
    """A copy of the good frames folder whose frame ``k`` is replaced."""
    folder = d / "frames"
    folder.mkdir()
    for p in g.folder.iterdir():
        (folder / p.name).write_bytes(p.read_bytes())
    target = folder / f"{k:06d}.png"
    if data is not None:
        target.write_bytes(data)
    else:
        _png(target, img)
    return folder


def _dataset_with(d: Path, g: Good, k: int, data: bytes) -> Path:
    """An eval folder dataset (blurry/ + events.npz with one window per frame), frame k
    replaced."""
    ds = d / "dataset"
    ds.mkdir()
    _folder_with(ds, g, k, data=data).rename(ds / "blurry")
    (ds / "events.npz").write_bytes(g.folder_events.read_bytes())
    return ds


def _png_header(w: int, h: int) -> bytes:
    """A PNG whose header says w×h 8-bit gray, followed by no pixel data at all."""
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b""))


def _h5_rec(path: Path, s, blurry: np.ndarray, exposures: list[Exposure]) -> Path:
    """trmd layout written by hand: frames of any size, windows anywhere."""
    with h5py.File(path, "w") as f:
        f.attrs.update(format="trmd", width=W, height=H)
        for key in "xytp":
            f[f"events/{key}"] = getattr(s, key)
        f["frames/blurry"] = blurry
        f["frames/exposure_start"] = [e.start_us for e in exposures]
        f["frames/exposure_end"] = [e.end_us for e in exposures]
    return path


def _h5_unsorted_late(path: Path) -> Path:
    """Times go back once, inside the last frame's window, between the reader's index points:
    found only when that window is read, after the first frames were deblurred."""
    n = 40_000
    t = np.linspace(0, 200_000, n).astype(np.int64)
    i = int(np.searchsorted(t, EXPOSURES[-1].mid_us)) + 7
    t[i] = t[i - 3]
    rng = np.random.default_rng(1)
    x, y, p = rng.integers(0, W, n), rng.integers(0, H, n), np.where(rng.random(n) < .5, 1, -1)
    with h5py.File(path, "w") as f:
        f.attrs.update(format="trmd", width=W, height=H)
        for key, v in dict(x=x.astype("u2"), y=y.astype("u2"), t=t, p=p.astype("i1")).items():
            f[f"events/{key}"] = v
        f["frames/blurry"] = frames()
        f["frames/exposure_start"] = [e.start_us for e in EXPOSURES]
        f["frames/exposure_end"] = [e.end_us for e in EXPOSURES]
    return path


def _safetensors_header(data: bytes) -> tuple[dict, bytes]:
    (size,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8:8 + size]), data[8 + size:]


def _with_header(header: dict, body: bytes) -> bytes:
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    return struct.pack("<Q", len(raw)) + raw + body


def _weights_meta(g: Good, path: Path, **updates: str) -> Path:
    """The good weights with metadata entries replaced (tensors untouched)."""
    header, body = _safetensors_header(g.weights.read_bytes())
    header["__metadata__"].update(updates)
    return _w(path, _with_header(header, body))


def _weights_nan(g: Good, path: Path) -> Path:
    from safetensors.numpy import load_file, save_file

    from trmd_cli.models.weights import read_metadata

    header, _ = _safetensors_header(g.weights.read_bytes())
    tensors = load_file(str(g.weights))
    name = next(k for k, v in tensors.items() if v.dtype.kind == "f" and v.size > 4)
    tensors[name] = tensors[name].copy()
    tensors[name].flat[2] = np.nan
    save_file(tensors, str(path), metadata=header["__metadata__"])
    assert read_metadata(path)["n"] == 3
    return path


def _torch_zip(path: Path) -> Path:
    import torch

    torch.save({"state_dict": {"w": torch.zeros(3)}}, path)
    return path


class _Evil:
    def __reduce__(self):  # would run a command if anything unpickled it
        return (print, ("unpickled!",))


# -- the matrix -----------------------------------------------------------------------------------

DH = ("deblur", "hfr")
ALL = ("deblur", "hfr", "eval")


@dataclass(frozen=True)
class Case:
    """One malformed input. ``build(dir, good)`` returns the positional inputs and the extra
    options; ``names``: what the error line must name (``"{0}"`` = the first input,
    ``"{-1}"`` = the last, ``"{weights}"`` = the ``--weights`` file, else literal text);
    ``needle``: regex the line must match."""

    id: str
    build: Callable[[Path, Good], tuple[list[Path], list[str]]]
    needle: str
    names: str = "{0}"
    commands: tuple[str, ...] = DH


def _img_ev(image: Path, events: Good | Path, *extra: str):
    """A blurry image and an event file (the good one when given the ``Good`` inputs)."""
    return [image, events.events if isinstance(events, Good) else events], list(extra)


def _trmd(weights: Path, *extra: str) -> list[str]:
    return ["--method", "trmd", "--weights", str(weights), "--threads", "1", *extra]


UNREADABLE = "not a readable image"
TRUNC = "truncated|corrupt|cannot be read|not a readable"

CASES = [
    # ---- blurry images
    Case("image-taller-than-sensor", lambda d, g: _img_ev(_png(d / "b.png", frames(1, W, H + 2)[0]),
                                                          g),
         r"image is 64x50 but the events' sensor is 64x48"),
    Case("image-rgb-wider-than-sensor", lambda d, g: _img_ev(_png(
        d / "b.png", np.dstack([frames(1, W + 1, H)[0]] * 3)), g), r"image is 65x48"),
    Case("image-empty", lambda d, g: _img_ev(_w(d / "b.png", b""), g), UNREADABLE),
    Case("image-cut-half", lambda d, g: _img_ev(_w(d / "b.png", g.image.read_bytes()[:200]), g),
         UNREADABLE),
    Case("image-zeroed-after-magic", lambda d, g: _img_ev(_w(d / "b.png", g.image.read_bytes()[:8]
                                                             + bytes(300)), g), UNREADABLE),
    Case("image-is-text", lambda d, g: _img_ev(_w(d / "b.png", b"0.1 1 1 1\n" * 30), g),
         UNREADABLE),
    Case("image-header-claims-40000x40000", lambda d, g: _img_ev(_w(d / "b.png", _png_header(
        40_000, 40_000)), g), UNREADABLE),  # OpenCV raised cv2.error (exit 1)
    Case("image-png-without-pixels", lambda d, g: _img_ev(_w(d / "b.png", _png_header(W, H)), g),
         UNREADABLE),
    Case("image-missing", lambda d, g: _img_ev(d / "nowhere.png", g), "not found"),
    Case("image-without-events", lambda d, g: ([g.image], []), "no events"),
    Case("folder-frame-2-unreadable", lambda d, g: (
        [_folder_with(d, g, 2, data=g.image.read_bytes()[:100]), g.folder_events], []),
         UNREADABLE, names="000002.png"),
    Case("folder-frame-3-wrong-size", lambda d, g: (
        [_folder_with(d, g, 3, img=frames(1, W, H - 1)[0]), g.folder_events], []),
         r"image is 64x47", names="000003.png"),
    Case("recording-frames-wrong-size", lambda d, g: (
        [_h5_rec(d / "r.h5", stream(), frames(K, W, H + 1), EXPOSURES)], []),
         r"frame 0 is 64x49 but the events' sensor is 64x48", commands=ALL),
    # ---- exposure windows
    Case("exposure-after-the-events", lambda d, g: _img_ev(g.image, g, "--exposure", "5000000",
                                                           "6000000"),
         r"lies outside the events' time range", names="{-1}"),
    Case("exposure-before-the-events", lambda d, g: _img_ev(
        g.image, _as_events(d, stream(t_max=200_000).slice(100_000, 200_001)), "--exposure",
        "1000", "2000"), "lies outside the events' time range", names="{-1}"),
    Case("exposure-reversed", lambda d, g: _img_ev(g.image, g, "--exposure", "30000", "20000"),
         "empty or reversed", names="--exposure"),
    Case("exposure-out-of-range", lambda d, g: _img_ev(g.image, g, "--exposure", "0", "1e25"),
         "out of range", names="--exposure"),
    Case("time-offset-fraction-of-a-microsecond", lambda d, g: (
        [g.recording], ["--time-offset=-0.004"]), "not a whole number of microseconds",
         names="-0.004"),
    Case("hfr-overlapping-windows", lambda d, g: (
        [g.folder, _as_events(d, stream(), [Exposure(e.start_us - 40_000 * (k > 0),
                                                     e.end_us) for k, e in
                                            enumerate(EXPOSURES)])], []),
         r"#0 \[10000, 30000\] µs and #1 \[20000, 80000\] µs overlap", commands=("hfr",)),
    Case("time-offset-moves-every-window-out", lambda d, g: ([g.recording],
                                                              ["--time-offset", "10s"]),
         "lies outside the events' time range"),
    Case("stored-windows-all-after-the-events", lambda d, g: (
        [_h5_rec(d / "r.h5", stream(), frames(), [e.shifted(10**7) for e in EXPOSURES])], []),
         "lies outside the events' time range"),
    Case("folder-windows-all-outside", lambda d, g: (
        [g.folder, _as_events(d, stream(), [e.shifted(10**7) for e in EXPOSURES])], []),
         "lies outside the events' time range", names="{-1}"),
    # ---- events
    Case("events-empty-file", lambda d, g: _img_ev(g.image, _as_events(d, stream(0))),
         "holds no events", names="{-1}"),
    Case("events-empty-with-exposure", lambda d, g: _img_ev(
        g.image, _as_events(d, stream(0)), "--exposure", "0", "1000"), "holds no events",
         names="{-1}"),
    Case("recording-frames-without-events", lambda d, g: (
        [_h5_rec(d / "r.h5", stream(0), frames(), EXPOSURES)], []), "holds no events",
         commands=ALL),
    Case("events-is-an-image", lambda d, g: ([g.image, g.image], []),
         "unknown event file format", names="{-1}"),
    Case("events-is-weights", lambda d, g: ([g.image, g.weights], []),
         "unknown event file format", names="{-1}"),
    Case("events-random-bytes", lambda d, g: ([g.image, _w(d / "e.h5", _noise(5000))], []),
         "not the content of a HDF5|unknown event file format", names="{-1}"),
    Case("events-npz-cut", lambda d, g: ([g.image, _w(d / "e.npz", g.events.read_bytes()[
        : len(g.events.read_bytes()) // 2])], []), TRUNC, names="{-1}"),
    Case("recording-cut", lambda d, g: ([_w(d / "r.h5", g.recording.read_bytes()[
        : len(g.recording.read_bytes()) // 3])], []), TRUNC, commands=ALL),
    Case("recording-unsorted-in-the-last-window", lambda d, g: ([_h5_unsorted_late(d / "u.h5")],
                                                                ["--contrast", "0.2"]),
         "not sorted", commands=DH),
    Case("recording-without-frames", lambda d, g: ([_as_events(d, stream(), name="e.h5")], []),
         "holds events but no frames", commands=ALL),
    # ---- weights (TRMD)
    Case("weights-random-bytes", lambda d, g: _img_ev(g.image, g, *_trmd(
        _w(d / "w.safetensors", _noise(4000)))), "not a readable safetensors",
         names="{weights}"),
    Case("weights-cut-in-header", lambda d, g: _img_ev(g.image, g, *_trmd(
        _w(d / "w.safetensors", g.weights.read_bytes()[:5]))), "not a readable safetensors",
         names="{weights}"),
    Case("weights-cut-in-tensors", lambda d, g: _img_ev(g.image, g, *_trmd(_w(
        d / "w.safetensors", g.weights.read_bytes()[: len(g.weights.read_bytes()) * 2 // 3]))),
         "not a readable safetensors|cannot read tensors", names="{weights}"),
    Case("weights-pickle-renamed", lambda d, g: _img_ev(g.image, g, *_trmd(
        _w(d / "w.safetensors", pickle.dumps({"w": _Evil()})))), "Python pickle",
         names="{weights}"),
    Case("weights-torch-zip-renamed", lambda d, g: _img_ev(g.image, g, *_trmd(
        _torch_zip(d / "w.safetensors"))), "PyTorch checkpoint", names="{weights}"),
    Case("weights-foreign-safetensors", lambda d, g: _img_ev(g.image, g, *_trmd(
        _foreign_safetensors(d / "w.safetensors"))), "without trmd metadata",
         names="{weights}"),
    Case("weights-for-another-n", lambda d, g: _img_ev(g.image, g, *_trmd(g.weights, "--n", "2")),
         r"weights are for N = 3, not N = 2", names="{weights}"),
    Case("weights-metadata-says-other-n", lambda d, g: _img_ev(g.image, g, *_trmd(_weights_meta(
        g, d / "w.safetensors", args=json.dumps({**_args(g), "n": 2})))),
         "tensor|do not match", names="{weights}"),
    Case("weights-metadata-says-2-channels", lambda d, g: _img_ev(g.image, g, *_trmd(
        _weights_meta(g, d / "w.safetensors", args=json.dumps({**_args(g), "channels": 2})))),
         "do not describe a RENet|metadata says channels = 1 but the architecture it describes "
         "has channels = 2", names="{weights}"),
    # sizes come from the metadata: checked against the tensors before anything is allocated
    # (these two would ask for 1.3 TB of parameters, and for a billion modules)
    Case("weights-metadata-says-huge-widths", lambda d, g: _img_ev(g.image, g, *_trmd(
        _weights_meta(g, d / "w.safetensors", args=json.dumps(
            {**_args(g), "widths": [20_000, 40_000, 40_000, 40_000]})))),
         r"tensor \S+ has shape \(4,\), the architecture needs \(20000,\)",
         names="{weights}"),
    Case("weights-metadata-says-a-billion-blocks", lambda d, g: _img_ev(g.image, g, *_trmd(
        _weights_meta(g, d / "w.safetensors", args=json.dumps(
            {**_args(g), "num_res_blocks": 10**9})))), "residual blocks but the file holds",
         names="{weights}"),
    Case("weights-metadata-not-json", lambda d, g: _img_ev(g.image, g, *_trmd(_weights_meta(
        g, d / "w.safetensors", args="{not json"))), "malformed", names="{weights}"),
    Case("weights-other-model-class", lambda d, g: _img_ev(g.image, g, *_trmd(_weights_meta(
        g, d / "w.safetensors", model_class="ResNet"))), "model class 'ResNet'",
         names="{weights}"),
    Case("weights-nan", lambda d, g: _img_ev(g.image, g, *_trmd(
        _weights_nan(g, d / "w.safetensors"))), "NaN or infinite", names="{weights}"),
    Case("weights-missing", lambda d, g: _img_ev(g.image, g, *_trmd(d / "none.safetensors")),
         "weights file not found", names="{weights}"),
    Case("weights-is-a-folder", lambda d, g: _img_ev(g.image, g, *_trmd(d)), "is not a file",
         names="{weights}"),
    Case("weights-without-method-still-checked", lambda d, g: _img_ev(
        g.image, g, "--weights", str(_w(d / "w.safetensors", _noise(100)))),
         "not a readable safetensors", names="{weights}"),
    # ---- options
    *[Case(f"contrast-{v}", lambda d, g, v=v: _img_ev(g.image, g, "--contrast", v),
           "--contrast", names="--contrast") for v in ("abc", "-1", "0", "nan", "inf")],
    Case("method-unknown", lambda d, g: _img_ev(g.image, g, "--method", "magic"),
         "unknown method 'magic'", names="--method"),
    Case("device-unknown", lambda d, g: _img_ev(g.image, g, *_trmd(g.weights, "--device", "tpu")),
         "unknown device 'tpu'", names="tpu"),
    Case("precision-unknown", lambda d, g: _img_ev(g.image, g, *_trmd(g.weights, "--precision",
                                                                      "half")),
         "unknown precision 'half'", names="--precision"),
    Case("precision-fp16-on-cpu", lambda d, g: _img_ev(
        g.image, g, *_trmd(g.weights, "--device", "cpu", "--precision", "fp16")),
         "float16 needs a CUDA device", names="--precision"),
    Case("bit-depth-12", lambda d, g: _img_ev(g.image, g, "--bit-depth", "12"), "8 or 16",
         names="--bit-depth"),
    Case("time-offset-not-a-duration", lambda d, g: ([g.recording], ["--time-offset", "soon"]),
         "not a duration", names="soon"),
    Case("deblur-video-avi", lambda d, g: _img_ev(g.image, g, "--video", str(d / "v.avi")),
         "must end in .mp4 or .gif", names="v.avi", commands=("deblur",)),
    Case("deblur-fps-zero", lambda d, g: _img_ev(g.image, g, "--video", str(d / "v.mp4"),
                                                 "--fps", "0"), "--fps", names="--fps",
         commands=("deblur",)),
    Case("deblur-three-inputs", lambda d, g: ([g.image, g.events, g.events], []),
         "one or two inputs", names="deblur", commands=("deblur",)),
    Case("hfr-fps-nan", lambda d, g: ([g.recording], ["--fps", "nan"]), "--fps", names="--fps",
         commands=("hfr",)),
    Case("eval-unknown-method", lambda d, g: ([g.recording], ["--methods", "blurry,magic"]),
         "unknown method 'magic'", names="magic", commands=("eval",)),
    Case("eval-weights-random-bytes", lambda d, g: ([g.recording], [
        "--methods", "blurry,trmd", "--weights", str(_w(d / "w.safetensors", _noise(4000)))]),
         "not a readable safetensors", names="{weights}", commands=("eval",)),
    Case("eval-weights-pickle", lambda d, g: ([g.recording], [
        "--methods", "trmd", "--weights", str(_w(d / "w.safetensors", pickle.dumps(_Evil())))]),
         "Python pickle", names="{weights}", commands=("eval",)),
    Case("eval-weights-for-another-n", lambda d, g: ([g.recording], [
        "--methods", "trmd", "--n", "2", "--weights", str(g.weights)]),
         r"weights are for N = 3, not N = 2", names="{weights}", commands=("eval",)),
    Case("eval-missing-dataset", lambda d, g: ([d / "none.h5"], []), "not found",
         commands=("eval",)),
    Case("eval-folder-frame-2-unreadable", lambda d, g: ([_dataset_with(d, g, 2, data=b"")], []),
         UNREADABLE, names="000002.png", commands=("eval",)),
    Case("eval-folder-without-blurry", lambda d, g: ([g.folder], []), "no blurry/",
         commands=("eval",)),
]


def _as_events(d: Path, s, exposures=None, name: str = "e.npz") -> Path:
    path = d / name
    if name.endswith(".h5"):
        return write_h5(path, s)
    return write_events_npz(path, s, exposures)


def _args(g: Good) -> dict:
    header, _ = _safetensors_header(g.weights.read_bytes())
    return json.loads(header["__metadata__"]["args"])


def _foreign_safetensors(path: Path) -> Path:
    from safetensors.numpy import save_file

    save_file({"weight": np.zeros((3, 3), np.float32)}, str(path))
    return path


# -- running one case -----------------------------------------------------------------------------

HFR_OUTPUTS = ("out.mp4", "out.gif", "out")


def output_args(command: str, out_dir: Path, variant: int, previous: bool
                ) -> tuple[list[str], list[Path]]:
    """``-o`` (or ``--json``) for ``command``; with ``previous`` the user's earlier output is
    there (a file, or a folder holding one) and ``--overwrite`` is passed."""
    out_dir.mkdir()
    if command == "deblur":
        out = out_dir / "out"
        args = ["-o", str(out)]
    elif command == "hfr":
        out = out_dir / HFR_OUTPUTS[variant % 3]
        args = ["-o", str(out)]
    else:
        out = out_dir / "scores.json"
        args = ["--json", str(out)]
    if previous:
        if out.suffix:
            out.write_bytes(PREVIOUS)
        else:
            out.mkdir()
            (out / "meta.json").write_bytes(PREVIOUS)
        args.append("--overwrite")
    return args, [out]


def assert_one_clear_line(result, names: str, needle: str) -> str:
    """The one error line, and no weights file was ever unpickled."""
    line = assert_one_error_line(result, names, needle)
    assert "unpickled!" not in result.output
    return line


def assert_untouched(out_dir: Path, outputs: list[Path], previous: bool) -> None:
    """The output is absent, or exactly the previous one; nothing else is in its folder."""
    for out in outputs:
        if not previous:
            assert not out.exists(), out
        elif out.is_dir():
            assert [p.name for p in out.iterdir()] == ["meta.json"]
            assert (out / "meta.json").read_bytes() == PREVIOUS
        else:
            assert out.read_bytes() == PREVIOUS
    left = sorted(p.name for p in out_dir.iterdir())
    assert left == (sorted(o.name for o in outputs) if previous else []), left


def _names(case: Case, inputs: list[Path], extra: list[str]) -> str:
    if case.names == "{0}":
        return str(inputs[0])
    if case.names == "{-1}":
        return str(inputs[-1])
    if case.names == "{weights}":
        return extra[extra.index("--weights") + 1]
    return case.names


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_refused_with_one_line_and_exit_2(case, good, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    inputs, extra = case.build(src, good)
    names = _names(case, inputs, extra)
    i = CASES.index(case)
    for j, command in enumerate(case.commands):
        previous = (i + j) % 2 == 1
        if command == "eval" and "--weights" not in extra and "--methods" not in extra:
            extra_c = ["--methods", "blurry,edi", *extra]
        else:
            extra_c = extra
        out_dir = tmp_path / f"out-{command}"
        out_args, outputs = output_args(command, out_dir, i, previous)
        if "--video" in extra_c:
            outputs.append(Path(extra_c[extra_c.index("--video") + 1]))
        r = runner.invoke(app, [command, *map(str, inputs), *extra_c, *out_args])
        assert_one_clear_line(r, names, case.needle)
        assert_untouched(out_dir, [o for o in outputs if o.parent == out_dir], previous)
        assert not any(".tmp" in p.name for p in src.iterdir())


# -- failures after frames were written: every hfr output kind, and deblur with --video -----------


@pytest.mark.parametrize("target", [*HFR_OUTPUTS, "deblur+video"])
@pytest.mark.parametrize("previous", [False, True], ids=["fresh", "over-previous"])
def test_failure_in_the_middle_leaves_no_partial_output(good, tmp_path, target, previous):
    """Frame 3 of 4 is unreadable: frames 1–2 were already deblurred and written (or encoded)
    into temporaries, which must vanish; a previous output stays as it was."""
    folder = _folder_with(tmp_path, good, 3, data=good.image.read_bytes()[:150])
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    if target == "deblur+video":
        outputs = [out_dir / "frames", out_dir / "v.mp4"]
        argv = ["deblur", str(folder), str(good.folder_events), "-o", str(outputs[0]),
                "--video", str(outputs[1]), "--contrast", "0.2"]
    else:
        outputs = [out_dir / target]
        argv = ["hfr", str(folder), str(good.folder_events), "-o", str(outputs[0]),
                "--contrast", "0.2"]
    if previous:
        for out in outputs:
            if out.suffix:
                out.write_bytes(PREVIOUS)
            else:
                out.mkdir()
                (out / "meta.json").write_bytes(PREVIOUS)
        argv.append("--overwrite")
    r = runner.invoke(app, argv)
    assert_one_clear_line(r, "000003.png", UNREADABLE)
    assert_untouched(out_dir, outputs, previous)


def test_unsorted_events_found_late_leave_no_partial_output(tmp_path, monkeypatch):
    """The damage is in the last window of a lazily read recording: three frames are done
    before it is found."""
    from trmd_cli import write

    rec = _h5_unsorted_late(tmp_path / "u.h5")
    calls = []
    real = write.write_result_folder

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(write, "write_result_folder", counting)
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(tmp_path / "out"), "--contrast", "0.2"])
    assert_one_clear_line(r, str(rec), "not sorted")
    assert len(calls) == K - 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["u.h5"]


# -- outputs --------------------------------------------------------------------------------------


@pytest.mark.parametrize("command,out_name", [("deblur", "out"), ("hfr", "out.mp4"),
                                              ("hfr", "out.gif"), ("hfr", "out"),
                                              ("eval", "scores.json"), ("eval", "strips")])
def test_output_exists_or_parent_missing(good, tmp_path, command, out_name):
    inputs = [str(good.recording)]
    flag = "-o" if command != "eval" else ("--json" if out_name.endswith(".json") else "--strip")
    extra = ["--methods", "blurry"] if command == "eval" else ["--contrast", "0.2"]
    out = tmp_path / out_name
    if out.suffix:
        out.write_bytes(PREVIOUS)
    else:
        out.mkdir()
        (out / "meta.json").write_bytes(PREVIOUS)
    r = runner.invoke(app, [command, *inputs, *extra, flag, str(out)])
    assert_one_clear_line(r, str(out), "already exists.*--overwrite")
    r = runner.invoke(app, [command, *inputs, *extra, flag, str(tmp_path / "no" / out_name)])
    assert_one_clear_line(r, str(tmp_path / "no"), "parent folder does not exist")
    assert sorted(p.name for p in tmp_path.iterdir()) == [out_name]
    assert (out.read_bytes() if out.suffix else (out / "meta.json").read_bytes()) == PREVIOUS


def test_output_of_the_wrong_kind(good, tmp_path):
    # deblur writes a folder: a video name for -o is a mistake, not a folder named .mp4
    r = runner.invoke(app, ["deblur", str(good.recording), "-o", str(tmp_path / "x.mp4")])
    assert_one_clear_line(r, "x.mp4", "--video x.mp4")
    # an existing file where deblur's folder goes, even with --overwrite
    (tmp_path / "file").write_bytes(PREVIOUS)
    r = runner.invoke(app, ["deblur", str(good.recording), "-o", str(tmp_path / "file"),
                            "--overwrite"])
    assert_one_clear_line(r, "file", "not a folder")
    # a folder where a video goes, even with --overwrite
    (tmp_path / "v.mp4").mkdir()
    (tmp_path / "v.mp4" / "keep").write_bytes(PREVIOUS)
    for argv in (["hfr", str(good.recording), "-o", str(tmp_path / "v.mp4")],
                 ["deblur", str(good.recording), "-o", str(tmp_path / "o"), "--video",
                  str(tmp_path / "v.mp4")]):
        r = runner.invoke(app, [*argv, "--overwrite", "--contrast", "0.2"])
        assert_one_clear_line(r, "v.mp4", "is a folder")
    # hfr: neither a video nor a folder
    r = runner.invoke(app, ["hfr", str(good.recording), "-o", str(tmp_path / "x.avi")])
    assert_one_clear_line(r, "x.avi", "unknown output type")
    # the video exists: refused before the frames folder is made
    (tmp_path / "old.mp4").write_bytes(PREVIOUS)
    r = runner.invoke(app, ["deblur", str(good.recording), "-o", str(tmp_path / "new"),
                            "--video", str(tmp_path / "old.mp4")])
    assert_one_clear_line(r, "old.mp4", "already exists")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "old.mp4", "v.mp4"]
    assert (tmp_path / "v.mp4" / "keep").read_bytes() == PREVIOUS


# -- what is accepted, and said -------------------------------------------------------------------


def test_trmd_without_any_weights_says_how_to_get_them(good, tmp_path, no_shipped_weights):
    for command, out in (("deblur", "o"), ("hfr", "o.mp4")):
        r = runner.invoke(app, [command, str(good.image), str(good.events), "-o",
                                str(tmp_path / out), "--method", "trmd"])
        line = assert_one_clear_line(r, "--weights", "no shipped TRMD weights")
        assert "trmd train" in line
    # eval scores what it can: trmd is skipped with that note, exit 0
    r = runner.invoke(app, ["eval", str(good.recording), "--methods", "blurry,trmd"])
    assert r.exit_code == 0 and "trmd skipped" in r.stderr and "--weights" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_weights_with_method_edi_are_ignored_with_a_warning(good, tmp_path):
    r = runner.invoke(app, ["deblur", str(good.image), str(good.events), "-o", str(tmp_path / "o"),
                            "--method", "edi", "--weights", str(tmp_path / "none.safetensors"),
                            "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert "warning: --weights is ignored: --method is edi" in r.stderr
    assert json.loads((tmp_path / "o" / "meta.json").read_text())["method"] == "edi"


def test_weights_for_another_channel_count_are_adapted(good, tmp_path):
    """Not refused, by design (TrmdEstimator): an RGB model sees a gray frame replicated and
    returns gray; a gray model runs once per colour channel of an RGB frame."""
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights
    from trmd_cli.read import read_image

    rgb_w = save_weights(tmp_path / "rgb.safetensors", create_model("test_trmd", n=3, channels=3),
                         meta={})
    rgb_img = _png(tmp_path / "rgb.png", np.dstack([frames(1)[0], 0.5 * frames(1)[0],
                                                    0.25 * frames(1)[0]]))
    for image, weights, shape in ((good.image, rgb_w, (H, W)),
                                  (rgb_img, good.weights, (H, W, 3))):
        out = tmp_path / f"o-{weights.stem}"
        r = runner.invoke(app, ["deblur", str(image), str(good.events), "-o", str(out),
                                *_trmd(weights)])
        assert r.exit_code == 0, r.output
        assert read_image(out / "sharp.png").shape == shape


def test_some_windows_outside_pass_through_with_a_warning(tmp_path):
    """Only when *every* window misses the events is it bad input; a few pass through."""
    s = stream(t_max=130_000)  # the last frame's window [160, 180] ms has no events
    rec = _h5_rec(tmp_path / "r.h5", s, frames(), EXPOSURES)
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(tmp_path / "o"), "--contrast", "0.2"])
    assert r.exit_code == 0, r.output
    assert "frame r.h5#frame3: no events in its exposure window [160000, 180000] µs; passed " \
        "through unchanged" in r.stderr
    assert "(1 passed through without events)" in r.stdout
    meta = json.loads((tmp_path / "o" / "meta.json").read_text())
    assert [f["passthrough"] for f in meta["frames"]] == [False, False, False, True]


# -- what a user really sees: real processes (torch, safetensors, OpenCV and FFmpeg print to fd 2
#    on their own) --------------------------------------------------------------------------------


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}


@pytest.mark.parametrize("what", ["weights-torch-zip", "weights-cut", "frame-unreadable-hfr-mp4",
                                  "png-without-pixels"])
def test_real_process_prints_one_line(good, tmp_path, what):
    if what == "png-without-pixels":  # libpng wrote "libpng error: …" to fd 2 by itself
        image = _w(tmp_path / "b.png", _png_header(W, H))
        argv, out, names = ["deblur", str(image), str(good.events)], tmp_path / "o", str(image)
    elif what == "weights-torch-zip":
        weights = _torch_zip(tmp_path / "w.safetensors")
        argv, out, names = ["deblur", str(good.image), str(good.events), *_trmd(weights)], \
            tmp_path / "o", str(weights)
    elif what == "weights-cut":
        weights = _w(tmp_path / "w.safetensors", good.weights.read_bytes()[:-100])
        argv, out, names = ["hfr", str(good.recording), *_trmd(weights)], tmp_path / "o.mp4", \
            str(weights)
    else:
        folder = _folder_with(tmp_path, good, 2, data=good.image.read_bytes()[:120])
        argv, out, names = ["hfr", str(folder), str(good.folder_events), "--contrast", "0.2"], \
            tmp_path / "o.mp4", "000002.png"
    before = sorted(p.name for p in tmp_path.iterdir())
    r = subprocess.run([sys.executable, "-m", "trmd_cli", *argv, "-o", str(out)],
                       capture_output=True, text=True, timeout=120, env=_env())
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert names in lines[0] and " — " in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before
