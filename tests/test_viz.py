"""Strips (trmd_cli.viz.strip): the 8-bit preview form and the float form compare.png is made of."""

from __future__ import annotations

import numpy as np

from trmd_cli.viz import strip


def test_float_strip_keeps_gray_values_and_depth():
    a = np.full((40, 30), 0.25, np.float32)
    b = np.linspace(-0.5, 1.5, 40 * 30, dtype=np.float32).reshape(40, 30)
    out = strip([a, b], gap=4, keep_float=True)
    assert out.dtype == np.float32 and out.shape == (40, 64)
    np.testing.assert_array_equal(out[:, :30], a)
    np.testing.assert_array_equal(out[:, 30:34], 1.0)  # white separator
    np.testing.assert_array_equal(out[:, 34:], np.clip(b, 0, 1))  # no 8-bit rounding


def test_float_strip_labels_are_light_text_on_a_dark_outline():
    a = np.full((60, 80), 0.5, np.float32)
    out = strip([a, a], ("blurry", "sharp"), keep_float=True)
    for tile in (out[:, :80], out[:, 84:]):
        top = tile[:20]
        assert (top == 1.0).any() and (top == 0.0).any()
        np.testing.assert_array_equal(tile[30:], 0.5)  # the label stays in its corner


def test_float_strip_mixes_gray_and_colour_as_colour():
    gray = np.full((10, 12), 0.2, np.float32)
    rgb = np.zeros((10, 12, 3), np.float32)
    out = strip([gray, rgb], keep_float=True)
    assert out.shape == (10, 28, 3)
    np.testing.assert_array_equal(out[:, :12], np.float32(0.2))


def test_preview_strip_is_rgb8_with_padding():
    tall = np.ones((20, 10), np.float32)
    short = np.zeros((10, 10, 3), np.uint8)
    out = strip([tall, short], gap=2)
    assert out.dtype == np.uint8 and out.shape == (20, 22, 3)
    assert (out[:, :10] == 255).all() and (out[10:, 12:] == 0).all()
