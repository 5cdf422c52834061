"""NYU-Depth V2 readers: the official labeled ``.mat`` and the DELTAR release's h5 + json.

- ``nyu_depth_v2_labeled.mat`` is a MATLAB v7.3 file (HDF5). MATLAB stores arrays
  column-major, so h5py sees them transposed: ``images`` (N, 3, W, H) uint8 and
  ``depths`` (N, W, H) float metres.
- The release's training files are one HDF5 per frame with ``rgb`` (3, H, W) uint8 and
  ``depth`` (H, W) metres, listed in a json such as ``nyu_sync.json``:
  ``{"train": [{"filename": "train/<scene>/<frame>.h5"}, ...], "test": [...]}`` with paths
  relative to the data root.

Both are sequences of :class:`~deltar.data.rgbd.RGBDFrame` with the NYU Kinect intrinsics.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.data.rgbd import RGBDFrame
from deltar.data.sequence import checked_index
from deltar.io.input_file import input_file, reading
from deltar.io.json_file import read_split_filenames

#: NYU-Depth V2 colour camera at 480x640 (fx, fy, cx, cy from the dataset's toolbox).
NYU_INTRINSICS = CameraIntrinsics(518.86, 519.47, 325.58, 253.74, 640, 480)
#: (rows, columns) cut from each side by ``crop_border``: the release's training crop.
BORDER_CROP: tuple[int, int] = (12, 16)


def _clean_depth(depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth, dtype=np.float32)
    return np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))


def _check_intrinsics(intrinsics: CameraIntrinsics, shape: tuple[int, int],
                      source: Path) -> CameraIntrinsics:
    if (intrinsics.height, intrinsics.width) == shape:
        return intrinsics
    raise ValueError(f"{source}: images are {shape[0]}x{shape[1]} but the intrinsics are for "
                     f"{intrinsics.height}x{intrinsics.width}; pass matching intrinsics")


def _check_dtypes(path: Path, image: np.dtype, depth: np.dtype, image_key: str,
                  depth_key: str) -> None:
    """Refuse a colour dataset that is not uint8 and a depth dataset that is not float
    metres (integers are a depth camera's raw units, millimetres: 1000 times too far)."""
    if image != np.uint8:
        raise ValueError(f"NYU file {path}: {image_key} must be uint8, got {image}")
    if depth.kind != "f":
        raise ValueError(f"NYU file {path}: {depth_key} must be float metres, got {depth} "
                         "(millimetres? store depth / 1000 as float32)")


def _open_h5(path: Path, what: str) -> h5py.File:
    input_file(path, what)
    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"cannot read {what} {path} as HDF5 (MATLAB files must be saved "
                         f"as v7.3): {err}") from err


class NYULabeledReader(Sequence):
    """Frames of the official ``nyu_depth_v2_labeled.mat`` (1449 labeled frames).

    Args:
        mat_path: path to the v7.3 ``.mat`` file.
        indices: optional subset of frame indices (e.g. the official test split, 0-based).
        intrinsics: camera intrinsics; NYU's by default.

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: not an HDF5 file, ``images`` / ``depths`` missing or inconsistent.
    """

    def __init__(self, mat_path: str | Path, indices: Sequence[int] | None = None,
                 intrinsics: CameraIntrinsics = NYU_INTRINSICS) -> None:
        self.path = Path(mat_path)
        with _open_h5(self.path, "NYU labeled file") as f, reading(self.path,
                                                                   "NYU labeled file"):
            missing = [k for k in ("images", "depths") if k not in f]
            if missing:
                raise ValueError(f"NYU labeled file {self.path} lacks datasets {missing}")
            images, depths = f["images"].shape, f["depths"].shape
            _check_dtypes(self.path, f["images"].dtype, f["depths"].dtype, "images", "depths")
        if len(images) != 4 or images[1] != 3 or len(depths) != 3 or (
                images[0], images[2], images[3]) != depths:
            raise ValueError(f"NYU labeled file {self.path}: expected images (N, 3, W, H) and "
                             f"depths (N, W, H), got {images} and {depths}")
        count = images[0]
        self.indices = list(range(count)) if indices is None else [int(i) for i in indices]
        bad = [i for i in self.indices if not 0 <= i < count]
        if bad:
            raise ValueError(f"indices {bad[:5]} out of range for {count} frames in {self.path}")
        self.intrinsics = _check_intrinsics(intrinsics, (depths[2], depths[1]), self.path)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> RGBDFrame:  # type: ignore[override]
        i = self.indices[checked_index(index, len(self))]
        # Opened per access: h5py handles must not be shared across DataLoader workers.
        with h5py.File(self.path, "r") as f, reading(self.path, "NYU labeled file"):
            image = np.ascontiguousarray(f["images"][i].transpose(2, 1, 0))  # (3,W,H)->(H,W,3)
            depth = f["depths"][i].T  # (W, H) -> (H, W)
        return RGBDFrame(image=image.astype(np.uint8), depth_m=_clean_depth(depth),
                         intrinsics=self.intrinsics, name=f"nyu_labeled/{i:05d}")


