"""--exposure-length, --stamp and --topics: parsed exactly, refused with one line, and said to
be ignored where they do not apply."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.helpers.cli import assert_one_error_line
from trmd_cli.cli.app import app
from trmd_cli.cli.boundary import as_flags
from trmd_cli.cli.options import parse_duration_us, parse_exposure_length_us, read_options
from trmd_cli.errors import InputError

runner = CliRunner()


@pytest.mark.parametrize("text,us", [("20ms", 20_000), ("500us", 500), ("500µs", 500),
                                     ("0.02s", 20_000), (".5ms", 500), ("7000ns", 7),
                                     ("20 ms", 20_000), ("0.0200000s", 20_000)])
def test_exposure_length_is_exact(text, us):
    assert parse_exposure_length_us(text) == us


@pytest.mark.parametrize("text,needle", [("20", "needs its unit"), ("1.5us", "whole number"),
                                         ("20.0005ms", "20000.5 µs"), ("0s", "not positive"),
                                         ("fast", "not a duration"), ("-2ms", "not a duration")])
def test_bad_exposure_length(text, needle):
    with pytest.raises(InputError, match=needle):
        parse_exposure_length_us(text)


@pytest.mark.parametrize("text,us", [("-40ms", -40_000), ("1.5s", 1_500_000), ("250", 250),
                                     ("-0.004s", -4_000), ("1e3us", 1_000), ("2000ns", 2),
                                     (".5ms", 500)])
def test_time_offset_is_exact(text, us):
    assert parse_duration_us(text) == us


@pytest.mark.parametrize("text,needle", [("-0.004", "-0.004 µs .a number without a unit is µs"),
                                         ("1.5us", "not a whole number"),
                                         ("1ns", "0.001 µs"), ("1e30s", "out of range"),
                                         ("soon", "not a duration")])
def test_bad_time_offset_is_refused_not_rounded(text, needle):
    with pytest.raises(InputError, match=needle):
        parse_duration_us(text)


def test_options_reach_read_options():
    o = read_options(exposure_length="2ms", stamp="Middle", topics="/a, /b,")
    assert (o.exposure_length_us, o.stamp, o.topics) == (2000, "middle", ("/a", "/b"))
    with pytest.raises(InputError, match="neither start nor middle"):
        read_options(stamp="end")


def test_library_names_become_flags():
    assert as_flags("pass `exposure_length_us` and `stamp='middle'`, or `topics=/e,/i`") == \
        "pass --exposure-length and --stamp middle, or --topics /e,/i"


def _npz(tmp_path):
    path = tmp_path / "e.npz"
    np.savez(path, x=np.array([1, 2]), y=np.array([1, 2]), t=np.array([10, 20]),
             p=np.array([1, 0]), width=np.int64(8), height=np.int64(8))
    return path


@pytest.mark.parametrize("args,names", [(["--exposure-length", "20"], "--exposure-length"),
                                        (["--stamp", "end"], "--stamp"),
                                        (["--topics", ","], "--topics")])
def test_bad_values_are_one_line(tmp_path, args, names):
    r = runner.invoke(app, ["info", str(_npz(tmp_path)), *args])
    assert_one_error_line(r, names, ".")


def test_options_that_do_not_apply_are_said_to_be_ignored(tmp_path):
    r = runner.invoke(app, ["info", str(_npz(tmp_path)), "--topics", "/e", "--stamp", "middle",
                            "--exposure-length", "1ms"])
    assert r.exit_code == 0, r.output
    for flag in ("--topics", "--stamp", "--exposure-length"):
        assert f"warning: {flag} ignored: it applies to ROS bags" in r.stderr, r.stderr
