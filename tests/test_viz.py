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


def _hue(rgb):
    import cv2

    img = rgb.astype(np.float32)[None] / 255  # a (1, N, 3) image for OpenCV
    return cv2.cvtColor(img, cv2.COLOR_RGB2HSV)[0, :, 0]


def test_flow_colours_hue_is_the_direction_and_saturation_the_length():
    import cv2

    from trmd_cli.viz import flow_colours

    angles = np.arange(0, 360, 15.0)
    dx, dy = np.cos(np.radians(angles)), np.sin(np.radians(angles))
    rgb = flow_colours(dx * 4, dy * 4, 4.0)
    err = (_hue(rgb) - angles + 180) % 360 - 180
    assert np.abs(err).max() < 1.5
    # right is red, down (image y grows downwards) is at 90°, no motion is white
    assert tuple(rgb[0]) == (255, 0, 0)
    assert tuple(flow_colours(np.zeros(1), np.zeros(1), 1.0)[0]) == (255, 255, 255)
    half = cv2.cvtColor(flow_colours(np.array([2.0]), np.array([0.0]), 4.0)[None].astype(
        np.float32) / 255, cv2.COLOR_RGB2HSV)[0, 0, 1]
    assert abs(half - 0.5) < 0.01


def test_colour_wheel_agrees_with_the_picture():
    from trmd_cli.viz import colour_wheel, flow_colours, flow_picture

    wheel = colour_wheel(41)
    # the rim point in direction 135° (down-left) has the colour of a full-length 135° motion
    r = 20
    x, y = 20 + round(r * np.cos(np.radians(135))), 20 + round(r * np.sin(np.radians(135)))
    want = flow_colours(np.array([np.cos(np.radians(135))]), np.array([np.sin(np.radians(135))]),
                        1.0)[0]
    assert np.abs(wheel[y, x].astype(int) - want.astype(int)).max() <= 12
    d = np.zeros((90, 120, 2), np.float32)
    d[..., 0] = 3.0  # 3 px to the right everywhere
    pic = flow_picture(d)
    assert tuple(pic[5, 5]) == (255, 0, 0)
    # the legend sits in the bottom right corner and shows the wheel
    assert not np.array_equal(pic[-20:, -20:], np.broadcast_to(pic[5, 5], (20, 20, 3)))
    assert np.array_equal(flow_picture(d, legend=False)[-20:, -20:],
                          np.broadcast_to(pic[5, 5], (20, 20, 3)))


def test_event_picture_shares_one_scale():
    from trmd_cli.viz import event_picture

    a = np.zeros((10, 12))
    b = np.zeros((10, 12))
    a[5, 5], b[5, 5] = 1.0, 4.0
    out = event_picture([a, b])
    assert out.shape == (10, 28, 3)
    left, right = out[5, 5, 0], out[5, 16 + 5, 0]
    assert right == 0 and left > 150  # the stronger image sets the scale, white background
    assert out[0, 0, 0] == 255
