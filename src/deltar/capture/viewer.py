"""A live 3D view of the rig with rerun (``rerun-sdk``, the ``viewer`` extra).

Per frame, on the timeline ``time`` (seconds, the capture time) and ``frame``:

- ``world/camera/image``: the camera as a pinhole (``rr.Pinhole``, x right, y down,
  z forward) with the colour image;
- ``world/camera/image/zones``: the zones as 2D boxes coloured by their distance (turbo
  over ``depth_range_m``; invalid zones grey), labelled with it (``"-"`` if invalid;
  labels show on hover);
- ``world/camera/image/depth``: the predicted depth as a depth image in metres
  (``meter=1``), which the viewer back-projects to 3D through the pinhole;
- ``uncertainty``: the per-pixel uncertainty in metres (a depth image outside the
  pinhole, so 2D only, viridis);
- ``world/camera/tof``: the ToF sensor's pose (sensor to camera, from the rig
  calibration; identity without one) and ``world/camera/tof/zones``: each valid zone's
  reading as a 3D point on its zone's central ray, in the sensor frame.

``RerunLogger(save_path=...)`` writes an ``.rrd`` recording instead of spawning the
viewer (open it later with ``rerun FILE.rrd``). The recording carries a layout
(:func:`default_blueprint`): the 3D scene beside the camera image with its zones, the
depth and the uncertainty.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics, zone_angles_deg

if TYPE_CHECKING:
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.inference.prediction import DepthPrediction
    from deltar.sensor.zone_frame import ZoneFrame

_EXTRA_HINT = 'the rerun viewer needs the "viewer" extra: pip install "deltar[viewer]"'
#: Colour of invalid zones (RGB).
INVALID_ZONE_RGB = (150, 150, 150)


def require_rerun() -> Any:
    """Import ``rerun`` or raise ``ImportError`` naming the extra to install."""
    try:
        import rerun
    except ImportError as err:
        raise ImportError(f"{_EXTRA_HINT} ({err})") from err
    return rerun


def zone_points_m(frame: ZoneFrame, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Each valid zone's reading as a 3D point in the sensor frame.

    The point lies on the ray through the centre of the zone's angular cell, at the
    zone's distance (z-depth along the sensor axis).

    Args:
        frame: the zone frame.
        fov_deg: (horizontal, vertical) sensor field of view, degrees.

    Returns:
        (V, 3) float32 points in metres (x along the grid's columns, y along its rows,
        z forward) and the (V,) int indices of the valid zones they belong to.
    """
    angles = np.deg2rad(zone_angles_deg(frame.grid, fov_deg))  # (Z, 4): ay0 ax0 ay1 ax1
    ax = (angles[:, 1] + angles[:, 3]) / 2
    ay = (angles[:, 0] + angles[:, 2]) / 2
    mean, _, valid = frame.flat()
    index = np.flatnonzero(valid)
    depth = mean[index].astype(np.float64)
    points = np.stack([np.tan(ax[index]) * depth, np.tan(ay[index]) * depth, depth], axis=1)
    return points.astype(np.float32), index


def zone_colors(frame: ZoneFrame, depth_range_m: tuple[float, float]) -> np.ndarray:
    """(Z,) RGB uint8 colours: turbo by distance over ``depth_range_m``, grey if invalid."""
    from deltar.io.render import colormap

    mean, _, valid = frame.flat()
    low, high = depth_range_m
    scaled = np.clip((mean - low) / max(high - low, 1e-9), 0.0, 1.0)
    rgb = (colormap(scaled, "turbo") * 255 + 0.5).astype(np.uint8)
    rgb[~valid] = INVALID_ZONE_RGB
    return rgb


def default_blueprint() -> Any:
    """The layout: the 3D scene beside the camera image (with zones) and the uncertainty."""
    import rerun.blueprint as rrb
    from rerun.blueprint.archetypes import EyeControls3D

    # Look at the scene from behind, beside and above the camera (x right, y down, z forward).
    eye = EyeControls3D(kind="Orbital", position=[1.6, -1.4, -1.8],
                        look_target=[0.0, 0.0, 2.5], eye_up=[0.0, -1.0, 0.0])
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="3D: depth and zone readings",
                              eye_controls=eye),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="camera and zones",
                                  contents=["$origin", "$origin/zones"]),
                rrb.Spatial2DView(origin="world/camera/image", name="depth (m)",
                                  contents=["$origin/depth"]),
                rrb.Spatial2DView(origin="uncertainty", name="uncertainty (m)")),
            column_shares=[3, 2]),
        collapse_panels=True)


