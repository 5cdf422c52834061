"""ROS 2 messages to and from numpy, with the pure-Python ``rosbags`` library.

The type store (:func:`typestore`: ROS 2 Humble's types with this package's
``deltar_msgs/msg/ZoneFrame``, defined in ``msg/ZoneFrame.msg`` beside this module),
stamps, headers, and the decoders of the messages a bag is read from: camera images
(``sensor_msgs/msg/Image`` in ``rgb8`` / ``bgr8``, ``CompressedImage``), metric images
(``32FC1``), ``CameraInfo`` and zone frames (``deltar_msgs/msg/ZoneFrame`` or the
``vl53l5cx_ros2`` driver's 32FC1 image), and :func:`deserialize`, which reads this
package's messages with the definition a bag stores (older layouts still read). Reading
bags is :mod:`deltar.io.rosbag_reader`, writing them :mod:`deltar.io.rosbag_writer`.

All times are integer nanoseconds (``header.stamp``) unless named ``_s`` (seconds).
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.sensor.zone_frame import Orientation, ZoneFrame
from deltar.sensor.zone_values import DEFAULT_VALID_STATUS, valid_status_codes

#: The ToF message type shipped with the package.
ZONE_FRAME_MSGTYPE = "deltar_msgs/msg/ZoneFrame"
#: Where its definition lives (package data).
ZONE_FRAME_MSG_PATH = Path(__file__).with_name("msg") / "ZoneFrame.msg"
#: The ToF message with several targets per zone (``ZoneFrame``'s fields, then the targets).
MULTI_TARGET_ZONE_FRAME_MSGTYPE = "deltar_msgs/msg/MultiTargetZoneFrame"
MULTI_TARGET_ZONE_FRAME_MSG_PATH = Path(__file__).with_name("msg") / "MultiTargetZoneFrame.msg"
#: Message types a zone frame is read from (``zone_frame_from_msg``).
ZONE_FRAME_MSGTYPES = (ZONE_FRAME_MSGTYPE, MULTI_TARGET_ZONE_FRAME_MSGTYPE)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
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
    """The ROS 2 Humble type store with ``deltar_msgs/msg/ZoneFrame`` and
    ``deltar_msgs/msg/MultiTargetZoneFrame`` registered."""
    return _store_with(((ZONE_FRAME_MSGTYPE, ZONE_FRAME_MSG_PATH.read_text(encoding="utf-8")),
                        (MULTI_TARGET_ZONE_FRAME_MSGTYPE, _multi_target_definition())))


def _multi_target_definition(with_signal: bool = True) -> str:
    """``MultiTargetZoneFrame.msg``; without ``target_signal``: the layout before it."""
    text = MULTI_TARGET_ZONE_FRAME_MSG_PATH.read_text(encoding="utf-8")
    if with_signal:
        return text
    return "\n".join(line for line in text.splitlines()
                     if not line.strip().endswith(" target_signal"))


@functools.lru_cache(maxsize=8)
def _store_with(definitions: tuple[tuple[str, str], ...]) -> Any:
    """A ROS 2 Humble type store with these ``(msgtype, .msg text)`` pairs registered."""
    require_rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in definitions:
        store.register(get_types_from_msg(text, name))
    return store


def _previous_layout_store() -> Any:
    """The type store of bags written before ``MultiTargetZoneFrame.target_signal``."""
    return _store_with(((MULTI_TARGET_ZONE_FRAME_MSGTYPE, _multi_target_definition(False)),))


def deserialize(connection: Any, rawdata: bytes, source: str = "bag") -> Any:
    """Deserialise one message of a bag connection (``rosbags`` ``Connection``).

    ``deltar_msgs`` messages are read with the definition stored in the bag when it
    has one (a bag written before a field was added holds the older layout), else with
    this package's definition, then with the layout before ``target_signal`` (bags
    without stored definitions, e.g. recorded by ROS 2 Humble). Other types use
    :func:`typestore`.

    Raises:
        ValueError: corrupt message bytes or an unparsable stored definition, naming
            ``source`` and the type.
    """
    msgtype = connection.msgtype
    stores = [typestore()]
    if msgtype in ZONE_FRAME_MSGTYPES:
        msgdef = getattr(connection, "msgdef", None)
        stored = getattr(msgdef, "data", "") or ""
        if getattr(getattr(msgdef, "format", None), "name", "") == "MSG" and stored.strip():
            try:
                stores = [_store_with(((msgtype, stored),))]
            except Exception as err:  # rosbags raises its own parse / type errors
                raise ValueError(f"{source}: the bag's definition of {msgtype} cannot be "
                                 f"read: {err}") from err
        elif msgtype == MULTI_TARGET_ZONE_FRAME_MSGTYPE:
            stores.append(_previous_layout_store())
    for store in stores[:-1]:
        try:
            return store.deserialize_cdr(rawdata, msgtype)
        except Exception:  # rosbags' SerdeError: not this layout, try the next
            continue
    try:
        return stores[-1].deserialize_cdr(rawdata, msgtype)
    except Exception as err:  # corrupt bytes (rosbags' SerdeError and others)
        raise ValueError(f"{source}: corrupt {msgtype} message: {err}") from err


#: The largest seconds a ``builtin_interfaces/msg/Time`` holds (int32).
MAX_STAMP_SECONDS = 2**31 - 1


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/msg/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamped_header(stamp_ns: int, frame_id: str) -> Any:
    """A ``std_msgs/msg/Header`` with the stamp ``stamp_ns`` (integer ns) and ``frame_id``.

    Raises:
        ValueError: a stamp outside what ``builtin_interfaces/msg/Time`` holds (its
            seconds are a signed 32-bit integer: up to 2**31 - 1 s, i.e. before 2038).
    """
    types = typestore().types
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if not -MAX_STAMP_SECONDS - 1 <= sec <= MAX_STAMP_SECONDS:
        raise ValueError(f"a ROS stamp holds at most {MAX_STAMP_SECONDS} s either side of 0 "
                         f"(32-bit seconds), got {stamp_ns} ns ({sec} s)")
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](
        sec=sec, nanosec=nanosec), frame_id=frame_id)


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
    """A :class:`ZoneFrame` from a ``deltar_msgs/msg/ZoneFrame`` or
    ``deltar_msgs/msg/MultiTargetZoneFrame`` (see their ``.msg``); the latter fills the
    frame's target arrays.

    Raises:
        ValueError: lengths that do not match ``zone_count`` (and ``targets_per_zone``),
            naming the field.
    """
    count = int(msg.zone_count)
    distance = np.asarray(msg.distance_m, dtype=np.float64)
    if distance.size != count or count not in (16, 64):
        raise ValueError(f"{source}: zone_count is {count} and distance_m has "
                         f"{distance.size} entries; expected 16 or 64 of each")
    arrays = _optional_fields(msg, ("sigma_m", "status", "valid"), count, source)
    valid, sigma, status = _readings_validity(distance, arrays["sigma_m"], arrays["status"],
                                              arrays["valid"], valid_status)
    edges = np.asarray(msg.hist_edges_m, dtype=np.float64)
    counts = np.asarray(msg.hist_counts, dtype=np.float64)
    hist = {}
    if edges.size or counts.size:
        bins = edges.size - 1
        if bins < 1 or counts.size != count * bins:
            raise ValueError(f"{source}: hist_counts has {counts.size} values, expected "
                             f"zone_count x {max(bins, 0)} bins from hist_edges_m")
        hist = {"hist_edges_m": edges, "hist_counts": counts.reshape(count, bins)}
    targets = {}
    if hasattr(msg, "target_distance_m"):
        targets = _targets_from_msg(msg, count, source, valid_status)
    try:
        return ZoneFrame(mean_m=np.where(valid, distance, 0.0),
                         sigma_m=np.where(valid, sigma, 0.0), valid=valid, status=status,
                         timestamp_s=stamp_to_ns(msg.header.stamp) / 1e9,
                         sensor_model=str(msg.sensor_model) or "VL53L5CX", **hist, **targets)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from err


def _targets_from_msg(msg: Any, count: int, source: str,
                      valid_status: tuple[int, ...]) -> dict[str, Any]:
    """The target arrays of a ``MultiTargetZoneFrame`` as ``ZoneFrame`` arguments.

    Validity as for the primary fields: ``target_valid`` when given, else a positive,
    finite distance with (when given) a status in ``valid_status``. ``target_signal``
    is absent from messages of the layout before it, and may be empty: no signals.
    """
    per_zone = int(msg.targets_per_zone)
    if not 1 <= per_zone <= 4:
        raise ValueError(f"{source}: targets_per_zone is {per_zone}; expected 1..4")
    size = count * per_zone
    distance = np.asarray(msg.target_distance_m, dtype=np.float64)
    if distance.size != size:
        raise ValueError(f"{source}: target_distance_m has {distance.size} entries; expected "
                         f"zone_count x targets_per_zone = {size}")
    # target_signal is absent from messages of the layout before it.
    arrays = _optional_fields(msg, ("target_sigma_m", "target_status", "target_valid",
                                    "target_signal"), size, source)
    signal = arrays["target_signal"]
    valid, sigma, status = _readings_validity(distance, arrays["target_sigma_m"],
                                              arrays["target_status"], arrays["target_valid"],
                                              valid_status)
    shape = (count, per_zone)
    return {"target_mean_m": np.where(valid, distance, 0.0).reshape(shape),
            "target_sigma_m": np.where(valid, sigma, 0.0).reshape(shape),
            "target_valid": valid.reshape(shape),
            "target_status": None if status is None else status.reshape(shape),
            "target_signal": None if signal is None else
            np.where(valid, signal.astype(np.float64), 0.0).reshape(shape),
            "target_order": str(msg.target_order) or "strongest"}


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


def metric_image_from_msg(msg: Any, source: str = "image") -> np.ndarray:
    """(H, W) float32 metres from a depth ``sensor_msgs/msg/Image`` (REP 118).

    ``32FC1`` is metres (NaN kept); ``16UC1`` is millimetres (0 = invalid, returned as
    NaN), as RealSense and Kinect drivers publish depth.

    Raises:
        ValueError: another encoding, or fewer bytes than the rows need (naming
            ``source``).
    """
    encoding = str(msg.encoding)
    if encoding not in ("32FC1", "16UC1"):
        raise ValueError(f"{source}: expected encoding 32FC1 or 16UC1, got {encoding!r}")
    size = 4 if encoding == "32FC1" else 2
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < size * width or data.size < step * height:
        raise ValueError(f"{source}: image data has {data.size} bytes, expected "
                         f"{height} rows of step {step}")
    rows = data[:step * height].reshape(height, step)[:, :size * width].copy()
    order = ">" if msg.is_bigendian else "<"
    if encoding == "32FC1":
        return rows.view(f"{order}f4").reshape(height, width).astype(np.float32)
    millimetres = rows.view(f"{order}u2").reshape(height, width)
    return np.where(millimetres > 0, millimetres / np.float32(1000.0),
                    np.float32(np.nan)).astype(np.float32)


def _optional_fields(msg: Any, names: tuple[str, ...], size: int, source: str
                     ) -> dict[str, np.ndarray | None]:
    """A message's optional flat fields: each ``size`` entries, or empty (then None; a
    field the message's layout lacks counts as empty).

    Raises:
        ValueError: a field of another length, naming it.
    """
    arrays = {}
    for name in names:
        values = np.asarray(getattr(msg, name, ()))
        if values.size not in (0, size):
            raise ValueError(f"{source}: {name} has {values.size} entries; expected {size} "
                             "or none")
        arrays[name] = values if values.size else None
    return arrays


def _readings_validity(distance: np.ndarray, sigma_m: np.ndarray | None,
                       status: np.ndarray | None, valid: np.ndarray | None,
                       valid_status: Sequence[int]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Which of a message's flat readings are valid, and their sigma and status.

    A reading is valid when its flag says so (when the message has flags), else when its
    status is one of ``valid_status`` (when it has codes), and in any case when its
    distance is positive and finite and its sigma finite and >= 0.

    Args:
        distance: (N,) metres; sigma_m: (N,) metres or None (then 0); status: (N,)
            codes or None; valid: (N,) flags or None.

    Returns:
        ``(valid, sigma, status)``: (N,) bool, (N,) float64 metres, (N,) uint8 or None.
    """
    ok = np.isfinite(distance) & (distance > 0)
    codes = None if status is None else status.astype(np.uint8)
    if valid is not None:
        valid = valid.astype(bool) & ok
    elif codes is not None:
        valid = ok & np.isin(codes, valid_status_codes(valid_status))
    else:
        valid = ok
    sigma = np.zeros(distance.shape) if sigma_m is None else sigma_m.astype(np.float64)
    return valid & np.isfinite(sigma) & (sigma >= 0), sigma, codes
