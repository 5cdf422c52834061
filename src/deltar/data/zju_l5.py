"""The ZJU-L5 layout: one HDF5 file per frame, listed in a ``data.json``.

``data.json`` is ``{"<split>": [{"filename": "scene/frame.h5"}, ...]}`` with paths
relative to the folder holding it. Each HDF5 file holds:

- ``rgb``: (H, W, 3) uint8 colour image, RGB.
- ``depth``: (H, W) float ground-truth depth in metres (0 where invalid).
- ``hist_data``: (Z, 2) float per-zone [mean, sigma] in metres.
- ``fr``: (Z, 4) float zone rectangles (y0, x0, y1, x1) in image pixels; they may
  extend past the image.
- ``mask``: (Z,) bool valid zones (0/1 numbers are read as bool; anything else is
  refused).

Z is 64 (8x8) for the released data; 16 (4x4) is accepted too. Files written by
:func:`write_zju_l5` also carry the camera intrinsics as attributes ``fx, fy, cx, cy``,
and, for histogram sensors, optional datasets ``hist_edges_m`` (B + 1,) bin edges in
metres and ``hist_counts`` (Z, B) per-zone histograms (e.g. ST's CNH), and an optional
``no_target`` (Z,) bool dataset: invalid zones that reported no target (ST status 255,
nothing within the sensor's range; ``deltar simulate`` writes it), and, for a sensor
that reports several targets per zone (``deltar simulate --targets``), optional datasets
``target_mean_m``, ``target_sigma_m`` (Z, T) float metres, ``target_valid`` (Z, T) bool
and ``target_signal`` (Z, T) float (each target's return signal, any unit), T = 1..4,
strongest first, target 0 the primary reading.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics, check_image
from deltar.data.sequence import checked_index
from deltar.io.atomic import write_bytes_atomic
from deltar.io.input_file import input_file, reading
from deltar.io.json_file import read_split_filenames

#: Zone counts accepted in a ZJU-L5 file (4x4 and 8x8 grids).
ZONE_COUNTS: tuple[int, ...] = (16, 64)
_REQUIRED_KEYS: tuple[str, ...] = ("rgb", "depth", "hist_data", "fr", "mask")
_HISTOGRAM_KEYS: tuple[str, ...] = ("hist_edges_m", "hist_counts")
#: Optional dataset of this library's files (not in the released ones): (Z,) bool zones
#: that reported no target (nothing within the sensor's range).
_NO_TARGET_KEY = "no_target"
#: Optional datasets of a sensor that reports several targets per zone, (Z, T) each.
_TARGET_KEYS: tuple[str, ...] = ("target_mean_m", "target_sigma_m", "target_valid",
                                 "target_signal")


@dataclass
class ZJUL5Sample:
    """One ZJU-L5 frame: colour image, ground-truth depth and one L5 zone reading.

    Attributes:
        rgb: (H, W, 3) uint8 RGB image.
        depth_m: (H, W) float32 depth in metres, 0.0 where invalid.
        zone_mean_sigma: (Z, 2) float32 per-zone [mean, sigma] in metres (0 where invalid).
        zone_rects: (Z, 4) float32 zone rectangles (y0, x0, y1, x1) in pixels.
        zone_valid: (Z,) bool valid zones.
        name: frame name, the file path relative to the set without ``.h5``
            (e.g. ``"kitchen/00012"``).
        intrinsics: camera intrinsics if known (the released files do not store them;
            the reader fills in the paper's ZJU-L5 camera for them).
        hist_edges_m: optional (B + 1,) float32 histogram bin edges in metres.
        hist_counts: optional (Z, B) float32 per-zone histograms (histogram sensors);
            when present, models sample their depth hypotheses from them.
        zone_no_target: optional (Z,) bool, invalid zones that reported *no target*
            (nothing within the sensor's range); the released files do not have it.
        target_mean_m, target_sigma_m: optional (Z, T) float32 every target of each zone,
            metres (0 where not valid), strongest first; target 0 is the primary reading.
        target_valid: optional (Z, T) bool (given with the two above).
        target_signal: optional (Z, T) float32 each target's return signal (any unit;
            only ratios within a zone matter).
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    zone_mean_sigma: np.ndarray
    zone_rects: np.ndarray
    zone_valid: np.ndarray
    name: str
    intrinsics: CameraIntrinsics | None = None
    hist_edges_m: np.ndarray | None = None
    hist_counts: np.ndarray | None = None
    zone_no_target: np.ndarray | None = None
    target_mean_m: np.ndarray | None = None
    target_sigma_m: np.ndarray | None = None
    target_valid: np.ndarray | None = None
    target_signal: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.rgb = np.asarray(self.rgb)
        self.depth_m = np.asarray(self.depth_m, dtype=np.float32)
        self.zone_mean_sigma = np.asarray(self.zone_mean_sigma, dtype=np.float32)
        self.zone_rects = np.asarray(self.zone_rects, dtype=np.float32)
        self.zone_valid = np.asarray(self.zone_valid, dtype=bool)
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when shapes or values are inconsistent."""
        where = f"ZJUL5Sample {self.name!r}"
        check_image(self.rgb, f"{where}: rgb")
        if self.depth_m.shape != self.rgb.shape[:2]:
            raise ValueError(f"{where}: depth_m shape {self.depth_m.shape} does not match the "
                             f"image size {self.rgb.shape[:2]}")
        if not np.all(np.isfinite(self.depth_m)) or np.any(self.depth_m < 0):
            raise ValueError(f"{where}: depth_m must be finite and >= 0 (0 marks invalid)")
        zones = self.zone_valid.shape[0] if self.zone_valid.ndim == 1 else -1
        if zones not in ZONE_COUNTS:
            raise ValueError(f"{where}: zone_valid must be (Z,) with Z in {ZONE_COUNTS}, got "
                             f"{self.zone_valid.shape}")
        if self.zone_mean_sigma.shape != (zones, 2):
            raise ValueError(f"{where}: zone_mean_sigma must be ({zones}, 2), got "
                             f"{self.zone_mean_sigma.shape}")
        if self.zone_rects.shape != (zones, 4):
            raise ValueError(f"{where}: zone_rects must be ({zones}, 4), got "
                             f"{self.zone_rects.shape}")
        valid_ms = self.zone_mean_sigma[self.zone_valid]
        if not np.all(np.isfinite(valid_ms)) or np.any(valid_ms < 0):
            raise ValueError(f"{where}: zone_mean_sigma must be finite and >= 0 in valid zones")
        if not np.all(np.isfinite(self.zone_rects)):
            raise ValueError(f"{where}: zone_rects must be finite")
        if self.zone_no_target is not None:
            flags = np.asarray(self.zone_no_target)
            if flags.size == zones:  # stored as a grid, like some masks
                flags = flags.reshape(zones)
            if flags.shape != (zones,) or (flags.dtype != bool
                                           and not np.isin(flags, (0, 1)).all()):
                raise ValueError(f"{where}: zone_no_target must be ({zones},) bool, got "
                                 f"{flags.shape} {flags.dtype}")
            self.zone_no_target = flags.astype(bool)
            if np.any(self.zone_no_target & self.zone_valid):
                both = np.flatnonzero(self.zone_no_target & self.zone_valid).tolist()
                raise ValueError(f"{where}: zone_no_target marks valid zones {both}")
        if (self.hist_edges_m is None) != (self.hist_counts is None):
            raise ValueError(f"{where}: hist_edges_m and hist_counts must be given together")
        if self.hist_counts is not None:
            self.hist_edges_m = np.asarray(self.hist_edges_m, dtype=np.float32).reshape(-1)
            self.hist_counts = np.asarray(self.hist_counts, dtype=np.float32)
            bins = self.hist_edges_m.size - 1
            if bins < 1 or np.any(np.diff(self.hist_edges_m) <= 0):
                raise ValueError(f"{where}: hist_edges_m must be strictly increasing")
            if self.hist_counts.shape != (zones, bins):
                raise ValueError(f"{where}: hist_counts must be ({zones}, {bins}), got "
                                 f"{self.hist_counts.shape}")
            if not np.all(np.isfinite(self.hist_counts)) or np.any(self.hist_counts < 0):
                raise ValueError(f"{where}: hist_counts must be finite and >= 0")
        self._validate_targets(where, zones)

    def _validate_targets(self, where: str, zones: int) -> None:
        given = [getattr(self, key) is not None for key in _TARGET_KEYS[:3]]
        if any(given) and not all(given):
            raise ValueError(f"{where}: target_mean_m, target_sigma_m and target_valid must "
                             "be given together")
        if self.target_signal is not None and not all(given):
            raise ValueError(f"{where}: target_signal needs target_mean_m, target_sigma_m "
                             "and target_valid")
        if not all(given):
            return
        self.target_mean_m = np.asarray(self.target_mean_m, dtype=np.float32)
        self.target_sigma_m = np.asarray(self.target_sigma_m, dtype=np.float32)
        self.target_valid = np.asarray(self.target_valid).astype(bool)
        if self.target_signal is not None:
            self.target_signal = np.asarray(self.target_signal, dtype=np.float32)
        shape = self.target_mean_m.shape
        if len(shape) != 2 or shape[0] != zones or not 1 <= shape[1] <= 4:
            raise ValueError(f"{where}: target_mean_m must be ({zones}, T) with T in 1..4, got "
                             f"{shape}")
        for key in _TARGET_KEYS[1:]:
            value = getattr(self, key)
            if value is not None and value.shape != shape:
                raise ValueError(f"{where}: {key} must have target_mean_m's shape {shape}, got "
                                 f"{value.shape}")
        for key in ("target_mean_m", "target_sigma_m", "target_signal"):
            value = getattr(self, key)
            if value is not None and (not np.all(np.isfinite(value[self.target_valid]))
                                      or np.any(value[self.target_valid] < 0)):
                raise ValueError(f"{where}: {key} must be finite and >= 0 where target_valid")

    @property
    def grid(self) -> int:
        """Zones per side (4 or 8)."""
        return math.isqrt(self.zone_valid.shape[0])

    def zone_frame(self):
        """The sample's zone reading as a :class:`~deltar.sensor.zone_frame.ZoneFrame`.

        Mean and sigma (metres) are zero in invalid zones; zones flagged valid but
        reporting no distance (mean <= 0) are invalid, as the classical baselines treat
        them. The histogram, the no-target flags and the targets are attached when the
        sample has them.
        """
        from deltar.sensor.zone_frame import ZoneFrame

        valid = np.asarray(self.zone_valid, dtype=bool) & (self.zone_mean_sigma[:, 0] > 0)
        targets = {}
        if self.target_mean_m is not None:
            n = self.grid
            target_valid = self.target_valid & valid[:, None]
            targets = {"target_mean_m": np.where(target_valid, self.target_mean_m, 0.0),
                       "target_sigma_m": np.where(target_valid, self.target_sigma_m, 0.0),
                       "target_valid": target_valid}
            if self.target_signal is not None:
                targets["target_signal"] = np.where(target_valid, self.target_signal, 0.0)
            targets = {key: value.reshape(n, n, -1) for key, value in targets.items()}
        return ZoneFrame(mean_m=np.where(valid, self.zone_mean_sigma[:, 0], 0.0),
                         sigma_m=np.where(valid, self.zone_mean_sigma[:, 1], 0.0),
                         valid=valid, hist_edges_m=self.hist_edges_m,
                         hist_counts=self.hist_counts, no_target=self.zone_no_target,
                         **targets)


def _read_sample(path: Path, name: str, default_intrinsics: CameraIntrinsics | None
                 ) -> ZJUL5Sample:
    input_file(path, "ZJU-L5 frame file")
    with reading(path, "ZJU-L5 frame file"):
        return _decode_sample(path, name, default_intrinsics)


def _decode_sample(path: Path, name: str, default_intrinsics: CameraIntrinsics | None
                   ) -> ZJUL5Sample:
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in _REQUIRED_KEYS if k not in f]
            if missing:
                raise ValueError(f"ZJU-L5 file {path} is missing datasets {missing}")
            arrays = {k: f[k][()] for k in (*_REQUIRED_KEYS, *_HISTOGRAM_KEYS, _NO_TARGET_KEY,
                                            *_TARGET_KEYS) if k in f}
            attrs = {k: f.attrs[k] for k in ("fx", "fy", "cx", "cy") if k in f.attrs}
    except OSError as err:  # h5py raises OSError for truncated / non-HDF5 files
        raise ValueError(f"cannot read ZJU-L5 file {path}: {err}") from err
    if np.asarray(arrays["depth"]).dtype.kind != "f":
        # Integer depth is a depth camera's raw units (millimetres): read as metres it
        # would be 1000 times too far and every pixel beyond the scored range.
        raise ValueError(f"ZJU-L5 file {path}: depth must be float metres, got "
                         f"{np.asarray(arrays['depth']).dtype} (millimetres? store depth / 1000 "
                         "as float32)")
    depth = np.asarray(arrays["depth"], dtype=np.float32)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    # Ground truth may mark holes with NaN or negative values; the convention is 0.0.
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))
    rgb = np.asarray(arrays["rgb"])
    if rgb.dtype != np.uint8:
        raise ValueError(f"ZJU-L5 file {path}: rgb must be uint8, got {rgb.dtype}")
    intrinsics = default_intrinsics
    if len(attrs) == 4:
        intrinsics = CameraIntrinsics(*(float(attrs[k]) for k in ("fx", "fy", "cx", "cy")),
                                      width=rgb.shape[1], height=rgb.shape[0])
    elif intrinsics is not None and rgb.ndim == 3 and (
            (intrinsics.height, intrinsics.width) != rgb.shape[:2]):
        intrinsics = intrinsics.scaled(rgb.shape[0], rgb.shape[1])
    mean_sigma = np.array(arrays["hist_data"], dtype=np.float32)
    mask = np.asarray(arrays["mask"])
    if mask.dtype != bool and (mask.dtype.kind not in "iuf" or not np.isin(mask, (0, 1)).all()):
        # Cast to bool, 0.5 (or NaN) would read as a valid zone.
        bad = mask[~np.isin(mask, (0, 1))].ravel() if mask.dtype.kind in "iuf" else None
        raise ValueError(f"ZJU-L5 file {path}: mask must be bool (or 0/1), got {mask.dtype}"
                         + (f" holding {bad[0].item()!r}" if bad is not None else ""))
    valid = mask.astype(bool).reshape(-1)
    if mean_sigma.ndim == 2 and mean_sigma.shape[0] == valid.shape[0]:
        # Released files may keep stale values in masked zones; the convention is 0.0.
        mean_sigma[~valid] = 0.0
    try:
        return ZJUL5Sample(rgb=rgb, depth_m=depth, zone_mean_sigma=mean_sigma,
                           zone_rects=np.asarray(arrays["fr"], dtype=np.float32),
                           zone_valid=valid, name=name, intrinsics=intrinsics,
                           hist_edges_m=arrays.get("hist_edges_m"),
                           hist_counts=arrays.get("hist_counts"),
                           zone_no_target=arrays.get(_NO_TARGET_KEY),
                           **{key: arrays.get(key) for key in _TARGET_KEYS})
    except ValueError as err:
        raise ValueError(f"ZJU-L5 file {path}: {err}") from err


class ZJUL5Dataset(Sequence):
    """Read a ZJU-L5-layout set (``data.json`` + one HDF5 file per frame).

    Frames are read lazily on indexing.

    Args:
        data_json_path: path to ``data.json`` (or the folder that holds it).
        split: key of the frame list in ``data.json`` (``"test"`` in the release).
        intrinsics: camera intrinsics for files that do not store them; defaults to the
            paper's ZJU-L5 camera (611.2, 609.6, 323.4, 244.9 at 480x640).

    Raises:
        FileNotFoundError: ``data.json`` is missing.
        ValueError: ``data.json`` is not valid JSON or lacks the split, the split lists
            no frames, or an entry is not a relative path without ``..``.
    """

    def __init__(self, data_json_path: str | Path, split: str = "test",
                 intrinsics: CameraIntrinsics | None = ZJU_L5_INTRINSICS) -> None:
        path = Path(data_json_path)
        if path.is_dir():
            path = path / "data.json"
        filenames = read_split_filenames(path, split, "ZJU-L5 index", relative=True)
        if not filenames:  # an empty set would read as no frames, naming nothing
            raise ValueError(f"ZJU-L5 index {path}: split {split!r} lists no frames (a set "
                             "holds at least one)")
        self.root = path.parent
        self.split = split
        self.intrinsics = intrinsics
        self.filenames: list[str] = filenames

    def __len__(self) -> int:
        return len(self.filenames)

    def frame_files(self, index: int) -> list[Path]:
        """The file frame ``index`` reads (its ``.h5``), without reading it."""
        return [self.root / self.filenames[checked_index(index, len(self))]]

    def __getitem__(self, index: int) -> ZJUL5Sample:  # type: ignore[override]
        rel = self.filenames[checked_index(index, len(self))]
        name = rel[:-3] if rel.endswith(".h5") else rel
        return _read_sample(self.root / rel, name, self.intrinsics)


def _relative_filename(name: str) -> str:
    rel = name if name.endswith(".h5") else f"{name}.h5"
    parts = Path(rel).parts
    if Path(rel).is_absolute() or ".." in parts or not parts:
        raise ValueError(f"sample name {name!r} must be a relative path without '..'")
    return Path(rel).as_posix()


def write_zju_l5(out_dir: str | Path, samples: Iterable[ZJUL5Sample],
                 split: str = "test") -> Path:
    """Write samples as a ZJU-L5-layout set that :class:`ZJUL5Dataset` (and the release) read.

    Each sample goes to ``out_dir / (sample.name + ".h5")``; ``data.json`` is written last,
    so a set without ``data.json`` is incomplete. Every file is written atomically, and a
    failure (a frame that cannot be read or written) removes the files and folders this
    call made before it re-raises: a set is whole or absent, and a re-run can start over.

    Args:
        out_dir: output folder; created if needed. It must not already hold a
            ``data.json`` or any of the frame files.
        samples: the frames; names must be unique relative paths (e.g. ``"scene/00001"``).
        split: key of the frame list in ``data.json``.

    Returns:
        Path of the written ``data.json``.

    Raises:
        FileExistsError: ``data.json`` or a frame file already exists.
        ValueError: a sample is inconsistent or two samples share a name, no samples, or
            an empty ``split`` name.
    """
    if not isinstance(split, str) or not split.strip():  # before any frame is made
        raise ValueError(f"split must be a non-empty name, got {split!r}")
    out = Path(out_dir)
    index_path = out / "data.json"
    if index_path.exists():
        raise FileExistsError(f"refusing to overwrite existing ZJU-L5 set: {index_path}")
    filenames: list[str] = []
    made: list[Path] = []  # files and folders this call created, in order
    try:
        _write_frames(out, samples, filenames, made)
        if not filenames:  # a set of no frame reads as an error in every reader
            raise ValueError(f"no frames to write to {out}: a set holds at least one")
        text = json.dumps({split: [{"filename": rel} for rel in filenames]}, indent=2)
        if index_path.exists():  # appeared meanwhile: not this call's to remove
            raise FileExistsError(f"refusing to overwrite existing ZJU-L5 set: {index_path}")
        _write_new(index_path, (text + "\n").encode("utf-8"), made)
        return index_path
    except BaseException:
        for path in reversed(made):
            with contextlib.suppress(OSError):
                path.unlink() if path.is_file() else path.rmdir()
        raise


def _write_frames(out: Path, samples: Iterable[ZJUL5Sample], filenames: list[str],
                  made: list[Path]) -> None:
    """:func:`write_zju_l5`'s frame files, each name appended to ``filenames`` and each
    file or folder it creates to ``made``."""
    seen: set[str] = set()
    for sample in samples:
        sample.validate()
        rel = _relative_filename(sample.name)
        if rel in seen:
            raise ValueError(f"two samples share the name {sample.name!r}")
        seen.add(rel)
        target = out / rel
        # HDF5 is built in memory and written in one go: a write error (a full disk) is
        # then an ordinary OSError of the atomic write, never an HDF5 library failure.
        buffer = io.BytesIO()
        with h5py.File(buffer, "w") as f:
            f.create_dataset("rgb", data=sample.rgb, compression="gzip", compression_opts=4)
            f.create_dataset("depth", data=sample.depth_m.astype(np.float32),
                             compression="gzip", compression_opts=4)
            f.create_dataset("hist_data", data=sample.zone_mean_sigma.astype(np.float32))
            f.create_dataset("fr", data=sample.zone_rects.astype(np.float32))
            f.create_dataset("mask", data=sample.zone_valid.astype(bool))
            if sample.hist_counts is not None:
                f.create_dataset("hist_edges_m", data=sample.hist_edges_m.astype(np.float32))
                f.create_dataset("hist_counts", data=sample.hist_counts.astype(np.float32))
            if sample.zone_no_target is not None:
                f.create_dataset(_NO_TARGET_KEY, data=sample.zone_no_target.astype(bool))
            for key in _TARGET_KEYS:
                if getattr(sample, key) is not None:
                    f.create_dataset(key, data=getattr(sample, key))
            if sample.intrinsics is not None:
                for key in ("fx", "fy", "cx", "cy"):
                    f.attrs[key] = float(getattr(sample.intrinsics, key))
        made.extend(reversed([d for d in (target.parent, *target.parent.parents)
                              if not d.exists()]))
        if target.exists():  # never listed for removal: it is not this call's
            raise FileExistsError(f"refusing to overwrite existing file: {target}")
        _write_new(target, buffer.getvalue(), made)
        filenames.append(rel)


def _write_new(path: Path, data: bytes, made: list[Path]) -> None:
    """Write a file that must not exist yet, atomically. It is listed in ``made`` before
    it is written, so a stop right after its rename removes it too, and unlisted when
    another writer made it first (``FileExistsError``): that file is not this call's."""
    made.append(path)
    try:
        write_bytes_atomic(path, data, overwrite=False)
    except FileExistsError:
        made.remove(path)
        raise
