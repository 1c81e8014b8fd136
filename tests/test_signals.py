"""An interrupt that something swallows on its way still stops the commit of an output.

``io.BufferedWriter(raw)`` calls ``raw.tell()`` and clears whatever it raised: a Ctrl-C landing
in that call (1 run in ~30 of an interrupted ``trmd hfr`` into a folder) used to vanish, and the
run went on to finish and replace the user's previous output.
"""

from __future__ import annotations

import signal
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from trmd_cli import write
from trmd_cli.cli.app import app
from trmd_cli.signals import Terminated, handled, raise_if_received

pytestmark = pytest.mark.skipif(not hasattr(signal, "raise_signal") or sys.platform == "win32",
                                reason="POSIX signals")


def signal_in_tell(monkeypatch, sig: signal.Signals, at_call: int = 1) -> None:
    """Deliver ``sig`` from inside the ``at_call``-th ``tell()`` of a trmd output file, where
    the buffered writer's constructor drops the exception."""
    calls = {"n": 0}
    tell = write._OutputFile.tell

    def interrupted_tell(self):
        calls["n"] += 1
        if calls["n"] == at_call:
            signal.raise_signal(sig)
        return tell(self)

    monkeypatch.setattr(write._OutputFile, "tell", interrupted_tell)


def test_the_buffered_writer_does_swallow_it(tmp_path, monkeypatch):
    """The premise: without the re-raise, the interrupt is gone."""
    signal_in_tell(monkeypatch, signal.SIGINT)
    with handled():
        import io

        io.BufferedWriter(write._OutputFile(tmp_path / "x"), buffer_size=16).close()
        with pytest.raises(KeyboardInterrupt):
            raise_if_received()


@pytest.mark.parametrize("sig,exc", [(signal.SIGINT, KeyboardInterrupt),
                                     (signal.SIGTERM, Terminated)])
def test_swallowed_interrupt_stops_the_write(tmp_path, monkeypatch, sig, exc):
    out = tmp_path / "a.png"
    out.write_bytes(b"previous")
    signal_in_tell(monkeypatch, sig)
    with handled(), pytest.raises(exc):
        write.write_image(out, np.zeros((4, 5), np.float32))
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]


def test_outside_handled_nothing_is_recorded(tmp_path):
    """Used as a library, trmd leaves Python's signal handling alone."""
    before = signal.getsignal(signal.SIGINT)
    with handled():
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before
    raise_if_received()  # nothing pending once left


def test_hfr_into_a_folder_interrupted_in_tell(tmp_path, monkeypatch):
    """The CLI path of the flaky run: Ctrl-C inside the 5th frame's tell(); exit 130, the
    previous output untouched, no temporaries."""
    from tests.cli.test_interrupt_deblur import write_recording

    rec = write_recording(tmp_path / "rec.h5", 4)
    out = tmp_path / "slowmo"
    (out / "000000").mkdir(parents=True)
    (out / "meta.json").write_text("previous")
    signal_in_tell(monkeypatch, signal.SIGINT, at_call=5)
    r = CliRunner().invoke(app, ["hfr", str(rec), "-o", str(out), "--overwrite",
                                 "--contrast", "0.2"])
    assert r.exit_code == 130, r.output
    assert "interrupted; no partial output was left" in r.output
    assert sorted(p.name for p in out.iterdir()) == ["000000", "meta.json"]
    assert (out / "meta.json").read_text() == "previous"
    assert [p.name for p in tmp_path.iterdir() if ".tmp" in p.name] == []


class _TakesThenInterrupted:
    """A lock whose ``__enter__`` is interrupted just after it took the lock, before the
    ``with`` statement owns it: where a Ctrl-C may land in any ``with lock:``."""

    def __init__(self) -> None:
        import threading

        self.lock = threading.Lock()

    def __enter__(self):
        self.lock.acquire()
        signal.raise_signal(signal.SIGINT)
        return self

    def __exit__(self, *exc) -> None:
        self.lock.release()


def test_shielded_raises_the_signal_after_the_call_and_the_lock_is_released():
    """Unshielded, the interrupt leaves the lock held (the hang of an interrupted run whose
    cleanup then waits for that lock); shielded, the call completes, releases it, and the
    interrupt is raised as the block ends."""
    from trmd_cli.signals import shielded

    with handled():
        bare = _TakesThenInterrupted()
        with pytest.raises(KeyboardInterrupt):
            with bare:
                pass
        assert bare.lock.locked()
        held = _TakesThenInterrupted()
        went_on = []
        with pytest.raises(KeyboardInterrupt):
            with shielded():
                with held:
                    went_on.append(True)
        assert went_on and not held.lock.locked()
        with pytest.raises(Terminated):
            with shielded():
                signal.raise_signal(signal.SIGTERM)
        with shielded():  # the signals raised before are not raised again
            pass


def test_a_ctrl_c_inside_the_queues_lock_does_not_hang_the_consumer():
    """overlap.ahead: a Ctrl-C that lands in the consumer's ``get`` just after it took the
    queue's lock. Raised there, it left the lock held: the producer could not hand over its
    next item and the consumer's join of it waited for ever (an interrupted ``deblur --video``
    that did not end). Now it is raised once ``get`` has returned, and the run ends. In a
    process of its own, with a time limit: the old code hangs."""
    import subprocess
    import textwrap

    code = textwrap.dedent("""
        import queue, signal, time
        from trmd_cli import overlap
        from trmd_cli.signals import handled

        class Interrupted(queue.Queue):
            calls = 0

            def get(self, *args, **kwargs):
                self.mutex.acquire()
                Interrupted.calls += 1
                if Interrupted.calls == 2:
                    signal.raise_signal(signal.SIGINT)  # raised here, the lock stays held
                self.mutex.release()
                return super().get(*args, **kwargs)

        overlap.queue.Queue = Interrupted

        with handled():
            try:
                # the producer is ahead, waiting to hand over its next item, when the
                # consumer comes back for it
                for item in overlap.ahead(iter(range(50))):
                    time.sleep(0.2)
            except KeyboardInterrupt:
                print("interrupted")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=30)
    assert run.returncode == 0 and run.stdout.strip() == "interrupted", run.stderr
