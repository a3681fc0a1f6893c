"""How values are written for people: the CLI's output and the error messages."""

import math


def format_seconds(dt):
    """A time step for people: '1/60 s' when 1/dt is a whole number (to 1e-6), else '2e-05 s'."""
    inverse = 1.0 / dt if dt else math.inf
    if 2 <= inverse < 1e15 and abs(inverse - round(inverse)) <= 1e-6 * inverse:
        return f"1/{round(inverse)} s"
    return f"{dt:.4g} s"


def brief(value, limit=80) -> str:
    """``repr(value)`` cut to about ``limit`` characters, for echoing bad input in errors."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 20]}...{text[-12:]} ({len(text):,} characters)"


def clipped(message, limit=1000) -> str:
    """An error ``message`` fit for one line of a terminal: control characters written
    as escapes (a NUL byte as \\x00), and at most about ``limit`` characters (a 100 KB
    value echoed in it is cut in the middle, saying how long it was)."""
    text = "".join(c if c.isprintable() or c == "\n" else repr(c)[1:-1] for c in message)
    if len(text) <= limit:
        return text
    return f"{text[:limit - 200]}...({len(text):,} characters)...{text[-150:]}"

