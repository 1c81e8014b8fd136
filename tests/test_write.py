"""Atomic writers: what they leave behind, and with which permissions."""

from __future__ import annotations

import os
import stat

import pytest

from trmd_cli.write import atomic_dir, atomic_path


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_output_folders_follow_the_umask_like_mkdir(tmp_path, umask_022):
    """mkdtemp makes private folders; a finished output folder is as mkdir would make it."""
    reference = tmp_path / "made_by_mkdir"
    reference.mkdir()
    with atomic_dir(tmp_path / "out") as tmp:
        (tmp / "a.txt").write_text("x")
    mode = stat.S_IMODE((tmp_path / "out").stat().st_mode)
    assert mode == stat.S_IMODE(reference.stat().st_mode) == 0o755
    assert sorted(p.name for p in tmp_path.iterdir()) == ["made_by_mkdir", "out"]


def test_a_failed_folder_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError), atomic_dir(tmp_path / "out") as tmp:
        (tmp / "a.txt").write_text("x")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_file_appears_only_when_complete(tmp_path):
    target = tmp_path / "f.bin"
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"123")
        assert not target.exists()
    assert target.read_bytes() == b"123"
