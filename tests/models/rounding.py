"""Checks of reported figures that are ratios of other, separately rounded figures."""

from __future__ import annotations


def ratio_bounds(numerator: float, numerator_step: float, denominator: float,
                 denominator_step: float, ratio_step: float) -> tuple[float, float]:
    """(low, high): where a ratio reported to ``ratio_step`` can lie, given its numerator
    and denominator as reported, each rounded to its step (half a step either way)."""
    low = (numerator - numerator_step / 2) / (denominator + denominator_step / 2)
    high = (numerator + numerator_step / 2) / max(denominator - denominator_step / 2, 1e-9)
    return low - ratio_step / 2, high + ratio_step / 2
