"""ToF-sensor-to-camera calibration (camera intrinsics re-exported from :mod:`deltar.camera`)."""

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics

__all__ = ["ZJU_L5_INTRINSICS", "CameraIntrinsics"]
