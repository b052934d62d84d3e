"""The one check of a number typed on the command line: argparse ``type=`` functions.

``nan``, ``inf`` and numbers out of an option's range are refused while the options are read,
before any work (and before any background import starts), with a line that names the option,
what it takes and what was typed: ``argument --lr: must be a positive number, got 'nan'``.

    p.add_argument("--lr", type=positive_float)
    p.add_argument("--height", type=bounded_float(0, 10, low_open=True, unit="m"))

Plain Python: a command's ``--help`` needs no numerics.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def _number(text: str, kind: type, allow_inf: bool) -> float:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(
            f"must be {'a whole number' if kind is int else 'a number'}, got {text!r}"
        ) from None
    if kind is float and (math.isnan(value) or (math.isinf(value) and not allow_inf)):
        raise argparse.ArgumentTypeError(
            f"must be {'a number or inf' if allow_inf else 'a finite number'}, got {text!r}"
        )
    return value


def _checked(kind: type, words: str, ok: Callable[[float], bool], allow_inf: bool = False) -> Callable[[str], float]:
    def parse(text: str):
        value = _number(text, kind, allow_inf)
        if not ok(value):
            raise argparse.ArgumentTypeError(f"must be {words}, got {text!r}")
        return value

    parse.__name__ = words.replace(" ", "_")  # argparse names the type in some messages
    return parse


#: any finite number (``nan`` and ``inf`` refused)
finite_float = _checked(float, "a finite number", lambda v: True)
#: a finite number > 0
positive_float = _checked(float, "a positive number", lambda v: v > 0)
#: a finite number >= 0
non_negative_float = _checked(float, "a number >= 0", lambda v: v >= 0)
#: a number, ``inf`` and ``-inf`` included (``nan`` refused): where infinity means "none" (an SNR)
number_or_inf = _checked(float, "a number or inf", lambda v: True, allow_inf=True)
#: a whole number > 0
positive_int = _checked(int, "a whole number >= 1", lambda v: v >= 1)
#: a whole number >= 0
non_negative_int = _checked(int, "a whole number >= 0", lambda v: v >= 0)


def bounded_float(low: float, high: float, *, low_open: bool = False, unit: str = "") -> Callable[[str], float]:
    """A finite number in [low, high] (or (low, high] with ``low_open``); ``unit`` for the message."""
    u = f" {unit}" if unit else ""
    words = f"a number {'above' if low_open else 'from'} {low:g}{u} {'and at most' if low_open else 'to'} {high:g}{u}"
    return _checked(float, words, lambda v: (v > low if low_open else v >= low) and v <= high)


def bounded_int(low: int, high: int) -> Callable[[str], float]:
    """A whole number in [low, high]."""
    return _checked(int, f"a whole number from {low} to {high}", lambda v: low <= v <= high)


#: add_argument keywords of a region option (``--reference-roi``, ``--seed-roi``): x and y extent
#: and depth, metres, five finite numbers
REGION: dict = {"nargs": 5, "type": finite_float, "metavar": ("X0", "X1", "Y0", "Y1", "Z")}
#: add_argument keywords of a point option (``--camera-position-mm``): x, y and z, three finite numbers
POINT: dict = {"nargs": 3, "type": finite_float, "metavar": ("X", "Y", "Z")}
#: add_argument keywords of a displacement option (``--template-offset-mm``, ``--extrinsic-error-mm``):
#: dx, dy and dz, three finite numbers
DISPLACEMENT: dict = {"nargs": 3, "type": finite_float, "metavar": ("DX", "DY", "DZ")}

#: Setting.check name -> its type function (twinfocus.focus.settings)
CHECKS: dict[str, Callable[[str], float]] = {
    "finite": finite_float,
    "positive": positive_float,
    "non_negative": non_negative_float,
    "positive_int": positive_int,
    "non_negative_int": non_negative_int,
}
