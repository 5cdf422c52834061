"""Recording layout shared by ``deltar calibrate``, recording and replay.

A recording is a folder::

    meta.json            schema_version, intrinsics, sensor_model, grid, fov_deg
    zones.jsonl          one zone frame per line (``deltar.io.zone_file`` schema, with
                         timestamp_s), timestamps strictly increasing
    color/<ns>.png       RGB images, file name = capture time in integer nanoseconds
    depth/<ns>.png       optional depth maps, uint16 millimetres, 0 = invalid
    pose/<ns>.txt        optional camera poses, 4x4 camera-to-world (deltar.io.pose_file)

All timestamps are seconds on one clock shared by the sensor and the cameras.
"""

from __future__ import annotations

import json
import numbers
import os
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from deltar.camera import CameraIntrinsics, check_image, strict_integer, strict_number
from deltar.io.atomic import atomic_path, write_text_atomic
from deltar.io.input_file import input_file, input_folder, not_8bit_colour, reading
from deltar.io.json_file import read_json
from deltar.io.pose_file import POSE_DIR, write_pose_file
from deltar.io.zone_file import check_writable, zone_frame_from_dict, zone_frame_to_dict
from deltar.io.zone_lines import append_zone_line, end_partial_line, last_zone_timestamp
from deltar.sensor.geometry import DEFAULT_FOV_DEG
from deltar.sensor.zone_frame import ZoneFrame

RECORDING_SCHEMA_VERSION = 1
META_FILE = "meta.json"
ZONES_FILE = "zones.jsonl"
COLOR_DIR = "color"
DEPTH_DIR = "depth"


@dataclass(frozen=True)
class RecordingMeta:
    """What ``meta.json`` holds.

    Attributes:
        intrinsics: colour camera intrinsics (pixels); depth images are aligned to colour.
        sensor_model: e.g. ``"VL53L5CX"``.
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) sensor field of view in degrees.
        created: ISO 8601 creation time (UTC).
    """

    intrinsics: CameraIntrinsics
    sensor_model: str = "VL53L5CX"
    grid: int = 8
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG
    created: str = ""

    def __post_init__(self) -> None:  # what the reader refuses is never written
        if self.grid not in (4, 8) or isinstance(self.grid, bool):
            raise ValueError(f"RecordingMeta.grid must be 4 or 8, got {self.grid!r}")
        if len(self.fov_deg) != 2 or not all(isinstance(f, numbers.Real) and 0 < f < 180
                                             for f in self.fov_deg):
            raise ValueError(f"RecordingMeta.fov_deg must be two angles in (0, 180) degrees, "
                             f"got {self.fov_deg!r}")

    def to_dict(self) -> dict:
        return {"schema_version": RECORDING_SCHEMA_VERSION,
                "intrinsics": self.intrinsics.to_dict(), "sensor_model": self.sensor_model,
                "grid": int(self.grid), "fov_deg": [float(f) for f in self.fov_deg],
                "created": self.created}

    @classmethod
    def from_dict(cls, data: dict, source: str = META_FILE) -> RecordingMeta:
        if not isinstance(data, dict):
            raise ValueError(f"{source}: expected a JSON object")
        if data.get("schema_version") != RECORDING_SCHEMA_VERSION:
            raise ValueError(f"{source}: unsupported schema_version "
                             f"{data.get('schema_version')!r}")
        try:
            intr = CameraIntrinsics.from_dict(data["intrinsics"])
            fov_values = [strict_number(f, "fov_deg") for f in data.get("fov_deg",
                                                                        DEFAULT_FOV_DEG)]
            grid = strict_integer(data.get("grid", 8), "grid")
            return cls(intr, str(data.get("sensor_model", "VL53L5CX")), grid,  # checks them
                       tuple(fov_values), str(data.get("created", "")))
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{source}: invalid recording metadata: {err}") from err


def timestamp_to_ns(timestamp_s: float) -> int:
    """Seconds -> integer nanoseconds (the image file name).

    Raises:
        ValueError: a time that is not a finite number of seconds.
    """
    value = float(timestamp_s)
    if not np.isfinite(value):
        raise ValueError(f"timestamp_s must be a finite time in seconds, got {timestamp_s}")
    return round(value * 1e9)


