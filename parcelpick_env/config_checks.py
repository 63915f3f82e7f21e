"""Checks and dict round-trips shared by every dataclass config, so each config states only its own rules.

Every failed check raises ``ValueError("<Owner>: <field> ...")``: the owner says which config was
wrong and the message always names the field, whichever config or caller built it.
"""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral, Real
from typing import TYPE_CHECKING, Any, Iterable, Mapping, TypeVar

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

T = TypeVar("T", bound="DataclassInstance")


def require(ok: bool, owner: str, message: str) -> None:
    """Raise ``ValueError("owner: message")`` unless ``ok``; the message should name the field."""
    if not ok:
        raise ValueError(f"{owner}: {message}")


def require_choice(owner: str, name: str, value: Any, allowed: tuple[Any, ...]) -> None:
    """``value`` is one of ``allowed``; the error lists them so the caller sees what would work."""
    require(value in allowed, owner, f"{name} must be one of {allowed}, got {value!r}")


def _bounds_text(lo: int | None, hi: int | None) -> str:
    if lo is not None and hi is not None:
        return f" in [{lo}, {hi}]"
    if lo is not None:
        return f" >= {lo}"
    return f" <= {hi}" if hi is not None else ""


def require_int(owner: str, name: str, value: Any, lo: int | None = None, hi: int | None = None) -> None:
    """``value`` is an integer (numpy ones too, bools not) within ``[lo, hi]``; a ``None`` bound is open."""
    ok = (isinstance(value, Integral) and not isinstance(value, bool)
          and (lo is None or int(value) >= lo) and (hi is None or int(value) <= hi))
    require(ok, owner, f"{name} must be an int{_bounds_text(lo, hi)}, got {value!r}")


def require_positive_ints(obj: Any, names: Iterable[str]) -> None:
    """Each named field of ``obj`` is an int >= 1 (counts, sizes, widths)."""
    for name in names:
        require_int(type(obj).__name__, name, getattr(obj, name), lo=1)


def require_positive_numbers(obj: Any, names: Iterable[str]) -> None:
    """Each named field of ``obj`` is a finite real > 0 (lengths, rates, scales); NaN and inf are refused."""
    for name in names:
        value = getattr(obj, name)
        ok = isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value) and float(value) > 0
        require(ok, type(obj).__name__, f"{name} must be a finite number > 0, got {value!r}")


def require_finite_numbers(obj: Any, names: Iterable[str]) -> None:
    """Each named field of ``obj`` is a finite real (bools, strings, NaN and inf refused): check before comparing."""
    for name in names:
        value = getattr(obj, name)
        ok = isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)
        require(ok, type(obj).__name__, f"{name} must be a finite number, got {value!r}")


def lists_to_tuples(value: Any) -> Any:
    """Lists (JSON's only sequence) back to the tuples a frozen, hashable config holds, at any depth."""
    if isinstance(value, (list, tuple)):
        return tuple(lists_to_tuples(v) for v in value)
    return value


def _tuples_to_lists(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _tuples_to_lists(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_tuples_to_lists(v) for v in value]
    return value


def config_to_dict(config: Any) -> dict[str, Any]:
    """A dataclass config as plain JSON types (tuples as lists), so a stored copy compares equal after a reload."""
    return _tuples_to_lists(dataclasses.asdict(config))


def config_from_dict(cls: type[T], data: Mapping[str, Any], nested: Mapping[str, type[DataclassInstance]] | None = None) -> T:
    """Rebuild ``cls`` from a stored dict: unknown keys are refused (a renamed or foreign field must not pass
    silently), lists become tuples, and each ``nested`` field given as a dict is rebuilt as its dataclass."""
    unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
    more = f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""
    require(not unknown, cls.__name__, f"unknown keys {unknown[:5]}{more}")
    nested = nested or {}
    kwargs = {key: config_from_dict(nested[key], value) if key in nested and isinstance(value, Mapping)
              else lists_to_tuples(value) for key, value in data.items()}
    return cls(**kwargs)
