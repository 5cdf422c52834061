"""Writing ROS 2 bags: :class:`BagWriter`, and the recording writer of ``deltar record
--bag`` (:class:`BagRecordingWriter`).

Depth and uncertainty as ``sensor_msgs/msg/Image`` ``32FC1`` in metres with NaN where
invalid (REP 118), ``CameraInfo``, coloured ``PointCloud2`` (x, y, z float32 + rgb
packed in a float32), camera images and zone frames, into a new bag (sqlite3 or mcap
storage). The bag is written into a hidden folder beside its destination and renamed
when complete, so a bag is either whole or absent; an existing path is never written
into. The messages are built with :func:`deltar.io.ros_messages.typestore`.

All times are integer nanoseconds (``header.stamp``) unless named ``_s`` (seconds).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

import numpy as np

from deltar.camera import CameraIntrinsics, check_image
from deltar.io.atomic import staging_folder
from deltar.io.ros_messages import (
    CAMERA_INFO_TYPE,
    MULTI_TARGET_ZONE_FRAME_MSGTYPE,
    ZONE_FRAME_MSGTYPE,
    require_rosbags,
    stamped_header,
    typestore,
)
from deltar.io.zone_file import check_writable
from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_values import NO_TARGET_STATUS

#: Storage plugins :class:`BagWriter` writes.
STORAGES: tuple[str, ...] = ("sqlite3", "mcap")
#: Topics ``deltar record --bag`` writes (and :class:`~deltar.io.rosbag_reader.BagInput`
#: finds by type).
RECORD_TOPICS = {"image": "/camera/color/image_raw",
                 "camera_info": "/camera/color/camera_info",
                 "depth": "/camera/depth/image", "zones": "/tof/zones",
                 "pose": "/camera/pose"}
#: Frame ids of recorded messages (``world``: the frame the recorded poses are in).
RECORD_FRAME_IDS = {"camera": "camera_color_optical_frame", "tof": "tof_sensor",
                    "world": "world"}
#: The message type of camera poses.
POSE_MSGTYPE = "geometry_msgs/msg/PoseStamped"
#: Output topics of ``deltar replay --out-bag`` below its prefix (default ``/deltar``).
OUTPUT_TOPICS = {"depth": "depth", "uncertainty": "uncertainty",
                 "camera_info": "camera_info", "points": "points"}


class BagWriter:
    """Write a new ROS 2 bag; complete only when closed (use as a context manager).

    Args:
        path: the bag folder to create; it must not exist.
        storage: ``"sqlite3"`` (ROS 2 Humble's default) or ``"mcap"``.

    Raises:
        FileExistsError: ``path`` exists.
    """

    def __init__(self, path: str | os.PathLike, storage: str = "sqlite3") -> None:
        require_rosbags()
        from rosbags.rosbag2 import StoragePlugin, Writer

        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"refusing to write into existing path: {self.path}")
        # The staging folder is registered before it exists: a stop at any moment, even
        # here before the writer opens, leaves no hidden folder (deltar.io.atomic).
        self._staged = contextlib.ExitStack()
        try:
            self._staging = self._staged.enter_context(staging_folder(self.path))
            plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
            self._writer = Writer(self._staging / self.path.name, version=8,
                                  storage_plugin=plugin)
            self._writer.open()
        except BaseException:
            self._staged.close()
            raise
        self._connections: dict[str, Any] = {}
        self.messages = 0
        self._closed = False

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(keep=exc_type is None)

    def close(self, keep: bool = True) -> Path | None:
        """Finish the bag and move it to its path (``keep=False`` discards it).

        Returns:
            The bag path, or None when discarded.
        """
        if self._closed:
            return self.path if keep else None
        self._closed = True
        with self._staged:  # the staging folder goes, whatever happens
            self._writer.close()
            if keep:
                if self.path.exists():
                    raise FileExistsError(f"refusing to replace {self.path}, which appeared "
                                          "while writing")
                os.rename(self._staging / self.path.name, self.path)
                return self.path
            return None

    def _write(self, topic: str, msgtype: str, msg: Any, log_ns: int) -> None:
        store = typestore()
        if topic not in self._connections:
            # The type store (ZoneFrame registered) gives the definition stored in the bag.
            self._connections[topic] = self._writer.add_connection(topic, msgtype,
                                                                   typestore=store)
        elif self._connections[topic].msgtype != msgtype:
            raise ValueError(f"topic {topic} already carries "
                             f"{self._connections[topic].msgtype}, not {msgtype}")
        self._writer.write(self._connections[topic], int(log_ns),
                           store.serialize_cdr(msg, msgtype))
        self.messages += 1

    def add_rgb_image(self, topic: str, stamp_ns: int, frame_id: str, rgb: np.ndarray,
                      log_ns: int | None = None) -> None:
        """An (H, W, 3) uint8 RGB image as ``sensor_msgs/msg/Image`` ``rgb8``."""
        image = check_image(rgb, "rgb")
        height, width = image.shape[:2]
        msg = typestore().types["sensor_msgs/msg/Image"](
            header=stamped_header(stamp_ns, frame_id), height=height, width=width, encoding="rgb8",
            is_bigendian=0, step=3 * width, data=image.reshape(-1))
        self._write(topic, "sensor_msgs/msg/Image", msg, stamp_ns if log_ns is None else log_ns)

    def add_metric_image(self, topic: str, stamp_ns: int, frame_id: str, values_m: np.ndarray,
                         log_ns: int | None = None) -> None:
        """An (H, W) map in metres as ``32FC1`` (REP 118); values <= 0 or non-finite -> NaN."""
        values = np.asarray(values_m, dtype=np.float32)
        if values.ndim != 2:
            raise ValueError(f"values_m must be (H, W), got {values.shape}")
        values = np.where(np.isfinite(values) & (values > 0), values, np.float32(np.nan))
        height, width = values.shape
        data = np.ascontiguousarray(values.astype("<f4")).view(np.uint8).reshape(-1)
        msg = typestore().types["sensor_msgs/msg/Image"](
            header=stamped_header(stamp_ns, frame_id), height=height, width=width, encoding="32FC1",
            is_bigendian=0, step=4 * width, data=data)
        self._write(topic, "sensor_msgs/msg/Image", msg, stamp_ns if log_ns is None else log_ns)

    def add_camera_info(self, topic: str, stamp_ns: int, frame_id: str,
                        intrinsics: CameraIntrinsics, log_ns: int | None = None) -> None:
        """Pinhole ``sensor_msgs/msg/CameraInfo`` (``plumb_bob``, no distortion)."""
        types = typestore().types
        intr = intrinsics
        k = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], dtype=np.float64)
        p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0],
                     dtype=np.float64)
        roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                        width=0, do_rectify=False)
        msg = types[CAMERA_INFO_TYPE](
            header=stamped_header(stamp_ns, frame_id), height=int(intr.height),
            width=int(intr.width), distortion_model="plumb_bob", d=np.zeros(5), k=k,
            r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0, roi=roi)
        self._write(topic, CAMERA_INFO_TYPE, msg, stamp_ns if log_ns is None else log_ns)

    def add_pose(self, topic: str, stamp_ns: int, frame_id: str, pose: np.ndarray,
                 log_ns: int | None = None) -> None:
        """A (4, 4) camera-to-world transform (metres) as ``geometry_msgs/msg/PoseStamped``
        in ``frame_id`` (the world frame)."""
        from scipy.spatial.transform import Rotation

        from deltar.io.pose_file import check_pose

        matrix = check_pose(pose, "pose")
        types = typestore().types
        x, y, z = (float(v) for v in matrix[:3, 3])
        qx, qy, qz, qw = (float(v) for v in Rotation.from_matrix(matrix[:3, :3]).as_quat())
        msg = types[POSE_MSGTYPE](
            header=stamped_header(stamp_ns, frame_id),
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))
        self._write(topic, POSE_MSGTYPE, msg, stamp_ns if log_ns is None else log_ns)

    def add_point_cloud(self, topic: str, stamp_ns: int, frame_id: str, points: np.ndarray,
                        colors: np.ndarray, log_ns: int | None = None) -> None:
        """(N, 3) float32 metres + (N, 3) uint8 RGB as ``PointCloud2`` (x y z rgb).

        ``rgb`` is the PCL convention: 0x00RRGGBB stored in the bytes of a float32.
        """
        types = typestore().types
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        rgb = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        if pts.shape[0] != rgb.shape[0]:
            raise ValueError(f"{pts.shape[0]} points but {rgb.shape[0]} colours")
        record = np.zeros(pts.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                               ("rgb", "<u4")])
        record["x"], record["y"], record["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
        record["rgb"] = (rgb[:, 0].astype(np.uint32) << 16) | \
            (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2].astype(np.uint32)
        field = types["sensor_msgs/msg/PointField"]
        fields = [field(name=name, offset=4 * i, datatype=field.FLOAT32, count=1)
                  for i, name in enumerate(("x", "y", "z", "rgb"))]
        msg = types["sensor_msgs/msg/PointCloud2"](
            header=stamped_header(stamp_ns, frame_id), height=1, width=pts.shape[0], fields=fields,
            is_bigendian=False, point_step=16, row_step=16 * pts.shape[0],
            data=record.view(np.uint8).reshape(-1), is_dense=True)
        self._write(topic, "sensor_msgs/msg/PointCloud2", msg,
                    stamp_ns if log_ns is None else log_ns)

    def add_zone_frame(self, topic: str, stamp_ns: int, frame_id: str, frame: ZoneFrame,
                       log_ns: int | None = None) -> None:
        """A :class:`ZoneFrame` as ``deltar_msgs/msg/ZoneFrame``, or, when it holds several
        targets per zone (``frame.target_mean_m``), as
        ``deltar_msgs/msg/MultiTargetZoneFrame`` (the same fields and every target).

        A topic carries one type: the first frame written to it decides. On a
        ``MultiTargetZoneFrame`` topic, frames without target arrays are written with
        T = 1 (their primary reading); a frame with targets on a ``ZoneFrame`` topic is
        an error.

        A frame's no-target flags are written as status 255; a frame without status
        codes (e.g. a simulated one) gets 5 (valid), 255 (no target) and 0 (anything
        else), so that the flags survive the message.

        Raises:
            ValueError: a frame with targets for a topic that carries ``ZoneFrame``, or
                one a reader would refuse (:func:`deltar.io.zone_file.check_writable`).
        """
        check_writable(frame)
        mean, sigma, valid = frame.flat()
        empty = np.zeros(0, dtype=np.float32)
        status = frame.status
        if frame.no_target is not None:
            flags = frame.flat_no_target()
            codes = np.where(valid, 5, 0) if status is None else status.reshape(-1)
            # Flags from elsewhere (e.g. a CNH reading's target count) become status 255.
            status = np.where(flags, NO_TARGET_STATUS, codes)
        msg = typestore().types[ZONE_FRAME_MSGTYPE](
            header=stamped_header(stamp_ns, frame_id), sensor_model=frame.sensor_model,
            zone_count=frame.zone_count,
            distance_m=np.where(valid, mean, np.nan).astype(np.float32),
            sigma_m=np.where(valid, sigma, 0.0).astype(np.float32),
            status=(np.zeros(0, np.uint8) if status is None
                    else status.reshape(-1).astype(np.uint8)),
            valid=valid.astype(bool),
            hist_edges_m=empty if frame.hist_edges_m is None else
            frame.hist_edges_m.astype(np.float32),
            hist_counts=empty if frame.hist_counts is None else
            frame.hist_counts.reshape(-1).astype(np.float32))
        connection = self._connections.get(topic)
        multi = frame.target_mean_m is not None if connection is None else \
            connection.msgtype == MULTI_TARGET_ZONE_FRAME_MSGTYPE
        if multi:
            msgtype = MULTI_TARGET_ZONE_FRAME_MSGTYPE
            msg = _with_targets(msg, frame)
        elif frame.target_mean_m is not None:
            raise ValueError(f"topic {topic} carries {ZONE_FRAME_MSGTYPE} (one target per "
                             "zone) but this frame holds several targets per zone; write "
                             "multi-target frames to their own topic")
        else:
            msgtype = ZONE_FRAME_MSGTYPE
        self._write(topic, msgtype, msg, stamp_ns if log_ns is None else log_ns)


def _with_targets(msg: Any, frame: ZoneFrame) -> Any:
    """A ``MultiTargetZoneFrame`` with ``msg``'s fields and every target of ``frame``.

    Targets that are not valid are written as NaN; target statuses as for the primary
    status (no-target flags of target 0 as 255; 5 / 0 when the frame has no codes);
    ``target_signal`` empty when the frame has no signals.
    """
    mean, sigma, valid = frame.flat_targets()
    status = frame.target_status
    if status is None:
        status = np.where(valid, 5, 0).astype(np.uint8)
        if frame.no_target is not None:
            status[:, 0] = np.where(frame.flat_no_target(), NO_TARGET_STATUS, status[:, 0])
    fields = {name: getattr(msg, name) for name in
              ("header", "sensor_model", "zone_count", "distance_m", "sigma_m", "status",
               "valid", "hist_edges_m", "hist_counts")}
    return typestore().types[MULTI_TARGET_ZONE_FRAME_MSGTYPE](
        **fields, targets_per_zone=frame.targets_per_zone, target_order=frame.target_order,
        target_distance_m=np.where(valid, mean, np.nan).reshape(-1).astype(np.float32),
        target_sigma_m=np.where(valid, sigma, 0.0).reshape(-1).astype(np.float32),
        target_status=np.asarray(status, dtype=np.uint8).reshape(-1),
        target_valid=valid.reshape(-1).astype(bool),
        target_signal=np.zeros(0, np.float32) if frame.target_signal is None else
        frame.target_signal.reshape(-1).astype(np.float32))


class BagRecordingWriter:
    """The recording writer of ``deltar record --bag``: a rig's frames as a ROS 2 bag.

    Same methods as :class:`deltar.io.recording.RecordingWriter`; writes the topics of
    :data:`RECORD_TOPICS`: colour images (``rgb8``) each with a ``CameraInfo``,
    reference depth (``32FC1``, metres, NaN = invalid), zone frames
    (``deltar_msgs/msg/ZoneFrame``, or ``MultiTargetZoneFrame`` with every target and its
    signal when the first frame holds several targets per zone) and camera poses
    (``PoseStamped`` in ``world``). Stamps are the capture times; the bag is complete
    when :meth:`close` is called.

    Args:
        path: the bag folder to create (must not exist).
        meta: the rig's camera intrinsics and sensor (``RecordingMeta``).
        storage: ``"sqlite3"`` or ``"mcap"``.
    """

    def __init__(self, path: str | os.PathLike, meta: Any, storage: str = "sqlite3") -> None:
        self.meta = meta
        self.writer = BagWriter(path, storage=storage)

    @staticmethod
    def _ns(timestamp_s: float) -> int:
        if not (np.isfinite(timestamp_s) and timestamp_s >= 0):
            raise ValueError(f"ROS stamps need a time >= 0 s, got {timestamp_s}")
        return round(float(timestamp_s) * 1e9)

    def add_color(self, timestamp_s: float, image_rgb: np.ndarray) -> None:
        """An (H, W, 3) uint8 RGB image of the camera size, with its CameraInfo."""
        intr = self.meta.intrinsics
        image = check_image(image_rgb, "image_rgb", (intr.height, intr.width))
        stamp, frame_id = self._ns(timestamp_s), RECORD_FRAME_IDS["camera"]
        self.writer.add_rgb_image(RECORD_TOPICS["image"], stamp, frame_id, image)
        self.writer.add_camera_info(RECORD_TOPICS["camera_info"], stamp, frame_id, intr)

    def add_depth(self, timestamp_s: float, depth_m: np.ndarray) -> None:
        """An (H, W) reference depth map in metres (0 = invalid)."""
        self.writer.add_metric_image(RECORD_TOPICS["depth"], self._ns(timestamp_s),
                                     RECORD_FRAME_IDS["camera"], depth_m)

    def add_zone_frame(self, frame: ZoneFrame) -> None:
        """A zone frame; its ``timestamp_s`` is the stamp."""
        if frame.timestamp_s is None:
            raise ValueError("frame.timestamp_s is required in a recording")
        self.writer.add_zone_frame(RECORD_TOPICS["zones"], self._ns(frame.timestamp_s),
                                   RECORD_FRAME_IDS["tof"], frame)

    def add_pose(self, timestamp_s: float, pose: np.ndarray) -> None:
        """The colour camera's (4, 4) camera-to-world pose (metres) at ``timestamp_s``."""
        self.writer.add_pose(RECORD_TOPICS["pose"], self._ns(timestamp_s),
                             RECORD_FRAME_IDS["world"], pose)

    def close(self) -> None:
        """Finish the bag and move it to its path; a bag without a message (stopped before
        the first capture was written) is not kept: it would only block a new recording
        to the same path."""
        self.writer.close(keep=self.writer.messages > 0)
