"""Build a map: choose the poses, check everything, then integrate frame by frame.

:func:`plan_map` does every check that needs no depth (poses found and valid and
covering frames, motion for odometry, the volume's memory estimate) so bad input
fails before the long part; :func:`build_map` then predicts (or reads) each frame's
depth and fuses it into a :class:`~deltar.mapping.tsdf.TSDFMap`.

Poses, in this order:

1. the recording's own ``pose/<ns>.txt`` files (:data:`POSE_DIR`, docs/formats.md);
2. a TUM trajectory file (``trajectory``);
3. a bag's ``PoseStamped`` topic (``pose_topic``) or its ``/tf`` chain to the camera's
   frame;
4. RGB-D odometry on the mapped depth (:mod:`deltar.mapping.odometry`), also when
   ``force_odometry`` (then the poses above, if any, are the reference its trajectory
   error is measured against).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deltar.io.pose_file import POSE_DIR
from deltar.io.resources import available_memory_bytes
from deltar.mapping.frames import DepthSource, FrameSource, MapFrame
from deltar.mapping.odometry import OdometryReport, RGBDOdometry, check_motion
from deltar.mapping.poses import (
    DEFAULT_POSE_TOLERANCE_S,
    absolute_trajectory_error,
    match_poses,
    read_bag_poses,
    read_pose_folder,
    read_tum_trajectory,
)
from deltar.mapping.tsdf import (
    INITIAL_BLOCKS,
    MapSettings,
    TSDFMap,
    block_bytes,
    estimate_blocks,
)

#: Frames sampled evenly for the odometry motion check.
_MOTION_SAMPLES = 24
#: The truncation distance may be at most this share of the depth limit: a surface is
#: made of the voxels within the truncation distance on both sides of the depth, so a
#: band as deep as the depth range (or voxels as large) leaves no surface to extract.
MAX_TRUNCATION_SHARE = 0.25
#: A camera faster than this (median over the frames, metres a second) is warned of:
#: poses in millimetres, or a time base that is off, look like this.
IMPLAUSIBLE_SPEED_M_S = 20.0


@dataclass
class MapPlan:
    """What :func:`plan_map` decided.

    Attributes:
        frames: the frames to integrate (with a pose, or all for odometry).
        poses: (N, 4, 4) camera-to-world poses of ``frames``, None for odometry.
        pose_source: where the poses come from (text).
        reference_poses: (N, 4, 4) given poses of ``frames`` when odometry is forced
            over them (for the trajectory error), else None.
        capacity_blocks: the volume's first block capacity (it doubles as needed, up to
            the budget).
        estimated_blocks: the upper estimate of blocks the map needs
            (:func:`~deltar.mapping.tsdf.estimate_blocks`).
        skipped_no_pose: frames left out because no pose covers them.
    """

    frames: list[MapFrame]
    poses: np.ndarray | None
    pose_source: str
    reference_poses: np.ndarray | None
    capacity_blocks: int
    estimated_blocks: int
    skipped_no_pose: int = 0


@dataclass
class MapResult:
    """A built map and how it went.

    Attributes:
        volume: the TSDF map.
        poses: (N, 4, 4) camera-to-world poses used, one per integrated frame.
        times_s: (N,) the frames' times, seconds.
        odometry: the odometry report (None with given poses).
        ate_m: the odometry's trajectory error against the given poses, metres (None
            without both).
        integrate_s: seconds spent in the volume (without depth prediction).
        depth_s: seconds spent predicting (or reading) depth.
        empty_frames: frames whose depth had no pixel to integrate.
    """

    volume: TSDFMap
    poses: np.ndarray
    times_s: np.ndarray
    odometry: OdometryReport | None = None
    ate_m: float | None = None
    integrate_s: float = 0.0
    depth_s: float = 0.0
    empty_frames: int = 0
    frame_names: list[str] = field(default_factory=list)


def _given_poses(source: FrameSource, trajectory: Path | None, pose_topic: str | None,
                 tolerance_s: float) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(poses, covered, description) from the first pose source there is, or None."""
    if pose_topic is not None and source.kind != "bag":
        raise ValueError("--pose-topic is for ROS 2 bags; a recording keeps its poses in "
                         f"{POSE_DIR}/ (or give --trajectory)")
    if pose_topic is not None and trajectory is not None:
        raise ValueError(f"--trajectory {trajectory} would replace the bag's --pose-topic "
                         f"{pose_topic}: give only one")
    names = [f.name for f in source.frames]
    times = np.array([f.time_s for f in source.frames])
    own = source.path / POSE_DIR
    if source.kind == "recording" and own.is_dir():
        if trajectory is not None:
            raise ValueError(f"{source.path} has its own poses in {own}; --trajectory "
                             f"{trajectory} would be ignored: give only one")
        found = read_pose_folder(own)
        poses, covered = match_poses(found, times, names, tolerance_s)
        return poses, covered, f"{own} (recorded poses)"
    if trajectory is not None:
        found = read_tum_trajectory(trajectory)
        poses, covered = match_poses(found, times, names, tolerance_s)
        return poses, covered, f"{trajectory} (TUM trajectory)"
    if source.kind == "bag":
        camera = source.frames[0].camera_frame_id if source.frames else None
        found = read_bag_poses(source.path, pose_topic=pose_topic, camera_frame=camera)
        if found is not None:
            poses, covered = match_poses(found, times, names, tolerance_s)
            return poses, covered, found.source
    return None


