"""Reading ROS 2 bags: :class:`BagInput` pairs a camera topic with a ToF topic.

A camera topic (``sensor_msgs/msg/Image`` in ``rgb8`` or ``bgr8``, or
``sensor_msgs/msg/CompressedImage``), its ``sensor_msgs/msg/CameraInfo`` and a ToF
topic, either this package's ``deltar_msgs/msg/ZoneFrame`` (``msg/ZoneFrame.msg``; or
``deltar_msgs/msg/MultiTargetZoneFrame`` with several targets per zone) or the
``sensor_msgs/msg/Image`` (32FC1, 4x4 or 8x8, metres, NaN = invalid) that the
``vl53l5cx_ros2`` driver node (github.com/skhbk/vl53l5cx_ros2) publishes. Zone frames
are paired with the image nearest in header stamp; a depth topic (``32FC1`` metres or
``16UC1`` millimetres, registered to the camera) can be read beside the images. The
messages are decoded by :mod:`deltar.io.ros_messages`.

All times are integer nanoseconds (``header.stamp``) unless named ``_s`` (seconds).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.io.pairing import one_per_image
from deltar.io.recording import nearest_in_time
from deltar.io.ros_messages import (
    CAMERA_INFO_TYPE,
    IMAGE_TYPES,
    ZONE_FRAME_MSGTYPES,
    deserialize,
    image_from_msg,
    intrinsics_from_camera_info,
    metric_image_from_msg,
    require_rosbags,
    stamp_to_ns,
    zone_frame_from_msg,
    zone_frame_from_vl53l5cx_ros2,
)
from deltar.io.rosbag_writer import RECORD_TOPICS
from deltar.sensor.zone_frame import Orientation, ZoneFrame

#: ToF topic formats :class:`BagInput` reads.
TOF_FORMATS: tuple[str, ...] = ("deltar", "vl53l5cx_ros2")
#: The depth topic :class:`BagInput` reads when told to find one (``deltar record --bag``'s).
DEFAULT_DEPTH_TOPIC = RECORD_TOPICS["depth"]
#: ``BagInput(depth_topic=AUTO_DEPTH_TOPIC)``: read :data:`DEFAULT_DEPTH_TOPIC` if present
#: (``deltar map --method recorded`` passes it when no ``--depth-topic`` is given).
AUTO_DEPTH_TOPIC = "auto"


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
        offset_s: image stamp minus ToF stamp, seconds (including any time offset the
            pairing applied).
        tof_stamp_ns: the ToF message's header stamp (exact; ``zone_frame.timestamp_s``
            holds it in float seconds).
    """

    zone_frame: ZoneFrame
    image_index: int
    image_stamp_ns: int
    image_log_ns: int
    frame_id: str
    intrinsics: CameraIntrinsics | None
    offset_s: float
    tof_stamp_ns: int = 0


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
        depth_topic: a depth ``Image`` topic registered to the camera
            (:meth:`images_with_depth`); :data:`AUTO_DEPTH_TOPIC`:
            :data:`DEFAULT_DEPTH_TOPIC` when the bag has it; None: no depth.

    Raises:
        FileNotFoundError: no bag at ``path``.
        ValueError: an unreadable bag, a missing topic or one of the wrong type, or
            several candidates (the message lists the topics and how to choose).
    """

    def __init__(self, path: str | os.PathLike, *, image_topic: str | None = None,
                 info_topic: str | None = None, tof_topic: str | None = None,
                 tof_format: str = "deltar", tof_orientation: Orientation | None = None,
                 tof_sigma_m: float = 0.0, depth_topic: str | None = None) -> None:
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
        tof_types = ZONE_FRAME_MSGTYPES if tof_format == "deltar" else \
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
        if depth_topic == AUTO_DEPTH_TOPIC:
            found = self.topics.get(DEFAULT_DEPTH_TOPIC) == "sensor_msgs/msg/Image" and \
                DEFAULT_DEPTH_TOPIC != self.image_topic
            depth_topic = DEFAULT_DEPTH_TOPIC if found else None
        self.depth_topic = None if depth_topic is None else self._pick(
            depth_topic, ("sensor_msgs/msg/Image",), "depth", "--depth-topic")
        if self.depth_topic in (self.image_topic, self.tof_topic):
            raise ValueError(f"{self.path}: the depth topic {self.depth_topic} is also the "
                             "camera or ToF topic")

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

    def _deserialize(self, connection: Any, rawdata: bytes) -> Any:
        return deserialize(connection, rawdata, f"{self.path}: {connection.topic}")

    def _zone_frame(self, msg: Any) -> ZoneFrame:
        if self.tof_format == "deltar":
            return zone_frame_from_msg(msg, source=self.tof_topic)
        return zone_frame_from_vl53l5cx_ros2(msg, orientation=self.tof_orientation,
                                             sigma_m=self.tof_sigma_m, source=self.tof_topic)

    def pairs(self, tolerance_s: float = 0.02, time_offset_s: float = 0.0) -> list[BagPair]:
        """Pair every ToF frame with the camera image nearest in header stamp, one ToF
        frame per image.

        ToF frames without an image within ``tolerance_s`` are skipped with one warning;
        of several ToF frames nearest one image only the nearest is kept (a warning
        counts the others: an image gives one output). Camera images are not decoded here.

        Args:
            tolerance_s: largest |image stamp - (ToF stamp + offset)|, seconds.
            time_offset_s: how far the camera's stamps run ahead of the sensor's, seconds
                (as for recordings: ``deltar calibrate --time-offset`` estimates it).

        Raises:
            ValueError: no ToF message, no camera message, two ToF messages with one
                stamp, or no pair at all (the message gives both stamp ranges).
        """
        from rosbags.rosbag2 import Reader

        if not tolerance_s >= 0:
            raise ValueError(f"tolerance_s must be >= 0, got {tolerance_s}")
        if not np.isfinite(time_offset_s):
            raise ValueError(f"time_offset_s must be finite, got {time_offset_s}")
        images: list[tuple[int, int, str, tuple[int, int]]] = []  # stamp, log, frame, size
        infos: list[tuple[int, Any]] = []
        frames: list[ZoneFrame] = []
        tof_stamps: list[int] = []
        with Reader(self.path) as reader:
            wanted = [c for c in reader.connections
                      if c.topic in (self.image_topic, self.tof_topic, self.info_topic)]
            for connection, log_ns, raw in reader.messages(connections=wanted):
                msg = self._deserialize(connection, raw)
                stamp = stamp_to_ns(msg.header.stamp)
                if connection.topic == self.image_topic:
                    size = (int(getattr(msg, "height", 0)), int(getattr(msg, "width", 0)))
                    images.append((stamp, int(log_ns), str(msg.header.frame_id), size))
                elif connection.topic == self.tof_topic:
                    frames.append(self._zone_frame(msg))
                    tof_stamps.append(stamp)
                else:
                    infos.append((stamp, msg))
        if not frames:
            raise ValueError(f"{self.path}: the ToF topic {self.tof_topic} has no messages")
        if not images:
            raise ValueError(f"{self.path}: the camera topic {self.image_topic} has no "
                             "messages")
        self._refuse_repeated_stamps(tof_stamps)
        order = np.argsort([i[0] for i in images], kind="stable")
        image_times = np.array([images[i][0] for i in order], dtype=np.float64) / 1e9
        info_order = sorted(range(len(infos)), key=lambda i: infos[i][0])
        info_times = np.array([infos[i][0] for i in info_order], dtype=np.float64) / 1e9
        tof_times = np.array([f.timestamp_s for f in frames], dtype=np.float64)
        nearest, gap = nearest_in_time(image_times, tof_times + time_offset_s)
        out: list[BagPair] = []
        for frame, tof_stamp, idx, distance in zip(frames, tof_stamps, nearest, gap,
                                                   strict=True):
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
                               stamp / 1e9 - float(frame.timestamp_s), tof_stamp))
        if not out:
            shifted = f" plus the time offset {time_offset_s:g} s:" if time_offset_s else ""
            raise ValueError(
                f"{self.path}: no ToF message on {self.tof_topic} has a camera image within "
                f"{tolerance_s} s (ToF stamps{shifted} {tof_times.min() + time_offset_s:.3f}.."
                f"{tof_times.max() + time_offset_s:.3f} s, images {image_times.min():.3f}.."
                f"{image_times.max():.3f} s); check the header stamps, the time offset or "
                "raise --tolerance")
        if len(out) < len(frames):
            warnings.warn(f"{self.path}: skipped {len(frames) - len(out)} of {len(frames)} ToF "
                          f"frames with no camera image within {tolerance_s} s", stacklevel=2)
        return one_per_image(out, lambda p: p.image_index,
                             lambda p: abs(p.offset_s - time_offset_s), self.path, "ToF frame")

    def _refuse_repeated_stamps(self, stamps: list[int]) -> None:
        """Two ToF messages with one header stamp are one reading sent twice, or a
        driver that does not stamp: either way no time tells them apart (a recording
        refuses a repeated timestamp too)."""
        unique, counts = np.unique(np.asarray(stamps, dtype=np.int64), return_counts=True)
        if (counts > 1).any():
            first = int(np.argmax(counts > 1))
            stamp = int(unique[first])
            raise ValueError(f"{self.path}: {int(counts[first])} messages on the ToF topic "
                             f"{self.tof_topic} have the header stamp {stamp} ns "
                             f"({stamp / 1e9:.9f} s); each reading needs its own stamp")

    def images(self, pairs: list[BagPair]) -> Iterator[tuple[BagPair, np.ndarray]]:
        """Decode the camera images of ``pairs`` in bag order: (pair, (H, W, 3) uint8 RGB).

        A pair's image is decoded once even if several pairs share it.
        """
        for pair, rgb, _ in self.images_with_depth(pairs, [None] * len(pairs)):
            yield pair, rgb

    def depth_indices(self, pairs: list[BagPair], tolerance_s: float = 0.02
                      ) -> list[int | None]:
        """For each pair, the position of the depth message nearest its image in header
        stamp among the depth topic's messages, or None when none lies within
        ``tolerance_s`` (or the bag has no depth topic)."""
        from rosbags.rosbag2 import Reader

        if self.depth_topic is None:
            return [None] * len(pairs)
        with Reader(self.path) as reader:
            wanted = [c for c in reader.connections if c.topic == self.depth_topic]
            stamps = [stamp_to_ns(self._deserialize(c, raw).header.stamp) / 1e9
                      for c, _, raw in reader.messages(connections=wanted)]
        if not stamps:
            return [None] * len(pairs)
        order = np.argsort(stamps, kind="stable")
        times = np.asarray(stamps, dtype=np.float64)[order]
        nearest, gap = nearest_in_time(times, np.array([p.image_stamp_ns / 1e9 for p in pairs]))
        return [int(order[i]) if g <= tolerance_s else None
                for i, g in zip(nearest, gap, strict=True)]

    def images_with_depth(self, pairs: list[BagPair], depth_indices: list[int | None]
                          ) -> Iterator[tuple[BagPair, np.ndarray, np.ndarray | None]]:
        """:meth:`images` with each pair's depth: (pair, (H, W, 3) uint8 RGB, (H, W)
        float32 metres with 0 where invalid, or None), in one pass over the bag and in the
        order :meth:`images` yields (the images' order in the bag).

        ``depth_indices`` comes from :meth:`depth_indices`. A decoded image waits only
        until its depth map arrives (both are logged at about the same time), and the
        images after it wait behind it, so the order holds.

        Raises:
            ValueError: a depth map of another size than its image, or not a depth
                encoding (naming the topic).
        """
        from rosbags.rosbag2 import Reader

        wanted_images: dict[int, list[tuple[BagPair, int | None]]] = {}
        depth_users: dict[int, int] = {}
        for pair, depth_index in zip(pairs, depth_indices, strict=True):
            wanted_images.setdefault(pair.image_index, []).append((pair, depth_index))
            if depth_index is not None:
                depth_users[depth_index] = depth_users.get(depth_index, 0) + 1
        held_depth: dict[int, np.ndarray] = {}
        queue: list[tuple[BagPair, int | None, np.ndarray]] = []  # in image order

        def ready() -> Iterator[tuple[BagPair, np.ndarray, np.ndarray | None]]:
            while queue and (queue[0][1] is None or queue[0][1] in held_depth):
                pair, depth_index, rgb = queue.pop(0)
                if depth_index is None:
                    yield pair, rgb, None
                    continue
                depth = held_depth[depth_index]
                if depth.shape != rgb.shape[:2]:
                    raise ValueError(f"{self.path}: depth on {self.depth_topic} is "
                                     f"{depth.shape}, the camera image {rgb.shape[:2]}: the "
                                     "depth must be registered to the camera (e.g. "
                                     "aligned_depth_to_color)")
                depth_users[depth_index] -= 1
                if not depth_users[depth_index]:
                    del held_depth[depth_index]
                yield pair, rgb, depth

        # The depth topic is read only when some pair wants its depth.
        topics = (self.image_topic, self.depth_topic) if depth_users else (self.image_topic,)
        counts = {topic: 0 for topic in topics}
        with Reader(self.path) as reader:
            wanted = [c for c in reader.connections if c.topic in topics]
            for connection, _, raw in reader.messages(connections=wanted):
                index = counts[connection.topic]
                counts[connection.topic] += 1
                if connection.topic == self.image_topic:
                    if index not in wanted_images:
                        continue
                    msg = self._deserialize(connection, raw)
                    rgb = image_from_msg(msg, connection.msgtype, source=self.image_topic)
                    queue.extend((pair, depth_index, rgb)
                                 for pair, depth_index in wanted_images.pop(index))
                elif index in depth_users:
                    msg = self._deserialize(connection, raw)
                    depth = metric_image_from_msg(msg, source=self.depth_topic)
                    held_depth[index] = np.where(np.isfinite(depth), depth, np.float32(0.0))
                else:
                    continue
                yield from ready()
        if queue:  # cannot happen with depth_indices' numbering; never drop a frame silently
            raise ValueError(f"{self.path}: {len(queue)} image(s) of {self.image_topic} "
                             f"never got their depth message on {self.depth_topic}")


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
        return [(int(log_ns), deserialize(conn, raw, f"{path}: {topic}"))
                for conn, log_ns, raw in reader.messages(connections=wanted)]
