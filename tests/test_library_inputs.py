"""The library's public functions given what a caller may pass by mistake: a clear
InputError/ShapeError saying what and how to fix, or the right answer — never a bare
IndexError deep inside, never a silently wrong result."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.edi import edi_from_bins, edi_latent
from trmd_cli.errors import InputError, ShapeError
from trmd_cli.events import EventStream, Exposure, make_stream
from trmd_cli.methods import EdiMethod, MethodConfig, make_method
from trmd_cli.read import ReadOptions
from trmd_cli.threshold import search_contrast
from trmd_cli.voxel import scer_from_bins, scer_voxels


def test_unsigned_bins_give_signed_voxels():
    """V(k) = sgn(k − N) · the counts between the middle and k (Eq. 13): by hand, four bins
    of 200 are −400, −200, 200, 400 whatever type holds them."""
    for dtype in (np.uint8, np.uint16, np.int16, np.float32):
        got = scer_from_bins(np.full((4, 1, 1), 200, dtype)).ravel()
        assert got.tolist() == [-400, -200, 200, 400], dtype


def test_a_hot_mask_of_another_shape_or_type_is_refused():
    ev = make_stream([1], [1], [50], [1], 2, 2)
    b = np.full((2, 2), 0.5, np.float32)
    wrong = np.zeros((3, 3), bool)
    wrong[1, 0] = True  # flattened against 2×2 it would mark pixel (1, 1), the one that fired
    with pytest.raises(InputError, match=r"shape \(2, 2\)"):
        edi_latent(b, ev, Exposure(0, 100), [100], 0.2, hot_mask=wrong)
    with pytest.raises(InputError, match="expected bool"):
        edi_latent(b, ev, Exposure(0, 100), [100], 0.2, hot_mask=np.ones((2, 2)))
    # the mask of the pixel that fired drops its event: the latent frame is B
    right = np.zeros((2, 2), bool)
    right[1, 1] = True
    out = edi_latent(b, ev, Exposure(0, 100), [100], 0.2, hot_mask=right)
    np.testing.assert_array_equal(out[0], b)


def test_instants_that_are_not_numbers_are_refused():
    ev = make_stream([1], [1], [50], [1], 2, 2)
    b = np.full((2, 2), 0.5, np.float32)
    with pytest.raises(InputError, match="instant is nan"):
        edi_latent(b, ev, Exposure(0, 100), [np.nan], 0.2)
    with pytest.raises(InputError, match="instant is inf"):
        EdiMethod(3, 0.2, drop_isolated=False)(b, ev, Exposure(0, 100), [np.inf])
    with pytest.raises(InputError, match="instant is nan"):
        edi_from_bins(b, np.ones((2, 2, 2)), [np.nan], 0.2)
    with pytest.raises(ShapeError, match="M ≥ 1"):
        edi_from_bins(b, np.zeros((0, 2, 2)), [0.5], 0.2)


def test_columns_must_be_one_dimensional_and_of_one_length():
    with pytest.raises(InputError, match="differ in length"):
        make_stream([0, 1], [0, 0, 0], [3, 1, 2], [1, 1, 1], sort=True)
    with pytest.raises(InputError, match="differ in length"):
        make_stream([0, 1, 2, 3], [0, 0, 0], [3, 1, 2], [1, 1, 1], sort=True)
    with pytest.raises(InputError, match=r"'t' has shape \(1, 2\)"):
        make_stream([[0, 1]], [[0, 1]], [[0, 1]], [[1, 1]])
    with pytest.raises(InputError, match=r"'t' has shape \(\)"):
        make_stream([0], [0], 5, [1])


def test_a_stream_is_immutable_and_what_is_kept_for_it_stays_true():
    """The window model kept for a stream (by identity) cannot go stale: the stream's arrays
    are read-only views; the caller's own arrays keep their flags."""
    t = np.array([120, 150], np.int64)
    ev = make_stream([0, 0], [0, 0], t, [1, 1], 1, 1)
    assert t.flags.writeable  # the caller's array, untouched
    with pytest.raises(ValueError, match="read-only"):
        ev.p[:] = -1
    with pytest.raises(ValueError, match="read-only"):
        ev.slice(0, 200).t[0] = 0


