"""The shared config checks and dict round-trips every dataclass config relies on."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import pytest

from parcelpick_env.config_checks import (config_from_dict, config_to_dict, require_choice, require_int,
                                          require_positive_ints, require_positive_numbers)


@dataclass(frozen=True)
class Inner:
    radius: float = 0.01
    sizes: tuple[int, ...] = (1, 2)


@dataclass(frozen=True)
class Outer:
    widths: tuple[int, ...] = (8, 16)
    radii: tuple[tuple[float, ...], ...] = ((0.1, 0.2), (0.3,))
    name: str = "a"
    inner: Inner = field(default_factory=Inner)


def test_config_round_trips_through_json_with_tuples_and_nested_dataclass():
    config = Outer(widths=(4,), inner=Inner(radius=0.5, sizes=(3, 4, 5)))
    stored = json.loads(json.dumps(config_to_dict(config)))
    assert stored == config_to_dict(config)  # already JSON types: lists, not tuples
    assert stored["radii"] == [[0.1, 0.2], [0.3]] and stored["inner"]["sizes"] == [3, 4, 5]
    rebuilt = config_from_dict(Outer, stored, nested={"inner": Inner})
    assert rebuilt == config
    assert isinstance(rebuilt.radii[0], tuple) and isinstance(rebuilt.inner, Inner)
    hash(rebuilt)  # frozen configs stay hashable: no list survives the rebuild


def test_config_from_dict_rejects_unknown_keys_naming_them():
    with pytest.raises(ValueError, match=r"Outer: unknown keys \['bogus', 'extra'\]"):
        config_from_dict(Outer, {"name": "b", "extra": 1, "bogus": 2})
    with pytest.raises(ValueError, match=r"Inner: unknown keys \['colour'\]"):
        config_from_dict(Outer, {"inner": {"colour": "red"}}, nested={"inner": Inner})


def test_require_int_rejects_bools_floats_and_out_of_range():
    require_int("C", "n", np.int64(3), 1, 5)
    for bad in (True, 2.0, "3", 0, 6):
        with pytest.raises(ValueError, match=r"C: n must be an int in \[1, 5\]"):
            require_int("C", "n", bad, 1, 5)
    with pytest.raises(ValueError, match="n must be an int >= 0, got -1"):
        require_int("C", "n", -1, lo=0)


def test_require_choice_names_the_field_and_allowed_values():
    require_choice("C", "mode", "pose", ("pose", "pixel"))
    with pytest.raises(ValueError, match=r"C: mode must be one of \('pose', 'pixel'\), got 'joint'"):
        require_choice("C", "mode", "joint", ("pose", "pixel"))


def test_field_loops_name_the_bad_field_and_refuse_nan():
    require_positive_numbers(Inner(), ("radius",))
    with pytest.raises(ValueError, match="Inner: radius must be a finite number > 0, got nan"):
        require_positive_numbers(Inner(radius=float("nan")), ("radius",))
    with pytest.raises(ValueError, match="Outer: name must be an int >= 1"):
        require_positive_ints(Outer(), ("name",))


def test_env_config_checks_pile_fields_at_construction():
    from parcelpick_env.envs.config import EnvConfig
    from parcelpick_env.scene.config import PileConfig

    for cls in (EnvConfig, PileConfig):
        for name, bad in (("num_parcels", 51), ("num_parcels", True), ("layout", "heap"), ("object_set", "spheres"),
                          ("split", "val")):
            with pytest.raises(ValueError, match=f"{cls.__name__}: {name}"):
                cls(**{name: bad})
