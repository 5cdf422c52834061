"""Camera intrinsics and ToF-sensor-to-camera calibration."""

from deltar.calibration.camera import CameraIntrinsics

__all__ = ["CameraIntrinsics"]
