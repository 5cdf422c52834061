"""The two-region coefficient mappings of the blend and the uncertainty calibration."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from deltar.inference.regions import REGIONS, regions_from_dict, regions_to_dict


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
