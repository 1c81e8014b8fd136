"""Outputs that cannot be written, and outputs that would destroy the inputs.

A full disk (ENOSPC, injected where the bytes reach the disk: ``os.pwrite``), a read-only mount
(EROFS, where the temporary is created) and a folder without write permission must end every
writer with one line — ``FOLDER: cannot write here (No space left on device) — …`` — exit code 2,
and nothing left behind: no output, no temporary, a previous output byte-identical. An MP4 that
FFmpeg did not finish (a 4,096-byte file without its index, exit code 0: what FFmpeg did on a
full disk) is an error too, never "wrote". An output that is, or holds, one of the inputs is
refused whatever the flags, before anything is touched. Inputs that cannot be read (a pipe, a
file without read permission) get the one line as well.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.faults import disk_full, fake_ffmpeg, read_only
from trmd_cli.cli.app import app
from trmd_cli.events import Exposure, make_stream
from trmd_cli.write import write_events_npz, write_image

W, H = 64, 48
PREVIOUS = b"the user's previous output\n"
runner = CliRunner()


@dataclass(frozen=True)
class Inputs:
    image: Path
    events: Path


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Inputs:
    d = tmp_path_factory.mktemp("in")
    rng = np.random.default_rng(5)
    n = 6000
    s = make_stream(rng.integers(0, W, n), rng.integers(0, H, n),
                    np.sort(rng.integers(0, 100_000, n)), rng.integers(0, 2, n), W, H)
    yy, xx = np.mgrid[0:H, 0:W]
    write_image(d / "blurry.png", (0.2 + 0.6 * (((xx // 8) + (yy // 8)) % 2)).astype(np.float32))
    write_events_npz(d / "events.npz", s, [Exposure(10_000, 60_000)])
    return Inputs(d / "blurry.png", d / "events.npz")


def one_line(stderr: str) -> str:
    """The one error line (warnings about the input may come before it)."""
    lines = [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ") and "Traceback" not in stderr, stderr
    return lines[0]


def listing(folder: Path) -> dict[str, bytes | None]:
    """Every name under ``folder`` with its bytes (None for folders)."""
    return {str(p.relative_to(folder)): None if p.is_dir() else p.read_bytes()
            for p in sorted(folder.rglob("*"))}


#: command line (before -o) and the output's name: one per writer
WRITERS = {
    "convert-h5": (["convert", "{events}"], "c.h5"),
    "convert-npz": (["convert", "{events}"], "c.npz"),
    "convert-txt": (["convert", "{events}"], "c.txt"),
    "voxelize": (["voxelize", "{events}", "--n", "1"], "v.npz"),
    "voxelize-preview": (["voxelize", "{events}", "--n", "1", "--preview", "{out}/p.png"],
                         "v.npz"),
    "deblur": (["deblur", "{image}", "{events}", "--method", "edi", "--n", "1"], "d"),
    "deblur-gif": (["deblur", "{image}", "{events}", "--method", "edi", "--n", "1",
                    "--video", "{out}/v.gif"], "d"),
    "hfr-gif": (["hfr", "{image}", "{events}", "--method", "edi", "--n", "1"], "v.gif"),
    "hfr-folder": (["hfr", "{image}", "{events}", "--method", "edi", "--n", "1"], "f"),
}


def run(good: Inputs, out_dir: Path, args: list[str], name: str, *extra: str):
    fill = {"events": str(good.events), "image": str(good.image), "out": str(out_dir)}
    argv = [a.format(**fill) for a in args] + ["-o", str(out_dir / name), *extra]
    return runner.invoke(app, argv)


def previous(out_dir: Path, name: str) -> None:
    """What a previous run left at the output (a file, or a folder with a file)."""
    target = out_dir / name
    if target.suffix:
        target.write_bytes(PREVIOUS)
    else:
        target.mkdir()
        (target / "meta.json").write_bytes(PREVIOUS)


@pytest.mark.parametrize("after", [0, 3000], ids=["at-once", "half-way"])
@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_full_disk_is_one_line_and_leaves_nothing(tmp_path, good, monkeypatch, writer, after):
    args, name = WRITERS[writer]
    previous(tmp_path, name)
    before = listing(tmp_path)
    seen = disk_full(monkeypatch, after_bytes=after)
    r = run(good, tmp_path, args, name, "--overwrite", "--contrast", "0.2") if writer.startswith(
        ("deblur", "hfr")) else run(good, tmp_path, args, name, "--overwrite")
    monkeypatch.undo()
    assert seen["failed"] >= 1, r.output  # the injected failure was met
    assert r.exit_code == 2, r.output
    line = one_line(r.stderr)
    assert f"{tmp_path}: cannot write here (No space left on device)" in line, line
    assert "wrote" not in r.stdout
    assert listing(tmp_path) == before  # nothing new, nothing changed, no temporary


@pytest.mark.parametrize("writer", ["convert-h5", "convert-npz", "voxelize", "deblur", "hfr-gif"])
def test_read_only_mount_is_one_line(tmp_path, good, monkeypatch, writer):
    args, name = WRITERS[writer]
    read_only(monkeypatch)
    extra = ["--contrast", "0.2"] if writer.startswith(("deblur", "hfr")) else []
    r = run(good, tmp_path, args, name, *extra)
    monkeypatch.undo()
    assert r.exit_code == 2, r.output
    assert f"{tmp_path}: cannot write here (Read-only file system)" in one_line(r.stderr)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(os.name != "posix", reason="folder permissions")
@pytest.mark.parametrize("writer", ["convert-h5", "voxelize", "deblur"])
def test_folder_without_write_permission_is_one_line(tmp_path, good, writer):
    """A real process as a user who may not write there (root: without the capabilities that
    let it write anywhere)."""
    args, name = WRITERS[writer]
    out = tmp_path / "locked"
    out.mkdir()
    out.chmod(0o555)
    fill = {"events": str(good.events), "image": str(good.image), "out": str(out)}
    extra = ["--contrast", "0.2"] if writer.startswith("deblur") else []
    try:
        proc = _trmd(*(a.format(**fill) for a in args), "-o", str(out / name), *extra,
                     demote=True)
    finally:
        out.chmod(0o755)
    assert proc.returncode == 2, proc.stderr
    assert f"{out}: cannot write here (Permission denied)" in one_line(proc.stderr)
    assert list(out.iterdir()) == []


# -- MP4: FFmpeg's result is checked before it is renamed into place ----------------------------


@pytest.mark.parametrize("how,said", [("cut", "the video encoder did not finish the file"),
                                      ("enospc", "cannot write here (No space left on device)")])
@pytest.mark.parametrize("command", ["hfr", "deblur"])
def test_mp4_that_ffmpeg_did_not_finish_is_an_error(tmp_path, good, monkeypatch, how, said,
                                                    command):
    fake_ffmpeg(monkeypatch, tmp_path, how)
    out = tmp_path / "out"
    out.mkdir()
    video = out / "v.mp4"
    video.write_bytes(PREVIOUS)
    base = [str(good.image), str(good.events), "--method", "edi", "--n", "1", "--contrast",
            "0.2", "--overwrite"]
    if command == "hfr":
        r = runner.invoke(app, ["hfr", *base, "-o", str(video)])
    else:
        r = runner.invoke(app, ["deblur", *base, "-o", str(out / "d"), "--video", str(video)])
    assert r.exit_code == 2, r.output
    assert said in one_line(r.stderr)
    assert "wrote" not in r.stdout
    assert sorted(p.name for p in out.iterdir()) == ["v.mp4"]  # no folder, no temporary
    assert video.read_bytes() == PREVIOUS


def test_a_whole_mp4_passes_the_check(tmp_path, good):
    """The check does not refuse what FFmpeg writes when all is well (and the file opens)."""
    import imageio.v3 as iio

    from trmd_cli.video import mp4_problem

    r = runner.invoke(app, ["hfr", str(good.image), str(good.events), "--method", "edi", "--n",
                            "1", "--contrast", "0.2", "-o", str(tmp_path / "v.mp4")])
    assert r.exit_code == 0, r.output
    assert mp4_problem(tmp_path / "v.mp4") is None
    assert len(iio.imread(tmp_path / "v.mp4", plugin="pyav" if _has_av() else "FFMPEG")) == 3


def _has_av() -> bool:
    try:
        import av  # noqa: F401
    except ImportError:
        return False
    return True


# -- a real full disk: a tiny tmpfs (root only; fault injection above covers the rest) -----------


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 KiB tmpfs with ~4 KiB free, unmounted afterwards; skipped where it cannot be made."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if os.name != "posix" or os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a tmpfs needs root")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                          capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.decode().strip()}")
    try:
        (mnt / "fill").write_bytes(b"\0" * (60 << 10))
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.parametrize("argv,name", [
    (["hfr", "{image}", "{events}", "--method", "edi", "--contrast", "0.2"], "v.mp4"),
    (["deblur", "{image}", "{events}", "--method", "edi", "--contrast", "0.2", "--video",
      "{out}/v.mp4"], "d"),
    (["convert", "{events}"], "c.h5"),
])
def test_real_full_disk(tiny_disk, good, argv, name):
    """The reported failures as they happened: an MP4 FFmpeg could not finish, and HDF5 dying
    with SIGSEGV on the way out (real processes: a crash must not take the test with it)."""
    fill = {"events": str(good.events), "image": str(good.image), "out": str(tiny_disk)}
    cmd = [sys.executable, "-m", "trmd_cli", *(a.format(**fill) for a in argv), "-o",
           str(tiny_disk / name)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "cannot write here (No space left on device)" in one_line(proc.stderr)
    assert "wrote" not in proc.stdout
    assert sorted(p.name for p in tiny_disk.iterdir()) == ["fill"]


# -- an output that is, or holds, an input ------------------------------------------------------


def test_voxelize_onto_its_input_is_refused_even_with_overwrite(tmp_path, good):
    ev = tmp_path / "ev.npz"
    shutil.copy(good.events, ev)
    before = ev.read_bytes()
    r = runner.invoke(app, ["voxelize", str(ev), "-o", str(ev), "--overwrite"])
    assert r.exit_code == 2, r.output
    assert f"{ev}: the output is the input {ev}" in one_line(r.stderr)
    assert ev.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ev.npz"]


def test_deblur_into_the_folder_holding_its_events_is_refused(tmp_path, good):
    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(good.events, d / "ev.npz")
    before = listing(d)
    r = runner.invoke(app, ["deblur", str(good.image), str(d / "ev.npz"), "-o", str(d),
                            "--overwrite", "--method", "edi"])
    assert r.exit_code == 2, r.output
    assert "the output folder holds the input" in one_line(r.stderr)
    assert listing(d) == before


@pytest.mark.parametrize("link", ["symlink", "hardlink", "dotted"])
def test_the_same_file_by_another_name_is_refused(tmp_path, good, link):
    ev = tmp_path / "ev.npz"
    shutil.copy(good.events, ev)
    before = ev.read_bytes()
    other = tmp_path / "other.npz"
    if link == "symlink":
        other.symlink_to(ev)
    elif link == "hardlink":
        os.link(ev, other)
    else:
        other = tmp_path / "." / "sub" / ".." / "ev.npz"
        (tmp_path / "sub").mkdir()
    for argv in (["convert", str(ev), "-o", str(other)], ["voxelize", str(ev), "-o", str(other)]):
        r = runner.invoke(app, [*argv, "--overwrite"])
        assert r.exit_code == 2, (argv, r.output)
        assert "the output is the input" in one_line(r.stderr)
        assert ev.read_bytes() == before
    # a folder output (hfr's frames) given as the folder that holds the events
    r = runner.invoke(app, ["hfr", str(good.image), str(other), "--method", "edi", "-o",
                            str(tmp_path / "sub" / ".."), "--overwrite"])
    assert r.exit_code == 2, r.output
    assert "the output folder holds the input" in one_line(r.stderr)
    assert ev.read_bytes() == before


def test_refuse_inputs_names_what_it_protects(tmp_path):
    from trmd_cli.write import refuse_inputs

    (tmp_path / "a").mkdir()
    with pytest.raises(Exception, match="holds the input"):
        refuse_inputs(tmp_path, [tmp_path / "a" / "x.npz"])
    refuse_inputs(tmp_path / "a" / "out", [tmp_path / "a" / "x.npz"])  # beside it: fine
    refuse_inputs(tmp_path / "b.npz", [None, tmp_path / "a"])


# -- outputs whose folder is not one; inputs that cannot be read --------------------------------


def test_output_inside_a_file_is_one_line(tmp_path, good):
    f = tmp_path / "existing_file"
    f.write_bytes(PREVIOUS)
    r = runner.invoke(app, ["voxelize", str(good.events), "-o", str(f / "x.npz")])
    assert r.exit_code == 2, r.output
    assert "the output's parent is a file, not a folder" in one_line(r.stderr)
    assert f.read_bytes() == PREVIOUS


def _trmd(*args: str, timeout: float = 60, pass_fds=(), demote: bool = False):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    cmd = [sys.executable, "-m", "trmd_cli", *args]
    if demote:  # as root, drop the capabilities that let root read any file
        if os.geteuid() == 0:
            if not shutil.which("setpriv"):
                pytest.skip("root, and no setpriv to act as another user")
            cmd = ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--", *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout,
                          pass_fds=pass_fds)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
@pytest.mark.parametrize("command", [["info"], ["voxelize"], ["convert"]])
def test_a_fifo_is_refused_at_once(tmp_path, command):
    fifo = tmp_path / "ev.txt"
    os.mkfifo(fifo)
    argv = [*command, str(fifo)] + ([] if command == ["info"] else ["-o", str(tmp_path / "o.npz")])
    proc = _trmd(*argv, timeout=30)  # before: waited forever for a writer
    assert proc.returncode == 2, proc.stderr
    assert f"{fifo}: is a pipe, not a file" in one_line(proc.stderr)


def test_process_substitution_is_refused_not_misread(tmp_path, good):
    """``trmd info <(cat ev.txt)``: the shell passes /dev/fd/N, a pipe. Read once to sniff the
    format, its start was gone and the rest read as 'event lines have 1 columns'."""
    read, write = os.pipe()
    os.write(write, b"64 48\n0.000100 1 2 1\n0.000200 3 4 0\n")
    os.close(write)
    try:
        proc = _trmd("info", f"/dev/fd/{read}", pass_fds=(read,))
    finally:
        os.close(read)
    assert proc.returncode == 2, proc.stderr
    assert "is a pipe, not a file" in one_line(proc.stderr)


@pytest.mark.skipif(os.name != "posix", reason="file modes")
def test_an_unreadable_input_is_one_line_not_a_usage_box(tmp_path, good):
    ev = tmp_path / "ev.npz"
    shutil.copy(good.events, ev)
    ev.chmod(0)
    for argv in (["info", str(ev)], ["voxelize", str(ev), "-o", str(tmp_path / "v.npz")],
                 ["deblur", str(good.image), str(ev), "-o", str(tmp_path / "d")]):
        proc = _trmd(*argv, demote=True)
        assert proc.returncode == 2, proc.stderr
        assert f"{ev}: cannot be read (permission denied" in one_line(proc.stderr)
        assert "Usage" not in proc.stderr
