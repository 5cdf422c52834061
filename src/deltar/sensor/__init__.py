"""The multi-zone ToF sensor: zone frames, zone geometry, simulation and sampling.

The batched simulator, the PyTorch sampling and the augmentation names need torch; they
are imported on first use so that ``import deltar.sensor`` (and ``deltar --help``) stays
light. ``simulate_zone_frame`` (one frame, numpy) and :mod:`deltar.sensor.hypotheses`
(the estimator's sampling, numpy) run without it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from deltar.extras import lazy_attributes
from deltar.sensor.cnh import CNHConfig, zone_frame_from_cnh
from deltar.sensor.geometry import (
    SensorExtrinsics,
    zone_angles_deg,
    zone_rects,
    zone_rects_to_pixel_bounds,
)
from deltar.sensor.zone_frame import Orientation, ZoneFrame
from deltar.sensor.zone_values import DEFAULT_VALID_STATUS

if TYPE_CHECKING:
    from deltar.sensor.augment import SignalAugmentation, training_zone_rects
    from deltar.sensor.sampling import sample_hypotheses, sample_hypotheses_from_histogram
    from deltar.sensor.simulate import SimulatedZones, simulate_zones
    from deltar.sensor.simulate_frame import simulate_zone_frame
    from deltar.sensor.simulator_config import SimulatorConfig

_LAZY = {
    "SignalAugmentation": "deltar.sensor.augment",
    "training_zone_rects": "deltar.sensor.augment",
    "sample_hypotheses": "deltar.sensor.sampling",
    "sample_hypotheses_from_histogram": "deltar.sensor.sampling",
    "SimulatedZones": "deltar.sensor.simulate",
    "SimulatorConfig": "deltar.sensor.simulator_config",
    "simulate_zone_frame": "deltar.sensor.simulate_frame",
    "simulate_zones": "deltar.sensor.simulate",
}


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = [
    "DEFAULT_VALID_STATUS",
    "CNHConfig",
    "Orientation",
    "SensorExtrinsics",
    "SignalAugmentation",
    "SimulatedZones",
    "SimulatorConfig",
    "ZoneFrame",
    "sample_hypotheses",
    "sample_hypotheses_from_histogram",
    "simulate_zone_frame",
    "simulate_zones",
    "training_zone_rects",
    "zone_angles_deg",
    "zone_frame_from_cnh",
    "zone_rects",
    "zone_rects_to_pixel_bounds",
]
