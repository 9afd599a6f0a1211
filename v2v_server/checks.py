"""The one set of validators of configuration values, raising ``ValueError`` that names the field:
``check_int``, ``check_float``, ``check_prob``, ``check_choice``, ``check_bool``, and
:func:`check_keys`, the one unknown-key check of every configuration mapping. Below every stage
of the server (the simulation's parameter mappings, the samples' ablations, the serve and
trainer configurations all use them), so no stage imports the operations layer for them."""
from __future__ import annotations

import math
from typing import Iterable, Optional, Sequence


def check_keys(given, allowed: Iterable, section: str = "", source: str = "") -> None:
    """Check that the mapping ``given`` uses only keys from ``allowed``.

    Args:
        given: the mapping read from a file, a flag or a message (or its keys).
        allowed: the keys it may hold (e.g. a dataclass's field names).
        section: where the mapping sits, e.g. ``"nonidealities"`` or ``"optim"`` (empty: the
            top level).
        source: what it was read from, e.g. the YAML file's path (empty: not named).

    Raises:
        ValueError: ``"<source>: unknown key(s) [...] in <section>; allowed keys: [...]"``,
            naming every unknown key and every allowed one.
    """
    allowed = set(allowed)
    unknown = sorted((k for k in given if k not in allowed), key=str)
    if unknown:
        where = f" in {section}" if section else ""
        raise ValueError(f"{source + ': ' if source else ''}unknown key(s) {unknown}{where}; "
                         f"allowed keys: {sorted(allowed, key=str)}")


def check_int(name: str, v, lo: Optional[int] = None, hi: Optional[int] = None, why: str = "") -> int:
    """``v`` as an int in [lo, hi]; booleans are not ints here.

    Raises:
        ValueError: naming ``name``.
    """
    if isinstance(v, bool) or not isinstance(v, int) or (lo is not None and v < lo):
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}" if lo is not None
                         else f"{name} must be an integer, got {v!r}")
    if hi is not None and v > hi:
        raise ValueError(f"{name} must be <= {hi}{f' ({why})' if why else ''}, got {v}")
    return v


def check_float(name: str, v, positive: bool = True) -> float:
    """``v`` as a finite float (> 0 when ``positive``).

    Raises:
        ValueError: naming ``name``.
    """
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"{name} must be a finite number{' > 0' if positive else ''}, got {v!r}")
    return float(v)


def check_prob(name: str, v) -> float:
    """``v`` as a probability in [0, 1].

    Raises:
        ValueError: naming ``name``.
    """
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 <= v <= 1.0):
        raise ValueError(f"{name} must be a probability in [0, 1], got {v!r}")
    return float(v)


def check_choice(name: str, v, choices: Sequence):
    """``v`` if it is one of ``choices``.

    Raises:
        ValueError: naming ``name`` and the choices.
    """
    if v not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}, got {v!r}")
    return v


def check_bool(name: str, v) -> bool:
    """``v`` if it is a bool.

    Raises:
        ValueError: naming ``name``.
    """
    if not isinstance(v, bool):
        raise ValueError(f"{name} must be true or false, got {v!r}")
    return v
