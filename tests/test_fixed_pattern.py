"""The sensor's fixed pattern: estimated where the scene moves and the frames agree, kept
otherwise, and removed before every method (trmd_cli.fixed_pattern, deblur.settle)."""

from __future__ import annotations

import numpy as np
import pytest

from trmd_cli.errors import InputError
from trmd_cli.fixed_pattern import MIN_FRAMES, FixedPattern, estimate_fixed_pattern

H, W = 96, 128


def _scene(rng: np.random.Generator, shift: int, size: tuple[int, int] = (H, W)) -> np.ndarray:
    """A textured scene seen ``shift`` px further along a wide random image: blobs of
    about 6–12 px, intensity 0.2–0.8, the detail a blurry frame keeps."""
    import cv2

    h, w = size
    wide = cv2.GaussianBlur(rng.random((h, w + 400)).astype(np.float32), (0, 0), 3.0)
    wide = (wide - wide.min()) / (wide.max() - wide.min())
    return (0.2 + 0.6 * wide[:, shift:shift + w]).astype(np.float32)


def _pattern(seed: int = 7, sigma: float = 0.01) -> np.ndarray:
    """A pixel offset of σ = ``sigma`` and a column offset of half that."""
    r = np.random.default_rng(seed)
    return (r.normal(0, sigma, (H, W)) + r.normal(0, sigma / 2, (1, W))).astype(np.float32)


