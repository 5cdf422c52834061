"""The two-region coefficient mappings of the blend and the uncertainty calibration."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from deltar.inference.regions import (
    REGIONS,
    RegionPair,
    check_coefficients,
    regions_from_dict,
    regions_to_dict,
)


@dataclass(frozen=True)
class _Pair:
    a: float
    b: float


@dataclass(frozen=True)
class _Both:
    inside: _Pair
    outside: _Pair


def test_round_trip_and_refusals_name_the_mapping():
    both = _Both(_Pair(1, 2.5), _Pair(-3, 4))
    stored = regions_to_dict(both, ("a", "b"))
    assert stored == {"inside": {"a": 1.0, "b": 2.5}, "outside": {"a": -3.0, "b": 4.0}}
    assert all(type(v) is float for region in stored.values() for v in region.values())
    assert _Both(**regions_from_dict(stored, _Pair, ("a", "b"), "pair")) == both
    assert REGIONS == ("inside", "outside")
    with pytest.raises(ValueError, match=r"pair must have regions \['inside', 'outside'\]"):
        regions_from_dict({"inside": stored["inside"]}, _Pair, ("a", "b"), "pair")
    with pytest.raises(ValueError, match=r"pair 'outside' needs keys \['a', 'b'\]"):
        regions_from_dict({**stored, "outside": {"a": 1.0}}, _Pair, ("a", "b"), "pair")
    with pytest.raises(ValueError, match="pair must have regions"):
        regions_from_dict([1, 2], _Pair, ("a", "b"), "pair")


@dataclass(frozen=True)
class _Checked:
    a: float
    b: float

    def __post_init__(self) -> None:
        check_coefficients(self, "pair", nonnegative=True)


@dataclass(frozen=True)
class _CheckedBoth(RegionPair, region_type=_Checked, what="pair"):
    inside: _Checked
    outside: _Checked


def test_region_pair_checks_its_regions_and_keys_its_json_by_the_region_fields():
    both = _CheckedBoth(_Checked(1.0, 0.0), _Checked(2, 3.5))
    assert _CheckedBoth.region_keys == ("a", "b")
    assert both.to_dict() == {"inside": {"a": 1.0, "b": 0.0}, "outside": {"a": 2.0, "b": 3.5}}
    assert _CheckedBoth.from_dict(both.to_dict()) == both
    with pytest.raises(ValueError, match=r"_CheckedBoth\.outside must be a _Checked"):
        _CheckedBoth(_Checked(1.0, 0.0), (1.0, 2.0))
    with pytest.raises(ValueError, match="pair 'inside' needs keys"):
        _CheckedBoth.from_dict({"inside": {"a": 1.0}, "outside": {"a": 1.0, "b": 1.0}})
    with pytest.raises(ValueError, match="pair b must be a finite number >= 0, got -1"):
        _Checked(1.0, -1)
    with pytest.raises(ValueError, match="pair a must be a finite number >= 0, got True"):
        _Checked(True, 1.0)
    with pytest.raises(ValueError, match="pair a must be a finite number >= 0, got nan"):
        _Checked(float("nan"), 1.0)
