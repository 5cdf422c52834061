"""Options and helpers for ROS 2 bags and the rerun viewer in ``predict``/``record``/``replay``.

The commands in :mod:`deltar.cli.capture` and :mod:`deltar.cli.predict` declare these
options and call the helpers; ``rosbags`` and ``rerun`` are imported only when a bag or
the viewer is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from deltar.cli.option_groups import option_group

if TYPE_CHECKING:
    from deltar.capture.viewer import RerunLogger
    from deltar.sensor.zone_frame import Orientation

RerunOption = typer.Option(False, "--rerun", help="Show the frames live in the rerun viewer "
                           "(needs the 'viewer' extra).")
RerunSaveOption = typer.Option(None, "--rerun-save", help="Write a rerun recording (.rrd) "
                               "instead of spawning the viewer.")
BagStorageOption = typer.Option("sqlite3", "--bag-storage", help="Storage of written bags: "
                                "sqlite3 or mcap.")
BagOption = typer.Option(None, "--bag", help="Read this ROS 2 bag instead of a recording "
                         "folder (needs the 'ros' extra).")
OutBagOption = typer.Option(None, "--out-bag", help="Write depth, uncertainty and CameraInfo "
                            "into this new ROS 2 bag.")
ImageTopicOption = Annotated[str | None, typer.Option(
    "--image-topic", help="Camera topic (Image rgb8/bgr8 or CompressedImage); found by type "
    "when unique.")]
InfoTopicOption = Annotated[str | None, typer.Option(
    "--info-topic", help="CameraInfo topic; found by type when unique.")]
TofTopicOption = Annotated[str | None, typer.Option(
    "--tof-topic", help="ToF topic; a deltar_msgs/msg/ZoneFrame topic is found by type when "
    "unique.")]
TofFormatOption = Annotated[str, typer.Option(
    "--tof-format", help="ToF topic format: deltar (deltar_msgs/msg/ZoneFrame) or "
    "vl53l5cx_ros2 (that driver's 32FC1 distance image).")]
TofOrientationOption = Annotated[str, typer.Option(
    "--tof-orientation", help="vl53l5cx_ros2 only: zone grid to image, a comma list of "
    "flip_ud, flip_lr, rot90:K, or 'none'.")]
TofSigmaOption = Annotated[float, typer.Option(
    "--tof-sigma", help="vl53l5cx_ros2 only: sigma in metres given to every zone (the driver "
    "publishes none).")]
PointsOption = typer.Option(False, "--points", help="Also write a coloured PointCloud2 per "
                            "frame into --out-bag.")
TopicPrefixOption = typer.Option("/deltar", "--topic-prefix", help="Prefix of the topics "
                                 "written into --out-bag.")


def parse_orientation(text: str, option: str = "--tof-orientation") -> Orientation:
    """``"flip_ud"``, ``"flip_lr,rot90:1"``, ``"none"``... -> :class:`Orientation` (a
    ``typer.BadParameter`` naming ``option`` for anything else)."""
    from deltar.sensor.zone_frame import Orientation

    flip_ud = flip_lr = False
    rot = 0
    for part in (p.strip() for p in text.split(",") if p.strip()):
        if part == "none":
            continue
        if part == "flip_ud":
            flip_ud = True
        elif part == "flip_lr":
            flip_lr = True
        elif part.startswith("rot90:") and part[6:].lstrip("-").isdigit():
            rot = int(part[6:])
        else:
            raise typer.BadParameter(f"unknown orientation part {part!r}; use flip_ud, "
                                     "flip_lr, rot90:K or none", param_hint=option)
    return Orientation(flip_ud=flip_ud, flip_lr=flip_lr, rot90=rot)


@dataclass(frozen=True)
class BagTopics:
    """A bag's topics and ToF format as given on the command line (``--image-topic`` ...
    ``--tof-sigma``; None: found by type)."""

    image_topic: str | None = None
    info_topic: str | None = None
    tof_topic: str | None = None
    tof_format: str = "deltar"
    tof_orientation: str = "flip_ud"
    tof_sigma: float = 0.0

    def bag_input_options(self) -> dict[str, Any]:
        """Keyword arguments of :class:`~deltar.io.rosbag_reader.BagInput` (the orientation
        parsed; ``typer.BadParameter`` naming ``--tof-orientation`` if it is not valid)."""
        return {"image_topic": self.image_topic, "info_topic": self.info_topic,
                "tof_topic": self.tof_topic, "tof_format": self.tof_format,
                "tof_orientation": parse_orientation(self.tof_orientation),
                "tof_sigma_m": self.tof_sigma}


#: Placeholder default of a command's ``topics`` parameter (the decorator replaces it).
BAG_TOPICS = BagTopics()
_BAG_TOPICS_GROUP = option_group("topics", BagTopics, {
    "image_topic": ImageTopicOption, "info_topic": InfoTopicOption,
    "tof_topic": TofTopicOption, "tof_format": TofFormatOption,
    "tof_orientation": TofOrientationOption, "tof_sigma": TofSigmaOption})


def bag_topic_options(command):
    """Replace the command's ``topics: BagTopics`` parameter by the six bag topic options
    (:func:`~deltar.cli.option_groups.option_group`)."""
    return _BAG_TOPICS_GROUP(command)


def check_viewer(rerun: bool, rerun_save: Path | None) -> None:
    """Refuse an existing ``--rerun-save`` file (the viewer streams into the file as
    frames come, so it never replaces one) and ``--rerun`` without a display (the viewer
    it spawns could not open); commands call it before their work."""
    from deltar.cli.checks import has_display

    if rerun_save is not None and rerun_save.exists():
        raise typer.BadParameter(f"{rerun_save} exists; give a new file (an existing "
                                 "recording is never replaced)", param_hint="--rerun-save")
    if rerun and rerun_save is None and not has_display() and not _viewer_listening():
        raise typer.BadParameter("the viewer needs a display (DISPLAY is not set); write a "
                                 "recording with --rerun-save FILE.rrd and open it where "
                                 "there is one (rerun FILE.rrd), or start a viewer here "
                                 "first (rerun --web-viewer)", param_hint="--rerun")


#: Where a running rerun viewer listens (rerun's default gRPC port on this machine).
RERUN_VIEWER_ADDRESS = ("127.0.0.1", 9876)


def _viewer_listening() -> bool:
    """Whether a rerun viewer (e.g. ``rerun --web-viewer`` on a headless machine) already
    listens on :data:`RERUN_VIEWER_ADDRESS`: ``--rerun`` then connects to it."""
    import socket

    try:
        with socket.create_connection(RERUN_VIEWER_ADDRESS, timeout=0.2):
            return True
    except OSError:
        return False


def open_viewer(rerun: bool, rerun_save: Path | None) -> RerunLogger | None:
    """A :class:`~deltar.capture.viewer.RerunLogger` when asked for, else None."""
    if not rerun and rerun_save is None:
        return None
    check_viewer(rerun, rerun_save)
    from deltar.capture.viewer import RerunLogger

    return RerunLogger(rerun_save)


def replay_bag_command(bag: Path, build_estimator, calibration, *, out, show, out_bag,
                       storage: str, topics: BagTopics, points: bool, prefix: str,
                       rerun: bool, rerun_save: Path | None, tolerance: float, every: int,
                       limit: int | None, time_offset: float | None = None,
                       skip_no_zones: bool = True) -> str:
    """Run ``deltar replay --bag``: write the output bag and/or feed the viewer.

    Args:
        bag: the input bag (only read).
        build_estimator: returns the depth estimator (called after the checks).
        calibration: a rig calibration, or None (nominal, from CameraInfo).
        topics: the bag's topics and ToF format.
        time_offset: ``--time-offset`` (None: the calibration's, else 0).
        skip_no_zones: not ``--allow-no-zones``.
        other arguments: the command's options.

    Returns:
        A one-line summary for the terminal.
    """
    from deltar.capture.bag_replay import replay_bag, replay_bag_to_bag
    from deltar.cli.progress import ProgressReport
    from deltar.io.rosbag_reader import BagInput

    if out is not None or show:
        raise typer.BadParameter("with --bag, write with --out-bag and/or view with --rerun "
                                 "/ --rerun-save (not --out / --show)")
    if out_bag is None and not rerun and rerun_save is None:
        raise typer.BadParameter("give --out-bag BAG, --rerun or --rerun-save FILE")
    if out_bag is not None:
        from deltar.io.input_file import refuse_input_as_output

        refuse_input_as_output(out_bag, [bag], "--out-bag", folder=True)
        if out_bag.exists():  # before the model: a bag is never written into
            raise typer.BadParameter(f"{out_bag} exists; a bag is written whole into a new "
                                     "path: choose another", param_hint="--out-bag")
    bag_input = BagInput(bag, **topics.bag_input_options())
    from deltar.calibration.rig import pairing_time_offset

    time_offset = pairing_time_offset(calibration, time_offset)
    pairs = bag_input.pairs(tolerance_s=tolerance, time_offset_s=time_offset)
    grid = _check_bag_fits(bag_input, pairs[0], calibration)
    estimator = build_estimator()  # after the checks: a bad bag fails first
    if estimator.onnx_model is not None:  # its zone grid is fixed: checked before any frame
        estimator.onnx_model.check_grid(grid, f"the bag {bag}")
    viewer = open_viewer(rerun, rerun_save)
    kwargs = {"calibration": calibration, "pairs": pairs, "every": every, "limit": limit,
              "skip_no_zones": skip_no_zones}
    with ProgressReport("replaying") as progress:
        kwargs["on_total"] = progress.set_total  # the frames replay_bag chose to predict

        def each(item) -> None:
            if viewer is not None:
                viewer.log_prediction(item.image, item.prediction,
                                      calibration=item.calibration,
                                      time_s=item.pair.image_stamp_ns / 1e9)
            progress.advance()

        try:
            if out_bag is not None:
                path, frames = replay_bag_to_bag(bag_input, estimator, out_bag,
                                                 storage=storage, prefix=prefix,
                                                 points=points, on_item=each, **kwargs)
                return f"wrote {frames} frames of depth to the bag {path}"
            frames = 0
            for item in replay_bag(bag_input, estimator, **kwargs):
                each(item)
                frames += 1
            return f"replayed {frames} frames of {bag_input.path}"
        finally:
            if viewer is not None:
                viewer.close()


def _check_bag_fits(bag, pair, calibration) -> int:
    """The bag's first pair against ``--calib`` (zone grid, image size), or its
    CameraInfo (without ``--calib``), before the model; returns the zone grid.

    Raises:
        ValueError: naming ``--calib`` and the topic that disagrees with it.
    """
    from deltar.capture.bag_replay import pair_calibration

    pair_calibration(pair, calibration)  # no CameraInfo and no --calib: refused here
    grid = pair.zone_frame.grid
    if calibration is None:
        return grid
    if calibration.grid != grid:
        raise ValueError(f"--calib is for a {calibration.grid}x{calibration.grid} zone grid, "
                         f"the bag {bag.path} has {grid}x{grid} on {bag.tof_topic}")
    # One image decoded (a compressed one has no size otherwise); the bag is read no
    # further than it.
    images = bag.images([pair])
    try:
        _, image = next(images)
    finally:
        images.close()
    calibration.check_image_size(image.shape[:2], f"the images of {bag.image_topic}",
                                 "--calib")
    return grid


class CaptureLogger:
    """Log recorded captures (image, latest zone frame, reference depth) to the viewer.

    Called as ``on_capture(capture, meta)`` by :func:`deltar.capture.record.record`.
    """

    def __init__(self, viewer: RerunLogger) -> None:
        self.viewer = viewer
        self.zone_frame = None

    def __call__(self, capture, meta) -> None:
        from deltar.calibration.rig import RigCalibration
        from deltar.sensor.geometry import SensorExtrinsics

        if capture.zone_frame is not None:
            self.zone_frame = capture.zone_frame
        if capture.image is None or self.zone_frame is None:
            return
        calib = RigCalibration(meta.intrinsics, SensorExtrinsics(), grid=meta.grid,
                               fov_deg=meta.fov_deg)
        rects = calib.zone_rects_for(self.zone_frame, capture.image.shape[:2])
        self.viewer.log_frame(capture.image, self.zone_frame, rects, meta.intrinsics,
                              time_s=capture.image_time_s, fov_deg=meta.fov_deg,
                              depth_m=capture.depth_m)


class ReplayViewer:
    """Pass replay items through, logging each to the viewer (when there is one).

    Args:
        viewer: a :class:`RerunLogger` or None (then items only pass through).
        recording: the recording folder (its metadata places the sensor without a
            calibration).
        calibration: the rig calibration the replay uses, or None.
    """

    def __init__(self, viewer: RerunLogger | None, recording: Path, calibration) -> None:
        self.viewer = viewer
        self.calibration = calibration
        if viewer is not None and calibration is None:
            from deltar.capture.replay import recording_calibration
            from deltar.io.recording import Recording

            self.calibration = recording_calibration(Recording(recording))

    def __call__(self, item):
        if self.viewer is not None:
            self.viewer.log_prediction(item.image, item.prediction,
                                       calibration=self.calibration,
                                       time_s=item.pair.zone_frame.timestamp_s)
        return item

    def close(self) -> None:
        """Finish the viewer's recording."""
        if self.viewer is not None:
            self.viewer.close()
