"""The CLI's single error boundary.

Library code raises :class:`~trmd_cli.errors.TrmdError` subclasses; here they become one line on
stderr and exit 2. Anything unexpected becomes one line and exit 1, with the traceback only under
``trmd -v``. Ctrl-C exits 130 and ``kill`` (SIGTERM) 143; outputs are untouched because every
writer is atomic and the signal arrives as an exception that unwinds through the writers.
"""

from __future__ import annotations

import functools
import os
import re
import signal
import sys
import threading
import warnings
from collections.abc import Callable
from typing import TypeVar

import typer
from rich.console import Console

from ..errors import TrmdError
from ..signals import Terminated, handled, raise_if_received

F = TypeVar("F", bound=Callable)

# OpenCV and its FFmpeg backend print their own complaints about damaged images and videos
# straight to stderr (before our one-line error). Read when cv2 first loads, which every command
# does inside its body, after this; a value the user set is kept.
os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
# OpenMP threads that wait by spinning steal the cores a competing process needs, and then wait
# for each other: on 2 cores beside one CPU-bound process the network ran 2.2× slower with
# spinning threads, 1.4× with sleeping ones (and no slower on an idle machine). Read when torch
# first loads, which every command does inside its body, after this; a value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

#: stderr console shared by all commands (progress bars, warnings, errors)
err = Console(stderr=True, highlight=False)
#: set by the app callback (``trmd -v``)
state = {"verbose": False}


#: the library's parameter names → this CLI's flags. Library messages name parameters in
#: backticks (``pass `sensor=(W, H)` ``) so that Python users read about arguments; the CLI says
#: the flag. A (on, off) pair is for booleans.
FLAGS: dict[str, str | tuple[str, str]] = {
    "bit_depth": "--bit-depth",
    "columns": "--columns",
    "contrast": "--contrast",
    "data": "--data",
    "device": "--device",
    "exposure": "--exposure",
    "exposure_us": "--exposure-ms",
    "exposure_length_us": "--exposure-length",
    "fill_gaps": ("--fill-gaps", "--no-fill-gaps"),
    "fps": "--fps",
    "frames": "--frames",
    "ground_truth": ("--gt", "--no-gt"),
    "limit": "--limit",
    "hot_pixels": ("--hot-pixels", "--keep-hot-pixels"),
    "drop_isolated": ("--drop-isolated", "--keep-isolated"),
    "fixed_pattern": ("--remove-pattern", "--keep-pattern"),
    "init_weights": "--init-weights",
    "interval_us": "--frame-interval-ms",
    "max_gap_frames": "--max-gap-frames",
    "method": "--method",
    "methods": "--methods",
    "n": "--n",
    "offset_us": "--time-offset",
    "one_based": ("--one-based", "--one-based"),
    "overwrite": ("--overwrite", "--overwrite"),
    "per_exposure": "--per-exposure",
    "precision": "--precision",
    "recipe": "--recipe",
    "resume": ("--resume", "--resume"),
    "run_dir": "--out",
    "sensor": "--sensor",
    "stamp": "--stamp",
    "threads": "--threads",
    "time_unit": "--time-unit",
    "times_us": "--timestamps",
    "topics": "--topics",
    "weights": "--weights",
}

_PARAM = re.compile(r"`([a-z_][a-z0-9_]*)(?:=([^`]*))?`")


def as_flags(text: str) -> str:
    """A library message with its backticked parameters (`` `n=3` ``, `` `sensor=(W, H)` ``,
    `` `one_based=True` ``) spelled as this CLI's flags (``--n 3``, ``--sensor WxH``,
    ``--one-based``). Backticked text that names no parameter (`` `trmd train` ``) is kept."""

    def flag(m: re.Match) -> str:
        name, value = m.group(1), m.group(2)
        spelled = FLAGS.get(name)
        if spelled is None:
            return m.group(0)
        if isinstance(spelled, tuple):
            return spelled[1] if value is not None and value.strip() == "False" else spelled[0]
        if value is None:
            return spelled
        value = value.strip()
        if value.startswith("(") and value.endswith(")"):
            parts = [v.strip() for v in value[1:-1].split(",")]
            value = "x".join(parts) if name == "sensor" else " ".join(parts)
        return f"{spelled} {value.strip(chr(39) + chr(34))}"

    return _PARAM.sub(flag, text)


def warn(message: str) -> None:
    err.print(f"[yellow]warning:[/] {as_flags(message)}", soft_wrap=True)


def fail(message: str, code: int) -> typer.Exit:
    err.print(f"[red]error:[/] {message}", soft_wrap=True, markup=True, emoji=False)
    return typer.Exit(code)


def _unraisable(hook) -> None:
    """An interrupt that lands inside a finaliser or weakref callback would be printed as
    "Exception ignored in …" and lost; hand it back to the main thread instead."""
    if isinstance(hook.exc_value, KeyboardInterrupt):
        import _thread

        signum = signal.SIGTERM if isinstance(hook.exc_value, Terminated) else signal.SIGINT
        # from another thread, a moment later: delivered now, the handler would raise inside
        # this hook, where the exception is printed with a traceback and lost again
        timer = threading.Timer(0.05, _thread.interrupt_main, args=(signum,))
        timer.daemon = True
        timer.start()
        return
    if state["verbose"]:
        sys.__unraisablehook__(hook)


