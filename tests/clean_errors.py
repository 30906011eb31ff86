"""The shape of a clean failure of the command line (a bad input, not a bug): exit 1, exactly
one line ``Error: ...`` on stderr, no traceback (docs/usage.md, "Rules every command follows")."""

from __future__ import annotations


def one_error(res, *needles) -> str:
    """`res` (a click CliRunner result) is a clean failure whose one line holds every needle;
    returns that line."""
    assert res.exit_code == 1, (res.exit_code, res.output, res.exception)
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    assert "Traceback" not in res.output and "weights_only" not in res.output
    return lines[0]
