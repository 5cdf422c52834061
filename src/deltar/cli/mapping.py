"""``deltar map``: a TSDF map (mesh + points) of a recording or a ROS 2 bag."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import typer

from deltar.cli.model_options import MODEL_OPTIONS, ModelOptions, model_options
from deltar.cli.robotics import (
    BAG_TOPICS,
    BagTopics,
    RerunOption,
    RerunSaveOption,
    bag_topic_options,
)


def _settings(voxel: float, truncation: float, max_depth: float, max_memory: float):
    from deltar.mapping.tsdf import MapSettings

    try:
        return MapSettings(voxel_size_m=voxel, truncation_voxels=truncation,
                           max_depth_m=max_depth, max_memory_bytes=int(max_memory * 2**20))
    except ValueError as err:
        option = {"voxel_size_m": "--voxel", "truncation_voxels": "--truncation",
                  "max_depth_m": "--max-depth", "max_memory_bytes": "--max-memory"}
        hint = next((o for k, o in option.items() if k in str(err)), None)
        raise typer.BadParameter(str(err), param_hint=hint) from err


#: The files ``deltar map`` writes into its ``--out`` folder (map.json last).
MAP_OUTPUTS = ("mesh.ply", "points.ply", "trajectory.txt", "map.json")


def _check_out(out: Path, recording: Path, inputs: list[Path | None], overwrite: bool) -> None:
    """Refuse an ``--out`` inside the recording, or one whose outputs would replace an input
    file (``inputs``: --calib, --trajectory, the model's files), whatever --overwrite."""
    from deltar.cli.checks import existing_outputs, output_folder
    from deltar.io.input_file import refuse_input_as_output

    refuse_input_as_output(out, [recording], "--out", folder=True)
    for name in MAP_OUTPUTS:
        refuse_input_as_output(out / name, inputs, "--out")
    output_folder(out, "--out")
    if not overwrite:
        outputs = [out / name for name in MAP_OUTPUTS[:-1]]
        if not (out / "map.json").exists() and any(p.exists() for p in outputs):
            # map.json is written last: without it the map was stopped while being written.
            held = ", ".join(p.name for p in outputs if p.exists())
            raise FileExistsError(f"--out: {out} holds an unfinished map ({held}, no map.json: "
                                  "it was stopped while being written); pass --overwrite to "
                                  "make it again")
        existing_outputs([*outputs, out / "map.json"])


def _check_rerun_save(rerun_save: Path | None, out: Path, recording: Path,
                      inputs: list[Path | None]) -> None:
    """Refuse a ``--rerun-save`` file inside the input, on an input file or on one of the
    map's outputs: the viewer streams into it from the first frame, so a clash would only
    show after the run (an existing file is refused by ``check_viewer``)."""
    from deltar.io.input_file import refuse_input_as_output

    if rerun_save is None:
        return
    refuse_input_as_output(rerun_save, [recording, *inputs], "--rerun-save", folder=True)
    outputs = {(out / name).resolve() for name in MAP_OUTPUTS}
    if rerun_save.resolve() in outputs:
        raise ValueError(f"--rerun-save {rerun_save} is one of the map's outputs in --out "
                         f"{out} ({', '.join(MAP_OUTPUTS)}); choose another file")


def _refuse_ignored_options(model: ModelOptions, method: str | None, blend: bool,
                            max_relative_sigma: float | None, is_bag: bool,
                            topics: BagTopics, pose_topic: str | None) -> None:
    """Refuse options that would be accepted and then have no effect: model options with
    --method (a baseline or the recorded depth runs no model), bag options on a recording
    folder (it has no topics)."""
    if method is not None:
        given = model.given_options() + ["--blend"] * blend + \
            ["--max-relative-sigma"] * (max_relative_sigma is not None)
        if given:
            raise typer.BadParameter(f"{given[0]} is a model option: give a model option or "
                                     "--method, not both", param_hint=given[0])
    if not is_bag:
        defaults = BagTopics()
        given = [f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(topics)
                 if getattr(topics, f.name) != getattr(defaults, f.name)]
        given += ["--pose-topic"] * (pose_topic is not None)
        if given:
            raise typer.BadParameter(f"{given[0]} is for ROS 2 bags; a recording folder has "
                                     "no topics", param_hint=given[0])


@model_options
@bag_topic_options
def map_command(
    recording: Path = typer.Argument(..., help="Recording folder (deltar record) or ROS 2 bag "
                                     "folder."),
    out: Path = typer.Option(..., "--out", help="Output folder: mesh.ply, points.ply, "
                             "trajectory.txt, map.json."),
    calib: Path | None = typer.Option(None, "--calib", help="Rig calibration JSON (deltar "
                                      "calibrate)."),
    model: ModelOptions = MODEL_OPTIONS,
    method: str | None = typer.Option(None, "--method", help="Depth from a classical "
                                      "baseline (e.g. colorization) instead of the model, "
                                      "or 'recorded': the recording's own depth images "
                                      "(a bag's depth topic)."),
    blend: bool = typer.Option(False, "--blend", help="Keep the estimator's confidence "
                               "blend with the colorization fill (off in maps: the network "
                               "alone fused into better maps, docs/mapping.md)."),
    trajectory: Path | None = typer.Option(None, "--trajectory", help="Camera poses as a "
                                           "TUM file (t tx ty tz qx qy qz qw, camera to "
                                           "world) for a recording without pose/."),
    pose_topic: str | None = typer.Option(None, "--pose-topic", help="Bags: a "
                                          "geometry_msgs/msg/PoseStamped topic of camera "
                                          "poses (default: /tf when the bag has it, else "
                                          "/camera/pose)."),
    depth_topic: str | None = typer.Option(None, "--depth-topic", help="Bags: the depth "
                                           "Image topic (32FC1 m or 16UC1 mm, registered to "
                                           "the camera) --method recorded maps (default: "
                                           "/camera/depth/image when the bag has it)."),
    odometry: bool = typer.Option(False, "--odometry", help="Use RGB-D odometry even when "
                                  "poses exist (they then measure its trajectory error)."),
    voxel: float = typer.Option(0.02, "--voxel", help="Voxel size, metres."),
    truncation: float = typer.Option(4.0, "--truncation", help="TSDF truncation, voxels."),
    max_depth: float | None = typer.Option(None, "--max-depth", help="Depth limit, metres "
                                           "(default: the ToF sensor's range, 4 m for the "
                                           "L5)."),
    max_relative_sigma: float | None = typer.Option(None, "--max-relative-sigma", help="Model "
                                                    "pixels whose uncertainty / depth exceeds "
                                                    "this (default 0.15) are skipped; below, a "
                                                    "pixel weighs 1 / (1 + (sigma / "
                                                    "truncation)^2)."),
    beyond_grid: bool = typer.Option(False, "--beyond-grid", help="Also fuse model pixels "
                                     "beyond the 8x8 zone grid (extrapolated from the "
                                     "image; still gated by --max-relative-sigma)."),
    max_memory: float = typer.Option(2048.0, "--max-memory", help="Memory budget of the "
                                     "volume, MiB (it never grows past it)."),
    tolerance: float = typer.Option(0.02, min=0.0, help="Largest image-zone time offset, "
                                    "seconds."),
    pose_tolerance: float = typer.Option(0.05, "--pose-tolerance", min=0.0, help="Largest "
                                         "gap of a trajectory around a frame, seconds."),
    every: int = typer.Option(1, min=1, help="Use every N-th frame."),
    limit: int | None = typer.Option(None, min=1, help="Map at most this many frames."),
    overwrite: bool = typer.Option(False, help="Replace existing outputs."),
    topics: BagTopics = BAG_TOPICS,
    rerun: bool = RerunOption,
    rerun_save: Path | None = RerunSaveOption,
) -> None:
    """Fuse every frame's depth into a TSDF map (Open3D) and write its mesh and points.

    The model runs without its colorization blend (--blend keeps it). Each pixel of
    the model's depth inside the zone grid is weighted by its confidence (--beyond-grid
    adds the pixels beyond it); depth beyond the sensor's range is not used. Poses: the
    recording's pose/ folder, --trajectory, the bag's /tf or --pose-topic, else RGB-D
    odometry. Everything is checked (inputs, poses, memory) before the first depth map
    is made.
    """
    from deltar.cli.checks import finite
    from deltar.cli.errors import warn
    from deltar.cli.progress import ProgressReport
    from deltar.cli.robotics import check_viewer
    from deltar.mapping.builder import build_map, plan_map
    from deltar.mapping.frames import DEFAULT_MAX_RELATIVE_SIGMA, RECORDED, DepthSource, FrameSource
    from deltar.mapping.poses import write_tum_trajectory
    from deltar.mapping.tsdf import require_open3d

    for value, option in ((voxel, "--voxel"), (truncation, "--truncation"),
                          (max_memory, "--max-memory")):
        finite(value, option, positive=True)
    for value, option in ((max_depth, "--max-depth"),
                          (max_relative_sigma, "--max-relative-sigma")):
        if value is not None:
            finite(value, option, positive=True)
    is_bag = (recording / "metadata.yaml").is_file()
    _refuse_ignored_options(model, method, blend, max_relative_sigma, is_bag, topics,
                            pose_topic)
    if max_relative_sigma is None:
        max_relative_sigma = DEFAULT_MAX_RELATIVE_SIGMA
    if beyond_grid and method is not None:
        raise typer.BadParameter("--beyond-grid is for the model's pixels; a --method "
                                 "baseline's are all integrated", param_hint="--beyond-grid")
    if blend and model.network_only:
        raise typer.BadParameter("give --blend or --network-only, not both",
                                 param_hint="--blend")
    # Maps fuse the network's own depth unless --blend (measured: benchmarks/RESULTS.md).
    model = dataclasses.replace(model, network_only=not blend)
    model.check()
    require_open3d()
    inputs = [calib, trajectory, *model.input_files()]
    _check_out(out, recording, inputs, overwrite)
    check_viewer(rerun, rerun_save)
    _check_rerun_save(rerun_save, out, recording, inputs)
    calibration = None
    if calib is not None:
        from deltar.calibration.rig import RigCalibration

        calibration = RigCalibration.load(calib)
    if depth_topic is not None and (not is_bag or method != RECORDED):
        raise typer.BadParameter("--depth-topic names the depth --method recorded maps from "
                                 "a ROS 2 bag (a recording keeps its depth in depth/)",
                                 param_hint="--depth-topic")
    bag_options = {}
    if is_bag:
        from deltar.io.rosbag_reader import AUTO_DEPTH_TOPIC

        # Depth is read only to be mapped: any other method ignores the bag's depth topic.
        bag_options = {**topics.bag_input_options(), "depth_topic":
                       (depth_topic or AUTO_DEPTH_TOPIC) if method == RECORDED else None}
    source = FrameSource(recording, calibration=calibration, tolerance_s=tolerance,
                         every=every, limit=limit, bag_options=bag_options)
    settings = _settings(voxel, truncation, max_depth or source.depth_limit_m(), max_memory)
    # A bad method name fails here, before the poses and the model.
    depth = DepthSource(method=method, max_relative_sigma=max_relative_sigma) \
        if method is not None else None
    missing = source.frames_without_recorded_depth() if method == RECORDED else 0
    if missing == len(source) and missing:
        where = f"a depth topic near its images (name it with --depth-topic; topics: " \
            f"{', '.join(sorted(source.bag.topics))})" if source.kind == "bag" else \
            "depth/ images"
        raise typer.BadParameter(f"{recording} has no recorded depth: --method recorded "
                                 f"needs {where}", param_hint="--method")
    if method == RECORDED:
        source.check_recorded_depth_size()
    if missing:
        raise typer.BadParameter(f"{missing} of {len(source)} frames of {recording} have no "
                                 f"recorded depth within --tolerance {tolerance:g} s of their "
                                 "image; --method recorded needs it for every frame (map "
                                 "fewer with --every / --limit, or raise --tolerance)",
                                 param_hint="--method")
    plan = plan_map(source, settings, trajectory=trajectory, pose_topic=pose_topic,
                    force_odometry=odometry, tolerance_s=pose_tolerance)
    if plan.skipped_no_pose:
        warn(f"{plan.skipped_no_pose} of {len(source)} frames have no pose and are left out")
    typer.echo(f"poses: {plan.pose_source}; {len(plan.frames)} frames; volume: at most "
               f"{settings.max_blocks} blocks = {settings.max_blocks * _block_mib(settings):.0f}"
               f" MiB, estimated <= {plan.estimated_blocks * _block_mib(settings):.0f} MiB "
               f"(voxel {settings.voxel_size_m * 100:g} cm, truncation "
               f"{settings.truncation_m * 100:g} cm, depth <= {settings.max_depth_m:g} m)")
    if settings.memory_clipped:
        warn(f"--max-memory {max_memory:g} MiB is clipped to {settings.max_blocks} blocks "
             f"({settings.max_blocks * _block_mib(settings):.0f} MiB): Open3D crashes "
             "extracting the surface of larger volumes")
    if depth is None:
        depth = DepthSource(model.load(), max_relative_sigma=max_relative_sigma,
                            truncation_m=settings.truncation_m, beyond_grid=beyond_grid)
    viewer = None
    if rerun or rerun_save is not None:
        from deltar.mapping.viewer import MapViewer

        viewer = MapViewer(rerun_save)
    with ProgressReport("mapping", total=len(plan.frames)) as progress:

        def each(frame, pose, depth_m, volume) -> None:
            if viewer is not None:
                viewer.log(frame, pose, volume, depth_m)
            progress.advance()

        result = build_map(source, depth, plan, settings, on_frame=each)
    if viewer is not None:
        viewer.close(result.volume)
    volume = result.volume
    paths = volume.write(out, overwrite=overwrite)
    write_tum_trajectory(out / "trajectory.txt", result.times_s, result.poses)
    bounds = volume.bounds_m()
    summary = {
        "input": str(recording), "depth": depth.name, "poses": plan.pose_source,
        "frames": len(result.poses), "empty_frames": result.empty_frames,
        "voxel_size_m": settings.voxel_size_m, "truncation_m": settings.truncation_m,
        "max_depth_m": settings.max_depth_m,
        "max_relative_sigma": max_relative_sigma if method is None else None,
        "beyond_grid": beyond_grid if method is None else None,
        "blocks": volume.block_count, "capacity_blocks": volume.capacity_blocks,
        "memory_bytes": volume.memory_bytes, "used_bytes": volume.used_bytes,
        "frames_over_capacity": volume.full_frames,
        "extent_m": None if bounds is None else (bounds[1] - bounds[0]).round(3).tolist(),
        "integrate_s": round(result.integrate_s, 3), "depth_s": round(result.depth_s, 3),
        "odometry": None if result.odometry is None else {
            "pairs": result.odometry.pairs, "failed": result.odometry.failed,
            "path_length_m": result.odometry.path_length_m},
        "ate_m": result.ate_m,
    }
    from deltar.io.atomic import write_text_atomic

    write_text_atomic(out / "map.json", json.dumps(summary, indent=2) + "\n")
    if result.odometry is not None:
        typer.echo(result.odometry.summary()
                   + ("" if result.ate_m is None else
                      f"; trajectory error (ATE) against the given poses {result.ate_m:.3f} m"))
        from deltar.mapping.odometry import MAX_CAMERA_SPEED_M_S, median_speed

        speed = median_speed(result.poses, result.times_s)
        if speed > MAX_CAMERA_SPEED_M_S:
            warn(f"the odometry moves the camera at a median {speed:.1f} m/s between "
                 f"frames (more than {MAX_CAMERA_SPEED_M_S:g} m/s): the frames may not be "
                 "one continuous sequence (e.g. generated rooms), so the map is unreliable; "
                 "give poses (pose/ folder, --trajectory) if there are any")
    if result.empty_frames:
        warn(f"{result.empty_frames} of {len(result.poses)} frames had no depth to fuse "
             "(e.g. no valid zone for a --method baseline)")
    extent = "empty" if bounds is None else \
        " x ".join(f"{v:.2f}" for v in bounds[1] - bounds[0]) + " m"
    typer.echo(f"volume: {volume.block_count} blocks ({extent}), "
               f"{volume.used_bytes / 2**20:.1f} MiB used of {volume.memory_bytes / 2**20:.0f} "
               f"MiB reserved; integration {len(result.poses) / max(result.integrate_s, 1e-9):.1f}"
               f" frames/s (depth {result.depth_s / max(len(result.poses), 1):.2f} s/frame)")
    typer.echo(f"wrote {paths['mesh']}, {paths['points']}, {out / 'trajectory.txt'}, "
               f"{out / 'map.json'}")


def _block_mib(settings) -> float:
    from deltar.mapping.tsdf import block_bytes

    return block_bytes(settings.block_resolution) / 2**20