def check_recording_folder(folder: str | os.PathLike) -> Path:
    """A folder a recording can be written to: new, empty (hidden files aside) or a
    recording (it holds ``meta.json``; frames are appended).

    Appending is for recordings only: frames added to another folder (an RGB-D set, a
    bag, outputs) would mix with its files.

    Raises:
        FileExistsError: ``folder`` holds files but no recording.
    """
    folder = Path(folder)
    if folder.is_dir() and not (folder / META_FILE).is_file() and any(
            not entry.name.startswith(".") for entry in folder.iterdir()):
        raise FileExistsError(f"{folder} is not empty and holds no recording (no "
                              f"{META_FILE}): record into a new or empty folder, or into a "
                              "recording to append to")
    return folder


class RecordingWriter:
    """Append-only writer of a recording folder; never overwrites an existing file.

    Args:
        folder: the recording folder (created if missing).
        meta: metadata written to ``meta.json``; when the folder already holds a
            recording, it must match (then new frames are appended).

    Raises:
        FileExistsError: ``folder`` holds files but no recording (no ``meta.json``).
        ValueError: the folder's recording is of another rig (intrinsics, sensor model,
            grid, fov), naming what differs.
    """

    def __init__(self, folder: str | os.PathLike, meta: RecordingMeta) -> None:
        self.folder = Path(folder)
        meta_path = self.folder / META_FILE
        if meta_path.exists():
            recording = Recording(self.folder)
            existing = recording.meta
            differ = [name for name, old, new in (
                ("intrinsics", existing.intrinsics, meta.intrinsics),
                ("sensor_model", existing.sensor_model, meta.sensor_model),
                ("grid", existing.grid, meta.grid),
                ("fov_deg", tuple(existing.fov_deg), tuple(meta.fov_deg))) if old != new]
            if differ:
                raise ValueError(f"{meta_path}: the existing recording has another "
                                 f"{', '.join(differ)} (another rig); write to a new folder")
            self.meta = existing
            end_partial_line(self.folder / ZONES_FILE)
            # Each stream against its own end (the sensor's stamps may run behind or ahead
            # of the camera's by time_offset_s); a stream still empty against the other's.
            camera = recording.camera_end_time_s()
            zones = last_zone_timestamp(self.folder / ZONES_FILE)
            self._camera_end = zones if camera is None else camera
            self._zone_end = self._camera_end if zones is None else zones
        else:
            check_recording_folder(self.folder)
            created = meta.created or datetime.now(timezone.utc).isoformat(timespec="seconds")
            self.meta = RecordingMeta(meta.intrinsics, meta.sensor_model, meta.grid,
                                      (float(meta.fov_deg[0]), float(meta.fov_deg[1])),
                                      created)
            write_text_atomic(meta_path, json.dumps(self.meta.to_dict(), indent=2) + "\n",
                              overwrite=False)
            self._camera_end = self._zone_end = None
        (self.folder / COLOR_DIR).mkdir(exist_ok=True)

    def _check_after_end(self, timestamp_s: float, what: str, end_s: float | None) -> None:
        """Appending: an item stamped before the end of its stream in the recording found
        at open would land among its frames (a clock that started again, e.g. a reboot)."""
        if end_s is not None and not timestamp_s > end_s:
            raise ValueError(f"{self.folder}: {what} stamped {timestamp_s} s is not after the "
                             f"end of the recording it appends to ({end_s} s): "
                             "the clock started again? record into a new folder")

    def close(self) -> None:
        """Nothing to finish: every item is complete on disk once its call returns."""

    def add_zone_frame(self, frame: ZoneFrame) -> None:
        """Append one zone frame (must have a timestamp later than the previous one).

        Raises:
            ValueError: no timestamp, another grid, a time not after the previous frame's,
                or a frame the reader would refuse (which would make the whole recording
                unreadable: :func:`deltar.io.zone_file.check_writable`).
        """
        check_writable(frame)
        if frame.timestamp_s is None:
            raise ValueError("frame.timestamp_s is required in a recording")
        if frame.grid != self.meta.grid:
            raise ValueError(f"frame has a {frame.grid}x{frame.grid} grid, recording is "
                             f"{self.meta.grid}x{self.meta.grid}")
        self._check_after_end(frame.timestamp_s, "zone frame", self._zone_end)
        line = json.dumps(zone_frame_to_dict(frame), allow_nan=False) + "\n"
        # Checked against the file's last frame, under a lock: another writer may append.
        append_zone_line(self.folder / ZONES_FILE, line, float(frame.timestamp_s))

    def add_color(self, timestamp_s: float, image_rgb: np.ndarray) -> Path:
        """Write ``color/<ns>.png`` from an (H, W, 3) uint8 RGB image of the camera size."""
        import cv2

        size = (self.meta.intrinsics.height, self.meta.intrinsics.width)
        image = check_image(image_rgb, "image_rgb", size)
        return self._write_png(COLOR_DIR, timestamp_s, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))

    def add_depth(self, timestamp_s: float, depth_m: np.ndarray) -> Path:
        """Write ``depth/<ns>.png`` (uint16 mm) from an (H, W) depth map in metres, 0 invalid."""
        depth = np.asarray(depth_m, dtype=np.float64)
        size = (self.meta.intrinsics.height, self.meta.intrinsics.width)
        if depth.shape != size:
            raise ValueError(f"depth_m must have shape {size}, got {depth.shape}")
        if not np.all(np.isfinite(depth)) or np.any(depth < 0) or np.any(depth > 65.535):
            raise ValueError("depth_m must be finite, >= 0 and <= 65.535 m")
        (self.folder / DEPTH_DIR).mkdir(exist_ok=True)
        return self._write_png(DEPTH_DIR, timestamp_s, np.round(depth * 1000).astype(np.uint16))

    def add_pose(self, timestamp_s: float, pose: np.ndarray) -> Path:
        """Write ``pose/<ns>.txt``: the colour camera's (4, 4) camera-to-world pose
        (metres) when the colour image of the same time was taken.

        Raises:
            ValueError: not a rigid transform (:func:`deltar.io.pose_file.check_pose`).
            FileExistsError: a pose of that time exists.
        """
        path = self.folder / POSE_DIR / f"{timestamp_to_ns(timestamp_s)}.txt"
        if not path.exists():  # an existing file: FileExistsError, as for images
            self._check_after_end(timestamp_s, "pose", self._camera_end)
        (self.folder / POSE_DIR).mkdir(exist_ok=True)
        return write_pose_file(path, pose)

    def _write_png(self, subdir: str, timestamp_s: float, image: np.ndarray) -> Path:
        import cv2

        path = self.folder / subdir / f"{timestamp_to_ns(timestamp_s)}.png"
        with atomic_path(path, overwrite=False) as tmp:  # an existing file: FileExistsError
            self._check_after_end(timestamp_s, f"{subdir} image", self._camera_end)
            ok, data = cv2.imencode(".png", image)
            if not ok:
                raise ValueError(f"could not encode {path}")
            tmp.write_bytes(data.tobytes())
        return path


