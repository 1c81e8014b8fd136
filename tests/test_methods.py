"""The method protocol (trmd_cli.methods): what ``prepare`` settles, declared needs, binned data,
the build-time setting that makes TRMD settle c, and the registry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from trmd_cli.edi import EdiBins, EdiEvents, PixelEvents, edi_from_bins, hot_pixel_mask
from trmd_cli.errors import InputError
from trmd_cli.events import make_stream
from trmd_cli.ghosts import without_ghosts
from trmd_cli.isolated import without_isolated
from trmd_cli.methods import (
    METHODS,
    REGISTRY,
    EdiMethod,
    MethodConfig,
    Prepared,
    TrmdMethod,
    make_method,
    unavailable,
)
from trmd_cli.simulate import SensorConfig, make_sample
from trmd_cli.threshold import estimate_contrast, search_contrast
from trmd_cli.voxel import event_bins, scer_from_bins, scer_voxels

N = 3


@pytest.fixture(scope="module")
def sample():
    rng = np.random.default_rng(0)
    image = rng.random((80, 96)).astype(np.float32)
    return make_sample(image, n=N, size=(64, 48), rng=rng, sensor=SensorConfig.clean(0.3))


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """A small network that takes no threshold (``prior`` other than ``edi_c``)."""
    from trmd_cli.models import create_model
    from trmd_cli.models.weights import save_weights

    net = create_model("test_trmd", n=N, prior="edi")
    return save_weights(tmp_path_factory.mktemp("w") / "w.safetensors", net, meta={})


def test_prepare_settles_the_threshold_edi_estimates(sample):
    s = sample
    prep = EdiMethod(N).prepare(s.blurry, s.events, s.exposure)
    assert isinstance(prep, Prepared)
    hot = hot_pixel_mask(s.events, s.exposure)
    kept = EdiMethod(N, drop_isolated=False).prepare(s.blurry, s.events, s.exposure)
    assert kept.contrast == estimate_contrast(s.blurry, s.events, s.exposure, hot_mask=hot)
    # by default the estimate leaves the isolated events out, as EDI's frames do
    used = without_isolated(PixelEvents.build(s.events, s.exposure).without(hot))
    assert prep.contrast == search_contrast(
        s.blurry, EdiEvents.build(s.events, s.exposure, window=used)).contrast
    assert prep.estimated and prep.reliable
    assert np.array_equal(prep.hot, hot) and prep.hot_pixels == int(hot.sum())
    with pytest.raises(dataclasses.FrozenInstanceError):
        prep.contrast = 0.1  # type: ignore[misc]
    given = EdiMethod(N, 0.37).prepare(s.blurry, s.events, s.exposure)
    assert given.contrast == 0.37 and not given.estimated
    assert EdiMethod(N, hot_pixels=False).prepare(s.blurry, s.events, s.exposure).hot is None


def test_prepare_keeps_the_one_sort_of_the_window_hot_pixels_included(sample):
    s = sample
    ev = s.events
    # a hot pixel, so that the sort the voxels reuse and the one EDI uses differ
    extra = 400
    t = np.concatenate([ev.t, np.linspace(s.exposure.start_us, s.exposure.end_us, extra)
                        .astype(np.int64)])
    order = np.argsort(t, kind="stable")
    hot_ev = make_stream(np.concatenate([ev.x, np.full(extra, 5)])[order],
                         np.concatenate([ev.y, np.full(extra, 7)])[order], t[order],
                         np.concatenate([ev.p, np.ones(extra, np.int8)])[order],
                         ev.width, ev.height)
    prep = EdiMethod(N).prepare(s.blurry, hot_ev, s.exposure)
    assert prep.hot[7, 5] and prep.window.exposure == s.exposure
    assert len(prep.window) == len(hot_ev.within(s.exposure))
    # the hot pixel's events are out of EDI's model, and so are the isolated ones
    without_hot = prep.window.without(prep.hot)
    assert len(without_hot) == len(prep.window) - int((prep.window.pix == 7 * ev.width + 5).sum())
    assert prep.model.count == len(without_isolated(without_hot)) < len(without_hot)
    np.testing.assert_array_equal(scer_voxels(hot_ev, s.exposure, N, window=prep.window),
                                  scer_voxels(hot_ev, s.exposure, N))
    assert EdiMethod(N).prepare(s.blurry, np.zeros((4, 48, 64))).window is None


def test_the_frame_is_deblurred_with_the_prepared_threshold(sample):
    s = sample
    method = EdiMethod(N)
    est = method(s.blurry, s.events, s.exposure)
    prep = method.prepare(s.blurry, s.events, s.exposure)
    assert est.contrast == prep.contrast and est.contrast_estimated
    fr = (s.exposure.instants_us(N) - s.exposure.start_us) / s.exposure.duration_us
    np.testing.assert_array_equal(est.frames, prep.model.latent(s.blurry, fr, prep.contrast))


def test_edi_on_bins_is_edi_from_bins_with_the_estimated_threshold(sample):
    s = sample
    bins = event_bins(s.events, s.exposure, 2 * N)
    prep = EdiMethod(N).prepare(s.blurry, bins)
    assert isinstance(prep.model, EdiBins) and prep.hot is None
    assert prep.contrast == search_contrast(s.blurry, EdiBins.build(bins)).contrast
    est = EdiMethod(N).from_bins(s.blurry, bins)
    fr = np.linspace(0, 1, 2 * N + 1)
    np.testing.assert_array_equal(est.instants_us, fr)
    np.testing.assert_array_equal(est.frames, edi_from_bins(s.blurry, bins, fr, prep.contrast))
    with pytest.raises(InputError, match="exposure window"):
        EdiMethod(N).prepare(s.blurry, s.events)


def test_declared_needs():
    assert EdiMethod.needs.contrast and not EdiMethod.needs.weights
    assert TrmdMethod.needs.weights
    assert METHODS == tuple(REGISTRY) == ("edi", "trmd", "motion", "fused")
    assert REGISTRY["fused"].needs.contrast and REGISTRY["fused"].needs.weights
    assert isinstance(make_method(MethodConfig("edi", n=2, contrast=0.2)), EdiMethod)


def test_trmd_settles_c_only_when_built_to(sample, weights):
    s = sample
    plain = make_method(MethodConfig("trmd", weights=weights, threads=1))
    assert not plain.needs.contrast and plain.needs.weights
    assert plain(s.blurry, s.events, s.exposure).contrast is None
    settling = make_method(MethodConfig("trmd", weights=weights, threads=1,
                                        settle_contrast=True))
    assert settling.needs.contrast
    est = settling(s.blurry, s.events, s.exposure)
    edi_c = EdiMethod(N).prepare(s.blurry, s.events, s.exposure).contrast
    assert est.contrast == edi_c and est.contrast_estimated
    # this network takes no threshold: its frames are the plain method's, with their ghosts
    # checked against the events with the settled c (which the plain method has not)
    prep = settling.prepare(s.blurry, s.events, s.exposure)
    levels = prep.model.levels_at(np.arange(2 * N + 1) / (2 * N))
    np.testing.assert_array_equal(
        est.frames, without_ghosts(plain(s.blurry, s.events, s.exposure).frames,
                                   (edi_c * (levels - levels[N])).astype(np.float32), N))
    assert settling.prepare(s.blurry, s.events, s.exposure).contrast == edi_c


def test_trmd_on_bins_runs_the_network_on_their_voxels(sample, weights):
    s = sample
    method = TrmdMethod(N, weights, threads=1)
    bins = event_bins(s.events, s.exposure, 2 * N)
    est = method.from_bins(s.blurry, bins)
    np.testing.assert_array_equal(est.frames, method.model(s.blurry, scer_from_bins(bins)))
    np.testing.assert_array_equal(scer_from_bins(bins), scer_voxels(s.events, s.exposure, N))
    with pytest.raises(InputError, match="own 7 frames"):
        method.from_bins(s.blurry, bins, [0.0, 0.5, 1.0])


def test_unavailable_says_why(weights, no_shipped_weights):
    assert unavailable(MethodConfig("edi")) is None
    assert unavailable(MethodConfig("trmd", weights=weights)) is None
    why = unavailable(MethodConfig("trmd"))
    assert "ships no trained weights" in why and "`weights=PATH`" in why


def test_config_errors_name_parameters_not_flags():
    with pytest.raises(InputError, match="use `method` edi or trmd"):
        MethodConfig("magic")
    with pytest.raises(InputError, match="`n=3`"):
        MethodConfig("edi", n=0)
    with pytest.raises(InputError, match="`contrast` must be a positive number"):
        MethodConfig("edi", contrast=-1.0)
    with pytest.raises(InputError, match="use `precision`"):
        MethodConfig("edi", precision="fp8")
