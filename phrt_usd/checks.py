"""The value checks every option goes through: each takes the value and the name its
message gives it, returns the value as the option holds it, and raises ``BadOption`` (one
line: the name, what it must be, what it got; the CLI exits 2) otherwise.

* ``check_number``: a real number, not a bool, not NaN (→ float);
* ``check_integer``: an integral number, not a bool (→ int);
* ``check_bool``: True or False;
* ``check_finite``: a finite number;
* ``check_range``: inside bounds (a missing upper bound: finite, for a float);
* ``check_choice``: one of a few words, in any case (→ lower case);
* ``check_token``: one of a few names, exactly (USD tokens, option names).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

from phrt_usd.errors import BadOption


def check_number(value: object, name: str) -> float:
    """``value`` as a float: a real number, not a bool, not NaN."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise BadOption(f"{name} must be a number, got {value!r}")
    value = float(value)
    if math.isnan(value):
        raise BadOption(f"{name} must be a number, got nan")
    return value


def check_integer(value: object, name: str) -> int:
    """``value`` as an int: an integral number (numpy's too), not a bool."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise BadOption(f"{name} must be an integer, got {value!r}")
    return int(value)


def check_bool(value: object, name: str) -> bool:
    """``value``, which must be True or False."""
    if not isinstance(value, bool):
        raise BadOption(f"{name} must be True or False, got {value!r}")
    return value


def check_finite(value: float, name: str, what: str = "a finite number") -> float:
    """``value`` when finite; ``what`` says what it must be (``"a finite time code"``)."""
    if not math.isfinite(value):
        raise BadOption(f"{name} must be {what}, got {value}")
    return value


def check_range(
    value: float,
    low: float,
    high: float | None,
    name: str,
    *,
    low_open: bool = False,
) -> float:
    """``value`` when ``low <= value <= high`` (``low < value`` with ``low_open``); with no
    ``high``, a float must be finite. The message states the range as the value's kind
    reads it: ``1..1024`` or ``>= 1`` for an int, ``(0, 1000]`` or ``a finite number
    >= 0`` for a float."""
    above = value > low if low_open else value >= low
    below = high is None or value <= high
    if isinstance(value, numbers.Integral):
        ok = above and below
        first = low + 1 if low_open else low  # the smallest integer allowed
        rule = f">= {first}" if high is None else f"in {first}..{high}"
    else:
        ok = above and below and math.isfinite(value)
        if high is None:
            rule = f"a finite number {'>' if low_open else '>='} {low:g}"
        else:
            rule = f"in {'(' if low_open else '['}{low:g}, {high:g}]"
    if not ok:
        raise BadOption(f"{name} must be {rule}, got {value}")
    return value


def check_choice(value: object, choices: Sequence[str], name: str) -> str:
    """``value`` in lower case when it is one of ``choices`` in any case (a command
    line's words: ``--gl EGL`` is ``egl``)."""
    if not isinstance(value, str) or value.lower() not in choices:
        raise BadOption(f"{name} must be one of {', '.join(choices)}, got {value!r}")
    return value.lower()


def check_token(value: object, choices: Sequence[str], name: str) -> str:
    """``value`` when it is exactly one of ``choices`` (a USD token, as the stage would
    author it, or a keyword's name)."""
    if not isinstance(value, str) or value not in choices:
        raise BadOption(f"unknown {name} {value!r}; expected one of {', '.join(choices)}")
    return value