@dataclass(frozen=True)
class RecordingPair:
    """One zone frame with its nearest colour (and depth) image.

    Attributes:
        zone_frame: the ToF reading.
        color_path: the colour PNG.
        depth_path: the depth PNG, or None when the recording has none near this time.
        color_offset_s: colour stamp minus zone stamp, seconds (including any time
            offset the pairing applied).
    """

    zone_frame: ZoneFrame
    color_path: Path
    depth_path: Path | None
    color_offset_s: float

    def load_color(self) -> np.ndarray:
        """The colour image, (H, W, 3) uint8 RGB (8-bit grey expanded, alpha dropped).

        Raises:
            ValueError: unreadable, or not 8 bits per channel (a 16-bit or float image
                is a depth map, not a colour image), naming the file.
        """
        import cv2

        image = cv2.imread(str(self.color_path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"{self.color_path}: unreadable image")
        if image.dtype != np.uint8:
            raise ValueError(not_8bit_colour(self.color_path, image.dtype,
                                             1 if image.ndim == 2 else image.shape[2]))
        if image.ndim == 2:
            return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
        code = cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB
        return cv2.cvtColor(image, code)

    def load_depth(self) -> np.ndarray:
        """The depth map, (H, W) float32 metres, 0 = invalid."""
        import cv2

        if self.depth_path is None:
            raise FileNotFoundError("this pair has no depth image")
        depth = cv2.imread(str(self.depth_path), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
            raise ValueError(f"{self.depth_path}: expected a single-channel uint16 PNG")
        return depth.astype(np.float32) / 1000.0

    def load_images(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(:meth:`load_color`, :meth:`load_depth` or None when the pair has no depth)."""
        return self.load_color(), None if self.depth_path is None else self.load_depth()


class Recording:
    """Reader of a recording folder.

    Args:
        folder: the folder written by ``RecordingWriter`` (or by hand in the same layout).

    Raises:
        FileNotFoundError: missing folder, ``meta.json`` or ``zones.jsonl``.
        ValueError: corrupt metadata or zone lines, unsorted or duplicate timestamps
            (the message names the file and line).
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = input_folder(folder, "recording folder")
        meta_path = self.folder / META_FILE
        if not meta_path.exists():
            hint = " (it is a ROS 2 bag, not a recording folder; 'deltar replay --bag' " \
                "reads bags)" if (self.folder / "metadata.yaml").is_file() else ""
            raise FileNotFoundError(f"recording has no {META_FILE}: {meta_path}{hint}")
        with reading(meta_path, "recording metadata"):
            self.meta = RecordingMeta.from_dict(read_json(meta_path, "recording metadata"),
                                                str(meta_path))
        self.color_times_s, self.color_paths = _image_index(self.folder / COLOR_DIR)
        self.depth_times_s, self.depth_paths = _image_index(self.folder / DEPTH_DIR)

    @property
    def zones_path(self) -> Path:
        """The recording's zone-frame file (``zones.jsonl``, docs/formats.md)."""
        return self.folder / ZONES_FILE

    def camera_end_time_s(self) -> float | None:
        """The latest time of any colour image or depth map, seconds; None without one."""
        times = [float(t[-1]) for t in (self.color_times_s, self.depth_times_s) if t.size]
        return max(times) if times else None

    def end_time_s(self) -> float | None:
        """The latest time of any colour image, depth map or zone frame, seconds; None
        for an empty recording (what a clock that appends must start after)."""
        times = [t for t in (self.camera_end_time_s(), last_zone_timestamp(self.zones_path))
                 if t is not None]
        return max(float(t) for t in times) if times else None

    def zone_frames(self) -> list[ZoneFrame]:
        """All zone frames in file order (timestamps strictly increasing, checked)."""
        path = self.zones_path
        if not path.exists():
            raise FileNotFoundError(f"recording has no {ZONES_FILE}: {path}")
        with reading(input_file(path, ZONES_FILE), "zone frames"):
            return self._read_zone_lines(path)

    def _read_zone_lines(self, path: Path) -> list[ZoneFrame]:
        lines = path.read_bytes().decode("utf-8").splitlines()
        frames: list[ZoneFrame] = []
        for number, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                data = json.loads(line)
            except json.JSONDecodeError as err:
                if number == len(lines):  # an interrupted final append
                    warnings.warn(f"{path}:{number}: skipping truncated last line",
                                  stacklevel=2)
                    continue
                raise ValueError(f"{path}:{number}: corrupt JSON line: {err}") from err
            frame = zone_frame_from_dict(data, source=f"{path}:{number}")
            if frame.timestamp_s is None:
                raise ValueError(f"{path}:{number}: zone frame has no timestamp_s")
            if frames and frame.timestamp_s <= frames[-1].timestamp_s:
                kind = "duplicate" if frame.timestamp_s == frames[-1].timestamp_s else "unsorted"
                raise ValueError(f"{path}:{number}: {kind} timestamp {frame.timestamp_s} "
                                 f"(previous line has {frames[-1].timestamp_s})")
            if frame.grid != self.meta.grid:
                raise ValueError(f"{path}:{number}: {frame.grid}x{frame.grid} grid, "
                                 f"meta.json says {self.meta.grid}x{self.meta.grid}")
            frames.append(frame)
        return frames

    def pairs(self, tolerance_s: float = 0.02, time_offset_s: float = 0.0
              ) -> list[RecordingPair]:
        """Pair each zone frame with the nearest colour (and depth) image in time.

        Zone frames without a colour image within ``tolerance_s`` are skipped with one
        warning naming how many; the depth map nearest the chosen colour image is attached
        when one lies within the tolerance of it.

        Args:
            tolerance_s: largest allowed |image time - (zone time + offset)| in seconds.
            time_offset_s: how far the camera's stamps run ahead of the sensor's (seconds):
                a zone frame stamped t is paired with the images nearest t + offset
                (``deltar calibrate --time-offset`` estimates it).

        Returns:
            The pairs, in time order.
        """
        if not tolerance_s >= 0:
            raise ValueError(f"tolerance_s must be >= 0, got {tolerance_s}")
        if not np.isfinite(time_offset_s):
            raise ValueError(f"time_offset_s must be finite, got {time_offset_s}")
        frames = self.zone_frames()
        if not self.color_paths:
            raise FileNotFoundError(f"recording has no colour images in "
                                    f"{self.folder / COLOR_DIR}")
        times = np.array([f.timestamp_s for f in frames], dtype=np.float64) + time_offset_s
        color_idx, color_gap = nearest_in_time(self.color_times_s, times)
        depth_idx, depth_gap = nearest_in_time(self.depth_times_s, self.color_times_s[color_idx])
        out, skipped = [], 0
        for i, frame in enumerate(frames):
            if color_gap[i] > tolerance_s:
                skipped += 1
                continue
            depth = (self.depth_paths[depth_idx[i]]
                     if self.depth_paths and depth_gap[i] <= tolerance_s else None)
            ci = color_idx[i]
            out.append(RecordingPair(frame, self.color_paths[ci], depth,
                                     float(self.color_times_s[ci] - frame.timestamp_s)))
        if skipped:
            warnings.warn(f"{self.folder}: skipped {skipped} of {len(frames)} zone frames with "
                          f"no colour image within {tolerance_s} s", stacklevel=2)
        return out


def no_pairs_message(recording: Recording, tolerance_s: float, time_offset_s: float) -> str:
    """Why a recording gave no (zone frame, colour image) pair: its zone frames, or the
    stamp ranges that did not meet within ``tolerance_s`` after ``time_offset_s`` (both
    seconds). For a refusal that must not blame anything else."""
    frames = recording.zone_frames()
    if not frames:
        return f"{recording.folder}: {ZONES_FILE} holds no zone frame"
    if not recording.color_paths:
        return f"{recording.folder}: no colour image in {COLOR_DIR}/"
    zone_t = [f.timestamp_s + time_offset_s for f in frames]
    return (f"{recording.folder}: none of its {len(frames)} zone frames has a colour image "
            f"within {tolerance_s:g} s (zone stamps plus the time offset {time_offset_s:g} s: "
            f"{min(zone_t):.3f}..{max(zone_t):.3f} s; images "
            f"{recording.color_times_s[0]:.3f}..{recording.color_times_s[-1]:.3f} s): check "
            "the time offset and the tolerance")


def _image_index(folder: Path) -> tuple[np.ndarray, list[Path]]:
    """Sorted capture times (s) and paths of ``<ns>.png`` files in ``folder``; hidden
    files (an interrupted atomic write's temporary) are no frames."""
    if not folder.is_dir():
        return np.zeros(0), []
    entries = []
    for path in folder.glob("*.png"):
        if path.name.startswith("."):
            continue
        try:
            entries.append((int(path.stem), path))
        except ValueError:
            raise ValueError(f"{path}: image names must be integer nanoseconds") from None
    entries.sort(key=lambda e: e[0])
    return np.array([ns * 1e-9 for ns, _ in entries]), [p for _, p in entries]


def nearest_in_time(sorted_times: np.ndarray, query: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest entry of ``sorted_times`` for each query, and |gap| (inf if none).

    Args:
        sorted_times: (N,) increasing times, seconds.
        query: (M,) times, seconds.

    Returns:
        (M,) int64 indices into ``sorted_times`` and (M,) float64 absolute gaps, seconds.
    """
    if sorted_times.size == 0:
        return np.zeros(query.size, dtype=np.int64), np.full(query.size, np.inf)
    right = np.clip(np.searchsorted(sorted_times, query), 1, sorted_times.size - 1) \
        if sorted_times.size > 1 else np.zeros(query.size, dtype=np.int64)
    left = np.maximum(right - 1, 0)
    pick_left = np.abs(query - sorted_times[left]) <= np.abs(sorted_times[right] - query)
    idx = np.where(pick_left, left, right)
    return idx, np.abs(sorted_times[idx] - query)