def _moving(frames: int = 8, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    wide_seed = rng.integers(1 << 30)
    return [_scene(np.random.default_rng(wide_seed), 37 * k) for k in range(frames)]


def _names(k: int) -> list[str]:
    return [f"{i:06d}" for i in range(k)]


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def test_pattern_under_a_moving_scene_is_found_and_removed():
    p = _pattern()
    scenes = _moving()
    frames = [s + p for s in scenes]
    got = estimate_fixed_pattern(frames, _names(8))
    assert got.removed and got.reason is None
    assert got.agreement > 0.8 and got.scene_correlation < 0.3
    # the estimate follows the pattern (its finest scale: what a σ = 1 px blur leaves)
    assert _corr(got.offsets, p) > 0.85
    # removing it brings every frame nearer its scene (the error that is left: the
    # pattern's smooth part, which the estimate does not hold, and the scene's residue)
    for s, f in zip(scenes, frames, strict=True):
        before = np.sqrt(np.mean((f - s) ** 2))
        after = np.sqrt(np.mean((got.removed_from(f) - s) ** 2))
        assert after < 0.6 * before
    assert got.meta()["removed"] is True and got.meta()["rms"] == pytest.approx(got.rms, 1e-4)


def test_still_scene_keeps_its_frames():
    """A static scene's detail is fixed to the pixels as the pattern is: nothing removed."""
    scene = _moving(1)[0]
    noise = np.random.default_rng(3)
    frames = [scene + _pattern() + noise.normal(0, 0.002, (H, W)).astype(np.float32)
              for _ in range(8)]
    got = estimate_fixed_pattern(frames, _names(8))
    assert not got.removed and got.offsets is None
    assert got.scene_correlation > 0.9 and "hardly moved" in got.reason
    assert got.removed_from(frames[0]) is frames[0]


def test_frames_without_a_pattern_keep_their_detail():
    """A moving scene with independent noise and no pattern: the halves disagree."""
    noise = np.random.default_rng(5)
    frames = [s + noise.normal(0, 0.005, (H, W)).astype(np.float32) for s in _moving()]
    got = estimate_fixed_pattern(frames, _names(8))
    assert not got.removed
    assert abs(got.agreement) < 0.3 and "share no fixed pattern" in got.reason
    assert got.meta() == {"removed": False, "frames": _names(8),
                          "agreement": round(got.agreement, 4),
                          "scene_correlation": round(got.scene_correlation, 4),
                          "reason": got.reason}


def test_too_few_frames():
    frames = [s + _pattern() for s in _moving(MIN_FRAMES - 1)]
    got = estimate_fixed_pattern(frames, _names(MIN_FRAMES - 1))
    assert not got.removed and f"at least {MIN_FRAMES}" in got.reason


def test_reliability_scales_a_noisy_estimate():
    """With noise as strong as the pattern the halves agree less, and the estimate is scaled
    by the split-half reliability 2r / (1 + r) rather than removed whole."""
    noise = np.random.default_rng(11)
    p = _pattern(sigma=0.01)
    frames = [s + p + noise.normal(0, 0.01, (H, W)).astype(np.float32) for s in _moving()]
    got = estimate_fixed_pattern(frames, _names(8))
    assert got.removed and got.agreement < 0.9
    clean = estimate_fixed_pattern([s + p for s in _moving()], _names(8))
    # the noise adds to the median's spread (unscaled it would exceed the clean estimate's
    # RMS); scaled by its reliability it stays below it
    scale = 2 * got.agreement / (1 + got.agreement)
    assert scale < 0.9 and got.rms < clean.rms


def test_colour_frames_get_a_pattern_per_channel():
    p = np.stack([_pattern(1), _pattern(2), _pattern(3)], axis=-1)
    frames = [np.repeat(s[..., None], 3, axis=-1) + p for s in _moving()]
    got = estimate_fixed_pattern(frames, _names(8))
    assert got.removed and got.offsets.shape == (H, W, 3)
    for ch in range(3):
        assert _corr(got.offsets[..., ch], p[..., ch]) > 0.85
    assert got.removed_from(frames[0]).dtype == np.float32


def test_mismatched_frames_are_one_clear_error():
    frames = [s + _pattern() for s in _moving()]
    got = estimate_fixed_pattern(frames, _names(8))
    with pytest.raises(InputError, match="does not match"):
        got.removed_from(np.zeros((H, W + 2), np.float32))
    with pytest.raises(InputError, match="frame 000003 is"):
        estimate_fixed_pattern([*frames[:3], frames[3][:, :-1], *frames[4:]], _names(8))
    with pytest.raises(InputError, match="names"):
        estimate_fixed_pattern(frames, _names(7))


def test_removed_from_clips_to_the_unit_range():
    offsets = np.full((4, 4), 0.1, np.float32)
    pattern = FixedPattern(offsets, ("a",), 0.9, 0.0)
    out = pattern.removed_from(np.array([[0.05, 0.5, 1.0, 0.0]] * 4, np.float32))
    np.testing.assert_allclose(out[0], [0.0, 0.4, 0.9, 0.0], atol=1e-7)
    assert pattern.rms == pytest.approx(0.1)


@pytest.mark.parametrize("k", [5, 6, 8])
def test_median_is_numpys(k):
    from trmd_cli.fixed_pattern import _median

    stack = np.random.default_rng(k).random((k, 7, 9)).astype(np.float32)
    np.testing.assert_array_equal(_median(stack), np.median(stack, axis=0))


def test_binned_folder_and_frames_folder_give_their_images(tmp_path):
    """``recording_pattern`` reads the frames alone from a binned set too (no bins needed), in
    order, and finds the pattern the frames carry."""
    from tests.helpers.bins import write_bins
    from trmd_cli.deblur import recording_pattern
    from trmd_cli.read.base import ReadOptions
    from trmd_cli.read.inputs import open_inputs
    from trmd_cli.write import write_image

    p = _pattern()
    (tmp_path / "blurry").mkdir()
    for k, s in enumerate(_moving()):
        write_image(tmp_path / "blurry" / f"{k:04d}.png", s + p, bit_depth=16)
    bins = write_bins(tmp_path / "event_bins.npz", np.ones((8, 6, H, W), np.int32))
    with open_inputs([tmp_path / "blurry", bins], ReadOptions()) as ins:
        assert ins.binned
        got = recording_pattern(ins.source)
    assert got.removed and got.frames == tuple(f"{k:04d}" for k in range(8))
    assert _corr(got.offsets, p) > 0.85