def guarded(fn: F) -> F:
    """Wrap a command so every failure leaves as one clear line and an exit code."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        previous_hook, sys.unraisablehook = sys.unraisablehook, _unraisable
        try:
            with handled(), warnings.catch_warnings():
                if not state["verbose"]:
                    # library warnings (numpy casts, h5py) would break the one-line promise;
                    # what users need to know is said by warn()
                    warnings.simplefilter("ignore")
                return _run(fn, args, kwargs)
        finally:
            sys.unraisablehook = previous_hook

    return wrapper  # type: ignore[return-value]


def _own_line(e: TrmdError) -> str:
    """The error's line; for one raised in a torch DataLoader worker (which raises it again
    as "Caught FormatError in DataLoader worker process 0." with the worker's traceback after
    it), the worker's own line: the file and the fix."""
    text = str(e)
    if text.startswith("Caught ") and "Original Traceback" in text:
        last = text.rstrip().splitlines()[-1]
        name = type(e).__name__
        for prefix in (f"{type(e).__module__}.{name}: ", f"{name}: "):
            if last.startswith(prefix):
                return last[len(prefix):]
    return text


def _run(fn: Callable, args, kwargs):
    """Call the command; turn every failure into one line on stderr and an exit code."""
    try:
        result = fn(*args, **kwargs)
        raise_if_received()  # swallowed on the way (see trmd_cli.signals): still an interrupt
        return result
    except (typer.Exit, typer.Abort):
        raise
    except typer.BadParameter as e:  # raised inside a command body: bad input, exit 2
        raise fail(_escape(e.format_message()), 2) from None
    except TrmdError as e:
        if state["verbose"]:
            err.print_exception()
        raise fail(_escape(as_flags(_own_line(e))), e.exit_code) from None
    except Terminated:
        raise fail("terminated; no partial output was left", 143) from None
    except KeyboardInterrupt:
        raise fail("interrupted; no partial output was left", 130) from None
    except MemoryError:
        raise fail(f"out of memory; {_LESS_MEMORY.get(fn.__name__, _LESS_MEMORY[''])}",
                   1) from None
    except OSError as e:
        said = _os_error(e)
        if said is None:
            raise _unexpected(e) from None
        if state["verbose"]:
            err.print_exception()
        raise fail(_escape(as_flags(said)), 2) from None
    except Exception as e:  # noqa: BLE001 - the boundary is the place for it
        raise _unexpected(e) from None
    except BaseException as e:
        # native extensions raise their crashes outside Exception (pyo3's PanicException)
        if isinstance(e, (SystemExit, GeneratorExit)):
            raise
        if state["verbose"]:
            err.print_exception()
        raise fail(f"unexpected {type(e).__name__} in a native library: "
                   f"{_escape(str(e))} (run `trmd -v …` for details and please report it)",
                   1) from None


def _unexpected(e: BaseException) -> typer.Exit:
    if state["verbose"]:
        err.print_exception()
        return fail(f"unexpected {type(e).__name__}: {_escape(str(e))}", 1)
    return fail(f"unexpected {type(e).__name__}: {_escape(str(e))} "
                "(run `trmd -v …` for the traceback and please report it)", 1)


#: what each command can be given less of when memory runs out ('' = any other command)
_LESS_MEMORY = {
    "train": "close other programs, or give the run less at once: --set data.batch_size=… "
             "or --set data.crop=…",
    "voxelize": "close other programs, or ask for fewer windows at once (--exposure T0 T1), "
                "or a smaller --n",
    "deblur": "close other programs, or use --method edi, a smaller --n or --precision bf16",
    "hfr": "close other programs, or write an .mp4 or a folder (a .gif keeps every frame "
           "until the end), or use fewer --per-exposure frames",
    "eval_command": "close other programs, or evaluate fewer methods at once (--methods)",
    "": "close other programs, or run it on a machine with more memory (check the sensor "
        "size the file declares: trmd info)",
}


def _os_error(e: OSError) -> str | None:
    """One line for an OSError no writer or reader turned into a TrmdError: a full disk or a
    read-only folder (cannot write here), a file it may not read; None for anything else."""
    import errno

    from ..write import write_failure

    name = getattr(e, "filename", None)
    folder = os.path.dirname(os.path.abspath(name)) if name else os.getcwd()
    failure = write_failure(e, folder)
    if failure is not None and (e.errno not in (errno.EACCES, errno.EPERM) or name is None):
        return str(failure)
    if e.errno in (errno.EACCES, errno.EPERM) and name is not None:
        return (f"{name}: permission denied ({e.strerror}) — check its permissions (and its "
                "folder's), or run as a user who may use it")
    return None


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(text.splitlines()[0] if text else text)


def progress_enabled() -> bool:
    return sys.stderr.isatty()