class RerunLogger:
    """Log rig frames and predictions to rerun.

    Args:
        save_path: write an ``.rrd`` file here (refuses an existing file); None spawns
            the viewer (``rerun`` must be installed) and streams to it.
        application_id: rerun application id.
        depth_range_m: (near, far) metres of the zone colour map.

    Raises:
        ImportError: rerun-sdk is not installed (names the extra).
        FileExistsError: ``save_path`` exists.
    """

    def __init__(self, save_path: str | os.PathLike | None = None, *,
                 application_id: str = "deltar",
                 depth_range_m: tuple[float, float] = (0.0, 5.0)) -> None:
        rr = require_rerun()
        self.rr = rr
        self.depth_range_m = depth_range_m
        self.stream = rr.RecordingStream(application_id)
        self.save_path = None if save_path is None else Path(save_path)
        if self.save_path is not None:
            if self.save_path.exists():
                raise FileExistsError(f"refusing to overwrite existing file: {self.save_path}")
            self.save_path.parent.mkdir(parents=True, exist_ok=True)
            self.stream.save(self.save_path)
        else:
            self.stream.spawn()
        self.stream.send_blueprint(default_blueprint())
        self.stream.log("world", rr.ViewCoordinates.RDF, static=True)
        self.frames = 0

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Flush everything (and finish the ``.rrd`` file)."""
        self.stream.flush()
        self.stream.disconnect()

    def log_frame(self, image: np.ndarray, frame: ZoneFrame, zone_rects: np.ndarray,
                  intrinsics: CameraIntrinsics, *, time_s: float | None = None,
                  extrinsics: SensorExtrinsics | None = None,
                  fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                  depth_m: np.ndarray | None = None,
                  uncertainty_m: np.ndarray | None = None) -> None:
        """Log one camera frame with its zones (and depth / uncertainty if given).

        Args:
            image: (H, W, 3) uint8 RGB.
            frame: the zone frame.
            zone_rects: (Z, 4) (y0, x0, y1, x1) zone rectangles in image pixels.
            intrinsics: camera intrinsics of the (H, W) image.
            time_s: capture time in seconds (the ``time`` timeline); the frame's
                timestamp, or the frame count, when None.
            extrinsics: sensor-to-camera transform (identity when None).
            fov_deg: sensor field of view, degrees.
            depth_m: optional (H, W) depth in metres (predicted or reference).
            uncertainty_m: optional (H, W) uncertainty in metres.
        """
        rr = self.rr
        stream = self.stream
        if time_s is None:
            time_s = frame.timestamp_s if frame.timestamp_s is not None else self.frames
        stream.set_time("frame", sequence=self.frames)
        stream.set_time("time", duration=float(time_s))
        height, width = image.shape[:2]
        # 2D content lives under the pinhole; the ToF points (3D) must not.
        stream.log("world/camera/image", rr.Pinhole(
            image_from_camera=intrinsics.matrix, width=width, height=height,
            camera_xyz=rr.ViewCoordinates.RDF))
        stream.log("world/camera/image", rr.Image(np.ascontiguousarray(image)))
        rects = np.asarray(zone_rects, dtype=np.float32)
        mean, _, valid = frame.flat()
        labels = [f"{m:.2f} m" if ok else "-" for m, ok in zip(mean, valid, strict=True)]
        # (y0, x0, y1, x1) with pixel centres at integers -> rerun's pixel-corner XYXY.
        boxes = rects[:, [1, 0, 3, 2]] + 0.5
        stream.log("world/camera/image/zones", rr.Boxes2D(
            array=boxes, array_format=rr.Box2DFormat.XYXY, labels=labels,
            colors=zone_colors(frame, self.depth_range_m), show_labels=False))
        if depth_m is not None:
            depth = np.asarray(depth_m, dtype=np.float32)
            depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))
            stream.log("world/camera/image/depth", rr.DepthImage(depth, meter=1.0))
        if uncertainty_m is not None:
            # A depth image outside the pinhole: 2D only, coloured, values in metres.
            stream.log("uncertainty", rr.DepthImage(np.asarray(uncertainty_m, dtype=np.float32),
                                                    meter=1.0, colormap="viridis"))
        ext = extrinsics or SensorExtrinsics()
        stream.log("world/camera/tof", rr.Transform3D(
            translation=ext.translation_m.astype(np.float32),
            mat3x3=ext.rotation.astype(np.float32)))
        points, index = zone_points_m(frame, fov_deg)
        colors = zone_colors(frame, self.depth_range_m)[index]
        stream.log("world/camera/tof/zones", rr.Points3D(
            points, colors=colors, radii=0.04, labels=[labels[i] for i in index]))
        self.frames += 1

    def log_prediction(self, image: np.ndarray, prediction: DepthPrediction, *,
                       calibration: RigCalibration | None = None,
                       time_s: float | None = None,
                       fov_deg: tuple[float, float] = DEFAULT_FOV_DEG) -> None:
        """Log an estimator result: image, zones, depth and uncertainty.

        The sensor pose and field of view come from ``calibration`` when given (else
        identity and ``fov_deg``).
        """
        extrinsics = None if calibration is None else calibration.extrinsics
        fov = fov_deg if calibration is None else calibration.fov_deg
        self.log_frame(image, prediction.zone_frame, prediction.zone_rects,
                       prediction.intrinsics, time_s=time_s, extrinsics=extrinsics,
                       fov_deg=fov, depth_m=prediction.depth_m,
                       uncertainty_m=prediction.uncertainty_m)
