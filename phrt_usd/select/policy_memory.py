"""Policy memory as plain JSON data, for checkpoints: the encoding of the tables a policy
keeps across frames (sets, int-keyed dicts, lists of numbers) and the check that decoded
memory has the shape of a fresh policy's before it is restored
(``BudgetedPolicy.memory`` / ``restore_memory`` in ``phrt_usd.select.policies``).
"""

from __future__ import annotations

import math

import numpy as np

from phrt_usd.errors import PhrtError


def to_plain(value):
    """Policy memory → JSON data: sets become ``{"set": [...]}``, dicts with int keys
    ``{"int_keys": [[k, v], ...]}`` (JSON keys are strings), tuples lists."""
    if isinstance(value, set | frozenset):
        return {"set": sorted(to_plain(v) for v in value)}
    if isinstance(value, dict):
        if all(isinstance(k, str) for k in value):
            return {"str_keys": {k: to_plain(v) for k, v in value.items()}}
        return {"int_keys": [[int(k), to_plain(v)] for k, v in value.items()]}
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise PhrtError(f"policy memory holds a {type(value).__name__}, not plain data")


def from_plain(value):
    """Inverse of ``to_plain``; PhrtError for anything it could not have written."""
    if isinstance(value, dict):
        if set(value) == {"set"} and isinstance(value["set"], list):
            return {_hashable(from_plain(v)) for v in value["set"]}
        if set(value) == {"str_keys"} and isinstance(value["str_keys"], dict):
            return {k: from_plain(v) for k, v in value["str_keys"].items()}
        if set(value) == {"int_keys"} and isinstance(value["int_keys"], list):
            pairs = value["int_keys"]
            if not all(isinstance(p, list) and len(p) == 2 and type(p[0]) is int for p in pairs):
                raise PhrtError("policy memory: a malformed int-keyed table")
            return {k: from_plain(v) for k, v in pairs}
        raise PhrtError("policy memory: an unknown table")
    if isinstance(value, list):
        return [from_plain(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise PhrtError("policy memory: not plain data")


def _hashable(value):
    if isinstance(value, list | dict | set):
        raise PhrtError("policy memory: a set holds a table")
    return value


def same_shape(got, want) -> bool:
    """``got`` has ``want``'s keys and, recursively, compatible types (a number where a
    number was, a container where one was). The policies' memory tables are keyed by
    element id and hold numbers (or tables and lists of numbers), so the content of a
    table that is empty in ``want`` must be that."""
    if isinstance(want, dict):
        if not isinstance(got, dict):
            return False
        if not want:
            return all(isinstance(k, int) and _numeric(v) for k, v in got.items())
        return set(got) == set(want) and all(same_shape(got[k], want[k]) for k in want)
    if isinstance(want, set | list):
        return isinstance(got, type(want)) and all(_number(v) for v in got)
    if isinstance(want, bool):
        return isinstance(got, bool)
    if isinstance(want, int | float):
        return _number(got)
    if want is None:
        return got is None or _number(got)
    return type(got) is type(want)


def _number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _numeric(value) -> bool:
    """A number, or a list or int-keyed table of numbers (any depth)."""
    if isinstance(value, dict):
        return all(isinstance(k, int) and _numeric(v) for k, v in value.items())
    if isinstance(value, list | set):
        return all(_numeric(v) for v in value)
    return _number(value)
