"""The fusion network and the fused method: its inputs, its start, its files."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from trmd_cli.errors import InputError, WeightsError
from trmd_cli.events import make_stream
from trmd_cli.fusion import (
    QUIET_SIGMA,
    fusion_inputs,
    keep_where_quiet,
    motion_where_trusted,
)
from trmd_cli.methods import EdiMethod, FusedMethod, MotionMethod, TrmdMethod
from trmd_cli.models.fusion import (
    EVENT_CLIP,
    FusionNet,
    default_fusion_path,
    fusion_planes,
    load_fusion,
    save_fusion,
)
from trmd_cli.models.weights import default_weights_path
from trmd_cli.simulate import MotionRanges, SensorConfig, make_sample

from .helpers.data import texture

needs_weights = pytest.mark.skipif(not default_weights_path().is_file(),
                                   reason="no shipped RE-Net weights")
needs_fusion = pytest.mark.skipif(
    not (default_fusion_path().is_file() and default_weights_path().is_file()),
    reason="no shipped fusion weights")


def _margins(frames: np.ndarray, other: np.ndarray, sharp: np.ndarray) -> tuple[float, float]:
    """PSNR of ``frames`` minus that of ``other`` (both clipped to [0, 1]) against the 2N+1
    ``sharp`` frames, dB: (middle frame, mean over the sequence)."""
    from trmd_cli.metrics import psnr

    def each(f):
        return [psnr(np.clip(a, 0, 1), b) for a, b in zip(f, sharp, strict=True)]

    a, b = each(frames), each(other)
    mid = len(sharp) // 2
    return a[mid] - b[mid], float(np.mean(a)) - float(np.mean(b))


#: a small camera shake, nothing moving on its own
MOVING = MotionRanges(translation_px=12, rotation_deg=0.5, scale=0.01, perspective=0,
                      curvature=0.2, foreground_prob=0.0)


def _sample(seed: int = 3):
    return make_sample(texture(300, 400, seed=seed), size=(96, 72),
                       rng=np.random.default_rng(seed), motion=MOVING,
                       sensor=SensorConfig.clean(0.2), read_noise=0.003)


def test_planes_are_laid_out_per_instant_and_channel():
    """Colour frames: one row per (instant, channel), k-major; the weight, the clipped events
    and the instant (k − N)/N shared by the channels; B repeated for every instant."""
    rng = np.random.default_rng(0)
    k, h, w, n = 5, 6, 7, 2
    m, t, e = (rng.random((k, h, w, 3)).astype(np.float32) for _ in range(3))
    b = rng.random((h, w, 3)).astype(np.float32)
    wt = rng.random((k, h, w)).astype(np.float32)
    ev = (10 * rng.standard_normal((k, h, w))).astype(np.float32)
    p = fusion_planes(m, t, e, b, wt, ev, n)
    assert p.shape == (k * 3, 7, h, w)
    row = 3 * 4 + 2  # instant 4, channel 2
    np.testing.assert_array_equal(p[row, 0].numpy(), m[4, ..., 2])
    np.testing.assert_array_equal(p[row, 1].numpy(), t[4, ..., 2])
    np.testing.assert_array_equal(p[row, 2].numpy(), e[4, ..., 2])
    np.testing.assert_array_equal(p[row, 3].numpy(), b[..., 2])
    np.testing.assert_array_equal(p[row, 4].numpy(), wt[4])
    np.testing.assert_array_equal(p[row, 5].numpy(), np.clip(ev[4], -EVENT_CLIP, EVENT_CLIP))
    assert (p[row, 6] == (4 - n) / n).all()


def test_an_untrained_network_returns_the_motion_frame():
    """The last convolution starts at zero: output = the first plane, exactly, at any size
    (odd sizes are padded inside and cropped back)."""
    x = torch.rand(3, 7, 33, 50)
    with torch.no_grad():
        out = FusionNet(8)(x)
    assert out.shape == (3, 1, 33, 50)
    assert torch.equal(out[:, 0], x[:, 0])


def test_weights_round_trip_and_bad_files(tmp_path):
    torch.manual_seed(0)
    net = FusionNet(8)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 0.05)
    path = save_fusion(tmp_path / "f.safetensors", net, {"trained_on": "x.h5", "steps": 3})
    back, meta = load_fusion(path)
    assert meta["trained_on"] == "x.h5" and meta["steps"] == "3"
    x = torch.rand(2, 7, 20, 24)
    with torch.no_grad():
        assert torch.equal(back(x), net(x))
    with pytest.raises(WeightsError, match="no fusion weights"):
        load_fusion(tmp_path / "missing.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a safetensors file")
    with pytest.raises(WeightsError, match="not a readable safetensors"):
        load_fusion(junk)
    from safetensors.torch import save_file

    other = tmp_path / "other.safetensors"
    save_file({"w": torch.zeros(1)}, str(other), metadata={"format": "trmd-weights"})
    with pytest.raises(WeightsError, match="not fusion weights"):
        load_fusion(other)


def test_where_nothing_fired_and_no_motion_is_used_the_frames_are_edis():
    """keep_where_quiet, by construction: the network's frames (1) where events fired densely
    or the motion method's weight is above 0, EDI's (0) more than 4σ from any event where the
    weight is 0, and a blend that falls monotonically in between; motion_where_trusted blends
    the motion frames in by the weight; colour frames alike."""
    k, h, w = 3, 40, 120
    fired = np.zeros((h, w), bool)
    fired[:, :30] = True  # every pixel of the left quarter fired
    weight = np.zeros((k, h, w), np.float32)
    weight[:, 10:20, 100:110] = 0.3  # the motion used there, far from any event
    for shape in ((k, h, w), (k, h, w, 3)):
        out = keep_where_quiet(np.ones(shape, np.float32), np.zeros(shape, np.float32), weight,
                               fired)
        assert out.shape == shape and out.dtype == np.float32
        row = out[1, 30] if out.ndim == 3 else out[1, 30, :, 1]
        assert np.all(row[:30] == 1.0)
        far = 30 + int(np.ceil(4 * QUIET_SIGMA))
        assert np.all(row[far:100] == 0.0)
        assert np.all(np.diff(row[:100]) <= 0) and 0 < row[45] < 1
        assert np.all(out[:, 10:20, 100:110] == 1.0)
        # beyond MAX_CONTRAST: the motion frames (here 2) by the weight, the fused (1) by
        # the rest
        got = motion_where_trusted(np.ones(shape, np.float32), np.full(shape, 2.0, np.float32),
                                   weight)
        assert got.shape == shape and got.dtype == np.float32
        assert np.allclose(got[:, 10:20, 100:110], 1.3) and np.all(got[:, 30:] == 1.0)


@needs_weights
def test_fused_with_an_untrained_network_is_the_motion_method(tmp_path):
    """With the network at its start the fused frames are the motion method's, frame for
    frame, and its inputs are the three methods as each runs alone (one c for all)."""
    s = _sample()
    path = save_fusion(tmp_path / "zero.safetensors", FusionNet(8), {})
    fused = FusedMethod(3, fusion_weights=path, threads=1)
    out = fused(s.blurry, s.events, s.exposure)
    c = out.contrast
    alone = MotionMethod(3, contrast=c)(s.blurry, s.events, s.exposure)
    np.testing.assert_allclose(out.frames, alone.frames, atol=1e-6)
    ins = fusion_inputs(s.blurry, s.events, s.exposure, TrmdMethod(3, contrast=c, threads=1), 3)
    trmd = TrmdMethod(3, contrast=c, threads=1)(s.blurry, s.events, s.exposure)
    np.testing.assert_allclose(ins.trmd, trmd.frames, atol=1e-6)
    assert ins.contrast == pytest.approx(c)
    assert np.all(ins.events[3] == 0)
    # instants on the grid are the grid's frames; one between them is propagated from the
    # nearest by the events, as TRMD does
    grid = s.exposure.instants_us(3)
    some = fused(s.blurry, s.events, s.exposure, grid[[0, 3]])
    np.testing.assert_allclose(some.frames, out.frames[[0, 3]], atol=1e-6)
    between = fused(s.blurry, s.events, s.exposure, np.array([grid[3] + 1.0]))
    assert between.frames.shape == (1, 72, 96)
    # 1 µs after the middle: almost no event between, so almost the middle frame
    assert np.abs(between.frames[0] - out.frames[3]).mean() < 1e-3
    # binned data: no event times, no motion: the motion method's fallback, EDI's frames, is
    # what the network corrects, said once; it gives its own 2N+1 frames only
    bins = np.random.default_rng(1).integers(-2, 3, (6, 72, 96)).astype(np.float32)
    got = fused.from_bins(s.blurry, bins)
    want = EdiMethod(3, contrast=got.contrast).from_bins(s.blurry, bins)
    np.testing.assert_allclose(got.frames, want.frames, atol=1e-6)
    assert any("no event times" in note for note in got.notes)
    with pytest.raises(InputError, match="own 7 frames"):
        fused.from_bins(s.blurry, bins, np.array([0.5]))


@needs_fusion
def test_shipped_fusion_beats_the_motion_method_on_clean_samples():
    """Synthetic camera shakes with known ground truth: in the mean over four of them the
    shipped fusion is above the motion method (which it starts from) on the middle frame and
    the sequence. (One sample alone can go either way: over twelve, the network's margin
    ranged from −0.2 to +1.5 dB on the middle frame, +0.4 in the mean.)"""

    method = FusedMethod(3, threads=1)  # the weights read once
    margins = []
    for seed in (2, 3, 4, 5):
        s = _sample(seed=seed)
        fused = method(s.blurry, s.events, s.exposure)
        alone = MotionMethod(3, contrast=fused.contrast)(s.blurry, s.events, s.exposure)
        margins.append(_margins(fused.frames, alone.frames, s.sharp))
    mid, whole = np.mean(margins, axis=0)  # over the samples
    assert mid > 0
    assert whole > 0


@needs_fusion
def test_shipped_fusion_beats_trmd_on_binned_samples():
    """The same camera shakes given as 18 bins (no event times, so no motion): the network
    on TRMD's frames and EDI's in the motion method's place is above TRMD's frames in the mean
    over four (measured +0.17…+0.81 dB on the middle frame, +0.51…+0.65 on the sequence)."""
    from trmd_cli.voxel import event_bins

    fused, trmd = FusedMethod(3, threads=1), TrmdMethod(3, threads=1, settle_contrast=True)
    margins = []
    for seed in (2, 3, 4, 5):
        s = _sample(seed=seed)
        bins = event_bins(s.events, s.exposure, 18)
        got, alone = fused.from_bins(s.blurry, bins), trmd.from_bins(s.blurry, bins)
        assert got.contrast == pytest.approx(alone.contrast)
        margins.append(_margins(got.frames, alone.frames, s.sharp))
    mid, whole = np.mean(margins, axis=0)  # over the samples
    assert mid > 0
    assert whole > 0.3


@needs_fusion
@pytest.mark.parametrize("mover", [False, True], ids=["still", "one mover"])
@pytest.mark.parametrize("contrast", [None, 0.75], ids=["DAVIS-like", "c=0.75"])
def test_shipped_fusion_keeps_what_a_still_camera_saw(mover, contrast):
    """A camera on a tripod (0.3 px of shake): B is sharp wherever nothing moves on its own,
    and EDI's frames are B there. The motion method finds no global motion and falls back to
    EDI; the network must not smooth what B holds. In the mean over four samples (PSNR near
    50 dB where nothing moves), on the DAVIS-like sensor the fused middle frame is within 1 dB
    of EDI's and the sequence within 0.5 dB. Measured: nothing moving +0.11 / +0.14 dB, one
    mover +2.02 / +2.61 (the network alone, without EDI's frames where nothing fired: −0.47 /
    +0.11 and +1.92 / +2.60); a network never shown a still camera gave −3.21 / −2.13 and
    +0.31 / +1.55, the texture smoothed. At c = 0.75, where hardly anything but the mover
    fires, both are within 0.25 dB: measured +0.05 / +0.05 and +0.07 / +0.33; the network
    alone −0.55 / −0.08 and −0.61 / +0.27."""
    still = MotionRanges(translation_px=0.3, rotation_deg=0.0, scale=0.0, perspective=0,
                         curvature=0.2, foreground_prob=1.0 if mover else 0.0, max_layers=1,
                         layer_translation_px=25.0, layer_size=(0.3, 0.5))
    sensor = SensorConfig() if contrast is None else replace(
        SensorConfig().with_contrast(contrast), contrast_sigma=0.1 * contrast)
    method = FusedMethod(3, threads=1)
    margins = []
    for seed in (2, 3, 4, 5):
        s = make_sample(texture(300, 400, seed=seed), size=(128, 96),
                        rng=np.random.default_rng(seed), motion=still, sensor=sensor,
                        read_noise=0.003)
        fused = method(s.blurry, s.events, s.exposure)
        edi = EdiMethod(3, contrast=fused.contrast)(s.blurry, s.events, s.exposure)
        margins.append(_margins(fused.frames, edi.frames, s.sharp))
    mid, whole = np.mean(margins, axis=0)  # over the samples
    if contrast is None:
        assert mid > -1.0
        assert whole > -0.5
    else:
        assert mid > -0.25
        assert whole > -0.25


@needs_weights
def test_beyond_its_sensors_the_network_is_used_where_the_motion_fell_back(tmp_path):
    """A network that changes every frame. At c = 0.2 the fused frames differ from the motion
    method's; beyond MAX_FALLBACK_CONTRAST (c = 1.2) they are the motion method's, with a
    note. Between it and MAX_CONTRAST (c = 0.8) they are the motion method's where its guard's
    weight is 1 and the network's where it is 0 (where events fired). Binned data (weight 0
    throughout) is fused up to MAX_FALLBACK_CONTRAST, beyond it gets TRMD's frames."""
    from trmd_cli.models.fusion import MAX_CONTRAST, MAX_FALLBACK_CONTRAST

    s = _sample()
    net = FusionNet(8)
    with torch.no_grad():
        net.out.bias.fill_(0.05)
    path = save_fusion(tmp_path / "shift.safetensors", net, {})
    inside = FusedMethod(3, contrast=0.2, fusion_weights=path, threads=1)(
        s.blurry, s.events, s.exposure)
    alone = MotionMethod(3, contrast=0.2)(s.blurry, s.events, s.exposure)
    assert np.abs(inside.frames - alone.frames).mean() > 0.04
    c = 0.8
    assert MAX_CONTRAST < c <= MAX_FALLBACK_CONTRAST < 1.2
    beyond = FusedMethod(3, contrast=1.2, fusion_weights=path, threads=1)(
        s.blurry, s.events, s.exposure)
    alone = MotionMethod(3, contrast=1.2)(s.blurry, s.events, s.exposure)
    np.testing.assert_allclose(beyond.frames, alone.frames, atol=1e-6)
    assert any("beyond the fusion network" in note for note in beyond.notes)
    # the camera moves and so does an object: the guard trusts the motion on about half the
    # frame and falls back to EDI on a tenth of it
    mixed = make_sample(texture(300, 400, seed=3), size=(128, 96),
                        rng=np.random.default_rng(3), sensor=SensorConfig.clean(0.2),
                        motion=replace(MOVING, foreground_prob=1.0, max_layers=1,
                                       layer_translation_px=25.0, layer_size=(0.3, 0.5)),
                        read_noise=0.003)
    ins = fusion_inputs(mixed.blurry, mixed.events, mixed.exposure,
                        TrmdMethod(3, contrast=c, threads=1), 3)
    trusted, fell_back = ins.weight == 1.0, (ins.weight == 0.0) & _fired_densely(mixed.events)
    assert trusted.mean() > 0.3 and fell_back.mean() > 0.03
    got = FusedMethod(3, contrast=c, fusion_weights=path, threads=1)(
        mixed.blurry, mixed.events, mixed.exposure)
    alone = MotionMethod(3, contrast=c)(mixed.blurry, mixed.events, mixed.exposure)
    assert not got.notes
    np.testing.assert_allclose(got.frames[trusted], alone.frames[trusted], atol=1e-6)
    assert np.abs(got.frames - alone.frames)[fell_back].mean() > 0.04
    bins = np.random.default_rng(1).integers(-2, 3, (6, 72, 96)).astype(np.float32)
    for c_bins, used in ((c, True), (1.2, False)):
        got = FusedMethod(3, contrast=c_bins, fusion_weights=path, threads=1).from_bins(
            s.blurry, bins)
        trmd = TrmdMethod(3, contrast=c_bins, threads=1).from_bins(s.blurry, bins)
        if used:
            assert np.abs(got.frames - trmd.frames).mean() > 0.02
            assert not any("beyond the fusion network" in note for note in got.notes)
        else:  # beyond them: TRMD's frames
            np.testing.assert_allclose(got.frames, trmd.frames, atol=1e-6)
            assert any("beyond the fusion network" in note for note in got.notes)


