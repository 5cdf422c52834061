"""The two pixel regions the estimator's output stage treats apart, and their JSON form.

The confidence blend (:mod:`deltar.inference.blend`) and the uncertainty calibration
(:mod:`deltar.inference.uncertainty`) each hold one set of coefficients for the pixels
inside the zone grid's bounding box and one for the pixels beyond it. Both travel in a
checkpoint's config as ``{"inside": {key: float, ...}, "outside": {...}}``;
:class:`RegionPair` is their common base.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

#: Pixels inside the zone grid's bounding box, and beyond it.
REGIONS = ("inside", "outside")


def regions_to_dict(coefficients: Any, keys: Sequence[str]) -> dict[str, dict[str, float]]:
    """``{region: {key: float}}`` of an object with ``inside`` / ``outside`` attributes
    whose ``keys`` attributes are numbers (plain floats, for JSON)."""
    return {name: {key: float(getattr(getattr(coefficients, name), key)) for key in keys}
            for name in REGIONS}


def regions_from_dict(data: Any, region_type: type, keys: Sequence[str], what: str
                      ) -> dict[str, Any]:
    """The inverse of :func:`regions_to_dict`: ``{region: region_type(*values)}``.

    Args:
        data: the stored mapping.
        region_type: built from the values of ``keys``, in order.
        keys: the coefficient names.
        what: the name errors give the mapping (e.g. ``"confidence blend"``).

    Raises:
        ValueError: missing or extra regions or keys (and whatever ``region_type``
            refuses).
    """
    if not isinstance(data, Mapping) or set(data) != set(REGIONS):
        raise ValueError(f"{what} must have regions {list(REGIONS)}, got {data!r}")
    regions = {}
    for name in REGIONS:
        entry = data[name]
        if not isinstance(entry, Mapping) or set(entry) != set(keys):
            raise ValueError(f"{what} {name!r} needs keys {list(keys)}, got {entry!r}")
        regions[name] = region_type(*(entry[key] for key in keys))
    return regions



def check_coefficients(region: Any, what: str, nonnegative: bool = False) -> None:
    """ValueError naming the coefficient unless each field of the dataclass ``region`` is a
    finite real number (and >= 0 when ``nonnegative``); booleans are refused.

    Args:
        region: one region's coefficients (a dataclass of numbers).
        what: the name errors give the coefficients (e.g. ``"confidence blend"``).
        nonnegative: refuse negative values too.
    """
    for field in dataclasses.fields(region):
        value = getattr(region, field.name)
        if isinstance(value, bool) or not (isinstance(value, numbers.Real)
                                           and math.isfinite(value)
                                           and (value >= 0 or not nonnegative)):
            need = "a finite number >= 0" if nonnegative else "a finite number"
            raise ValueError(f"{what} {field.name} must be {need}, got {value!r}")


class RegionPair:
    """Base of a frozen dataclass holding one coefficient set per region.

    A subclass declares the fields ``inside`` and ``outside`` and names, in its class
    line, ``region_type`` (the dataclass of one region's coefficients) and ``what`` (the
    name errors give the pair): ``class ConfidenceBlend(RegionPair,
    region_type=RegionBlend, what="confidence blend")``. It gets the check that both
    fields are ``region_type`` and the JSON form (:meth:`to_dict` / :meth:`from_dict`,
    keyed by ``region_type``'s field names).

    Attributes:
        inside: coefficients for pixels inside the zone grid's bounding box.
        outside: coefficients for the pixels beyond it.
    """

    region_type: ClassVar[type]
    region_keys: ClassVar[tuple[str, ...]]
    what: ClassVar[str]

    def __init_subclass__(cls, *, region_type: type, what: str, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.region_type, cls.what = region_type, what
        cls.region_keys = tuple(field.name for field in dataclasses.fields(region_type))

    def __post_init__(self) -> None:
        for name in REGIONS:
            if not isinstance(getattr(self, name), self.region_type):
                raise ValueError(f"{type(self).__name__}.{name} must be a "
                                 f"{self.region_type.__name__}, got {getattr(self, name)!r}")

    def to_dict(self) -> dict[str, dict[str, float]]:
        """Plain floats, for a checkpoint's config or ONNX metadata (JSON)."""
        return regions_to_dict(self, self.region_keys)

    @classmethod
    def from_dict(cls, data: Mapping) -> Any:
        """The inverse of :meth:`to_dict`.

        Raises:
            ValueError: missing regions or coefficients, or values the region type
                refuses.
        """
        return cls(**regions_from_dict(data, cls.region_type, cls.region_keys, cls.what))
