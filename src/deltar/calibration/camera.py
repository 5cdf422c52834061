"""Alias of :mod:`deltar.camera` (where the camera intrinsics now live)."""

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics

__all__ = ["ZJU_L5_INTRINSICS", "CameraIntrinsics"]