@needs_weights
@pytest.mark.parametrize("noise", [False, True], ids=["no event", "isolated events"])
def test_where_nothing_fired_a_still_camera_gets_edis_frames(tmp_path, noise):
    """A still camera and a noise-free sensor: no event fires, the motion method falls back to
    EDI whole, and nothing says anything moved, so even a network that changes every frame
    (by 0.05) gives EDI's frames (B, at every instant). The sensor's noise, 300 events at
    random pixels and times (one pixel in 23), says nothing either: EDI's model leaves out the
    events no neighbour corroborates, and so does the test of what fired (measured 0.0012 from
    EDI's frames on average; counting every event, 0.041: the network's almost everywhere)."""
    still = make_sample(texture(300, 400, seed=3), size=(96, 72), rng=np.random.default_rng(3),
                        motion=MotionRanges.static(), sensor=SensorConfig.clean(0.2),
                        read_noise=0.003)
    assert len(still.events) == 0
    events = still.events
    if noise:
        rng = np.random.default_rng(5)
        n = 300
        t = np.sort(rng.integers(still.exposure.start_us, still.exposure.end_us, n))
        events = make_stream(rng.integers(0, 96, n), rng.integers(0, 72, n), t,
                             rng.integers(0, 2, n), 96, 72)
    net = FusionNet(8)
    with torch.no_grad():
        net.out.bias.fill_(0.05)
    path = save_fusion(tmp_path / "shift.safetensors", net, {})
    got = FusedMethod(3, contrast=0.2, fusion_weights=path, threads=1)(
        still.blurry, events, still.exposure)
    edi = EdiMethod(3, contrast=0.2)(still.blurry, events, still.exposure)
    if noise:
        assert np.abs(got.frames - edi.frames).mean() < 0.005
    else:
        np.testing.assert_allclose(got.frames, edi.frames, atol=1e-6)
        np.testing.assert_allclose(edi.frames, np.repeat(still.blurry[None], 7, 0), atol=1e-6)


