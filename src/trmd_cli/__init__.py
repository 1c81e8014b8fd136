"""trmd — motion deblurring from a blurry frame and the events recorded during its exposure.

Implements TRMD (Chen & Yu, "Motion Deblur by Learning Residual from Events", TMM 2024) and the
weight-free EDI baseline (Pan et al., CVPR 2019). Light at import: torch is imported only by the
parts that need it.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import FormatError, InputError, ShapeError, TrmdError, WeightsError  # noqa: E402
from .events import EventStream, Exposure  # noqa: E402

__all__ = [
    "__version__",
    "EventStream",
    "Exposure",
    "TrmdError",
    "InputError",
    "FormatError",
    "ShapeError",
    "WeightsError",
]
