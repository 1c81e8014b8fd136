"""iniVation AEDAT 4.0 (DV software, DAVIS and DVXplorer cameras), read with the ``aedat`` package.

Units and conventions:

* time: microseconds since the Unix epoch, as DV writes them (int64 holds them exactly; nothing
  is subtracted, so frame exposures and events share one clock);
* x = column, y = row, (0, 0) at the top-left; polarity ``on`` True = +1, False = -1;
* sensor size from the event stream's description in the file header;
* APS frames (DAVIS): 8-bit gray (or colour) pixels → float32 [0, 1]; each frame's exposure is
  ``[exposure_begin_t, exposure_end_t]`` µs. Frames without a positive exposure get none.
* IMU samples and triggers are skipped. When a file holds several event or frame streams, the
  first of each is read (a warning says so).

The file is a sequence of compressed packets with no usable seek table in ``aedat``: opening it
decodes every packet once (indexing events, noting frame exposures); small files stay in memory,
large ones are decoded again per request, packet by packet (see
:class:`~trmd_cli.read.chunked.ChunkedRecording`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from ..events import Exposure
from .base import Frame, ReadOptions
from .chunked import Chunk, ChunkedRecording

__all__ = ["read_aedat4", "Aedat4Recording", "frame_pixels_to_float"]


def frame_pixels_to_float(pixels: np.ndarray, fmt: str) -> np.ndarray:
    """DV frame pixels → float32 [0, 1]: (H, W) gray or (H, W, 3) RGB (alpha dropped).

    ``fmt`` is the ``format`` the decoder reports: ``L``/``Gray``, ``RGB``/``RGBA`` or
    ``BGR``/``BGRA`` (older ``aedat`` releases).
    """
    px = np.asarray(pixels)
    scale = 65535.0 if px.dtype == np.uint16 else 255.0
    img = px.astype(np.float32) / scale
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        else:
            img = img[..., :3]
            if fmt.upper().startswith("BGR"):
                img = img[..., ::-1]
    return np.ascontiguousarray(img)


def _is_decoder_failure(e: BaseException) -> bool:
    """Errors of the ``aedat`` decoder on a damaged file. Its Rust code *panics* on some
    malformed headers; pyo3 raises that as ``PanicException``, a BaseException."""
    return (isinstance(e, (OSError, RuntimeError, ValueError))
            or type(e).__name__ == "PanicException")


#: hint for files that cannot be decoded
_DAMAGED = "the file may be incomplete or damaged: copy it again or re-export it from DV"


class _Capture:
    drop = False


@contextlib.contextmanager
def _native_stderr_captured() -> Iterator[_Capture]:
    """Hold what native code writes to file descriptor 2 while the block runs; write it out
    afterwards unless ``drop`` was set. A Rust panic prints its message (and, under
    RUST_BACKTRACE, a backtrace) straight to fd 2 before Python sees the exception: the user
    should get one line from the CLI instead."""
    capture = _Capture()
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable fd 2: nothing to protect
        yield capture
        return
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield capture
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            if not capture.drop:
                held.seek(0)
                data = held.read()
                if data:
                    os.write(2, data)


class Aedat4Recording(ChunkedRecording):
    """An AEDAT 4.0 file: polarity events (chunked by packet) and APS frames."""

    def __init__(self, path: Path, options: ReadOptions):
        from . import require

        self._aedat = require("aedat", path=path)
        warnings: list[str] = []
        if options.time_unit not in (None, "us"):
            warnings.append(f"`time_unit={options.time_unit!r}` ignored: AEDAT 4 times are "
                            "microseconds by specification")
        with _native_stderr_captured() as capture:
            try:
                streams = self._aedat.Decoder(str(path)).id_to_stream()
            except BaseException as e:
                if not _is_decoder_failure(e):
                    raise
                capture.drop = True
                raise FormatError(f"not a readable AEDAT 4 file: {e}", path=path,
                                  hint=_DAMAGED) from None
        ev_ids = sorted(i for i, s in streams.items() if s.get("type") == "events")
        fr_ids = sorted(i for i, s in streams.items() if s.get("type") == "frame")
        if not ev_ids and not fr_ids:
            raise FormatError("the file holds no event or frame stream", path=path,
                              hint="record or export it with the polarity/frame output enabled")
        if len(ev_ids) > 1 or len(fr_ids) > 1:
            warnings.append(f"the file has {len(ev_ids)} event and {len(fr_ids)} frame streams;"
                            " reading the first of each")
        self._ev_id = ev_ids[0] if ev_ids else None
        self._fr_id = fr_ids[0] if fr_ids else None
        main = streams[self._ev_id if ev_ids else self._fr_id]
        width, height = main.get("width"), main.get("height")
        if not width or not height:
            width, height = (options.sensor or options.frame_size or (None, None))
        super().__init__(path, "aedat4", width, height, warnings)
        self._frame_meta: list[dict[str, Any]] = []
        # the first pass decodes every packet: a damaged one fails here, before any output
        with _native_stderr_captured() as capture:
            try:
                self._build_index(self._first_pass())
            except FormatError:
                capture.drop = True
                raise
        self._note_frames()

    # -- decoding ---------------------------------------------------------------------------

    def _packets(self) -> Iterator[dict]:
        """Packets in file order; decoding failures become FormatError naming the packet."""
        try:
            decoder = self._aedat.Decoder(str(self.path))
        except BaseException as e:
            if not _is_decoder_failure(e):
                raise
            raise FormatError(f"not a readable AEDAT 4 file: {e}", path=self.path,
                              hint=_DAMAGED) from None
        k = 0
        while True:
            try:
                packet = next(decoder)
            except StopIteration:
                return
            except BaseException as e:
                if not _is_decoder_failure(e):
                    raise
                raise FormatError(f"packet {k} cannot be decoded ({e}): the file is truncated "
                                  "or corrupt", path=self.path,
                                  hint=_DAMAGED) from None
            k += 1
            yield packet

    def _chunk(self, k: int, ev: np.ndarray) -> Chunk:
        on = ev["on"] if "on" in (ev.dtype.fields or {}) else ev["p"]
        return Chunk(k, np.asarray(ev["x"], np.uint16), np.asarray(ev["y"], np.uint16),
                     ev["t"].astype(np.int64), np.where(on, 1, -1).astype(np.int8))

    def _first_pass(self) -> Iterator[Chunk]:
        k = 0
        for packet in self._packets():
            sid = packet.get("stream_id")
            if "events" in packet and sid == self._ev_id:
                yield self._chunk(k, packet["events"])
                k += 1
            elif "frame" in packet and sid == self._fr_id:
                meta = {key: v for key, v in packet["frame"].items() if key != "pixels"}
                self._frame_meta.append(meta)

    def _decode(self, start: int = 0, resume: Any = None) -> Iterator[Chunk]:
        k = 0
        for packet in self._packets():
            if "events" in packet and packet.get("stream_id") == self._ev_id:
                if k >= start:
                    yield self._chunk(k, packet["events"])
                k += 1

    # -- frames -----------------------------------------------------------------------------

    @staticmethod
    def _exposure(meta: dict[str, Any]) -> Exposure | None:
        b, e = int(meta.get("exposure_begin_t", 0)), int(meta.get("exposure_end_t", 0))
        return Exposure(b, e) if e > b else None

    def _note_frames(self) -> None:
        if not self._frame_meta:
            return
        missing = sum(self._exposure(m) is None for m in self._frame_meta)
        if missing:
            self.warnings.append(f"{missing} of {len(self._frame_meta)} frames have no exposure "
                                 "time; they cannot be deblurred")
        odd = [m for m in self._frame_meta
               if (m.get("width"), m.get("height")) != (self.width, self.height)]
        if odd:
            m = odd[0]
            self.warnings.append(f"{len(odd)} frame(s) are {m.get('width')}x{m.get('height')} "
                                 f"(offset {m.get('offset_x')},{m.get('offset_y')}), not the "
                                 f"{self.width}x{self.height} sensor")

    def frames(self) -> Iterator[Frame]:
        """APS frames in time order, decoded on demand (one at a time in memory)."""
        if not self._frame_meta:
            return
        i = 0
        for packet in self._packets():
            if "frame" in packet and packet.get("stream_id") == self._fr_id:
                fr = packet["frame"]
                yield Frame(frame_pixels_to_float(fr["pixels"], str(fr.get("format", "L"))),
                            self._exposure(fr), i, f"{i:06d}")
                i += 1

    def frame_exposures(self) -> list[Exposure]:
        """Exposure windows of the frames that have one, in order (no pixel decoding)."""
        return [e for e in map(self._exposure, self._frame_meta) if e is not None]

    def num_frames(self) -> int:
        return len(self._frame_meta)


def read_aedat4(path: Path, options: ReadOptions) -> Aedat4Recording:
    """Open an AEDAT 4.0 file: events (indexed by packet) and APS frames with exposures."""
    return Aedat4Recording(Path(path), options)
