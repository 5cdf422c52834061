"""ROS 2 bags in and out, with the pure-Python ``rosbags`` library (no ROS install).

Reading (:class:`BagInput`): a camera topic (``sensor_msgs/msg/Image`` in ``rgb8`` or
``bgr8``, or ``sensor_msgs/msg/CompressedImage``), its ``sensor_msgs/msg/CameraInfo``
and a ToF topic, either this package's ``deltar_msgs/msg/ZoneFrame``
(``msg/ZoneFrame.msg`` beside this module) or the ``sensor_msgs/msg/Image`` (32FC1,
4x4 or 8x8, metres, NaN = invalid) that the ``vl53l5cx_ros2`` driver node
(github.com/skhbk/vl53l5cx_ros2) publishes. Zone frames are paired with the image
nearest in header stamp.

Writing (:class:`BagWriter`): depth and uncertainty as ``sensor_msgs/msg/Image``
``32FC1`` in metres with NaN where invalid (REP 118), ``CameraInfo``, coloured
``PointCloud2`` (x, y, z float32 + rgb packed in a float32), camera images and zone
frames, into a new bag (sqlite3 or mcap storage). The bag is written into a hidden
folder beside its destination and renamed when complete, so a bag is either whole or
absent; an existing path is never written into.

All times are integer nanoseconds (``header.stamp``) unless named ``_s`` (seconds).
"""

from __future__ import annotations

import functools
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.io.recording import nearest_in_time
from deltar.sensor.zone_frame import (
    DEFAULT_VALID_STATUS,
    NO_TARGET_STATUS,
    Orientation,
    ZoneFrame,
)

#: The ToF message type shipped with the package.
ZONE_FRAME_MSGTYPE = "deltar_msgs/msg/ZoneFrame"
#: Where its definition lives (package data).
ZONE_FRAME_MSG_PATH = Path(__file__).with_name("msg") / "ZoneFrame.msg"
#: ToF topic formats :class:`BagInput` reads.
TOF_FORMATS: tuple[str, ...] = ("deltar", "vl53l5cx_ros2")
#: Storage plugins :class:`BagWriter` writes.
STORAGES: tuple[str, ...] = ("sqlite3", "mcap")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: Topics ``deltar record --bag`` writes (and :class:`BagInput` finds by type).
RECORD_TOPICS = {"image": "/camera/color/image_raw",
                 "camera_info": "/camera/color/camera_info",
                 "depth": "/camera/depth/image", "zones": "/tof/zones"}
#: Frame ids of recorded messages.
RECORD_FRAME_IDS = {"camera": "camera_color_optical_frame", "tof": "tof_sensor"}
#: Output topics of ``deltar replay --out-bag`` below its prefix (default ``/deltar``).
OUTPUT_TOPICS = {"depth": "depth", "uncertainty": "uncertainty",
                 "camera_info": "camera_info", "points": "points"}
_EXTRA_HINT = 'ROS 2 bag support needs the "ros" extra: pip install "deltar[ros]"'


def require_rosbags() -> Any:
    """Import ``rosbags`` or raise ``ImportError`` naming the extra to install."""
    try:
        import rosbags.rosbag2
        import rosbags.typesys
    except ImportError as err:
        raise ImportError(f"{_EXTRA_HINT} ({err})") from err
    return rosbags


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """The ROS 2 Humble type store with ``deltar_msgs/msg/ZoneFrame`` registered."""
    require_rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(ZONE_FRAME_MSG_PATH.read_text(encoding="utf-8"),
                                      ZONE_FRAME_MSGTYPE))
    return store


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/msg/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _header(stamp_ns: int, frame_id: str) -> Any:
    types = typestore().types
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](
        sec=sec, nanosec=nanosec), frame_id=frame_id)


