"""Camera poses for mapping: read, check, match to frames, compare (ATE).

A pose is a (4, 4) float64 camera-to-world transform: ``world = T @ camera`` for a
point in the camera's optical frame (x right, y down, z forward), translations in
metres. Sources, in the order ``deltar map`` tries them:

- a folder of 4x4 text files, one per frame (:func:`read_pose_folder`): a recording's
  ``pose/<ns>.txt`` (docs/formats.md), ``pose/NNNNNN.txt`` beside ``color/NNNNNN.*``
  (the shared TUM keyframes) or 7-Scenes' ``frame-NNNNNN.pose.txt``;
- a TUM trajectory file ``t tx ty tz qx qy qz qw`` (:func:`read_tum_trajectory`);
- a ROS 2 bag's ``/tf`` or a ``geometry_msgs/msg/PoseStamped`` topic
  (:func:`read_bag_poses`);
- otherwise RGB-D odometry (:mod:`deltar.mapping.odometry`).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deltar.io.input_file import input_folder
from deltar.io.pose_file import read_pose_file
from deltar.io.tum import quaternion_pose, read_tum_poses

#: Default largest |pose time - frame time| when poses are matched to frames, seconds.
DEFAULT_POSE_TOLERANCE_S = 0.05


@dataclass(frozen=True)
class Trajectory:
    """Timed camera-to-world poses.

    Attributes:
        times_s: (N,) float64 strictly increasing times in seconds (None for a pose
            folder matched by frame name instead of time).
        poses: (N, 4, 4) float64 camera-to-world transforms, metres.
        names: (N,) pose names (file stems) when read from a folder, else None.
        source: where the poses came from (for messages).
    """

    times_s: np.ndarray | None
    poses: np.ndarray
    names: tuple[str, ...] | None
    source: str


_SEVEN_SCENES_POSE = re.compile(r"^(frame-\d+)\.pose\.txt$")


def read_pose_folder(folder: str | os.PathLike) -> Trajectory:
    """Every pose file of a folder, by name.

    Files are 7-Scenes' ``frame-NNNNNN.pose.txt`` (name ``frame-NNNNNN``; other files
    of such a folder are ignored) or else every ``<stem>.txt`` (the stem is the frame's
    name: a recording's nanosecond time stamp, or ``NNNNNN`` as the frame's colour
    image).

    Raises:
        FileNotFoundError: no such folder.
        ValueError: no pose file, or a file that is not a rigid transform.
    """
    root = Path(folder)
    input_folder(root, "pose folder")
    files = sorted(p for p in root.iterdir() if p.is_file() and not p.name.startswith("."))
    # A 7-Scenes folder holds other .txt files too (camera-intrinsics.txt).
    entries = [(m.group(1), p) for p in files if (m := _SEVEN_SCENES_POSE.match(p.name))]
    if not entries:
        entries = [(p.stem, p) for p in files if p.suffix == ".txt"]
    if not entries:
        raise ValueError(f"{root}: no pose files (<name>.txt or frame-NNNNNN.pose.txt)")
    poses = np.stack([read_pose_file(p) for _, p in entries])
    return Trajectory(None, poses, tuple(n for n, _ in entries), str(root))


def read_tum_trajectory(path: str | os.PathLike) -> Trajectory:
    """A TUM RGB-D trajectory: lines ``t tx ty tz qx qy qz qw`` (``#`` comments).

    ``t`` is seconds, translations metres, the quaternion the camera-to-world rotation.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a line that is not 8 numbers, a quaternion that is not unit length,
            times not strictly increasing, or no pose (naming the file and line).
    """
    times, poses = read_tum_poses(path)
    return Trajectory(times, poses, None, str(path))


def write_tum_trajectory(path: str | os.PathLike, times_s: np.ndarray,
                         poses: np.ndarray) -> Path:
    """Write (N,) times in seconds and (N, 4, 4) camera-to-world poses as TUM lines, atomically."""
    from scipy.spatial.transform import Rotation

    from deltar.io.atomic import write_text_atomic

    lines = ["# deltar map: t tx ty tz qx qy qz qw (camera-to-world, metres)"]
    for t, pose in zip(times_s, poses, strict=True):
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        lines.append(" ".join(f"{v:.9f}" for v in (t, *pose[:3, 3], *q)))
    return write_text_atomic(path, "\n".join(lines) + "\n")


def interpolate_poses(trajectory: Trajectory, times_s: np.ndarray,
                      tolerance_s: float = DEFAULT_POSE_TOLERANCE_S
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The trajectory's pose at each time: linear in translation, slerp in rotation.

    A time is covered when it lies within the trajectory's time span (extended by
    ``tolerance_s`` at both ends, where the end pose is used) and the two poses around it
    are at most ``max(tolerance_s, 2 x the median pose period)`` apart (no pose is
    made up across a gap).

    Args:
        trajectory: timed poses (``times_s`` not None).
        times_s: (M,) frame times in seconds.
        tolerance_s: seconds.

    Returns:
        ((M, 4, 4) poses, (M,) bool covered); uncovered frames get the identity.
    """
    from scipy.spatial.transform import Rotation, Slerp

    if trajectory.times_s is None:
        raise ValueError(f"{trajectory.source}: poses without times cannot be interpolated")
    times = trajectory.times_s
    query = np.asarray(times_s, dtype=np.float64)
    out = np.tile(np.eye(4), (query.size, 1, 1))
    if times.size == 1:
        covered = np.abs(query - times[0]) <= tolerance_s
        out[covered] = trajectory.poses[0]
        return out, covered
    clipped = np.clip(query, times[0], times[-1])
    right = np.clip(np.searchsorted(times, clipped, side="left"), 1, times.size - 1)
    left = right - 1
    gap = times[right] - times[left]
    max_gap = max(tolerance_s, 2.0 * float(np.median(np.diff(times))))
    # A frame at a pose's own time has that pose, whatever gap lies on either side of it
    # (within a microsecond: frame names and trajectory files round times differently).
    at_pose = np.isclose(clipped, times[left], rtol=0, atol=1e-6) | \
        np.isclose(clipped, times[right], rtol=0, atol=1e-6)
    covered = (query >= times[0] - tolerance_s) & (query <= times[-1] + tolerance_s) & \
        ((gap <= max_gap) | at_pose)
    if covered.any():
        slerp = Slerp(times, Rotation.from_matrix(trajectory.poses[:, :3, :3]))
        fraction = ((clipped - times[left]) / gap)[:, None]
        translation = (1 - fraction) * trajectory.poses[left, :3, 3] + \
            fraction * trajectory.poses[right, :3, 3]
        out[:, :3, :3] = slerp(clipped).as_matrix()
        out[:, :3, 3] = translation
        out[~covered] = np.eye(4)
    return out, covered


def match_poses(trajectory: Trajectory, frame_times_s: np.ndarray,
                frame_names: Sequence[str], tolerance_s: float = DEFAULT_POSE_TOLERANCE_S
                ) -> tuple[np.ndarray, np.ndarray]:
    """The pose of each frame: by name for a pose folder, by time otherwise.

    Args:
        trajectory: the poses.
        frame_times_s: (M,) frame times in seconds.
        frame_names: M frame names (a recording's colour image stems).
        tolerance_s: see :func:`interpolate_poses`.

    Returns:
        ((M, 4, 4) poses, (M,) bool covered).

    Raises:
        ValueError: the trajectory covers none of the frames (the message gives both
            ranges).
    """
    if trajectory.names is not None:
        by_name = dict(zip(trajectory.names, trajectory.poses, strict=True))
        covered = np.array([n in by_name for n in frame_names], dtype=bool)
        poses = np.stack([by_name.get(n, np.eye(4)) for n in frame_names]) \
            if len(frame_names) else np.zeros((0, 4, 4))
        if not covered.any():
            raise ValueError(f"{trajectory.source}: no pose file is named like a frame "
                             f"(poses {_name_range(trajectory.names)}, frames "
                             f"{_name_range(frame_names)}); name them "
                             "<frame name>.txt")
        return poses, covered
    poses, covered = interpolate_poses(trajectory, frame_times_s, tolerance_s)
    if not covered.any():
        times = trajectory.times_s
        raise ValueError(f"{trajectory.source}: the trajectory covers none of the frames "
                         f"(poses {times[0]:.3f}..{times[-1]:.3f} s, frames "
                         f"{float(np.min(frame_times_s)):.3f}..{float(np.max(frame_times_s)):.3f}"
                         " s); check that both use the same clock")
    return poses, covered


def _name_range(names: Sequence[str]) -> str:
    """``first..last`` of frame names, numbers in numeric order (``9`` before ``10``)."""
    ordered = sorted(names, key=lambda n: (0, int(n), n) if n.isdigit() else (1, 0, n))
    return f"{ordered[0]}..{ordered[-1]}"


def _transform_matrix(translation, rotation) -> np.ndarray:
    return quaternion_pose(np.array([translation.x, translation.y, translation.z]),
                           np.array([rotation.x, rotation.y, rotation.z, rotation.w]),
                           "transform")


def read_bag_poses(path: str | os.PathLike, *, pose_topic: str | None = None,
                   camera_frame: str | None = None, world_frame: str | None = None
                   ) -> Trajectory | None:
    """Camera poses from a ROS 2 bag: a PoseStamped topic, or the camera's /tf chain.

    With ``pose_topic`` (``geometry_msgs/msg/PoseStamped``) its poses are the camera's
    in ``header.frame_id``. Otherwise ``/tf`` (``tf2_msgs/msg/TFMessage``) is followed
    from ``camera_frame`` (the camera image's frame id) up its parents to
    ``world_frame`` (default: the root of that chain); static transforms from
    ``/tf_static`` join every chain. A bag without ``/tf`` whose ``/camera/pose`` is a
    PoseStamped topic (what ``deltar record --bag`` writes from a source with poses)
    gives that topic's poses. Times are the header stamps.

    Returns:
        The trajectory, or None when the bag has none of these (then odometry is used).

    Raises:
        ValueError: a named topic that is missing or of another type, a quaternion that
            is not unit length, or a /tf without the camera frame.
    """
    from deltar.io.ros_messages import require_rosbags, stamp_to_ns
    from deltar.io.rosbag_reader import read_messages
    from deltar.io.rosbag_writer import POSE_MSGTYPE, RECORD_TOPICS

    require_rosbags()
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
    if pose_topic is None and topics.get("/tf") != "tf2_msgs/msg/TFMessage" and \
            topics.get(RECORD_TOPICS["pose"]) == POSE_MSGTYPE:
        pose_topic = RECORD_TOPICS["pose"]
    if pose_topic is not None:
        if topics.get(pose_topic) != POSE_MSGTYPE:
            raise ValueError(f"{path}: --pose-topic {pose_topic} is "
                             f"{topics.get(pose_topic, 'missing')}, expected "
                             "geometry_msgs/msg/PoseStamped")
        rows = []
        for _, msg in read_messages(path, pose_topic):
            p = msg.pose
            rows.append((stamp_to_ns(msg.header.stamp) / 1e9,
                         _transform_matrix(p.position, p.orientation)))
        return _timed(rows, f"{path} {pose_topic}")
    if topics.get("/tf") != "tf2_msgs/msg/TFMessage":
        return None
    if camera_frame is None:
        raise ValueError(f"{path}: /tf needs the camera's frame id to follow")
    static: dict[str, tuple[str, np.ndarray]] = {}
    if topics.get("/tf_static") == "tf2_msgs/msg/TFMessage":
        for _, msg in read_messages(path, "/tf_static"):
            for tf in msg.transforms:
                static[str(tf.child_frame_id)] = (
                    str(tf.header.frame_id),
                    _transform_matrix(tf.transform.translation, tf.transform.rotation))
    latest: dict[str, tuple[str, np.ndarray]] = dict(static)
    rows = []
    seen_camera = False
    for _, msg in read_messages(path, "/tf"):
        touched = False
        stamp = None
        for tf in msg.transforms:
            child = str(tf.child_frame_id)
            latest[child] = (str(tf.header.frame_id),
                             _transform_matrix(tf.transform.translation, tf.transform.rotation))
            touched = True
            stamp = stamp_to_ns(tf.header.stamp) / 1e9
        if not touched:
            continue
        chain = _chain(latest, camera_frame, world_frame)
        if chain is not None:
            seen_camera = True
            if not rows or stamp > rows[-1][0]:
                rows.append((stamp, chain))
    if not seen_camera:
        raise ValueError(f"{path}: /tf has no transform chain from the camera frame "
                         f"{camera_frame!r}" + (f" to {world_frame!r}" if world_frame else "")
                         + f"; frames: {sorted(latest)}")
    return _timed(rows, f"{path} /tf")


def _chain(latest: dict[str, tuple[str, np.ndarray]], frame: str, root: str | None
           ) -> np.ndarray | None:
    """frame-to-root transform from child -> (parent, parent_T_child), or None."""
    transform = np.eye(4)
    current, steps = frame, 0
    if current not in latest:
        return None
    while current in latest and current != root and steps < 64:
        parent, parent_from_child = latest[current]
        transform = parent_from_child @ transform
        current, steps = parent, steps + 1
    if root is not None and current != root:
        return None
    return transform


def _timed(rows: list[tuple[float, np.ndarray]], source: str) -> Trajectory:
    rows.sort(key=lambda r: r[0])
    unique = [r for i, r in enumerate(rows) if i == 0 or r[0] > rows[i - 1][0]]
    if not unique:
        raise ValueError(f"{source}: no poses")
    return Trajectory(np.array([r[0] for r in unique]), np.stack([r[1] for r in unique]),
                      None, source)


def absolute_trajectory_error(estimated: np.ndarray, reference: np.ndarray) -> float:
    """ATE RMSE in metres after the best rigid alignment (no scale) of the camera centres.

    Args:
        estimated, reference: (N, 4, 4) camera-to-world poses of the same N frames.

    Returns:
        sqrt(mean |R p_est + t - p_ref|^2) over the frames, metres (Horn / Umeyama
        alignment without scale, as TUM's evaluate_ate).
    """
    est = np.asarray(estimated)[:, :3, 3]
    ref = np.asarray(reference)[:, :3, 3]
    if est.shape != ref.shape or est.shape[0] < 2:
        raise ValueError(f"need two trajectories of the same N >= 2 poses, got {est.shape} "
                         f"and {ref.shape}")
    est_c, ref_c = est - est.mean(0), ref - ref.mean(0)
    u, _, vt = np.linalg.svd(ref_c.T @ est_c)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ flip @ vt
    aligned = est_c @ rotation.T + ref.mean(0)
    return float(np.sqrt(np.mean(np.sum((aligned - ref) ** 2, axis=1))))
