"""EVT 3.0 on its raw 16-bit words: the time words, the clock's wraps, and resuming the decoder.

EVT 3.0 is a stream of 16-bit words, the type in bits 15–12. TIME_HIGH (0x8) carries time bits
23–12 and TIME_LOW (0x6) bits 11–0; ADDR_Y (0x0) sets the row, ADDR_X (0x2) is one event,
VECT_BASE_X (0x3) sets the column and polarity of the vectors VECT_12 (0x4) and VECT_8 (0x5),
each of which moves that column on by 12 or 8. The decoder's state at any word is therefore
the last TIME_HIGH (with the number of times the 24-bit clock wrapped before it), the last
ADDR_Y and the vector column — so a decoder started at a TIME_HIGH word, and told the row and
the vector column there, decodes what one started at the beginning of the file decodes.

The scan here finds those points without decoding: per block of words a shift, a comparison
(where the TIME_HIGH words are) and a minimum and maximum of their values; only a block whose
values lie a wrap apart is read word by word, to count the wraps as the decoder does. It costs a
fifth of a decoding, and is what lets a large file open without being decoded (see
:class:`~trmd_cli.read.prophesee.Evt3Recording`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..errors import FormatError
from .chunked import IN_ORDER_HINT

__all__ = ["Evt3Scan", "scan_evt3", "resume_prefix", "WRAP_MIN_DROP", "SCAN_WORDS"]

#: the ``evt3`` decoder counts a wrap of the 24-bit clock when TIME_HIGH's 12-bit value drops
#: by at least this much from one TIME_HIGH word to the next (4095 → 0 …10); a smaller drop is
#: time going back (measured on the decoder, and checked by the tests against it)
WRAP_MIN_DROP = 4085
#: 16-bit words per block of the scan (256 KiB: the block and its temporaries stay in the
#: processor's cache between numpy's passes); also the size a segment of the index aims at
SCAN_WORDS = 1 << 17

#: the word types EVT 3.0 defines (bits 15–12): ADDR_Y, ADDR_X, VECT_BASE_X, VECT_12, VECT_8,
#: TIME_LOW, CONTINUED_4, TIME_HIGH, EXT_TRIGGER, OTHERS, CONTINUED_12
_VALID = np.zeros(16, bool)
_VALID[[0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0xA, 0xE, 0xF]] = True
#: the undefined types as the bits of one number: word type k is undefined when bit k is set
_UNDEFINED_BITS = np.uint16(sum(1 << k for k in range(16) if not _VALID[k]))

_ADDR_Y, _VECT_BASE_X, _VECT_12, _VECT_8, _TIME_HIGH = 0x0, 0x3, 0x4, 0x5, 0x8


@dataclass(frozen=True, eq=False)
class Evt3Scan:
    """What one pass over the raw words of an EVT 3.0 body found.

    Segment k spans words ``starts[k]`` to ``starts[k + 1]`` (the last one to the end); every
    segment after the first starts at a TIME_HIGH word, about every :data:`SCAN_WORDS` words.

    Attributes:
        starts: (S,) int64 first word of each segment (``starts[0] == 0``).
        wraps: (S,) int64 the clock's wraps up to each segment's first word, that word's own
            included (what a decoder started there must add).
        lo_us, hi_us: (S,) int64 µs, bounds on the times of the events each segment holds: at
            or after ``lo_us`` (its lowest TIME_HIGH), at or before ``hi_us`` (its highest plus
            4095 µs); both non-decreasing over the segments.
        first_time_word: the index of the first TIME_HIGH word (−1: none — the decoder
            decodes no event before it).
        undefined: ``(count, index of the first, their types)`` of the words whose type
            EVT 3.0 does not define (the decoder skips them), or None.
    """

    starts: np.ndarray
    wraps: np.ndarray
    lo_us: np.ndarray
    hi_us: np.ndarray
    first_time_word: int
    undefined: tuple[int, int, list[int]] | None


def scan_evt3(path: Path, offset: int, words: int, block_words: int | None = None) -> Evt3Scan:
    """Scan the ``words`` 16-bit words after byte ``offset`` of ``path``.

    Raises:
        FormatError: the time words go back (by less than a wrap within a block where the
            clock wraps; else below the segments before).
    """
    block_words = SCAN_WORDS if block_words is None else max(int(block_words), 1)
    starts, wraps, lo, hi = [0], [0], [0], [-1]
    undefined, first_undefined, kinds = 0, -1, set()
    first_time, last_value, wrapped = -1, -1, 0
    buf = np.empty(block_words, np.uint16)
    typ = np.empty(block_words, np.uint16)
    mask = np.empty(block_words, bool)
    spare = np.empty(block_words, np.uint16)
    with open(path, "rb") as fh:
        fh.seek(offset)
        for start in range(0, words, block_words):
            n = min(block_words, words - start)
            block, t = buf[:n], typ[:n]
            fh.readinto(memoryview(block).cast("B"))
            np.right_shift(block.view("<u2"), 12, out=t)
            is_time = np.equal(t, _TIME_HIGH, out=mask[:n])
            i0 = int(is_time.argmax())
            if is_time[i0]:
                i1 = _last_true(is_time)
                v0, v1 = int(block[i0]) & 0xFFF, int(block[i1]) & 0xFFF
                # TIME_HIGH words are 0x8000–0x8FFF: moved (mod 2**16) to the bottom, or the
                # top, of the range of all words, one minimum and one maximum find theirs
                work = spare[:n]
                vmin = int(np.subtract(block, 0x8000, out=work).min())
                vmax = int(np.add(block, 0x7000, out=work).max()) - 0xF000
                prev = v0 if last_value < 0 else last_value
                if vmax - vmin < WRAP_MIN_DROP and prev - v0 < WRAP_MIN_DROP:
                    # no wrap in the block (one needs values ≥ 4085 apart in it) nor into it
                    base = wrapped * 4096
                    first_wraps = block_wraps = 0
                    low, high = base + vmin, base + vmax
                else:
                    first_wraps, block_wraps, low, high = _wrapped_block(
                        block, is_time, prev, wrapped, start, path)
                first_at = start + i0
                if first_time < 0:
                    first_time = first_at
                    lo[0] = low << 12
                elif start > 0:
                    starts.append(first_at)
                    wraps.append(wrapped + first_wraps)
                    lo.append(low << 12)
                    hi.append(-1)
                hi[-1] = (high << 12) + 4095
                last_value = v1
                wrapped += block_wraps
            # bit `type` of the undefined-types number, for every word at once (numpy's
            # indexing is several times slower than its arithmetic); `block` is free now
            np.right_shift(_UNDEFINED_BITS, t, out=block)
            np.bitwise_and(block, 1, out=block)
            if block.max():  # (a reduction numpy vectorises, unlike any() on integers)
                bad = np.flatnonzero(block)
                undefined += len(bad)
                first_undefined = start + int(bad[0]) if first_undefined < 0 else first_undefined
                kinds.update(int(k) for k in np.unique(t[bad]))
    lo_us, hi_us = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
    # the segments' bounds come from each one's extreme time words: a segment whose words
    # reach below the one before went back in time (within a block, the events' times say so
    # when decoded)
    back = np.flatnonzero((lo_us[1:] < lo_us[:-1]) | (hi_us[1:] < hi_us[:-1]))
    if len(back):
        k = int(back[0]) + 1
        raise FormatError(f"the clock goes back in time near word {int(starts[k]):,} (its time "
                          "words fall below those before: corrupt file?)", path=path,
                          hint=IN_ORDER_HINT)
    return Evt3Scan(np.asarray(starts, np.int64), np.asarray(wraps, np.int64),
                    lo_us, hi_us, first_time,
                    (undefined, first_undefined, sorted(kinds)) if undefined else None)


def _last_true(mask: np.ndarray) -> int:
    """Index of the last True of ``mask`` (which holds one): searched from the end in growing
    tails, since a reversed view's argmax copies the whole array."""
    n = len(mask)
    k = 512
    while True:
        tail = mask[max(n - k, 0):]
        if tail.any():
            return n - 1 - int(tail[::-1].argmax())
        k *= 8


