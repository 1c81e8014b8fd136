"""One contrast threshold per recording: the pooled search against the per-frame one, which
frames it is estimated from, and what `trmd deblur` / `trmd hfr` do with it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from trmd_cli.cli.app import app
from trmd_cli.deblur import RECORDING_FRAMES, recording_contrast, settle_recording
from trmd_cli.events import EventStream
from trmd_cli.methods import EdiMethod, MethodConfig, window_model
from trmd_cli.read.base import Frame
from trmd_cli.read.folders import FrameWindow
from trmd_cli.threshold import (
    MIN_EVENTS,
    ContrastObjective,
    search_contrast,
    search_contrast_pooled,
)
from trmd_cli.write import write_h5

W, H = 160, 120
runner = CliRunner()


def texture(seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 1, (300, 400)).astype(np.float32), (0, 0), 3)
    return (0.1 + 0.8 * (img - img.min()) / np.ptp(img)).astype(np.float32)


@pytest.fixture(scope="module")
def seq():
    from trmd_cli.simulate import SensorConfig
    from trmd_cli.simulate.sample import make_sequence

    return make_sequence(texture(), frames=5, size=(W, H), rng=np.random.default_rng(3),
                         sensor=SensorConfig.clean(0.25))


class Recording:
    """Frames and their windows as a frame source (``len``, ``subset``), in memory."""

    def __init__(self, items) -> None:
        self.items = list(items)

    def __len__(self) -> int:
        return len(self.items)

    def subset(self, positions, keep=False):
        return [self.items[p] for p in sorted(set(positions))]


def windows(seq, keep=None) -> Recording:
    """The sequence's frames; ``keep(k, events)`` may thin frame k's events."""
    items = []
    for k, ex in enumerate(seq.exposures):
        ev = seq.events.slice(ex.start_us, ex.end_us + 1)
        if keep is not None:
            ev = keep(k, ev)
        items.append(FrameWindow(Frame(seq.blurry[k], ex, k, f"f{k}"), ev))
    return Recording(items)


def objective(item) -> ContrastObjective:
    model, _, _ = window_model(item.events, item.frame.exposure, True)
    return ContrastObjective.from_events(model, item.frame.image)


def test_pooled_search_of_one_frame_is_the_per_frame_search(seq):
    item = windows(seq).items[2]
    model, _, _ = window_model(item.events, item.frame.exposure, True)
    alone = search_contrast(item.frame.image, model)
    c, energy, at_bound, evaluations = search_contrast_pooled([objective(item)])
    assert (c, energy, at_bound, evaluations) == (alone.contrast, alone.energy,
                                                  alone.at_bound, alone.evaluations)


def test_pooled_search_of_a_frame_twice_is_the_frame_alone(seq):
    # Σ explained / Σ total over two equal objectives is the ratio of one, exactly
    item = windows(seq).items[1]
    once = search_contrast_pooled([objective(item)])
    twice = search_contrast_pooled([objective(item), objective(item)])
    assert once[:3] == twice[:3]


def test_recording_threshold_near_the_sensors(seq):
    rec = recording_contrast(windows(seq))
    assert rec is not None and len(rec.frames) == RECORDING_FRAMES == 3
    assert abs(np.log(rec.contrast / seq.contrast)) < 0.25, rec.contrast
    assert not rec.at_bound


def test_the_busiest_frames_are_used_and_quiet_ones_skipped(seq):
    counts = [len(it.events) for it in windows(seq).items]
    rec = recording_contrast(windows(seq))
    busiest = sorted(np.argsort(counts, kind="stable")[::-1][:3])
    assert rec.frames == tuple(f"f{k}" for k in busiest)
    # frames thinned below the minimum never count, however few the others are
    quiet = {int(busiest[0])}
    rec2 = recording_contrast(windows(seq, lambda k, ev: ev.take(slice(0, MIN_EVENTS // 2))
                                      if k in quiet else ev))
    assert f"f{busiest[0]}" not in rec2.frames and len(rec2.frames) == 3
    one = recording_contrast(windows(seq), frames=1)
    assert one.frames == (f"f{int(np.argmax(counts))}",)


def test_no_frame_with_enough_events_leaves_each_frame_its_own(seq):
    sparse = windows(seq, lambda k, ev: ev.take(slice(0, MIN_EVENTS - 1)))
    assert recording_contrast(sparse) is None
    method = EdiMethod()
    same, rec = settle_recording(method, sparse, MethodConfig(method="edi"))
    assert same is method and rec is None


def test_settled_method_uses_the_recordings_c_on_every_frame(seq):
    source = windows(seq)
    config = MethodConfig(method="edi")
    method, rec = settle_recording(EdiMethod(), source, config)
    assert rec is not None
    for item in source.items:
        est = method(item.frame.image, item.events, item.frame.exposure)
        assert est.contrast == rec.contrast and est.contrast_estimated
        assert est.contrast_note is None
    # given c, or per frame: nothing is settled
    for cfg in (MethodConfig(method="edi", contrast=0.3),
                MethodConfig(method="edi", contrast_scope="frame")):
        m = EdiMethod()
        assert settle_recording(m, source, cfg) == (m, None)


def test_bad_scope_is_refused():
    from trmd_cli.errors import InputError

    with pytest.raises(InputError, match="contrast scope"):
        MethodConfig(contrast_scope="clip")


def _recording_file(seq, path):
    write_h5(path, seq.events, blurry=seq.blurry, exposures=seq.exposures)
    return path


def test_deblur_estimates_once_and_says_from_which_frames(seq, tmp_path):
    rec = _recording_file(seq, tmp_path / "rec.h5")
    out = tmp_path / "out"
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(out), "--method", "edi"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())
    assert meta["contrast_mode"] == "recording"
    used = meta["contrast_recording"]
    assert len(used["frames"]) == 3 and used["evaluations"] == 9
    assert {f["contrast"] for f in meta["frames"]} == {used["contrast"]}
    assert all(f["contrast_estimated"] for f in meta["frames"])
    assert f"c = {used['contrast']:.3f}, estimated once for the recording" in r.stdout
    assert abs(np.log(used["contrast"] / seq.contrast)) < 0.25

    per_frame = tmp_path / "per_frame"
    r = runner.invoke(app, ["deblur", str(rec), "-o", str(per_frame), "--method", "edi",
                            "--contrast", "frame"])
    assert r.exit_code == 0, r.output
    meta = json.loads((per_frame / "meta.json").read_text())
    assert meta["contrast_mode"] == "frame" and "contrast_recording" not in meta
    assert len({f["contrast"] for f in meta["frames"]}) > 1  # each frame its own estimate
    assert "per frame" in r.stdout


def test_split_run_settles_the_same_c_as_one_process(seq, tmp_path):
    rec = _recording_file(seq, tmp_path / "rec.h5")
    one, two = tmp_path / "one", tmp_path / "two"
    for out, extra in ((one, []), (two, ["--jobs", "2"])):
        r = runner.invoke(app, ["deblur", str(rec), "-o", str(out), "--method", "edi", *extra])
        assert r.exit_code == 0, r.output
    a, b = (json.loads((o / "meta.json").read_text()) for o in (one, two))
    assert a["contrast_recording"] == b["contrast_recording"]
    assert [f["contrast"] for f in a["frames"]] == [f["contrast"] for f in b["frames"]]


def test_hfr_uses_the_recordings_c_for_exposures_and_gaps(seq, tmp_path):
    rec = _recording_file(seq, tmp_path / "rec.h5")
    out = tmp_path / "slow"
    r = runner.invoke(app, ["hfr", str(rec), "-o", str(out), "--method", "edi"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "meta.json").read_text())
    assert meta["contrast_mode"] == "recording"
    assert set(meta["contrast"]) == {meta["contrast_recording"]["contrast"]}
    assert "estimated once for the recording" in r.stdout


def test_events_on_one_frame_only_still_settle_from_it(seq):
    # a recording whose every frame but one is quiet: the one busy frame is the estimate
    source = windows(seq, lambda k, ev: ev if k == 3 else EventStream.empty(W, H))
    rec = recording_contrast(source)
    assert rec is not None and rec.frames == ("f3",)


def test_one_frame_settles_its_own(seq):
    one = Recording(windows(seq).items[:1])
    method = EdiMethod()
    assert settle_recording(method, one, MethodConfig(method="edi")) == (method, None)


def test_threaded_pooled_search_sums_as_one_by_one(seq):
    # the pooled energy, evaluated on two threads, is the in-order sum of the exposures' parts
    items = windows(seq).items[:3]
    objectives = [objective(it) for it in items]
    c, energy, _, evaluations = search_contrast_pooled(objectives)
    fresh = [objective(it) for it in items]
    total = sum(o.total for o in fresh)
    assert evaluations == 9
    from trmd_cli.threshold import _minimise

    x, e, _ = _minimise(lambda g: 1.0 - sum(o.explained(float(np.exp(g))) for o in fresh)
                        / total, np.log(0.05), np.log(1.0))
    assert float(np.exp(x)) == c and e == energy


def test_window_model_is_kept_for_the_same_stream_only(seq):
    import gc

    from trmd_cli import methods

    item = windows(seq).items[0]
    ev, exp = item.events, item.exposure
    first = window_model(ev, exp, True)
    assert window_model(ev, exp, True) is first  # the same stream: not sorted again
    other = window_model(ev, exp, False)  # another question: answered anew
    assert other is not first and other[1] is None
    copy = EventStream(ev.x.copy(), ev.y.copy(), ev.t.copy(), ev.p.copy(), ev.width, ev.height)
    again = window_model(copy, exp, False)
    assert again is not other
    np.testing.assert_array_equal(again[0].integral(0.3), other[0].integral(0.3))
    key = id(copy)
    del copy, again
    gc.collect()
    assert key not in methods._MODELS  # the entry went with its stream