def _sample_images(source: FrameSource, frames: list[MapFrame]) -> list[np.ndarray]:
    picks = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), _MOTION_SAMPLES))
                      .round().astype(int))
    chosen = [frames[i] for i in picks]
    return [frame.image.copy() for frame in source.load(chosen)]


def plan_map(source: FrameSource, settings: MapSettings, *, trajectory: Path | None = None,
             pose_topic: str | None = None, force_odometry: bool = False,
             tolerance_s: float = DEFAULT_POSE_TOLERANCE_S) -> MapPlan:
    """Find the poses and check the input and the memory, before any depth is made.

    Raises:
        ValueError: no frames; a truncation distance above a quarter of the depth
            limit; poses that are not rigid transforms or cover no frame; a
            recording too short or too still for odometry; a map whose single view
            already exceeds ``settings.max_memory_bytes``, or whose estimate exceeds the
            machine's available memory (each with its own message).
    """
    if not source.frames:
        raise ValueError(f"{source.path}: no frame to map (no zone frame has a camera image "
                         "near it)")
    _check_scale(settings)
    given = _given_poses(source, trajectory, pose_topic, tolerance_s)
    frames, poses, reference, skipped = source.frames, None, None, 0
    description = "RGB-D odometry on the mapped depth"
    if given is not None:
        all_poses, covered, where = given
        skipped = int(np.count_nonzero(~covered))
        frames = [f for f, ok in zip(source.frames, covered, strict=True) if ok]
        if force_odometry:
            reference = all_poses[covered]
            description += f" (reference for the trajectory error: {where})"
        else:
            poses, description = all_poses[covered], where
    if poses is None:
        check_motion(_sample_images(source, frames), str(source.path))
    else:
        _check_positions(poses[:, :3, 3], [f.time_s for f in frames], settings, description)
    intrinsics = frames[0].calibration.intrinsics
    per_frame = _frame_blocks_bound(settings, intrinsics)
    positions = None if poses is None else poses[:, :3, 3]
    estimated = estimate_blocks(settings, positions, per_frame, len(frames))
    unit = block_bytes(settings.block_resolution)
    if per_frame > settings.max_blocks:
        limit = f"the volume's limit of {settings.max_blocks} blocks (Open3D's)" \
            if settings.memory_clipped else \
            f"--max-memory {settings.max_memory_bytes / 2**20:.0f} MiB"
        raise ValueError(
            f"one frame's view alone needs up to {per_frame * unit / 2**20:.0f} MiB "
            f"({per_frame} blocks of {settings.block_size_m * 100:g} cm at voxel "
            f"{settings.voxel_size_m * 100:g} cm and depth up to {settings.max_depth_m:g} m), "
            f"more than {limit}; use a coarser --voxel, a smaller --max-depth"
            + ("" if settings.memory_clipped else " or a larger --max-memory"))
    available = available_memory_bytes()
    if available is not None and min(estimated, settings.max_blocks) * unit > available:
        raise ValueError(
            f"the map may need up to {min(estimated, settings.max_blocks) * unit / 2**20:.0f} "
            f"MiB but this machine has {available / 2**20:.0f} MiB available; lower "
            "--max-memory, use a coarser --voxel or a smaller --max-depth")
    capacity = min(INITIAL_BLOCKS, estimated, settings.max_blocks)
    return MapPlan(frames, poses, description, reference, capacity, estimated, skipped)


def _check_scale(settings: MapSettings) -> None:
    """Refuse a voxel size or truncation that leaves no room for a surface below the
    depth limit (every frame would be fused for nothing)."""
    if settings.truncation_m > MAX_TRUNCATION_SHARE * settings.max_depth_m:
        raise ValueError(
            f"the truncation distance ({settings.truncation_voxels:g} voxels of "
            f"{settings.voxel_size_m * 100:g} cm = {settings.truncation_m * 100:g} cm, "
            "--truncation x --voxel) must be at most a quarter of the depth limit "
            f"(--max-depth {settings.max_depth_m:g} m): no surface could be made; use a "
            "smaller --voxel or --truncation, or a larger --max-depth")


