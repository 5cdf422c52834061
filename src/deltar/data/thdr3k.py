"""THDR3K: real VL53L8CH histogram readings with RealSense colour and depth.

The set released with LiteSense pairs an ST VL53L8CH (8x8 zones, compact normalised
histograms) with an Intel RealSense camera. Its documented layout, per sample with
file root ``<root>`` (a path relative to the file list's folder):

- ``<root>_rgb.jpg``: the colour image (640x480);
- ``<root>_depth.png``: the RealSense depth, uint16 millimetres, 0 = invalid;
- ``<root>_tof.json``: the sensor reading, with ``distance_mm`` (64),
  ``nb_target_detected`` (64; 0 means no valid target, and the sensor does not clear
  the stale distance of such a zone) and ``cnh_data.bin_values`` (64 x 18).

The file list is a JSON object ``{"train": [{"filename": root}, ...], "test": [...]}``.

Reading conventions (:func:`read_thdr3k_sample`): the ToF grid is rotated by 90
degrees (``numpy.rot90(k=1)``) to match the image; zones with no target are invalid;
CNH values are clipped at 0 and normalised per zone to sum 1; the 8x8 grid covers the
480x480 square at x = 60..540 of the 640x480 image (60 px zones; scaled for other
image sizes). Samples are :class:`~deltar.data.zju_l5.ZJUL5Sample` objects with a
histogram, so ``deltar evaluate`` and fine-tuning read them like ZJU-L5 frames.

The CNH bin configuration is not part of the documented layout: a ``tof.json`` whose
``cnh_data`` holds ``start_bin``, ``num_bins`` and ``sub_sample`` is read with those,
otherwise with the reader's ``cnh_config`` (ST's example configuration by default, see
:class:`~deltar.sensor.cnh.CNHConfig`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.data.sequence import checked_index
from deltar.data.zju_l5 import ZJUL5Sample
from deltar.io.json_file import read_json, read_split_filenames
from deltar.sensor.cnh import CNHConfig, zone_frame_from_cnh
from deltar.sensor.zone_frame import Orientation

#: How the sensor's zone grid maps onto the image (``numpy.rot90(k=1)``).
THDR3K_ORIENTATION = Orientation(rot90=1)
#: Image size the zone layout is given for, (height, width) pixels.
THDR3K_IMAGE_SIZE = (480, 640)
#: Left edge and side of the square the 8x8 grid covers at 480x640, pixels.
THDR3K_GRID_LEFT_PX, THDR3K_GRID_SIDE_PX = 60, 480
SUFFIXES = {"rgb": "_rgb.jpg", "depth": "_depth.png", "tof": "_tof.json"}


def thdr3k_zone_rects(height: int = 480, width: int = 640, grid: int = 8) -> np.ndarray:
    """The set's zone rectangles for an image of ``height`` x ``width`` pixels.

    At 480x640, zone (r, c) of the 8x8 grid is rows ``60 r .. 60 (r + 1)`` and columns
    ``60 + 60 c .. 60 + 60 (c + 1)``; other sizes scale that layout.

    Returns:
        (grid * grid, 4) float32 (y0, x0, y1, x1) in pixels, row-major.
    """
    side = THDR3K_GRID_SIDE_PX / grid
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    y0 = rows.reshape(-1) * side
    x0 = THDR3K_GRID_LEFT_PX + cols.reshape(-1) * side
    rects = np.stack([y0, x0, y0 + side, x0 + side], axis=1)
    scale = np.array([height / THDR3K_IMAGE_SIZE[0], width / THDR3K_IMAGE_SIZE[1]] * 2)
    return (rects * scale).astype(np.float32)


def _cnh_config(cnh: dict, default: CNHConfig, source: str) -> CNHConfig:
    keys = ("start_bin", "num_bins", "sub_sample")
    present = [k for k in keys if k in cnh]
    if not present:
        return default
    if len(present) != len(keys):
        raise ValueError(f"{source}: cnh_data gives {present} but not all of {list(keys)}")
    try:
        return CNHConfig(*(cnh[k] for k in keys), device_bin_m=default.device_bin_m)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: invalid CNH bin configuration: {err}") from err


def read_thdr3k_sample(root: str | Path, name: str | None = None, *,
                       cnh_config: CNHConfig | None = None,
                       intrinsics: CameraIntrinsics | None = None) -> ZJUL5Sample:
    """Read one THDR3K sample from its file root.

    Args:
        root: the path without suffix (``<root>_rgb.jpg`` etc. must exist).
        name: sample name (default: the root's file name).
        cnh_config: bin configuration for files that do not give one.
        intrinsics: camera intrinsics of the colour image, if known (the layout does
            not carry them).

    Returns:
        A :class:`ZJUL5Sample`: rgb (H, W, 3) uint8, depth_m (H, W) float32 metres
        (0 invalid), zone_mean_sigma (64, 2) metres (sigma from the histogram's
        strongest run), zone_rects (64, 4) pixels, zone_valid (64,), hist_edges_m (19,)
        metres and hist_counts (64, 18) normalised, all in image orientation.

    Raises:
        FileNotFoundError: a file of the sample is missing (named).
        ValueError: a corrupt image or JSON, wrong lengths (naming the file and field).
    """
    from deltar.data.rgbd_files import read_color, read_depth

    base = Path(root)
    paths = {kind: base.with_name(base.name + suffix) for kind, suffix in SUFFIXES.items()}
    for kind, path in paths.items():
        if not path.is_file():
            raise FileNotFoundError(f"THDR3K sample {base}: {kind} file not found: {path}")
    tof = read_json(paths["tof"], "THDR3K ToF reading")
    source = str(paths["tof"])
    if not isinstance(tof, dict):
        raise ValueError(f"{source}: expected a JSON object")
    missing = [k for k in ("distance_mm", "nb_target_detected", "cnh_data") if k not in tof]
    cnh = tof.get("cnh_data")
    if not missing and (not isinstance(cnh, dict) or "bin_values" not in cnh):
        missing = ["cnh_data.bin_values"]
    if missing:
        raise ValueError(f"{source}: missing fields {missing}")
    config = _cnh_config(cnh, cnh_config or CNHConfig(), source)
    try:
        frame = zone_frame_from_cnh(tof["distance_mm"], cnh["bin_values"], config=config,
                                    nb_target_detected=tof["nb_target_detected"],
                                    range_sigma_mm=tof.get("range_sigma_mm"),
                                    orientation=THDR3K_ORIENTATION)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from err
    if frame.grid != 8:
        raise ValueError(f"{source}: THDR3K readings have 64 zones, got {frame.zone_count}")
    rgb = read_color(paths["rgb"])
    depth = read_depth(paths["depth"], 1000.0)
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"THDR3K sample {base}: depth {paths['depth'].name} is "
                         f"{depth.shape[0]}x{depth.shape[1]}, colour {paths['rgb'].name} is "
                         f"{rgb.shape[0]}x{rgb.shape[1]}")
    height, width = depth.shape
    if intrinsics is not None and (intrinsics.height, intrinsics.width) != (height, width):
        intrinsics = intrinsics.scaled(height, width)
    return ZJUL5Sample(rgb=rgb, depth_m=depth, zone_mean_sigma=frame.mean_sigma(),
                       zone_rects=thdr3k_zone_rects(height, width),
                       zone_valid=frame.valid.reshape(-1),
                       zone_no_target=frame.flat_no_target(), name=name or base.name,
                       intrinsics=intrinsics, hist_edges_m=frame.hist_edges_m,
                       hist_counts=frame.hist_counts.reshape(64, -1))


class THDR3KDataset(Sequence):
    """Read a THDR3K-layout set: a file list JSON and the per-sample files.

    Samples are read lazily on indexing, as :class:`ZJUL5Sample` objects.

    Args:
        list_path: the file list JSON (``{"train": [{"filename": root}], "test": ...}``).
        split: key of the list to read.
        cnh_config: bin configuration for readings that do not give one.
        intrinsics: colour camera intrinsics, if known.

    Raises:
        FileNotFoundError: the file list is missing.
        ValueError: corrupt JSON, no such split, or an entry that is not a relative path.
    """

    def __init__(self, list_path: str | Path, split: str = "test", *,
                 cnh_config: CNHConfig | None = None,
                 intrinsics: CameraIntrinsics | None = None) -> None:
        path = Path(list_path)
        self.filenames = read_split_filenames(path, split, "THDR3K file list", relative=True)
        self.root = path.parent
        self.split = split
        self.cnh_config = cnh_config
        self.intrinsics = intrinsics

    def __len__(self) -> int:
        return len(self.filenames)

    def frame_files(self, index: int) -> list[Path]:
        """The files sample ``index`` reads, without reading them: its zone reading
        (``<root>_tof.json``) first, then its image and depth."""
        base = self.root / self.filenames[checked_index(index, len(self), "sample")]
        return [base.with_name(base.name + SUFFIXES[kind]) for kind in ("tof", "rgb", "depth")]

    def __getitem__(self, index: int) -> ZJUL5Sample:  # type: ignore[override]
        rel = self.filenames[checked_index(index, len(self), "sample")]
        return read_thdr3k_sample(self.root / rel, Path(rel).as_posix(),
                                  cnh_config=self.cnh_config, intrinsics=self.intrinsics)


def is_thdr3k_list(list_path: str | Path, split: str) -> bool:
    """Whether a file list's first entry of ``split`` is a THDR3K sample root.

    True when ``<root>_tof.json`` exists beside the list for that entry; False for
    anything else (e.g. a ZJU-L5 ``data.json``, whose entries are ``.h5`` files).
    """
    path = Path(list_path)
    try:
        names = read_split_filenames(path, split, "file list")
    except (FileNotFoundError, ValueError):
        return False
    if not names:
        return False
    root = path.parent / names[0]
    return root.with_name(root.name + SUFFIXES["tof"]).is_file()
