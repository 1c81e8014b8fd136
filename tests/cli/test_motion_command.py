"""`trmd motion`: a known simulated translation shows in flow.png's hue and in motion.json's
numbers; bad input ends in one error line and leaves no output."""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from tests.helpers.data import texture
from trmd_cli.cli.app import app
from trmd_cli.motion import SampledMotion
from trmd_cli.read.frames import read_image
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample
from trmd_cli.write import write_events_npz, write_image

runner = CliRunner()
W, H = 128, 96


@pytest.fixture(scope="module")
def translation(tmp_path_factory):
    """A straight, uniform camera translation (no rotation, zoom, perspective or bending) and
    its true start-to-end displacement (pixels), from the simulator's own path."""
    d = tmp_path_factory.mktemp("motion")
    motion = MotionRanges(translation_px=18, rotation_deg=0, scale=0, perspective=0,
                          curvature=0)
    s = make_sample(texture(220, 280, seed=9), n=3, size=(W, H), rng=np.random.default_rng(4),
                    motion=motion, sensor=SensorConfig.clean(0.2), read_noise=0.0)
    true = SampledMotion(s.motion)
    x0, y0 = true.positions(0.0, 60.0, 40.0)
    x1, y1 = true.positions(1.0, 60.0, 40.0)
    shift = (float(x1 - x0), float(y1 - y0))
    assert math.hypot(*shift) > 6  # a motion worth measuring
    write_image(d / "blurry.png", s.blurry, 16)
    write_events_npz(d / "events.npz", s.events, [s.exposure])
    return d, shift


@pytest.fixture(scope="module")
def result(translation, tmp_path_factory):
    d, shift = translation
    out = tmp_path_factory.mktemp("out") / "m"
    r = runner.invoke(app, ["motion", str(d / "blurry.png"), str(d / "events.npz"), "-o",
                            str(out)])
    assert r.exit_code == 0, r.output
    return out, shift, r


def test_motion_json_has_the_known_translation(result):
    out, (dx, dy), r = result
    m = json.loads((out / "motion.json").read_text())
    vx, vy = m["velocity_px_per_exposure"]
    # uniform motion: the velocity is the start-to-end displacement
    assert abs(vx - dx) < 0.5 and abs(vy - dy) < 0.5, (m["velocity_px_per_exposure"], dx, dy)
    assert m["velocity_px_per_s"][0] == pytest.approx(vx * 1e6 / m["exposure_duration_us"],
                                                      rel=1e-3)
    want = math.degrees(math.atan2(dy, dx)) % 360
    assert abs((m["direction_deg"] - want + 180) % 360 - 180) < 3
    assert abs(m["rotation_deg_per_exposure"]) < 0.3
    assert abs(m["zoom_log_scale_per_exposure"]) < 0.01
    assert m["start_to_end_px"]["mean"] == pytest.approx(math.hypot(dx, dy), abs=0.6)
    assert m["confidence"] > 1.2 and m["events"] > 500
    # the estimated c refitted to the deconvolution (the sensor's threshold: 0.2)
    assert m["fallback_contrast"] == pytest.approx(0.2, rel=0.05)
    assert "velocity (" in r.stdout and "wrote" in r.stdout


def _hue_deg(rgb: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(rgb.astype(np.float32) / 255, cv2.COLOR_RGB2HSV)
    return hsv[..., 0]


def test_flow_picture_hue_is_the_direction(result):
    out, (dx, dy), _ = result
    flow = (read_image(out / "flow.png") * 255 + 0.5).astype(np.uint8)
    assert flow.shape == (H, W, 3)
    want = math.degrees(math.atan2(dy, dx)) % 360
    # the top left quarter: away from the legend in the bottom right corner
    hue = _hue_deg(flow[: H // 2, : W // 2])
    err = np.abs((hue - want + 180) % 360 - 180)
    assert np.median(err) < 4, (float(np.median(hue)), want)
    # uniform translation at full colour: every pixel saturated (the scale is the longest)
    sat = cv2.cvtColor(flow[: H // 2, : W // 2].astype(np.float32) / 255, cv2.COLOR_RGB2HSV)
    assert np.median(sat[..., 1]) > 0.95


def test_the_other_pictures(result):
    out, _, _ = result
    weight = read_image(out / "weight.png")
    assert weight.shape[:2] == (H, W)
    events = read_image(out / "events.png")
    assert events.shape[0] == H and events.shape[1] == 2 * W + 4
    gray = events.mean(-1) if events.ndim == 3 else events
    before, after = gray[:, :W], gray[:, W + 4:]
    # compensated events concentrate on the edges: more empty (white) pixels, darker lines
    assert (after > 0.99).mean() > (before > 0.99).mean()


def test_bad_input_gives_one_line(translation, tmp_path):
    d, _ = translation
    out = tmp_path / "m"
    r = runner.invoke(app, ["motion", str(d / "blurry.png"), "-o", str(out)])
    assert_one_error_line(r, "blurry.png", "no events")
    r = runner.invoke(app, ["motion", str(d / "missing.png"), str(d / "events.npz"), "-o",
                            str(out)])
    assert_one_error_line(r, "missing.png", "not found|does not exist|no such")
    r = runner.invoke(app, ["motion", str(d / "blurry.png"), str(d / "events.npz"), "-o",
                            str(out), "--contrast", "fast"])
    assert_one_error_line(r, "--contrast", "not a number")
    assert not out.exists()
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = runner.invoke(app, ["motion", str(d / "blurry.png"), str(d / "events.npz"), "-o",
                            str(out)])
    assert_one_error_line(r, str(out.name), "exists")
    assert (out / "keep.txt").read_text() == "mine" and len(list(out.iterdir())) == 1


def test_no_clear_motion_is_said_and_marked(translation, tmp_path):
    """Every event at one instant: nothing moves them, so the search's best candidate is no
    motion found, and the line and motion.json say so instead of reporting its velocity."""
    from trmd_cli.read import ReadOptions, open_events

    d, _ = translation
    with open_events(d / "events.npz", ReadOptions()) as rec:
        ev = rec.events()
        e = rec.stored_windows()[0]
    at_once = dataclasses.replace(ev, t=np.full(len(ev), int(e.mid_us), np.int64))
    write_events_npz(tmp_path / "still.npz", at_once, [e])
    out = tmp_path / "m"
    r = runner.invoke(app, ["motion", str(d / "blurry.png"), str(tmp_path / "still.npz"), "-o",
                            str(out)])
    assert r.exit_code == 0, r.output
    assert "no clear global motion in the events" in r.output
    m = json.loads((out / "motion.json").read_text())
    assert m["motion_found"] is False and m["confidence"] < 1.05
    assert m["deconvolution_share"] == 0.0


def test_a_clear_motion_is_marked_found(result):
    out, _, r = result
    assert json.loads((out / "motion.json").read_text())["motion_found"] is True
    assert "no clear global motion" not in r.output