def _check_positions(positions: np.ndarray, times_s: list[float], settings: MapSettings,
                     where: str) -> None:
    """Refuse camera positions (N, 3) metres beyond what the volume's block indices
    address (they would wrap, and the map be garbage); warn of a camera implausibly fast
    for a map (median speed between frames in ``times_s`` seconds)."""
    import warnings

    reach = 2.0**30 * settings.block_size_m  # int32 block indices, with a margin of 2
    farthest = float(np.abs(positions).max()) + settings.max_depth_m
    if farthest > reach:
        raise ValueError(f"{where}: camera positions lie up to {farthest:.3g} m from the world "
                         f"origin; the volume addresses {reach:.3g} m at voxel "
                         f"{settings.voxel_size_m * 100:g} cm: are the poses in metres?")
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    gaps = np.diff(np.asarray(times_s, dtype=np.float64))
    moving = gaps > 0
    if moving.any():
        speed = float(np.median(steps[moving] / gaps[moving]))
        if speed > IMPLAUSIBLE_SPEED_M_S:
            warnings.warn(f"{where}: the camera moves {speed:.3g} m/s between frames "
                          "(median); are the poses' translations in metres and their "
                          "times in seconds?", stacklevel=3)


def _frame_blocks_bound(settings: MapSettings, intrinsics) -> int:
    """Blocks a frame can touch: its view filled at the depth limit, counted by Open3D."""
    probe = TSDFMap(settings, capacity_blocks=1)
    depth = np.full((intrinsics.height, intrinsics.width), settings.max_depth_m * 0.999,
                    np.float32)
    return int(probe.frame_blocks(depth, intrinsics, np.eye(4)).shape[0])


def build_map(source: FrameSource, depth: DepthSource, plan: MapPlan, settings: MapSettings,
              *, on_frame: Callable[[MapFrame, np.ndarray, np.ndarray, TSDFMap], None] | None = None
              ) -> MapResult:
    """Predict each planned frame's depth and integrate it.

    Args:
        source: the frames.
        depth: the depth source (model, baseline or recorded).
        plan: from :func:`plan_map`.
        settings: the map settings.
        on_frame: called after each frame with (frame, its pose, its (H, W) depth in
            metres, the map) (progress, viewer).

    Returns:
        The map with the poses used and the timings.

    Raises:
        ValueError: a model depth source whose weights are made for another truncation
            distance than ``settings``'.
    """
    if depth.method is None and not math.isclose(depth.truncation_m, settings.truncation_m,
                                                 rel_tol=1e-6):
        raise ValueError(f"the depth source weighs pixels for a truncation of "
                         f"{depth.truncation_m:g} m, the map's is {settings.truncation_m:g} m: "
                         "give DepthSource(truncation_m=settings.truncation_m)")
    volume = TSDFMap(settings, capacity_blocks=plan.capacity_blocks)
    odometry = None
    if plan.poses is None:
        odometry = RGBDOdometry(plan.frames[0].calibration.intrinsics, settings.max_depth_m)
    used, times, names = [], [], []
    result = MapResult(volume, np.zeros((0, 4, 4)), np.zeros(0))
    for index, frame in enumerate(source.load(plan.frames)):
        start = time.perf_counter()
        depth_m, weight = depth(frame)
        depth_m = np.where(depth_m <= settings.max_depth_m, depth_m, 0.0).astype(np.float32)
        result.depth_s += time.perf_counter() - start
        # With lens distortion the depth is for the undistorted image (same intrinsics).
        colour = frame.calibration.undistort_image(frame.image)
        pose = odometry.step(colour, depth_m) if odometry is not None \
            else plan.poses[index]
        start = time.perf_counter()
        updated = volume.integrate(depth_m, colour, weight, frame.calibration.intrinsics,
                                   pose)
        result.integrate_s += time.perf_counter() - start
        result.empty_frames += int(updated == 0)
        used.append(pose)
        times.append(frame.time_s)
        names.append(frame.name)
        if on_frame is not None:
            on_frame(frame, pose, depth_m, volume)
    result.poses, result.times_s, result.frame_names = np.stack(used), np.array(times), names
    if odometry is not None:
        result.odometry = odometry.report
        if plan.reference_poses is not None and len(used) >= 2:
            result.ate_m = absolute_trajectory_error(result.poses, plan.reference_poses)
    return result