def _fired_densely(events, share: float = 0.5) -> np.ndarray:
    """(H, W) bool: pixels around which more than ``share`` of the pixels within a few fired."""
    import cv2

    fired = np.zeros((events.height, events.width), np.float32)
    fired[events.y, events.x] = 1.0
    return cv2.GaussianBlur(fired, (0, 0), 3.0) > share


def test_info_describes_fusion_weights(tmp_path):
    """`trmd info` on fusion weights: what they are, their size and held-out figures."""
    import json

    from typer.testing import CliRunner

    from trmd_cli.cli.app import app
    from trmd_cli.models.fusion import describe_fusion, is_fusion_file

    path = save_fusion(tmp_path / "f.safetensors", FusionNet(8),
                       {"trained_on": "set.h5", "steps": 7,
                        "held_out_psnr": {"motion": [30.0, 29.0], "fused": [31.0, 30.5]}})
    assert is_fusion_file(path) and not is_fusion_file(tmp_path / "missing.safetensors")
    d = describe_fusion(path)
    assert d["width"] == 8 and d["steps"] == 7 and d["held_out_psnr"]["fused"] == [31.0, 30.5]
    assert d["parameters"] == sum(p.numel() for p in FusionNet(8).parameters())
    r = CliRunner().invoke(app, ["info", "--json", str(path)])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["trained_on"] == "set.h5"
    r = CliRunner().invoke(app, ["info", str(path)])
    assert r.exit_code == 0 and "fusion network" in r.stdout and "31.00" in r.stdout


def test_one_instant_at_a_time_is_the_batch():
    """The fused method runs the network on one instant's planes at a time (small
    activations the C heap keeps); each instant's output is the one the whole batch gives."""
    torch.manual_seed(0)
    net = FusionNet(8).eval()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.2)
    planes = torch.rand((7, 7, 37, 50))
    with torch.inference_mode():
        batch = net(planes)
        alone = torch.cat([net(p) for p in planes.split(1)])
    assert batch.shape == alone.shape == (7, 1, 37, 50)
    assert float(batch.std()) > 0.05  # the network does change its input
    # float32 sums in another order: within 1e-5 of the outputs' range
    assert float((alone - batch).abs().max()) <= 1e-5 * float(batch.abs().max())