class NYUH5Reader(Sequence):
    """Frames of the release's NYU h5 files listed in a json (``nyu_sync.json`` layout).

    Args:
        json_path: the split file, ``{"train": [{"filename": ...}], "test": [...]}``.
        split: which list to read.
        data_root: folder the file names are relative to; the json's folder by default.
        intrinsics: camera intrinsics; NYU's by default.
        crop_border: cut ``BORDER_CROP`` pixels (12 rows, 16 columns) off every side, as
            the release does for training: NYU's registered frames have blank borders.
            The intrinsics are cropped to match.

    Raises:
        FileNotFoundError: the json is missing (frame files are checked on access).
        ValueError: the json is invalid or has no such split.
    """

    def __init__(self, json_path: str | Path, split: str = "train",
                 data_root: str | Path | None = None,
                 intrinsics: CameraIntrinsics = NYU_INTRINSICS,
                 crop_border: bool = False) -> None:
        path = Path(json_path)
        self.filenames = read_split_filenames(path, split, "NYU split file")
        self.root = Path(data_root) if data_root is not None else path.parent
        self.intrinsics = intrinsics
        self.crop_border = crop_border

    def __len__(self) -> int:
        return len(self.filenames)

    def __getitem__(self, index: int) -> RGBDFrame:  # type: ignore[override]
        rel = self.filenames[checked_index(index, len(self))]
        path = self.root / rel
        with _open_h5(path, "NYU frame file") as f, reading(path, "NYU frame file"):
            missing = [k for k in ("rgb", "depth") if k not in f]
            if missing:
                raise ValueError(f"NYU frame file {path} lacks datasets {missing}")
            rgb, depth = f["rgb"][()], f["depth"][()]
        _check_dtypes(path, rgb.dtype, depth.dtype, "rgb", "depth")
        if rgb.ndim != 3 or rgb.shape[0] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"NYU frame file {path}: rgb must be (3, H, W) uint8, got "
                             f"{rgb.shape} {rgb.dtype}")
        if depth.shape != rgb.shape[1:]:
            raise ValueError(f"NYU frame file {path}: depth {depth.shape} does not match rgb "
                             f"{rgb.shape[1:]}")
        intr = _check_intrinsics(self.intrinsics, depth.shape, path)
        image = rgb.transpose(1, 2, 0)
        if self.crop_border:
            rows, cols = BORDER_CROP
            height, width = depth.shape
            image = image[rows:height - rows, cols:width - cols]
            depth = depth[rows:height - rows, cols:width - cols]
            intr = intr.cropped(rows, cols, height - 2 * rows, width - 2 * cols)
        name = rel[:-3] if rel.endswith(".h5") else rel
        return RGBDFrame(image=np.ascontiguousarray(image), depth_m=_clean_depth(depth),
                         intrinsics=intr, name=name)
