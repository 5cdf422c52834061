"""The two pixel regions the estimator's output stage treats apart, and their JSON form.

The confidence blend (:mod:`deltar.inference.blend`) and the uncertainty calibration
(:mod:`deltar.inference.uncertainty`) each hold one set of coefficients for the pixels
inside the zone grid's bounding box and one for the pixels beyond it. Both travel in a
checkpoint's config as ``{"inside": {key: float, ...}, "outside": {...}}``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

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
