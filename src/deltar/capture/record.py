"""Record camera frames and ToF zone frames, with timestamps, into a recording folder.

The folder layout is :mod:`deltar.io.recording` (``meta.json``, ``zones.jsonl``,
``color/<ns>.png``, optional ``depth/<ns>.png`` and ``pose/<ns>.txt``). Nothing in a
recording is ever overwritten: recording into an existing folder appends (same camera
and sensor; the rig's clock must then run on after the recording's end,
``Recording.end_time_s``: an earlier item raises ``ValueError``, a simulated rig starts
after it), and a frame whose file already exists raises ``FileExistsError``. With
``bag_storage`` the same items go into a new ROS 2 bag instead
(:class:`deltar.io.rosbag_writer.BagRecordingWriter`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from deltar.camera import CameraIntrinsics
from deltar.io.recording import RecordingMeta, RecordingWriter
from deltar.sensor.geometry import DEFAULT_FOV_DEG

if TYPE_CHECKING:
    from deltar.capture.drivers import Capture
    from deltar.io.rosbag_writer import BagRecordingWriter


@dataclass
class RecordSummary:
    """How many items a recording run wrote.

    Attributes:
        folder: the recording folder.
        images: colour images written.
        zone_frames: zone frames written.
        depth_maps: reference depth maps written (simulated rigs).
        poses: camera poses written (simulated rigs whose source has poses).
        duration_s: time span covered, seconds.
    """

    folder: Path
    images: int = 0
    zone_frames: int = 0
    depth_maps: int = 0
    poses: int = 0
    duration_s: float = 0.0


def record(out: str | os.PathLike, rig, *, max_frames: int | None = None,
           duration_s: float | None = None, intrinsics: CameraIntrinsics | None = None,
           fov_deg: tuple[float, float] | None = None, save_depth: bool = True,
           on_step: Callable[[RecordSummary], None] | None = None,
           bag_storage: str | None = None,
           on_capture: Callable[[Capture, RecordingMeta], None] | None = None
           ) -> RecordSummary:
    """Grab from a rig into a recording folder (or a ROS 2 bag) until it ends or a limit.

    Args:
        out: the recording folder (created; appended to if it holds a recording of the
            same camera and sensor).
        rig: a :class:`~deltar.capture.drivers.SimulatedRig` or
            :class:`~deltar.capture.drivers.HardwareRig` (``grab()`` returns a
            ``Capture`` or None at the end; used as a context manager).
        max_frames: stop after this many camera frames.
        duration_s: stop after this much camera time, seconds.
        intrinsics: camera intrinsics for ``meta.json``; the rig's when None (a hardware
            rig has none: pass them, e.g. from a calibration).
        fov_deg: sensor field of view stored in ``meta.json``; the rig's, or the
            default 45 x 45 degrees, when None.
        save_depth: also store reference depth when the rig delivers it.
        on_step: called after each step with the running summary (progress display).
        bag_storage: write a new ROS 2 bag at ``out`` instead of a folder, with this
            storage (``"sqlite3"`` or ``"mcap"``; see
            :class:`deltar.io.rosbag_writer.BagRecordingWriter`).
        on_capture: called with each recorded capture and the recording's metadata
            (e.g. a live viewer).

    Returns:
        A :class:`RecordSummary`.
    """
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    intr = intrinsics or getattr(rig, "intrinsics", None)
    fov = tuple(fov_deg or getattr(rig, "fov_deg", DEFAULT_FOV_DEG))
    summary = RecordSummary(folder=Path(out))
    writer: RecordingWriter | BagRecordingWriter | None = None
    first_time: float | None = None
    try:
        with rig:
            while max_frames is None or summary.images < max_frames:
                capture = rig.grab()
                if capture is None:
                    break
                if capture.image is not None and writer is None:
                    height, width = capture.image.shape[:2]
                    if intr is None:
                        raise ValueError("camera intrinsics are unknown: pass intrinsics "
                                         "(e.g. from a calibration file)")
                    if (intr.height, intr.width) != (height, width):
                        raise ValueError(f"camera delivers {height}x{width} images, intrinsics "
                                         f"are for {intr.height}x{intr.width}")
                    meta = RecordingMeta(intrinsics=intr, sensor_model=rig.sensor_model,
                                         grid=rig.grid, fov_deg=fov)
                    if bag_storage is None:
                        writer = RecordingWriter(out, meta)
                    else:
                        from deltar.io.rosbag_writer import BagRecordingWriter

                        writer = BagRecordingWriter(out, meta, storage=bag_storage)
                if writer is None:
                    continue
                if capture.image is not None:
                    if first_time is None:
                        first_time = capture.image_time_s
                    if duration_s is not None and \
                            capture.image_time_s - first_time > duration_s:
                        break
                    writer.add_color(capture.image_time_s, capture.image)
                    summary.images += 1
                    summary.duration_s = capture.image_time_s - first_time
                    if save_depth and capture.depth_m is not None:
                        writer.add_depth(capture.image_time_s, capture.depth_m)
                        summary.depth_maps += 1
                    if capture.pose is not None:
                        writer.add_pose(capture.image_time_s, capture.pose)
                        summary.poses += 1
                if capture.zone_frame is not None:
                    writer.add_zone_frame(capture.zone_frame)
                    summary.zone_frames += 1
                if on_capture is not None:
                    on_capture(capture, writer.meta)
                if on_step is not None:
                    on_step(summary)
    finally:
        # A bag becomes readable only when closed: keep what was recorded, even on error.
        if writer is not None:
            writer.close()
    return summary
