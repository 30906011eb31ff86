"""Parsers of the CLI's small value syntaxes (``R,G,B``, ``WxH``) and their click types.

The parse functions raise ValueError with a message that names the value; the click types turn
that into click's usage error (``Invalid value for '--background': ...``, exit code 2).
"""

from __future__ import annotations

import math

import click

#: Largest image side `--size` accepts (a typo like 80000x800 should not allocate gigabytes).
MAX_SIDE = 32768


def parse_background(text: str) -> tuple[float, float, float]:
    """``"R,G,B"`` with each value in [0, 1] (e.g. ``1,1,1`` for white)."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ValueError(f"{text!r}: expected three comma-separated values R,G,B in [0, 1] "
                         f"(e.g. 1,1,1 for white), got {len(parts)}")
    values = []
    for p in parts:
        try:
            v = float(p)
        except ValueError:
            raise ValueError(f"{text!r}: {p!r} is not a number") from None
        if not math.isfinite(v) or not 0.0 <= v <= 1.0:
            raise ValueError(f"{text!r}: each value must be in [0, 1], got {p}")
        values.append(v)
    return tuple(values)


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` in pixels, e.g. ``800x600``."""
    s = str(text).strip().lower()
    parts = s.split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"{text!r}: expected WIDTHxHEIGHT in pixels, e.g. 800x600")
    w, h = (int(p) for p in parts)
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise ValueError(f"{text!r}: width and height must be in 1..{MAX_SIDE}")
    return w, h


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
