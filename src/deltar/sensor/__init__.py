"""The multi-zone ToF sensor: zone frames, zone geometry, simulation and sampling."""

from deltar.sensor.augment import SignalAugmentation, training_zone_rects
from deltar.sensor.geometry import (
    SensorExtrinsics,
    zone_angles_deg,
    zone_rects,
    zone_rects_to_pixel_bounds,
)
from deltar.sensor.sampling import sample_hypotheses, sample_hypotheses_from_histogram
from deltar.sensor.simulate import (
    SimulatedZones,
    SimulatorConfig,
    simulate_zone_frame,
    simulate_zones,
)
from deltar.sensor.zone_frame import DEFAULT_VALID_STATUS, Orientation, ZoneFrame

__all__ = [
    "DEFAULT_VALID_STATUS",
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
    "zone_rects",
    "zone_rects_to_pixel_bounds",
]
