"""What a refused command must look like: exit 2, one ``error:`` line naming the input and how
to fix it (warnings may precede it), no traceback."""

from __future__ import annotations

import re


def assert_one_error_line(result, names: str, needle: str) -> str:
    """Exit 2; stderr ends with the one error line (only warnings before it); the line names
    the file or option and says how to fix it; no traceback anywhere."""
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert "Traceback" not in result.output and "Traceback" not in result.stderr
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("error: "), result.stderr
    assert all(ln.startswith("warning: ") for ln in lines[:-1]), result.stderr
    line = lines[-1]
    assert names in line, (names, line)
    assert " — " in line, f"no hint: {line}"
    assert re.search(needle, line), (needle, line)
    return line