# ---------------------------------------------------------------------- messages -> numpy
def image_from_msg(msg: Any, msgtype: str, source: str = "image") -> np.ndarray:
    """Decode a camera message to (H, W, 3) uint8 RGB.

    Args:
        msg: a deserialised ``sensor_msgs/msg/Image`` (``rgb8`` or ``bgr8``) or
            ``sensor_msgs/msg/CompressedImage`` (JPEG, PNG...).
        msgtype: its type name.
        source: name used in error messages (e.g. the topic).

    Raises:
        ValueError: another encoding, a truncated buffer or an undecodable image.
    """
    import cv2

    if msgtype == "sensor_msgs/msg/CompressedImage":
        decoded = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if decoded is None:
            raise ValueError(f"{source}: cannot decode the compressed image "
                             f"(format {msg.format!r})")
        return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
    encoding = str(msg.encoding).lower()
    if encoding not in ("rgb8", "bgr8"):
        raise ValueError(f"{source}: image encoding {msg.encoding!r} is not supported; "
                         "expected rgb8 or bgr8 (or a CompressedImage)")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < 3 * width or data.size < step * height:
        raise ValueError(f"{source}: image data has {data.size} bytes, expected "
                         f"{height} rows of step {step} >= {3 * width}")
    rgb = data[:step * height].reshape(height, step)[:, :3 * width].reshape(height, width, 3)
    return np.ascontiguousarray(rgb[..., ::-1] if encoding == "bgr8" else rgb)


