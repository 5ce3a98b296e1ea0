"""Numbers written with a fixed count of decimals, as the tables and reports print them."""

from __future__ import annotations


def fixed(value: float, digits: int = 3, signed: bool = False) -> str:
    """``value`` with ``digits`` decimals; a value that rounds to zero prints as zero, never "-0.000".

    A fair CRPS median of -0.00001 m (a small negative estimate of a score near zero) prints
    "0.0000" at 4 digits, not "-0.0000"; -0.5 still prints "-0.500". NaN prints "nan".

    Args:
        value: the number, in whatever unit the column holds.
        digits: decimals after the point.
        signed: write the sign of a positive value too ("+0.5"; zero prints "+0").

    Returns:
        The formatted number.
    """
    sign = "+" if signed else ""
    return f"{round(float(value), digits) + 0.0:{sign}.{digits}f}"  # + 0.0 turns -0.0 into 0.0
