"""The CLI boundary spells the library's backticked parameter names as flags."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from trmd_cli.cli.app import app
from trmd_cli.cli.boundary import FLAGS, as_flags


@pytest.mark.parametrize("text, expected", [
    ("pass `sensor=(W, H)`", "pass --sensor WxH"),
    ("`sensor=(346, 260)` ignored", "--sensor 346x260 ignored"),
    ("give `exposure=(T0, T1)` with T1 > T0", "give --exposure T0 T1 with T1 > T0"),
    ("check `time_unit` and `offset_us`", "check --time-unit and --time-offset"),
    ("`time_unit='ms'` ignored", "--time-unit ms ignored"),
    ("pass `one_based=True`", "pass --one-based"),
    ("or `hot_pixels=False`", "or --keep-hot-pixels"),
    ("use `contrast='auto'` or a value like 0.2", "use --contrast auto or a value like 0.2"),
    ("use `n=3` (7 latent frames)", "use --n 3 (7 latent frames)"),
    ("raise `interval_us`", "raise --frame-interval-ms"),
    # backticked text that is no parameter stays as written
    ("weights written by `trmd train`", "weights written by `trmd train`"),
    ("`x_unknown=1`", "`x_unknown=1`"),
])
def test_parameters_become_flags(text, expected):
    assert as_flags(text) == expected


def test_every_flag_exists_on_some_command():
    """The table names only flags a command really has."""
    import typer.main

    group = typer.main.get_command(app)
    have: set[str] = set()
    for cmd in group.commands.values():
        for param in cmd.params:
            if param.param_type_name == "option":
                have.update(param.opts)
                have.update(param.secondary_opts)
    for name, spelled in FLAGS.items():
        for flag in (spelled if isinstance(spelled, tuple) else (spelled,)):
            assert flag in have, f"{name} → {flag}: no command has it"


def test_library_error_reaches_the_terminal_as_flags(tmp_path):
    """A reader's error names `sensor=(W, H)`; the CLI says --sensor WxH."""
    f = tmp_path / "ev.txt"
    f.write_text("0 5 5 1\n10 500 7 0\n")
    r = CliRunner().invoke(app, ["info", str(f), "--sensor", "64x48"])
    assert r.exit_code == 2
    assert "`" not in r.stderr.replace("`trmd", "")
    assert "--sensor" in r.stderr or "--columns" in r.stderr, r.stderr


@pytest.mark.parametrize("given,expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_openmp_threads_sleep_unless_the_user_says(given, expected):
    """Spinning OpenMP threads collapse beside a competing process (bench/bench_load.py): the
    CLI picks the passive wait policy before torch loads, and keeps a value the user set."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    code = ("import os, sys, trmd_cli.cli.app; "
            "print(os.environ['OMP_WAIT_POLICY'], 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [expected, "False"]
