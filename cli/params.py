"""The click types of the CLI's small value syntaxes (``R,G,B``, ``WxH``: parsed by
nehad.runtime.values, which batch files share). A parse error becomes click's usage error
(``Invalid value for '--background': ...``, exit code 2).
"""

from __future__ import annotations

import math

import click

from nehad.runtime.values import MAX_SIDE, parse_background, parse_size  # noqa: F401


class _Parsed(click.ParamType):
    def __init__(self, name: str, parse):
        self.name = name
        self._parse = parse

    def convert(self, value, param, ctx):
        if not isinstance(value, str):
            return value
        try:
            return self._parse(value)
        except ValueError as e:
            self.fail(str(e), param, ctx)


BACKGROUND = _Parsed("R,G,B", parse_background)
SIZE = _Parsed("WxH", parse_size)


class FiniteFloat(click.FloatRange):
    """A number option: finite (``nan``, ``inf`` refused), within [min, max] when given.

    click's ``float`` and ``FloatRange`` accept ``nan`` (every comparison with it is false),
    which then reaches the library as a value no check expected (issue 26)."""

    name = "number"

    def convert(self, value, param, ctx):
        try:
            v = click.FLOAT.convert(value, param, ctx)
            if not math.isfinite(v):
                self.fail(f"{value!r} is not a finite number.", param, ctx)
            if self.min is None and self.max is None:
                return v
            return super().convert(v, param, ctx)
        except click.BadParameter as e:
            # one line, as every bad input of nehad (not click's usage block)
            hint = e.param.get_error_hint(ctx) if e.param is not None else "the value"
            raise click.ClickException(f"Invalid value for {hint}: {e.message}") from None

    def __repr__(self) -> str:
        return f"FiniteFloat({self._describe_range()})"


#: any finite number (e.g. --time, range-checked by the library against the model's range)
FINITE = FiniteFloat()