def intrinsics_from_camera_info(msg: Any, image_size: tuple[int, int] | None = None,
                                source: str = "camera_info") -> CameraIntrinsics:
    """Camera intrinsics (pixels) from a ``sensor_msgs/msg/CameraInfo``'s K matrix.

    Args:
        msg: the message.
        image_size: (height, width) of the images, used when the message leaves them 0.
        source: name used in error messages.

    Raises:
        ValueError: a K without positive focal lengths, or a size that differs from
            ``image_size``.
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9 or not np.all(np.isfinite(k)) or k[0] <= 0 or k[4] <= 0:
        raise ValueError(f"{source}: K must hold positive focal lengths, got {k.tolist()}")
    height, width = int(msg.height), int(msg.width)
    if (height, width) == (0, 0) and image_size is not None:
        height, width = image_size
    if image_size is not None and (height, width) != tuple(image_size):
        raise ValueError(f"{source} is for {height}x{width} images, the camera topic has "
                         f"{image_size[0]}x{image_size[1]}")
    if np.any(np.asarray(msg.d, dtype=np.float64) != 0):
        warnings.warn(f"{source}: lens distortion ({msg.distortion_model}) is not "
                      "corrected; zones are placed with the pinhole model", stacklevel=2)
    return CameraIntrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]), width, height)


def zone_frame_from_msg(msg: Any, source: str = "zones",
                        valid_status: tuple[int, ...] = DEFAULT_VALID_STATUS) -> ZoneFrame:
    """A :class:`ZoneFrame` from a ``deltar_msgs/msg/ZoneFrame`` (see its ``.msg``).

    Raises:
        ValueError: lengths that do not match ``zone_count``, naming the field.
    """
    count = int(msg.zone_count)
    distance = np.asarray(msg.distance_m, dtype=np.float64)
    if distance.size != count or count not in (16, 64):
        raise ValueError(f"{source}: zone_count is {count} and distance_m has "
                         f"{distance.size} entries; expected 16 or 64 of each")
    arrays = {}
    for name in ("sigma_m", "status", "valid"):
        values = np.asarray(getattr(msg, name))
        if values.size not in (0, count):
            raise ValueError(f"{source}: {name} has {values.size} entries; expected "
                             f"{count} or none")
        arrays[name] = values if values.size else None
    ok = np.isfinite(distance) & (distance > 0)
    status = None if arrays["status"] is None else arrays["status"].astype(np.uint8)
    if arrays["valid"] is not None:
        valid = arrays["valid"].astype(bool) & ok
    elif status is not None:
        valid = ok & np.isin(status, np.asarray(valid_status, dtype=np.uint8))
    else:
        valid = ok
    sigma = np.zeros(count) if arrays["sigma_m"] is None else \
        arrays["sigma_m"].astype(np.float64)
    valid &= np.isfinite(sigma) & (sigma >= 0)
    edges = np.asarray(msg.hist_edges_m, dtype=np.float64)
    counts = np.asarray(msg.hist_counts, dtype=np.float64)
    hist = {}
    if edges.size or counts.size:
        bins = edges.size - 1
        if bins < 1 or counts.size != count * bins:
            raise ValueError(f"{source}: hist_counts has {counts.size} values, expected "
                             f"zone_count x {max(bins, 0)} bins from hist_edges_m")
        hist = {"hist_edges_m": edges, "hist_counts": counts.reshape(count, bins)}
    try:
        return ZoneFrame(mean_m=np.where(valid, distance, 0.0),
                         sigma_m=np.where(valid, sigma, 0.0), valid=valid, status=status,
                         timestamp_s=stamp_to_ns(msg.header.stamp) / 1e9,
                         sensor_model=str(msg.sensor_model) or "VL53L5CX", **hist)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from err


def zone_frame_from_vl53l5cx_ros2(msg: Any, *, orientation: Orientation | None = None,
                                  sigma_m: float = 0.0, source: str = "zones") -> ZoneFrame:
    """A :class:`ZoneFrame` from the ``vl53l5cx_ros2`` driver node's distance image.

    That node (github.com/skhbk/vl53l5cx_ros2) publishes ``~/x<ADDRESS>/image`` as a
    ``sensor_msgs/msg/Image`` of encoding ``32FC1``, ``resolution`` x ``resolution``
    (4 or 8) metres in ST's zone order, NaN in zones whose status is not in its
    ``valid_status`` parameter (when that parameter is set; otherwise every zone's
    distance is published). It publishes no sigma and no status.

    Args:
        msg: the deserialised image message.
        orientation: how ST's zone order maps onto the camera image (identity when
            None; ``deltar.capture.drivers`` uses ``Orientation(flip_ud=True)`` for
            the same ULD order).
        sigma_m: sigma given to every valid zone, metres (the node does not publish one;
            0 puts all depth hypotheses at the distance).
        source: name used in error messages.

    Raises:
        ValueError: another encoding or size.
    """
    if str(msg.encoding) != "32FC1" or int(msg.height) != int(msg.width) or \
            int(msg.width) not in (4, 8):
        raise ValueError(f"{source}: expected a 4x4 or 8x8 32FC1 distance image, got "
                         f"{msg.width}x{msg.height} {msg.encoding!r}")
    n = int(msg.width)
    dtype = ">f4" if msg.is_bigendian else "<f4"
    data = np.asarray(msg.data, dtype=np.uint8)
    if int(msg.step) != 4 * n or data.size != 4 * n * n:
        raise ValueError(f"{source}: expected {4 * n * n} bytes of data, got {data.size}")
    distance = data.view(dtype).astype(np.float64).reshape(n, n)
    if not (np.isfinite(sigma_m) and sigma_m >= 0):
        raise ValueError(f"sigma_m must be >= 0 metres, got {sigma_m}")
    orient = orientation or Orientation()
    distance = orient.apply(distance)
    valid = np.isfinite(distance) & (distance > 0)
    return ZoneFrame(mean_m=np.where(valid, distance, 0.0),
                     sigma_m=np.where(valid, sigma_m, 0.0), valid=valid,
                     timestamp_s=stamp_to_ns(msg.header.stamp) / 1e9, sensor_model="VL53L5CX")


# ---------------------------------------------------------------------- reading a bag
def _namespace(topic: str) -> str:
    """``/camera/color/image_raw`` -> ``/camera/color``."""
    return topic.rsplit("/", 1)[0]


@dataclass
class BagPair:
    """A ToF frame with the camera image nearest in header stamp.

    Attributes:
        zone_frame: the reading (``timestamp_s`` = its header stamp in seconds).
        image_index: position of the image among the camera topic's messages.
        image_stamp_ns: the image's header stamp.
        image_log_ns: the image's time in the bag (when it was recorded).
        frame_id: the image's ``header.frame_id``.
        intrinsics: from the CameraInfo nearest the image (None without one).
        offset_s: image stamp minus ToF stamp, seconds.
    """

    zone_frame: ZoneFrame
    image_index: int
    image_stamp_ns: int
    image_log_ns: int
    frame_id: str
    intrinsics: CameraIntrinsics | None
    offset_s: float


class BagInput:
    """A ROS 2 bag with a camera, its CameraInfo and a ToF topic.

    Topics not given are found by type when exactly one topic has it (camera: Image
    or CompressedImage; ToF: ``deltar_msgs/msg/ZoneFrame``), or, among several, the one
    image topic with a CameraInfo beside it (same namespace, the ROS convention) and
    the CameraInfo beside the image; with ``tof_format="vl53l5cx_ros2"`` the ToF topic
    must be named.

    Args:
        path: the bag folder (``metadata.yaml`` and its ``.db3`` / ``.mcap`` files).
        image_topic, info_topic, tof_topic: topic names (auto-detected when None).
        tof_format: ``"deltar"`` or ``"vl53l5cx_ros2"`` (see :data:`TOF_FORMATS`).
        tof_orientation: for ``vl53l5cx_ros2`` only, the zone grid's orientation.
        tof_sigma_m: for ``vl53l5cx_ros2`` only, the sigma given to its zones.

    Raises:
        FileNotFoundError: no bag at ``path``.
        ValueError: an unreadable bag, a missing topic or one of the wrong type, or
            several candidates (the message lists the topics and how to choose).
    """

    def __init__(self, path: str | os.PathLike, *, image_topic: str | None = None,
                 info_topic: str | None = None, tof_topic: str | None = None,
                 tof_format: str = "deltar", tof_orientation: Orientation | None = None,
                 tof_sigma_m: float = 0.0) -> None:
        require_rosbags()
        from rosbags.rosbag2 import Reader

        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"ROS 2 bag not found: {self.path}")
        if tof_format not in TOF_FORMATS:
            raise ValueError(f"tof_format must be one of {TOF_FORMATS}, got {tof_format!r}")
        try:
            with Reader(self.path) as reader:
                self.topics = {c.topic: c.msgtype for c in reader.connections}
        except Exception as err:  # rosbags raises its own error types for bad bags
            raise ValueError(f"{self.path}: not a readable ROS 2 bag: {err}") from err
        self.tof_format = tof_format
        self.tof_orientation = tof_orientation
        self.tof_sigma_m = float(tof_sigma_m)
        tof_types = (ZONE_FRAME_MSGTYPE,) if tof_format == "deltar" else \
            ("sensor_msgs/msg/Image",)
        if tof_format == "vl53l5cx_ros2" and tof_topic is None:
            raise ValueError("the vl53l5cx_ros2 format needs the ToF topic named "
                             "(--tof-topic, e.g. /vl53l5cx/x29/image)")
        self.tof_topic = self._pick(tof_topic, tof_types, "ToF", "--tof-topic")
        self.image_topic = self._pick(image_topic, IMAGE_TYPES, "camera", "--image-topic",
                                      exclude=self.tof_topic)
        if self.tof_topic == self.image_topic:
            raise ValueError(f"{self.path}: camera and ToF topic are both {self.tof_topic}")
        self.info_topic = self._pick(info_topic, (CAMERA_INFO_TYPE,), "CameraInfo",
                                     "--info-topic", required=False)

    def _pick(self, topic: str | None, types: tuple[str, ...], what: str, option: str,
              required: bool = True, exclude: str | None = None) -> str | None:
        """The given topic (checked) or the only topic of one of ``types``."""
        listing = ", ".join(f"{t} ({m})" for t, m in sorted(self.topics.items())) or "none"
        if topic is not None:
            if topic not in self.topics:
                raise ValueError(f"{self.path}: no topic {topic!r} ({option}); topics: "
                                 f"{listing}")
            if self.topics[topic] not in types:
                raise ValueError(f"{self.path}: topic {topic} is {self.topics[topic]}, "
                                 f"expected {' or '.join(types)} ({option})")
            return topic
        found = sorted(t for t, m in self.topics.items() if m in types and t != exclude)
        if len(found) > 1:
            # ROS convention: a camera's CameraInfo sits beside its image topic.
            beside = [t for t in found if _namespace(t) in self._info_namespaces(what)]
            found = beside if len(beside) == 1 else found
        if not found:
            if not required:
                return None
            raise ValueError(f"{self.path}: no {what} topic ({' or '.join(types)}); topics: "
                             f"{listing}")
        if len(found) > 1:
            raise ValueError(f"{self.path}: several {what} topics {found}; choose one with "
                             f"{option}")
        return found[0]

    def _info_namespaces(self, what: str) -> set[str]:
        """Namespaces that the topic being picked should share with its partner."""
        if what == "camera":
            return {_namespace(t) for t, m in self.topics.items() if m == CAMERA_INFO_TYPE}
        if what == "CameraInfo":
            return {_namespace(self.image_topic)}
        return set()

    def _deserialize(self, rawdata: bytes, msgtype: str, topic: str) -> Any:
        try:
            return typestore().deserialize_cdr(rawdata, msgtype)
        except Exception as err:  # corrupt message bytes
            raise ValueError(f"{self.path}: corrupt {msgtype} message on {topic}: {err}") \
                from err

    def _zone_frame(self, msg: Any) -> ZoneFrame:
        if self.tof_format == "deltar":
            return zone_frame_from_msg(msg, source=self.tof_topic)
        return zone_frame_from_vl53l5cx_ros2(msg, orientation=self.tof_orientation,
                                             sigma_m=self.tof_sigma_m, source=self.tof_topic)

    def pairs(self, tolerance_s: float = 0.02) -> list[BagPair]:
        """Pair every ToF frame with the camera image nearest in header stamp.

        ToF frames without an image within ``tolerance_s`` are skipped with one warning;
        camera images are not decoded here.

        Raises:
            ValueError: no ToF message, no camera message, or no pair at all (the message
                gives both stamp ranges).
        """
        from rosbags.rosbag2 import Reader

        if not tolerance_s >= 0:
            raise ValueError(f"tolerance_s must be >= 0, got {tolerance_s}")
        images: list[tuple[int, int, str, tuple[int, int]]] = []  # stamp, log, frame, size
        infos: list[tuple[int, Any]] = []
        frames: list[ZoneFrame] = []
        with Reader(self.path) as reader:
            wanted = [c for c in reader.connections
                      if c.topic in (self.image_topic, self.tof_topic, self.info_topic)]
            for connection, log_ns, raw in reader.messages(connections=wanted):
                msg = self._deserialize(raw, connection.msgtype, connection.topic)
                stamp = stamp_to_ns(msg.header.stamp)
                if connection.topic == self.image_topic:
                    size = (int(getattr(msg, "height", 0)), int(getattr(msg, "width", 0)))
                    images.append((stamp, int(log_ns), str(msg.header.frame_id), size))
                elif connection.topic == self.tof_topic:
                    frames.append(self._zone_frame(msg))
                else:
                    infos.append((stamp, msg))
        if not frames:
            raise ValueError(f"{self.path}: the ToF topic {self.tof_topic} has no messages")
        if not images:
            raise ValueError(f"{self.path}: the camera topic {self.image_topic} has no "
                             "messages")
        order = np.argsort([i[0] for i in images], kind="stable")
        image_times = np.array([images[i][0] for i in order], dtype=np.float64) / 1e9
        info_order = sorted(range(len(infos)), key=lambda i: infos[i][0])
        info_times = np.array([infos[i][0] for i in info_order], dtype=np.float64) / 1e9
        tof_times = np.array([f.timestamp_s for f in frames], dtype=np.float64)
        nearest, gap = nearest_in_time(image_times, tof_times)
        out: list[BagPair] = []
        for frame, idx, distance in zip(frames, nearest, gap, strict=True):
            if distance > tolerance_s:
                continue
            index = int(order[idx])
            stamp, log_ns, frame_id, size = images[index]
            intrinsics = None
            if infos:
                info_idx, _ = nearest_in_time(info_times, np.array([stamp / 1e9]))
                info = infos[info_order[int(info_idx[0])]][1]
                intrinsics = intrinsics_from_camera_info(
                    info, size if size[0] else None, source=self.info_topic)
            out.append(BagPair(frame, index, stamp, log_ns, frame_id, intrinsics,
                               stamp / 1e9 - float(frame.timestamp_s)))
        if not out:
            raise ValueError(
                f"{self.path}: no ToF message on {self.tof_topic} has a camera image within "
                f"{tolerance_s} s (ToF stamps {tof_times.min():.3f}..{tof_times.max():.3f} s, "
                f"images {image_times.min():.3f}..{image_times.max():.3f} s); check the "
                "header stamps or raise --tolerance")
        if len(out) < len(frames):
            warnings.warn(f"{self.path}: skipped {len(frames) - len(out)} of {len(frames)} ToF "
                          f"frames with no camera image within {tolerance_s} s", stacklevel=2)
        return out

    def images(self, pairs: list[BagPair]) -> Iterator[tuple[BagPair, np.ndarray]]:
        """Decode the camera images of ``pairs`` in bag order: (pair, (H, W, 3) uint8 RGB).

        A pair's image is decoded once even if several pairs share it.
        """
        from rosbags.rosbag2 import Reader

        by_index: dict[int, list[BagPair]] = {}
        for pair in pairs:
            by_index.setdefault(pair.image_index, []).append(pair)
        with Reader(self.path) as reader:
            wanted = [c for c in reader.connections if c.topic == self.image_topic]
            for index, (connection, _, raw) in enumerate(reader.messages(connections=wanted)):
                if index not in by_index:
                    continue
                msg = self._deserialize(raw, connection.msgtype, connection.topic)
                rgb = image_from_msg(msg, connection.msgtype, source=self.image_topic)
                for pair in by_index[index]:
                    yield pair, rgb


# ---------------------------------------------------------------------- writing a bag
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
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._staging = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial",
                                              dir=self.path.parent))
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        self._writer = Writer(self._staging / self.path.name, version=8,
                              storage_plugin=plugin)
        self._writer.open()
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
        self._writer.close()
        try:
            if keep:
                if self.path.exists():
                    raise FileExistsError(f"refusing to replace {self.path}, which appeared "
                                          "while writing")
                os.rename(self._staging / self.path.name, self.path)
                return self.path
            return None
        finally:
            shutil.rmtree(self._staging, ignore_errors=True)

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
        image = np.ascontiguousarray(rgb, dtype=np.uint8)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"rgb must be (H, W, 3) uint8, got {image.shape}")
        height, width = image.shape[:2]
        msg = typestore().types["sensor_msgs/msg/Image"](
            header=_header(stamp_ns, frame_id), height=height, width=width, encoding="rgb8",
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
            header=_header(stamp_ns, frame_id), height=height, width=width, encoding="32FC1",
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
            header=_header(stamp_ns, frame_id), height=int(intr.height), width=int(intr.width),
            distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).reshape(-1), p=p,
            binning_x=0, binning_y=0, roi=roi)
        self._write(topic, CAMERA_INFO_TYPE, msg, stamp_ns if log_ns is None else log_ns)

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
            header=_header(stamp_ns, frame_id), height=1, width=pts.shape[0], fields=fields,
            is_bigendian=False, point_step=16, row_step=16 * pts.shape[0],
            data=record.view(np.uint8).reshape(-1), is_dense=True)
        self._write(topic, "sensor_msgs/msg/PointCloud2", msg,
                    stamp_ns if log_ns is None else log_ns)

    def add_zone_frame(self, topic: str, stamp_ns: int, frame_id: str, frame: ZoneFrame,
                       log_ns: int | None = None) -> None:
        """A :class:`ZoneFrame` as ``deltar_msgs/msg/ZoneFrame``.

        A frame's no-target flags are written as status 255; a frame without status
        codes (e.g. a simulated one) gets 5 (valid), 255 (no target) and 0 (anything
        else), so that the flags survive the message.
        """
        mean, sigma, valid = frame.flat()
        empty = np.zeros(0, dtype=np.float32)
        status = frame.status
        if frame.no_target is not None:
            flags = frame.flat_no_target()
            codes = np.where(valid, 5, 0) if status is None else status.reshape(-1)
            # Flags from elsewhere (e.g. a CNH reading's target count) become status 255.
            status = np.where(flags, NO_TARGET_STATUS, codes)
        msg = typestore().types[ZONE_FRAME_MSGTYPE](
            header=_header(stamp_ns, frame_id), sensor_model=frame.sensor_model,
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
        self._write(topic, ZONE_FRAME_MSGTYPE, msg, stamp_ns if log_ns is None else log_ns)


def read_messages(path: str | os.PathLike, topic: str) -> list[tuple[int, Any]]:
    """All messages of one topic as (bag time ns, deserialised message), in bag order.

    Raises:
        ValueError: the bag has no such topic.
    """
    require_rosbags()
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as reader:
        wanted = [c for c in reader.connections if c.topic == topic]
        if not wanted:
            raise ValueError(f"{path}: no topic {topic!r}; topics: "
                             f"{sorted(c.topic for c in reader.connections)}")
        return [(int(log_ns), typestore().deserialize_cdr(raw, conn.msgtype))
                for conn, log_ns, raw in reader.messages(connections=wanted)]


def metric_image_from_msg(msg: Any, source: str = "image") -> np.ndarray:
    """(H, W) float32 metres from a ``32FC1`` ``sensor_msgs/msg/Image`` (NaN kept)."""
    if str(msg.encoding) != "32FC1":
        raise ValueError(f"{source}: expected encoding 32FC1, got {msg.encoding!r}")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < 4 * width or data.size < step * height:
        raise ValueError(f"{source}: image data has {data.size} bytes, expected "
                         f"{height} rows of step {step}")
    rows = data[:step * height].reshape(height, step)[:, :4 * width]
    return rows.copy().view(">f4" if msg.is_bigendian else "<f4").reshape(height, width) \
        .astype(np.float32)


class BagRecordingWriter:
    """The recording writer of ``deltar record --bag``: a rig's frames as a ROS 2 bag.

    Same methods as :class:`deltar.io.recording.RecordingWriter`; writes the topics of
    :data:`RECORD_TOPICS`: colour images (``rgb8``) each with a ``CameraInfo``,
    reference depth (``32FC1``, metres, NaN = invalid) and zone frames
    (``deltar_msgs/msg/ZoneFrame``). Stamps are the capture times; the bag is complete
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
        image = np.asarray(image_rgb)
        if image.dtype != np.uint8 or image.shape != (intr.height, intr.width, 3):
            raise ValueError(f"image_rgb must be {(intr.height, intr.width, 3)} uint8, got "
                             f"{image.shape} {image.dtype}")
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

    def close(self) -> None:
        """Finish the bag and move it to its path."""
        self.writer.close()
