"""Parsers of the small value syntaxes every front end shares: ``WxH`` image sizes and ``R,G,B``
backgrounds (the command line's options, batch files). Each raises ValueError with a message that
names the value; the caller adds where it came from."""

from __future__ import annotations

import math

#: Largest image side accepted (a typo like 80000x800 should not allocate gigabytes).
MAX_SIDE = 32768
#: Largest process pool (--workers, a jobs file's workers) and thread count per frame or model
#: (--threads): a typo like 10**20 should not reach the OS as a C int (an OverflowError), nor
#: start a hundred thousand onnxruntime threads.
MAX_WORKERS = 1024
MAX_THREADS = 1024


def count_problem(value, lowest: int, most: int) -> str | None:
    """Why `value` is not a usable worker or thread count, or None when it is a whole number in
    lowest..most (threads may be 0, "as many as there are cores", where the caller allows it) or
    None (not given). Every front end words its own error around this text, naming the input it
    came from."""
    if value is None:
        return None
    number = getattr(value, "__index__", None)
    if isinstance(value, bool) or number is None or not lowest <= number() <= most:
        return f"must be a whole number in {lowest}..{most}"
    return None


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
    """``"WxH"`` in pixels, e.g. ``800x600`` (each side 1..MAX_SIDE)."""
    s = str(text).strip().lower()
    parts = s.split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"{text!r}: expected WIDTHxHEIGHT in pixels, e.g. 800x600")
    w, h = (int(p) for p in parts)
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise ValueError(f"{text!r}: width and height must be in 1..{MAX_SIDE}")
    return w, h


__all__ = ["MAX_SIDE", "parse_background", "parse_size"]
