"""Binned events (trmd_cli.read.bins) and the binned frame source (read.folders): files
recognised by content, the flat and (F, B, H, W) layouts read alike, pairing by sorted frame
order, and layouts that do not fit refused with one clear message."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.bins import write_bins
from tests.helpers.data import SHARED, needs_shared
from trmd_cli.errors import FormatError, InputError
from trmd_cli.read import open_events
from trmd_cli.read.bins import BinnedEvents, is_bins_file, read_bins
from trmd_cli.read.folders import BinnedWindow, open_binned_folder
from trmd_cli.read.mat import mat_variable_names
from trmd_cli.write import write_events_npz, write_image

F, B, H, W = 3, 4, 5, 6


def counts(dtype=np.int16) -> np.ndarray:
    """(F, B, H, W): every value says where it is (frame·100 + bin·10 + a pixel's share)."""
    f, b, y, x = np.indices((F, B, H, W))
    return (100 * f + 10 * b + (y + x) % 7 - 3).astype(dtype)


@pytest.mark.parametrize("compress", [False, True])
def test_mat_variable_names_without_decoding(tmp_path, compress):
    sio = pytest.importorskip("scipy.io")
    path = tmp_path / "a.mat"
    sio.savemat(path, {"event_bins": counts(), "x": np.arange(3.0), "longer_name_here": 1.0},
                do_compression=compress)
    assert mat_variable_names(path) == [name for name, *_ in sio.whosmat(path)]
    assert set(mat_variable_names(path)) == {"event_bins", "x", "longer_name_here"}


@pytest.mark.parametrize("fmt", ["mat", "npz", "npy"])
def test_bins_files_are_recognised_by_content(tmp_path, fmt):
    path = write_bins(tmp_path / f"b.{fmt}", counts())
    assert is_bins_file(path)
    # whatever the name says
    other = path.rename(tmp_path / "renamed.dat")
    assert is_bins_file(other)


def test_event_files_and_others_are_not_bins(tmp_path):
    from tests.helpers.camera import good, stream

    sio = pytest.importorskip("scipy.io")
    for fmt in ("mat", "npz", "npy", "txt", "h5"):
        assert not is_bins_file(good(tmp_path, fmt)), fmt
    s = stream()
    sio.savemat(tmp_path / "esl.mat", {"section_event_timestamp": s.t / 1e6})
    assert not is_bins_file(tmp_path / "esl.mat")
    write_events_npz(tmp_path / "ev.npz", s)
    assert not is_bins_file(tmp_path / "ev.npz")
    write_image(tmp_path / "img.png", np.zeros((4, 4), np.float32))
    assert not is_bins_file(tmp_path / "img.png")
    assert not is_bins_file(tmp_path / "missing.mat")
    assert not is_bins_file(tmp_path)


@pytest.mark.parametrize("fmt", ["mat", "npz", "npy"])
def test_flat_and_4d_layouts_read_alike(tmp_path, fmt):
    four = write_bins(tmp_path / f"four.{fmt}", counts())
    flat = write_bins(tmp_path / f"flat.{fmt}", counts().reshape(F * B, H, W))
    a, b = read_bins(four, F), read_bins(flat, F)
    assert (a.frames, a.bins_per_frame, a.width, a.height) == (F, B, W, H)
    assert (b.frames, b.bins_per_frame, b.width, b.height) == (F, B, W, H)
    for i in range(F):
        np.testing.assert_array_equal(a.frame(i), counts()[i])
        np.testing.assert_array_equal(b.frame(i), counts()[i])
        assert a.frame(i).dtype == np.int16
    # the flat layout: B = rows / F, so frame i is rows B·i … B·(i+1) − 1
    np.testing.assert_array_equal(read_bins(flat, 1).frame(0), counts().reshape(F * B, H, W))


def test_npy_is_memory_mapped_and_whole_floats_pass(tmp_path):
    path = write_bins(tmp_path / "b.npy", counts(np.float64))
    got = read_bins(path, F)
    assert isinstance(got.counts, np.memmap)
    np.testing.assert_array_equal(got.frame(2), counts()[2])


@pytest.mark.parametrize("case, error, match", [
    ("rows", InputError, "13 bins, which 3 frames do not divide"),
    ("frames", InputError, "the bins of 2 frames, the images number 3"),
    ("size", InputError, "the bins are 6x5 but the frames are 7x5"),
    ("nan", InputError, "frame 1, bin 2 holds NaN or infinite counts"),
    ("fraction", InputError, r"frame 2, bin 0 holds a count that is not a whole number \(0.25\)"),
    ("ndim", FormatError, r"shape \(12, 30\), expected \(F·B, H, W\) or \(F, B, H, W\)"),
    ("key", FormatError, "holds no 'event_bins' key"),
])
def test_layouts_that_do_not_fit(tmp_path, case, error, match):
    c, size, frames = counts(), None, F
    path = tmp_path / "b.npy"
    if case == "rows":
        c = np.concatenate([c.reshape(F * B, H, W), c[0, :1]])
    elif case == "frames":
        c = c[:2]
    elif case == "size":
        size = (7, 5)
    elif case == "nan":
        c = c.astype(np.float32)
        c[1, 2, 0, 0] = np.inf
        c[1, 2, 3, 3] = np.nan
    elif case == "fraction":
        c = c.astype(np.float64)
        c[2, 0, 4, 5] = 0.25
    elif case == "ndim":
        c = c.reshape(12, 30)
        # a 2-D .npy is no bins file; read it as one anyway to see the message
    else:
        path = tmp_path / "b.npz"
        np.savez(path, other=c)
    if case != "key":
        write_bins(path, c)
    with pytest.raises(error, match=match):
        read_bins(path, frames, size)


def test_binned_folder_pairs_by_sorted_frame_number(tmp_path):
    (tmp_path / "frames").mkdir()
    for name in ("100.png", "9.png", "10.png"):  # numeric order: 9, 10, 100
        write_image(tmp_path / "frames" / name, np.full((H, W), 0.5, np.float32))
    (tmp_path / "frames" / "notes.txt").write_text("not a frame")
    bins = write_bins(tmp_path / "b.npy", counts().reshape(F * B, H, W))
    with open_binned_folder(tmp_path / "frames", bins) as src:
        assert len(src) == 3 and src.bins_per_frame == B and src.recording is None
        items = list(src)
        assert all(isinstance(it, BinnedWindow) for it in items)
        assert [it.frame.name for it in items] == ["9", "10", "100"]
        assert [it.frame.index for it in items] == [9, 10, 100]
        assert all(it.frame.exposure is None for it in items)
        for i, it in enumerate(items):
            np.testing.assert_array_equal(it.bins, counts()[i])
        sub = list(src.subset([2]))
        assert sub[0].frame.name == "100"
        np.testing.assert_array_equal(sub[0].bins, counts()[2])


def test_event_readers_point_a_bins_file_to_the_frames_folder(tmp_path):
    for fmt in ("mat", "npz", "npy"):
        path = write_bins(tmp_path / f"b.{fmt}", counts())
        with pytest.raises(FormatError, match="binned events.*IMAGES_DIR BINS_FILE"):
            open_events(path)


@needs_shared
def test_ledvdi_bins_read_as_the_readme_says():
    sio = pytest.importorskip("scipy.io")
    path = SHARED / "real" / "ledvdi-rotate" / "EventBin3.mat"
    assert is_bins_file(path)
    got = read_bins(path, 54, (240, 180))
    assert isinstance(got, BinnedEvents)
    assert (got.frames, got.bins_per_frame) == (54, 18)
    # frame k (image blurred/00kk.png, the (k−2)-th in sorted order) uses rows 18(k−2) … 18(k−1)−1
    ref = sio.loadmat(path)["event_bins"]
    for k in (2, 30, 55):
        np.testing.assert_array_equal(got.frame(k - 2), ref[18 * (k - 2): 18 * (k - 1)])
