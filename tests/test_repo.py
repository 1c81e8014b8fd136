"""The README's two set-up commands are the ones CI runs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup_commands() -> list[str]:
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Set up", 1)[1].split("\n## ", 1)[0]
    return [b.strip() for b in re.findall(r"```bash\n(.*?)```", section, re.S)]


def test_readme_has_exactly_two_setup_commands_and_ci_runs_the_test_one():
    cmds = _setup_commands()
    assert len(cmds) == 2 and all("\n" not in c for c in cmds)
    install_and_run, tests = cmds
    assert "pip install" in install_and_run and "trmd deblur examples/" in install_and_run
    assert "pytest" in tests
    ci = (ROOT / ".ci" / "run").read_text()
    assert tests in ci.splitlines()
    for path in re.findall(r"examples/\S+", install_and_run):
        assert (ROOT / path).exists(), path


def test_cli_reference_is_up_to_date():
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(ROOT / "docs" / "gen_cli.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr + " — run `python docs/gen_cli.py`"
