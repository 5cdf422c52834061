"""Camera intrinsics and lens distortion from board views, and their uncertainty.

``cv2.calibrateCamera`` on the board's corners, started again when it stops early, with
the covariance of the estimated parameters (the views' poses marginalised out) and how
each view's board plane follows them: the error of intrinsics calibrated from the same
views moves every view's plane together, so it is propagated to the extrinsic's
expected error (:mod:`deltar.calibration.board_uncertainty`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from deltar.calibration.board import BoardDetection, estimate_board_pose
from deltar.camera import CameraIntrinsics, distortion_fold_error

#: The camera parameters :func:`calibrate_camera` estimates, in the order of its covariance.
CAMERA_PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")


@dataclass(frozen=True)
class CameraCalibration:
    """Camera intrinsics and distortion estimated from board views.

    Attributes:
        intrinsics: fx, fy, cx, cy (pixels) and the image size.
        distortion: OpenCV's (k1, k2, p1, p2, k3); k3 is 0.
        rms_px: RMS corner reprojection error, pixels.
        covariance: (8, 8) covariance of ``CAMERA_PARAMETERS`` (fx, fy, cx, cy in pixels,
            k1, k2, p1, p2 unitless), the per-view poses marginalised out.
        views: board views used.
    """

    intrinsics: CameraIntrinsics
    distortion: tuple[float, ...]
    rms_px: float
    covariance: np.ndarray
    views: int

    @property
    def sd(self) -> np.ndarray:
        """(8,) standard deviations of ``CAMERA_PARAMETERS``."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def principal_point_sd_deg(self) -> float:
        """The principal point's standard deviation as an angle (degrees, root of the two
        axes' variances): how far it turns every view's board plane."""
        sd = self.sd
        return float(np.degrees(np.hypot(sd[2] / self.intrinsics.fx,
                                         sd[3] / self.intrinsics.fy)))


def calibrate_camera(detections: list[BoardDetection], intrinsics: CameraIntrinsics,
                     max_views: int = 40, max_restarts: int = 3) -> CameraCalibration:
    """``cv2.calibrateCamera`` from the board views, starting at ``intrinsics``.

    Estimates fx, fy, cx, cy and the distortion (k1, k2, p1, p2; k3 stays 0, which few
    views of a flat board cannot pin down). Uses at most ``max_views`` views, evenly
    spread. From a guess several percent off OpenCV's solver can stop early (its views'
    poses are first solved with the guess), so it is started again from its own answer
    while that lowers the reprojection error by more than 1 %. The covariance comes from
    the Jacobian of all corners' reprojections at the answer (the views' poses
    marginalised out), scaled by the residuals' variance.

    Args:
        detections: the board's corners in each view (at least 3 views).
        intrinsics: the starting guess (pixels; its size is the images').
        max_views: most views used.
        max_restarts: most times the solver is started again from its answer.

    Returns:
        ``CameraCalibration``.
    """
    import cv2

    picks = np.unique(np.linspace(0, len(detections) - 1, min(max_views, len(detections)))
                      .round().astype(int))
    objects = [detections[i].object_points.reshape(-1, 1, 3).astype(np.float64) for i in picks]
    images = [detections[i].image_points.reshape(-1, 1, 2).astype(np.float64) for i in picks]
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    size = (intrinsics.width, intrinsics.height)
    rms, matrix, dist, rvecs, tvecs = cv2.calibrateCamera(
        objects, images, size, intrinsics.matrix.copy(), np.zeros(5), flags=flags)
    for _ in range(max_restarts):
        again = cv2.calibrateCamera(objects, images, size, matrix.copy(), dist.copy(),
                                    flags=flags)
        if again[0] >= rms:
            break
        improved = again[0] < 0.99 * rms
        rms, matrix, dist, rvecs, tvecs = again
        if not improved:
            break
    dist = np.ravel(dist)[:5]
    covariance = _camera_covariance(objects, images, matrix, dist, rvecs, tvecs)
    calibrated = CameraIntrinsics(float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]),
                                  float(matrix[1, 2]), intrinsics.width, intrinsics.height)
    check_distortion_covers_image(calibrated, tuple(float(v) for v in dist))
    return CameraCalibration(calibrated, tuple(float(v) for v in dist), float(rms), covariance,
                             len(picks))


def check_distortion_covers_image(intrinsics: CameraIntrinsics,
                                  distortion: tuple[float, ...]) -> None:
    """Refuse a fitted radial distortion that turns back inside the image
    (:func:`~deltar.camera.distortion_fold_error`): fitted to views whose board never
    reaches the image's outer part, k1 and k2 can do that.

    Raises:
        ValueError: naming where it turns back, and the remedy.
    """
    problem = distortion_fold_error(intrinsics, distortion)
    if problem is not None:
        raise ValueError(f"the fitted {problem}: the board views do not reach far enough "
                         "out. Add views with the board near the image's edges and corners, "
                         "or keep the camera's intrinsics (without --calibrate-intrinsics)")


def _camera_covariance(objects, images, matrix, dist, rvecs, tvecs) -> np.ndarray:
    """(8, 8) covariance of fx, fy, cx, cy, k1, k2, p1, p2 from the corners' reprojection
    Jacobian, each view's pose eliminated (Schur complement)."""
    import cv2

    camera_columns = [6, 7, 8, 9, 10, 11, 12, 13]  # after rvec (3) and tvec (3); k3 fixed
    information = np.zeros((8, 8))
    squared, count = 0.0, 0
    for obj, img, rvec, tvec in zip(objects, images, rvecs, tvecs, strict=True):
        projected, jacobian = cv2.projectPoints(obj, rvec, tvec, matrix, dist)
        camera = jacobian[:, camera_columns]
        pose = jacobian[:, :6]
        cross = camera.T @ pose
        information += camera.T @ camera - cross @ np.linalg.pinv(pose.T @ pose) @ cross.T
        squared += float(np.sum((projected - img) ** 2))
        count += 2 * len(obj)
    sigma2 = squared / max(count - 8 - 6 * len(objects), 1)
    return sigma2 * np.linalg.pinv(information)


def board_plane_sensitivity(detection: BoardDetection,
                            camera_fit: CameraCalibration) -> np.ndarray:
    """How one view's board plane follows the camera parameters.

    Args:
        detection: the board's corners in the view.
        camera_fit: the calibrated camera (its standard deviations set the steps).

    Returns:
        (4, 8) derivative of the board's plane (unit normal x, y, z and offset in
        metres, camera frame) with respect to ``CAMERA_PARAMETERS`` (fx, fy, cx, cy in
        pixels, k1, k2, p1, p2), by solving the pose again with each parameter moved by
        half its standard deviation either way.
    """
    camera = camera_fit.intrinsics
    base = np.array([camera.fx, camera.fy, camera.cx, camera.cy,
                     *camera_fit.distortion[:4]], dtype=np.float64)
    k3 = tuple(camera_fit.distortion[4:5])
    steps = np.maximum(camera_fit.sd / 2, 1e-6 * np.maximum(np.abs(base), 1.0))
    columns = []
    for k, step in enumerate(steps):
        planes = []
        for sign in (1.0, -1.0):
            values = base.copy()
            values[k] += sign * step
            moved = replace(camera, fx=values[0], fy=values[1], cx=values[2], cy=values[3])
            pose = estimate_board_pose(detection, moved, tuple(values[4:]) + k3)
            planes.append(np.append(pose.normal_cam, pose.offset_cam_m))
        columns.append((planes[0] - planes[1]) / (2 * step))
    return np.stack(columns, axis=1)
