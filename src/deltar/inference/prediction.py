"""The estimator's result for one image: :class:`DepthPrediction`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.sensor.zone_frame import ZoneFrame


@dataclass
class DepthPrediction:
    """The estimator's result for one image.

    Attributes:
        depth_m: (H, W) float32 depth in metres at the input image's resolution.
        uncertainty_m: (H, W) float32 per-pixel standard deviation in metres: the
            calibrated sigma of ``depth_m`` when ``uncertainty_calibrated``
            (:mod:`deltar.inference.uncertainty`: fitted so that about 68 % of the
            errors lie within one sigma and 95 % within two), else the spread of the
            network's own depth distribution (the network's also when ``depth_m`` is
            blended).
        zone_rects: (Z, 4) float32 (y0, x0, y1, x1) zone rectangles in input-image pixels.
        zone_frame: the zone frame the prediction used (after outlier rejection), a copy:
            the caller may reuse its frame's arrays.
        intrinsics: camera intrinsics of the input image (calibrated or nominal).
        zones_used: number of valid zones the network saw (None when unknown).
        network_size: (h, w) network input size in pixels the image was resized to
            (:func:`deltar.inference.preprocess.network_input_size`, or the fixed size).
        network_depth_m: (H, W) float32 the network's own depth in metres when
            ``depth_m`` is its confidence blend with the colorization fill
            (:mod:`deltar.inference.blend`); None when ``depth_m`` is the network's.
        uncertainty_calibrated: whether ``uncertainty_m`` is the calibrated sigma.
        zone_no_target: (Z,) bool, the no-target flags the prediction used: the
            frame's own, or those inferred for a frame without them
            (:func:`deltar.sensor.no_target.frame_no_target`); None when unknown (then
            the frame's own).
        zone_rejected: (Z,) bool, valid zones the estimator set aside as outliers
            (:mod:`deltar.sensor.zone_outliers`; ``zone_frame`` has them invalid); None
            when the estimator has no outlier rule.
    """

    depth_m: np.ndarray
    uncertainty_m: np.ndarray
    zone_rects: np.ndarray
    zone_frame: ZoneFrame
    intrinsics: CameraIntrinsics
    zones_used: int | None = None
    network_size: tuple[int, int] | None = None
    network_depth_m: np.ndarray | None = None
    uncertainty_calibrated: bool = False
    zone_no_target: np.ndarray | None = None
    zone_rejected: np.ndarray | None = None

    @property
    def blended(self) -> bool:
        """True when ``depth_m`` is the confidence blend (``network_depth_m`` is the
        network's own depth); False when it is the network's depth."""
        return self.network_depth_m is not None

    @property
    def image_only(self) -> bool:
        """True when no zone was valid: the depth is a guess from the image alone.

        Its metric scale is then unknown; :meth:`DepthEstimator.predict` sets the
        uncertainty to at least the depth itself (100 %).
        """
        return self.zones_used == 0
