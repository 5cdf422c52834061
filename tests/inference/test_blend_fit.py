"""Fitting the confidence blend's coefficients on pixels with ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.inference.blend import blend_weight
from deltar.inference.blend_fit import BlendPixels, fit_confidence_blend


def _synthetic_pixels(rng: np.random.Generator, count: int) -> BlendPixels:
    """Pixels where the network is right when its spread is small and the fill when it is
    large (inside the grid the switch is at 5 % relative spread, beyond it at 20 %)."""
    truth = rng.uniform(0.5, 4.0, count)
    inside = rng.random(count) < 0.6
    relative = np.exp(rng.uniform(np.log(0.01), np.log(0.5), count))
    switch = np.where(inside, 0.05, 0.2)
    network_error = np.where(relative < switch, 0.01, 0.3) * rng.standard_normal(count)
    fill_error = 0.08 * rng.standard_normal(count)
    network = truth * np.exp(network_error)
    return BlendPixels(truth, network, truth * np.exp(fill_error), relative * network, inside)


@pytest.mark.parametrize("objective", ["relative", "squared"])
def test_fitted_blend_beats_network_and_fill_on_new_pixels(rng, objective):
    fitted = fit_confidence_blend(_synthetic_pixels(rng, 20000), objective=objective)
    # Less sure, less weight, in both regions.
    assert fitted.inside.spread_slope < 0 and fitted.outside.spread_slope < 0
    new = _synthetic_pixels(rng, 20000)

    def relative_error(depth):
        return np.mean(np.abs(depth - new.truth_m) / new.truth_m)

    blended = relative_error(new.blended(fitted))
    assert blended < 0.8 * min(relative_error(new.network_m), relative_error(new.fill_m))
    # The per-pixel path equals the map path of blend_weight / blend_with_fill.
    weight = blend_weight(new.network_m[None], new.spread_m[None], new.inside[None],
                          fitted)[0]
    expected = np.exp(weight * np.log(new.network_m) + (1 - weight) * np.log(new.fill_m))
    np.testing.assert_allclose(new.blended(fitted), expected, rtol=1e-5)


def test_blend_fit_needs_pixels_in_both_regions(rng):
    pixels = _synthetic_pixels(rng, 3000)
    pixels.inside[:] = True
    with pytest.raises(ValueError, match="0 pixels with ground truth outside the zone grid"):
        fit_confidence_blend(pixels)
    with pytest.raises(ValueError, match="objective must be one of"):
        fit_confidence_blend(_synthetic_pixels(rng, 3000), objective="rmse")
