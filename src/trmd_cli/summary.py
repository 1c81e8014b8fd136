"""Statistics of a recording for `trmd info` (streams in chunks: bounded memory)."""

from __future__ import annotations

import numpy as np

from .read.base import Recording

__all__ = ["summarize"]


def summarize(rec: Recording) -> dict:
    """Format, counts, sensor, duration, event rate, polarity balance, frames/windows."""
    n = rec.num_events()
    first, last = rec.time_range_us()
    on = 0
    for chunk in rec.iter_chunks():
        on += int(np.count_nonzero(chunk.p > 0))
    dur_s = (last - first) / 1e6
    out = {
        "file": str(rec.path),
        "format": rec.format,
        "events": n,
        "sensor": f"{rec.width}x{rec.height}",
        "first_event_us": first,
        "last_event_us": last,
        "duration_s": round(dur_s, 6),
        "rate_mev_per_s": round(n / dur_s / 1e6, 4) if dur_s > 0 else None,
        "on_fraction": round(on / n, 4) if n else None,
    }
    exposures = rec.frame_exposures()
    kind = "frames"
    if not exposures:
        exposures, kind = rec.stored_windows(), "windows"
    out["frames"] = []
    if exposures:
        out["exposure_source"] = kind
        for i, e in enumerate(exposures):
            out["frames"].append({
                "index": i, "start_us": e.start_us, "end_us": e.end_us,
                "duration_ms": e.duration_us / 1000,
                "events": len(rec.events(e.start_us, e.end_us + 1)),
            })
    return out