def _wrapped_block(block: np.ndarray, is_time: np.ndarray, prev: int, wrapped: int, start: int,
                   path: Path) -> tuple[int, int, int, int]:
    """For a block that may hold a wrap: (wraps before its first time word, wraps in it, its
    lowest and highest time word as whole TIME_HIGH counts), every time word compared with
    the one before as the decoder does."""
    where = np.flatnonzero(is_time)
    v = (block.take(where) & 0xFFF).astype(np.int64)
    drop = np.diff(v, prepend=prev)
    wrap = drop <= -WRAP_MIN_DROP
    back = np.flatnonzero((drop < 0) & ~wrap)
    if len(back):
        i = int(back[0])
        raise FormatError(f"the clock goes back in time at word {start + int(where[i]):,} (time "
                          f"word 0x{int(v[i - 1]) if i else prev:03X} then 0x{int(v[i]):03X}: "
                          "corrupt file?)", path=path, hint=IN_ORDER_HINT)
    high = (wrapped + np.cumsum(wrap)) * 4096 + v
    return int(wrap[0]), int(wrap.sum()), int(high.min()), int(high.max())


#: words read back per step when looking for the row and vector column before a point
_BACK_WORDS = 1 << 14


def resume_prefix(fh: BinaryIO, offset: int, at: int, first_time_word: int) -> np.ndarray:
    """The words that give a fresh decoder, fed them right after the TIME_HIGH word at index
    ``at``, the state a decoder that started at the beginning has there: the last ADDR_Y
    before ``at``, and the last VECT_BASE_X followed by an empty VECT_12 / VECT_8 for each
    vector since (an empty vector moves the column on and decodes no event).

    ``fh``: the file, open for reading (its position is left anywhere); ``offset``: the byte
    where its words start. The decoder ignores these words before the file's first TIME_HIGH:
    the search stops there.
    """
    y_word = base_word = None
    moves: list[np.ndarray] = []  # the vector words after the base, latest block first
    stop = max(first_time_word, 0)
    hi = at
    while hi > stop and (y_word is None or base_word is None):
        lo = max(stop, hi - _BACK_WORDS)
        fh.seek(offset + 2 * lo)
        w = np.frombuffer(fh.read(2 * (hi - lo)), "<u2")
        t = w >> 12
        if y_word is None:
            ys = np.flatnonzero(t == _ADDR_Y)
            if len(ys):
                y_word = int(w[ys[-1]])
        if base_word is None:
            bases = np.flatnonzero(t == _VECT_BASE_X)
            tail = t[int(bases[-1]) + 1:] if len(bases) else t
            moves.append(tail[(tail == _VECT_12) | (tail == _VECT_8)])
            if len(bases):
                base_word = int(w[bases[-1]])
        hi = lo
    words = [] if y_word is None else [y_word]
    if base_word is not None:
        words.append(base_word)
    if moves:
        # (with no base before, the column moved on from 0, where a fresh decoder starts)
        vec = np.concatenate(moves[::-1])
        words.extend((vec.astype(np.int64) << 12).tolist())
    return np.asarray(words, "<u2")
