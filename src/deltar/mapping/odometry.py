"""Camera poses from frame-to-frame RGB-D odometry (Open3D) when none are given.

Each frame is registered to the one before it with Open3D's multi-scale RGB-D
odometry (photometric + geometric "hybrid" term) on its colour image and its predicted
depth; the poses are the chained motions, so errors add up: there is no loop closure and
the drift grows without bound with the path. A pair that fails to register keeps the
previous pair's motion (constant velocity) and is counted.

Before any depth is predicted, :func:`check_motion` refuses recordings that are too
short or too still to register (the images barely change between frames).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.mapping.tsdf import require_open3d

#: Fewest frames odometry is run on.
MIN_ODOMETRY_FRAMES = 3
#: Median mean absolute grey-level change between consecutive frames (0..255) below
#: which a recording counts as still.
MIN_IMAGE_CHANGE = 1.0
#: Side of the thumbnails the motion check compares, pixels.
_THUMB = (60, 80)


def image_change(first_rgb: np.ndarray, second_rgb: np.ndarray) -> float:
    """Mean absolute grey-level difference (0..255) of two (H, W, 3) uint8 images' thumbnails."""
    import cv2

    grey = [cv2.resize(cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY),
                       _THUMB[::-1], interpolation=cv2.INTER_AREA).astype(np.float32)
            for img in (first_rgb, second_rgb)]
    return float(np.mean(np.abs(grey[0] - grey[1])))


def check_motion(images: Sequence[np.ndarray], source: str,
                 min_change: float = MIN_IMAGE_CHANGE) -> float:
    """Refuse a frame sequence that odometry cannot work on; return its median change.

    Args:
        images: the frames' (H, W, 3) uint8 RGB images in order (or an even sample).
        source: the recording, for the message.
        min_change: see :data:`MIN_IMAGE_CHANGE`.

    Raises:
        ValueError: fewer than :data:`MIN_ODOMETRY_FRAMES` frames, or the images barely
            change (a camera standing still gives odometry nothing to track).
    """
    if len(images) < MIN_ODOMETRY_FRAMES:
        raise ValueError(f"{source}: {len(images)} frame(s) is too short for odometry (needs "
                         f"at least {MIN_ODOMETRY_FRAMES}); give poses (pose/ folder, "
                         "--trajectory) or a longer recording")
    changes = [image_change(a, b) for a, b in itertools.pairwise(images)]
    median = float(np.median(changes))
    if median < min_change:
        raise ValueError(f"{source}: the camera is too still for odometry (median image "
                         f"change {median:.2f} grey levels between frames, needs "
                         f">= {min_change:g}); move the camera, or give poses (pose/ folder, "
                         "--trajectory)")
    return median


#: Camera speed (m/s) above which chained odometry is reported as implausible: faster
#: than a walking person or an indoor robot carries a camera.
MAX_CAMERA_SPEED_M_S = 3.0


def median_speed(poses: np.ndarray, times_s: np.ndarray) -> float:
    """Median speed of the camera between consecutive frames, metres per second.

    Args:
        poses: (N, 4, 4) camera-to-world transforms, metres, N >= 2.
        times_s: (N,) frame times, seconds, increasing.

    Returns:
        The median of |translation step| / time step (0 for fewer than two frames);
        above :data:`MAX_CAMERA_SPEED_M_S` the frames are probably not one continuous
        sequence (e.g. unrelated generated rooms), or their depth is wrong.
    """
    if len(poses) < 2:
        return 0.0
    steps = np.linalg.norm(np.diff(np.asarray(poses)[:, :3, 3], axis=0), axis=1)
    durations = np.maximum(np.diff(np.asarray(times_s, dtype=np.float64)), 1e-6)
    return float(np.median(steps / durations))


@dataclass
class OdometryReport:
    """How the odometry went.

    Attributes:
        pairs: frame pairs registered.
        failed: pairs that did not register (previous motion kept).
        path_length_m: length of the camera path, metres.
    """

    pairs: int = 0
    failed: int = 0
    path_length_m: float = 0.0

    def summary(self) -> str:
        """One line for the terminal."""
        return (f"odometry: {self.pairs} frame pairs, {self.failed} failed (previous motion "
                f"kept), path {self.path_length_m:.2f} m; frame-to-frame odometry has no loop "
                "closure: its drift grows with the path")


class RGBDOdometry:
    """Chain frame-to-frame Open3D RGB-D odometry into camera-to-world poses.

    Args:
        intrinsics: the camera's intrinsics at the frames' resolution.
        max_depth_m: depth beyond this is ignored, metres.
        max_depth_diff_m: largest depth difference of a matched pixel pair, metres.
    """

    def __init__(self, intrinsics: CameraIntrinsics, max_depth_m: float,
                 max_depth_diff_m: float = 0.07) -> None:
        self.o3d = require_open3d()
        self.intrinsics = intrinsics
        self.camera = self.o3d.camera.PinholeCameraIntrinsic(
            intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy,
            intrinsics.cx, intrinsics.cy)
        self.option = self.o3d.pipelines.odometry.OdometryOption()
        self.option.depth_max = float(max_depth_m)
        self.option.depth_diff_max = float(max_depth_diff_m)
        self.report = OdometryReport()
        self._previous = None
        self._motion = np.eye(4)
        self.pose = np.eye(4)

    def _rgbd(self, image: np.ndarray, depth_m: np.ndarray):
        o3d = self.o3d
        depth = np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float32)
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(image)), o3d.geometry.Image(depth),
            depth_scale=1.0, depth_trunc=self.option.depth_max,
            convert_rgb_to_intensity=True)

    def step(self, image: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """The next frame's (4, 4) camera-to-world pose (the first frame is the origin).

        Args:
            image: (H, W, 3) uint8 RGB.
            depth_m: (H, W) depth in metres (0 = none).
        """
        current = self._rgbd(image, depth_m)
        if self._previous is not None:
            odometry = self.o3d.pipelines.odometry
            # Motion of the current camera in the previous one's frame.
            ok, motion, _ = odometry.compute_rgbd_odometry(
                current, self._previous, self.camera, self._motion,
                odometry.RGBDOdometryJacobianFromHybridTerm(), self.option)
            self.report.pairs += 1
            if ok and np.all(np.isfinite(motion)):
                self._motion = np.asarray(motion)
            else:
                self.report.failed += 1
            previous_position = self.pose[:3, 3].copy()
            self.pose = self.pose @ self._motion
            self.report.path_length_m += float(np.linalg.norm(self.pose[:3, 3]
                                                              - previous_position))
        self._previous = current
        return self.pose.copy()
