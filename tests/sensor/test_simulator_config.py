"""The zone simulator's parameters refuse values it cannot run with."""

from __future__ import annotations

import pytest

from deltar.sensor.simulator_config import SimulatorConfig


@pytest.mark.parametrize("kwargs", [dict(bin_width_m=0.0), dict(max_range_m=4.01),
                                    dict(ignored_bins=-1), dict(noise_floor_counts=-1.0)])
def test_bad_config_raises(kwargs):
    with pytest.raises(ValueError):
        SimulatorConfig(**kwargs)
