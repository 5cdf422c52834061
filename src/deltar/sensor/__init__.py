"""The multi-zone ToF sensor: zone frames, zone geometry, simulation and sampling."""

from deltar.sensor.geometry import SensorExtrinsics, zone_angles_deg, zone_rects
from deltar.sensor.zone_frame import DEFAULT_VALID_STATUS, Orientation, ZoneFrame

__all__ = [
    "DEFAULT_VALID_STATUS",
    "Orientation",
    "SensorExtrinsics",
    "ZoneFrame",
    "zone_angles_deg",
    "zone_rects",
]