def test_concatenated_parts_are_of_one_sensor_and_come_out_in_time_order():
    a = make_stream([0, 1], [0, 0], [10, 30], [1, 1], 2, 2)
    with pytest.raises(InputError, match="5x5 sensor"):
        EventStream.concatenate([a, make_stream([4], [4], [40], [1], 5, 5)])
    merged = EventStream.concatenate([a, make_stream([1, 0], [1, 1], [5, 30], [0, 0], 2, 2)])
    assert merged.t.tolist() == [5, 10, 30, 30]
    assert merged.x.tolist() == [1, 0, 1, 0] and merged.p.tolist() == [-1, 1, 1, -1]
    both = EventStream.concatenate([a, make_stream([1], [1], [30], [0], 2, 2)])
    assert both.t.tolist() == [10, 30, 30] and both.p.tolist() == [1, 1, -1]


@pytest.mark.parametrize("make", [
    lambda: make_method(MethodConfig(method="edi", n=1.5, contrast=0.2)),
    lambda: MethodConfig(method="edi", contrast="0.2"),
    lambda: MethodConfig(method="edi", n=True),
    lambda: EdiMethod(0, 0.2),
    lambda: EdiMethod(3, -1.0),
    lambda: Exposure(0, 60).instants_us(0),
    lambda: scer_voxels(make_stream([0], [0], [5], [1], 1, 1), Exposure(0, 10), 1.5),
])
def test_n_and_c_that_cannot_be_are_refused(make):
    with pytest.raises(InputError, match="whole number|positive number"):
        make()


def test_an_unbounded_contrast_search_is_refused():
    from trmd_cli.edi import EdiEvents

    ev = make_stream([1], [1], [50], [1], 2, 2)
    prep = EdiEvents.build(ev, Exposure(0, 100))
    b = np.full((2, 2), 0.5, np.float32)
    for bounds in ((0.1, np.inf), (np.nan, 1.0), (0.5, 0.1)):
        with pytest.raises(InputError, match="bounds"):
            search_contrast(b, prep, bounds)


@pytest.mark.parametrize("kw, needle", [
    ({"sensor": (10, 10, 3)}, "`sensor`"),
    ({"sensor": (0, 10)}, "`sensor`"),
    ({"columns": ("t", "t", "x", "p")}, "`columns`"),
    ({"time_unit": "days"}, "`time_unit`"),
])
def test_read_options_that_cannot_be_are_refused(kw, needle):
    with pytest.raises(InputError, match=needle):
        ReadOptions(**kw)


def test_the_hdf5_writer_refuses_what_its_reader_would(tmp_path):
    from trmd_cli.write import H5Writer, write_h5

    with pytest.raises(InputError, match="outside the file's 5x4 sensor"):
        with H5Writer(tmp_path / "a.h5", 5, 4) as w:
            w.add_events(make_stream([9], [9], [10], [1], 10, 10))
    unsorted = EventStream(*(np.array(v, d) for v, d in (([0, 1], np.uint16),
                                                          ([0, 0], np.uint16),
                                                          ([20, 10], np.int64),
                                                          ([1, 1], np.int8))), 5, 4)
    with pytest.raises(InputError, match="time order"):
        with H5Writer(tmp_path / "b.h5", 5, 4) as w:
            w.add_events(unsorted)
    s = make_stream([0], [0], [10], [1], 5, 4)
    with pytest.raises(InputError, match="NaN"):
        write_h5(tmp_path / "c.h5", s, blurry=np.full((1, 4, 5), np.nan),
                 exposures=[Exposure(0, 20)])
    with pytest.raises(InputError, match="2 frames but 1 exposure windows"):
        write_h5(tmp_path / "d.h5", s, blurry=np.zeros((2, 4, 5)), exposures=[Exposure(0, 20)])
    assert not list(tmp_path.iterdir())  # nothing written, no temporary file left


def test_the_text_writer_refuses_a_stream_it_could_not_read_back(tmp_path):
    from trmd_cli.write import write_events_text

    with pytest.raises(InputError, match="no events to write"):
        write_events_text(tmp_path / "e.txt", EventStream.empty(5, 4))
    assert not list(tmp_path.iterdir())


def test_a_psnr_range_and_an_image_shape_that_cannot_be_are_refused(tmp_path):
    from trmd_cli.metrics import psnr
    from trmd_cli.write import write_image

    a = np.zeros((4, 4), np.float32)
    with pytest.raises(InputError, match="data_range"):
        psnr(a, a + 0.1, data_range=float("nan"))
    with pytest.raises(InputError, match=r"shape \(4, 4, 4\)"):
        write_image(tmp_path / "four.png", np.zeros((4, 4, 4), np.float32))
    with pytest.raises(InputError, match=r"shape \(16,\)"):
        write_image(tmp_path / "flat.png", np.zeros(16, np.float32))
    assert not list(tmp_path.iterdir())
