"""Zones that disagree with every neighbour: outliers a noisy sensor reports.

A VL53L5CX / L8CX zone can report a valid distance that is off by tens of centimetres
(multipath, a glossy or dark surface, ambient light): the status says valid, the
reading is not. The network and the fill extend each zone's reading over its pixels,
so one such zone puts a wrong patch into the depth map. Real structure rarely makes a
zone stand out from all eight of its neighbours on the same side: at a depth edge some
neighbours lie on the zone's side of the edge. The rule here therefore calls a valid
zone an outlier when its log distance lies more than ``tolerance`` beyond every one of
its valid neighbours (at least ``min_neighbours`` of them), all on the same side.

One zone standing out can still be a real object that fills exactly one zone, so a
frame's outliers are set aside only when it has at least ``min_zones`` of them: a
sensor that reports several such zones at once is reporting noise, a frame with one is
kept as it is. Rejected zones become invalid (not *no target*): the network and the
fill then extend their neighbours over them, as for a zone that failed. The rule's
parameters are chosen with the output stage on frames of the training scenes, clean and
with degraded zones, among candidates that include no rejection at all
(:func:`deltar.evaluation.uncertainty.fit_outlier_rule`), and travel with the weights
(``config["zone_outlier_rule"]``).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_outlier_detector import OutlierDetector
from deltar.sensor.zone_values import zone_neighbours

__all__ = ["OutlierRule", "find_outlier_zones", "outlier_rule_from_dict", "reject_outlier_zones",
           "resolve_outlier_rule"]


@dataclass(frozen=True)
class OutlierRule:
    """When a frame's zones are rejected as outliers (module docstring).

    Attributes:
        tolerance: how far beyond all its neighbours a zone's reading must lie, in log
            distance (0.05: about 5 %); > 0.
        min_zones: fewest outliers a frame must have for them to be rejected; >= 1.
        min_neighbours: fewest valid neighbours (of eight) a zone needs to be judged;
            1-8.
        grid: zones per side of the frames the rule applies to (4 or 8); frames of the
            other grid keep every zone. 8 for every rule chosen so far (and for stored
            rules without it): on 4 x 4 frames, whose zones are four times as large,
            real structure makes a zone stand out from its neighbours far more often.
    """

    tolerance: float
    min_zones: int = 1
    min_neighbours: int = 4
    grid: int = 8

    def __post_init__(self) -> None:
        if isinstance(self.tolerance, bool) or not isinstance(self.tolerance, numbers.Real) \
                or not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"zone outlier tolerance must be a finite number > 0 (log "
                             f"distance), got {self.tolerance!r}")
        if self.grid not in (4, 8) or isinstance(self.grid, bool):
            raise ValueError(f"zone outlier grid must be 4 or 8, got {self.grid!r}")
        for name, low, high in (("min_zones", 1, None), ("min_neighbours", 1, 8)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or \
                    value < low or (high is not None and value > high):
                bounds = f">= {low}" if high is None else f"in {low}..{high}"
                raise ValueError(f"zone outlier {name} must be an integer {bounds}, got "
                                 f"{value!r}")
        object.__setattr__(self, "tolerance", float(self.tolerance))
        object.__setattr__(self, "min_zones", int(self.min_zones))
        object.__setattr__(self, "min_neighbours", int(self.min_neighbours))

    def find(self, frame: ZoneFrame) -> np.ndarray:
        """(n, n) bool, the frame's outliers (:func:`find_outlier_zones`) when it has at
        least ``min_zones`` of them (and the rule's ``grid``), else none."""
        if frame.grid != self.grid:
            return np.zeros(frame.valid.shape, dtype=bool)
        outliers = find_outlier_zones(frame.mean_m, frame.valid, self.tolerance,
                                      self.min_neighbours)
        return outliers if int(outliers.sum()) >= self.min_zones else np.zeros_like(outliers)

    def to_dict(self) -> dict[str, float | int]:
        """The rule as a JSON-ready dict (a checkpoint's ``config["zone_outlier_rule"]``)."""
        stored: dict[str, float | int] = {"tolerance": self.tolerance,
                                          "min_zones": self.min_zones,
                                          "min_neighbours": self.min_neighbours}
        if self.grid != 8:  # 8 is what a stored rule without it means
            stored["grid"] = self.grid
        return stored

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> OutlierRule:
        """Read :meth:`to_dict`'s form.

        Raises:
            ValueError: not a mapping, unknown keys or bad values (the message says which).
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"zone_outlier_rule must be a dict, got {data!r}")
        unknown = sorted(set(data) - {"tolerance", "min_zones", "min_neighbours", "grid"})
        if unknown or "tolerance" not in data:
            raise ValueError(f"zone_outlier_rule needs 'tolerance' (and optionally "
                             f"'min_zones', 'min_neighbours', 'grid'), got keys "
                             f"{sorted(data)}")
        return cls(**data)


def outlier_rule_from_dict(data: Mapping[str, Any]) -> OutlierRule | OutlierDetector:
    """A stored ``zone_outlier_rule``: an :class:`OutlierRule` or, when it names a
    ``detector``, an :class:`~deltar.sensor.zone_outlier_detector.OutlierDetector`.

    Raises:
        ValueError: neither form reads (the message says why).
    """
    if isinstance(data, Mapping) and "detector" in data:
        return OutlierDetector.from_dict(data)
    return OutlierRule.from_dict(data)


def resolve_outlier_rule(rule: OutlierRule | OutlierDetector | str | None, contract: Mapping
                         ) -> OutlierRule | OutlierDetector | None:
    """The rule an estimator uses (its ``zone_outliers`` argument) given the weights'
    contract: ``"auto"`` the one they carry (``contract["zone_outlier_rule"]``, or None),
    a rule or detector as it is, None no rejection.

    Raises:
        ValueError: anything else, or a stored rule that does not read.
    """
    if rule == "auto":
        stored = contract.get("zone_outlier_rule")
        return None if stored is None else outlier_rule_from_dict(stored)
    if rule is not None and not isinstance(rule, OutlierRule | OutlierDetector):
        raise ValueError(f"zone_outliers must be 'auto', an OutlierRule, an OutlierDetector "
                         f"or None, got {rule!r}")
    return rule


def find_outlier_zones(zone_mean_m: np.ndarray, zone_valid: np.ndarray, tolerance: float,
                       min_neighbours: int = 4) -> np.ndarray:
    """Valid zones whose reading lies beyond all their valid neighbours (module docstring).

    Args:
        zone_mean_m: (n, n) zone readings in metres (ignored where not valid).
        zone_valid: (n, n) bool validity.
        tolerance: log distance a zone must lie beyond every neighbour (> 0).
        min_neighbours: fewest valid neighbours (of eight) a zone needs to be judged.

    Returns:
        (n, n) bool, True at the outlying zones (never at invalid ones).

    Raises:
        ValueError: shapes differ or are not square.
    """
    valid = np.asarray(zone_valid, dtype=bool)
    mean = np.asarray(zone_mean_m, dtype=np.float64)
    if valid.ndim != 2 or valid.shape[0] != valid.shape[1] or mean.shape != valid.shape:
        raise ValueError(f"zone_mean_m and zone_valid must both be (n, n), got "
                         f"{mean.shape} and {valid.shape}")
    log_mean = np.where(valid, np.log(np.maximum(mean, 1e-6)), np.nan)
    neighbours = zone_neighbours(log_mean)
    known = ~np.isnan(neighbours)
    # Differences to invalid neighbours are left out of both extremes.
    difference = log_mean[None] - neighbours
    nearest_above = np.where(known, difference, np.inf).min(axis=0)
    nearest_below = np.where(known, difference, -np.inf).max(axis=0)
    judged = valid & (known.sum(axis=0) >= min_neighbours)
    return judged & ((nearest_above > tolerance) | (nearest_below < -tolerance))


def reject_outlier_zones(frame: ZoneFrame, rule: OutlierRule | OutlierDetector | None,
                         no_target: np.ndarray) -> tuple[ZoneFrame, np.ndarray]:
    """The frame with its outlying zones set invalid: for a rule, when it has at least
    ``rule.min_zones`` of them; for a detector, the zones it finds.

    Args:
        frame: the zone frame.
        rule: the rule or detector; None rejects nothing.
        no_target: (Z,) bool, the no-target flags the estimator reads for ``frame``
            (its own or inferred): the returned frame carries them explicitly, so that
            a rejected zone is never inferred to be *no target* afterwards.

    Returns:
        (frame, (Z,) bool rejected zones). The frame is the input itself when nothing is
        rejected; otherwise a copy with the rejected zones (all their targets) invalid.
    """
    rejected = np.zeros(frame.zone_count, dtype=bool)
    if rule is None:
        return frame, rejected
    outliers = rule.find(frame)
    if not outliers.any():
        return frame, rejected
    changes: dict[str, Any] = {"valid": frame.valid & ~outliers,
                               "no_target": np.asarray(no_target, dtype=bool).reshape(
                                   frame.valid.shape)}
    if frame.target_valid is not None:
        changes["target_valid"] = frame.target_valid & ~outliers[..., None]
    return replace(frame, **changes), outliers.reshape(-1)
