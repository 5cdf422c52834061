"""Is the board printed at its spec's size? A page shrunk to fit prints a few % small.

The board's pose (and so its distance from the camera) scales with the size given in
``--target``; the zones measure the distance to the same surface in metres. A board
printed ``k`` times the spec's size is placed ``1 / k`` times too far, and the
calibration's translation is then off by about ``|1 - k|`` times the views' distance,
an error the expected-error report does not include. :func:`board_scale` estimates
``k`` from the views; :func:`warn_board_scale` warns when it is off.
"""

from __future__ import annotations

import warnings

import numpy as np

from deltar.calibration.board import BoardSpec

#: Printed size over the spec's (:func:`board_scale`) beyond which a calibration warns.
BOARD_SCALE_TOLERANCE = 0.02
#: Fewest views to judge the scale from (four unknowns).
MIN_SCALE_VIEWS = 5


def board_scale(normals_cam: np.ndarray, offsets_cam_m: np.ndarray,
                offsets_zone_m: np.ndarray) -> tuple[float, float]:
    """The printed board's size over its spec's, from its views and the zones' planes.

    With the sensor at ``t`` in the camera frame, each view gives
    ``k d_board + n . t = d_zones`` (planes ``n . p + d = 0``, normals towards the
    camera); ``k`` and ``t`` are solved by least squares over the views.

    Args:
        normals_cam: (N, 3) board plane normals in the camera frame, N >= 4.
        offsets_cam_m: (N,) board plane offsets from its pose (the spec's size), metres.
        offsets_zone_m: (N,) the zones' plane offsets in the sensor frame, metres.

    Returns:
        (k, its standard error from the residuals).
    """
    design = np.column_stack([offsets_cam_m, normals_cam])
    solution, *_ = np.linalg.lstsq(design, offsets_zone_m, rcond=None)
    residual = offsets_zone_m - design @ solution
    dof = max(len(offsets_zone_m) - design.shape[1], 1)
    covariance = np.linalg.pinv(design.T @ design) * float(residual @ residual) / dof
    return float(solution[0]), float(np.sqrt(max(covariance[0, 0], 0.0)))


def warn_board_scale(normals_cam: np.ndarray, offsets_cam_m: np.ndarray,
                     offsets_zone_m: np.ndarray, spec: BoardSpec) -> float | None:
    """Warn when :func:`board_scale` (arguments as there) is off by more than
    :data:`BOARD_SCALE_TOLERANCE` and two standard errors.

    Returns:
        The translation error in metres that such a scale implies (``|1 - k|`` times the
        views' median distance), not part of the expected error from the zones' noise;
        0 when the scale is within the tolerance, None when fewer than
        :data:`MIN_SCALE_VIEWS` views are left to judge it from.
    """
    if len(offsets_cam_m) < MIN_SCALE_VIEWS:
        return None
    scale, error = board_scale(normals_cam, offsets_cam_m, offsets_zone_m)
    off_m = 0.0
    if abs(scale - 1.0) > max(BOARD_SCALE_TOLERANCE, 2.0 * error):
        off_m = abs(1 - scale) * float(np.median(offsets_cam_m))
        off_cm = 100 * off_m
        warnings.warn(
            f"the board looks printed at {scale:.3f} times the size of {spec.text()} "
            f"(+-{error:.3f}; a square of about {1000 * spec.square_m * scale:.1f} mm rather "
            f"than {1000 * spec.square_m:g} mm): measure a printed square and give it as "
            f"SQUARE_M (and MARKER_M) in --target, or the translation is off by about "
            f"{off_cm:.1f} cm", stacklevel=3)
    return off_m
