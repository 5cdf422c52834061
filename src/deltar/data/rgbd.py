"""RGB-D frames and readers for common folder layouts (7-Scenes / 3DMatch, TUM, plain folders).

Every reader is a sequence of :class:`RGBDFrame`: ``len(reader)`` frames, ``reader[i]``
decodes frame ``i`` from disk. Depth images hold integers in ``1 / depth_scale`` metres
(millimetres: scale 1000; TUM benchmark: 5000); 0, 65535 and non-finite values are invalid
and become 0.0.

Per-folder option: a ``deltar_rgbd.json`` file in the dataset folder may set
``{"layout": ..., "depth_scale": ..., "intrinsics": {"fx": ..., "fy": ..., "cx": ...,
"cy": ...}}`` for :func:`open_rgbd`; keyword arguments override it.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deltar.camera import CameraIntrinsics, check_image
from deltar.data.rgbd_files import (
    check_depth_scale,
    color_image_size,
    default_intrinsics,
    read_color,
    read_depth,
    read_intrinsics_matrix,
)
from deltar.data.sequence import checked_index
from deltar.io.file_pairs import IMAGE_SUFFIXES
from deltar.io.input_file import input_folder, reading
from deltar.io.pose_file import frame_pose_file, read_pose_file

#: Name of the optional per-folder settings file read by :func:`open_rgbd`.
SIDECAR_NAME = "deltar_rgbd.json"
#: Layouts :func:`open_rgbd` recognises.
LAYOUTS: tuple[str, ...] = ("7scenes", "tum", "folder")
_DEPTH_SUFFIXES = (".png", ".tif", ".tiff", ".pgm", ".npy")


@dataclass
class RGBDFrame:
    """One registered colour + depth frame.

    Attributes:
        image: (H, W, 3) uint8 RGB image.
        depth_m: (H, W) float32 depth in metres (z-depth along the optical axis), 0.0 where
            invalid.
        intrinsics: pinhole intrinsics of the colour camera at this resolution.
        name: frame name, unique within its dataset.
        timestamp_s: capture time in seconds when known.
    """

    image: np.ndarray
    depth_m: np.ndarray
    intrinsics: CameraIntrinsics
    name: str
    timestamp_s: float | None = None

    def __post_init__(self) -> None:
        check_image(self.image, f"RGBDFrame {self.name!r}: image")
        if self.depth_m.shape != self.image.shape[:2]:
            raise ValueError(f"RGBDFrame {self.name!r}: depth size {self.depth_m.shape} differs "
                             f"from the colour size {self.image.shape[:2]}")
        size = (self.intrinsics.height, self.intrinsics.width)
        if size != self.image.shape[:2]:
            raise ValueError(f"RGBDFrame {self.name!r}: intrinsics are for {size}, image is "
                             f"{self.image.shape[:2]}")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _intrinsics_from_dict(data: dict, height: int, width: int, source: str
                          ) -> CameraIntrinsics:
    if not isinstance(data, dict):
        raise ValueError(f"{source}: intrinsics must be an object with fx, fy, cx, cy, got "
                         f"{type(data).__name__} {data!r}")
    missing = {"fx", "fy", "cx", "cy"} - set(data)
    if missing:
        raise ValueError(f"{source}: intrinsics are missing {sorted(missing)}")
    bad = [key for key, value in data.items() if not _is_number(value)]
    if bad:
        raise ValueError(f"{source}: intrinsics {bad[0]} must be a number of pixels, got "
                         f"{data[bad[0]]!r}")
    return CameraIntrinsics(float(data["fx"]), float(data["fy"]), float(data["cx"]),
                            float(data["cy"]), int(data.get("width", width)),
                            int(data.get("height", height)))


def _check_intrinsics(intrinsics: CameraIntrinsics, height: int, width: int,
                      source: str) -> CameraIntrinsics:
    if (intrinsics.height, intrinsics.width) != (height, width):
        raise ValueError(f"{source}: intrinsics are for {intrinsics.height}x{intrinsics.width} "
                         f"but the images are {height}x{width}")
    return intrinsics


class RGBDReader(Sequence):
    """Base of the folder readers: frames listed as file pairs, decoded on indexing.

    Args:
        pairs: (name, colour path, depth path, timestamp in seconds or None) per frame.
        depth_scale: raw depth units per metre.
        source: the dataset folder (for messages).

    Attributes:
        intrinsics: camera intrinsics shared by all frames (set by subclasses).
        frame_intrinsics: per-frame intrinsics by frame name, for the frames whose own
            differ from ``intrinsics`` (several cameras in one folder).
    """

    def __init__(self, pairs: list[tuple[str, Path, Path, float | None]], depth_scale: float,
                 source: Path) -> None:
        if not pairs:
            raise ValueError(f"no RGB-D frames found in {source}")
        self.root = source
        self.depth_scale = check_depth_scale(depth_scale)
        self._pairs = pairs
        self.intrinsics: CameraIntrinsics  # set by subclasses
        self.frame_intrinsics: dict[str, CameraIntrinsics] = {}

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the first colour image."""
        return color_image_size(self._pairs[0][1])

    @property
    def names(self) -> list[str]:
        """Frame names in reading order."""
        return [p[0] for p in self._pairs]

    def __len__(self) -> int:
        return len(self._pairs)

    def poses(self) -> list[np.ndarray | None] | None:
        """Each frame's camera pose from the folder's pose files, checked.

        Reads ``pose/<name>.txt`` (the shared TUM keyframes, recordings) or
        ``<name>.pose.txt`` (7-Scenes) for each frame (:mod:`deltar.io.pose_file`).

        Returns:
            Per frame in reading order a (4, 4) float64 camera-to-world transform in
            metres, or None for a frame without a pose file; None when no frame has one.

        Raises:
            ValueError: a pose file that is not a rigid transform (naming it).
        """
        paths = [frame_pose_file(self.root, name) for name in self.names]
        if all(path is None for path in paths):
            return None
        return [None if path is None else read_pose_file(path) for path in paths]

    def __getitem__(self, index: int) -> RGBDFrame:  # type: ignore[override]
        name, color_path, depth_path, stamp = self._pairs[checked_index(index, len(self))]
        image = read_color(color_path)
        depth = read_depth(depth_path, self.depth_scale)
        if depth.shape != image.shape[:2]:
            raise ValueError(f"colour {color_path} is {image.shape[:2]} but depth {depth_path} "
                             f"is {depth.shape}; they must be registered at the same size")
        intr = self.frame_intrinsics.get(name, self.intrinsics)
        if (intr.height, intr.width) != image.shape[:2]:
            raise ValueError(f"colour image {color_path} is {image.shape[:2]}, unlike the "
                             f"dataset's {intr.height}x{intr.width}")
        return RGBDFrame(image=image, depth_m=depth, intrinsics=intr, name=name,
                         timestamp_s=stamp)


# ---------------------------------------------------------------------- 7-Scenes / 3DMatch
_SEVEN_SCENES_COLOR = re.compile(r"^(frame-\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)


class SevenScenesReader(RGBDReader):
    """7-Scenes / 3DMatch layout: ``frame-NNNNNN.color.(jpg|png)``, ``frame-NNNNNN.depth.png``.

    Depth is in millimetres; ``camera-intrinsics.txt`` (3x3 matrix) in the folder gives the
    intrinsics unless ``intrinsics`` is passed.

    Args:
        folder: the sequence folder.
        depth_scale: raw depth units per metre (1000 = millimetres).
        intrinsics: override for the folder's ``camera-intrinsics.txt``.
    """

    def __init__(self, folder: str | Path, depth_scale: float = 1000.0,
                 intrinsics: CameraIntrinsics | None = None) -> None:
        root = Path(folder)
        input_folder(root, "7-Scenes folder")
        pairs = []
        for path in sorted(root.iterdir()):
            match = _SEVEN_SCENES_COLOR.match(path.name)
            if match:
                depth = root / f"{match.group(1)}.depth.png"
                if not depth.is_file():
                    raise FileNotFoundError(f"depth image missing for {path}: {depth}")
                pairs.append((match.group(1), path, depth, None))
        super().__init__(pairs, depth_scale, root)
        height, width = self.image_size
        if intrinsics is None:
            intrinsics = read_intrinsics_matrix(root / "camera-intrinsics.txt", height, width)
        self.intrinsics = _check_intrinsics(intrinsics, height, width, str(root))


# ---------------------------------------------------------------------- TUM
def _read_tum_table(path: Path, columns: tuple[str, ...]) -> list[tuple]:
    """Rows of a TUM text file, one line a row of ``columns`` (extra fields ignored).

    ``"timestamp"`` columns become float seconds, the others stay text; blank lines and
    ``#`` comments are skipped.

    Raises:
        ValueError: ``"<path>:<line>: ..."`` for a short row or a bad timestamp (not a
            number, or NaN or infinite).
    """
    rows = []
    with reading(path, "TUM list"):
        lines = path.read_text(encoding="utf-8").splitlines()
    for number, line in enumerate(lines, 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < len(columns):
            raise ValueError(f"{path}:{number}: expected '{' '.join(columns)}', got {line!r}")
        row = []
        for column, field in zip(columns, fields, strict=False):  # extra fields ignored
            if column != "timestamp":
                row.append(field)
                continue
            try:
                stamp = float(field)
            except ValueError as err:
                raise ValueError(f"{path}:{number}: bad timestamp {field!r}") from err
            if not math.isfinite(stamp):  # NaN pairs with nothing, inf with anything
                raise ValueError(f"{path}:{number}: bad timestamp {field!r} (not a finite "
                                 "number of seconds)")
            row.append(stamp)
        rows.append(tuple(row))
    return rows


def _read_tum_list(path: Path) -> list[tuple[float, str]]:
    """Read a TUM ``rgb.txt`` / ``depth.txt`` list: ``timestamp path`` per line."""
    return _read_tum_table(path, ("timestamp", "path"))


def _associate(rgb: list[tuple[float, str]], depth: list[tuple[float, str]],
               max_dt_s: float) -> list[tuple[float, str, float, str]]:
    """Pair each colour frame with the nearest depth frame within ``max_dt_s`` seconds."""
    if not rgb or not depth:
        return []
    d_times = np.array([t for t, _ in depth])
    order = np.argsort(d_times)
    d_sorted = d_times[order]
    out = []
    for t, rgb_path in rgb:
        i = int(np.searchsorted(d_sorted, t))
        candidates = [j for j in (i - 1, i) if 0 <= j < d_sorted.size]
        j = min(candidates, key=lambda k: abs(d_sorted[k] - t))
        if abs(d_sorted[j] - t) <= max_dt_s:
            dt, dpath = depth[order[j]]
            out.append((t, rgb_path, dt, dpath))
    return out


def _tum_rows(root: Path, associations: str = "associations.txt"
              ) -> list[tuple[float, str, float, str]]:
    """(t_rgb, rgb path, t_depth, depth path) rows of a TUM folder, paths relative to it."""
    assoc_path = root / associations
    if assoc_path.is_file():
        return _read_tum_table(assoc_path, ("timestamp", "rgb", "timestamp", "depth"))
    if (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        return _associate(_read_tum_list(root / "rgb.txt"), _read_tum_list(root / "depth.txt"),
                          max_dt_s=0.02)
    raise FileNotFoundError(f"TUM folder {root} has neither {associations} nor "
                            "rgb.txt + depth.txt")


class TUMReader(RGBDReader):
    """TUM RGB-D layout: an associations file ``t_rgb rgb/x.png t_depth depth/y.png``.

    Without ``associations.txt`` the TUM lists ``rgb.txt`` and ``depth.txt`` are paired by
    nearest timestamp (at most 20 ms apart, as TUM's ``associate.py`` does).

    Args:
        folder: the sequence folder.
        depth_scale: raw depth units per metre (TUM benchmark: 5000; most RealSense /
            Kinect recorders write millimetres: 1000).
        intrinsics: camera intrinsics; when None, :func:`default_intrinsics` (TUM's
            recommended defaults) with a warning.
        associations: associations file name inside ``folder``.
    """

    def __init__(self, folder: str | Path, depth_scale: float = 5000.0,
                 intrinsics: CameraIntrinsics | None = None,
                 associations: str = "associations.txt") -> None:
        root = Path(folder)
        input_folder(root, "TUM folder")
        rows = _tum_rows(root, associations)
        pairs = [(Path(rgb).stem, root / rgb, root / depth, t_rgb)
                 for t_rgb, rgb, _t_depth, depth in rows]
        super().__init__(pairs, depth_scale, root)
        height, width = self.image_size
        if intrinsics is None:
            warnings.warn(f"no intrinsics given for {root}; assuming the Kinect default "
                          "(fx = fy = 525 px at 640x480)", stacklevel=2)
            intrinsics = default_intrinsics(height, width)
        self.intrinsics = _check_intrinsics(intrinsics, height, width, str(root))


# ---------------------------------------------------------------------- plain folders
def _stem_map(folder: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    return {p.stem: p for p in sorted(folder.iterdir())  # hidden: temporaries, no frames
            if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith(".")}


class FolderReader(RGBDReader):
    """Two folders of images paired by file stem (``color/00012.jpg`` + ``depth/00012.png``).

    Args:
        folder: the dataset folder.
        depth_scale: raw depth units per metre (1000 = millimetres).
        intrinsics: camera intrinsics of the colour images.
        color_dir: colour sub-folder name.
        depth_dir: depth sub-folder name.
        intrinsics_dir: optional sub-folder of per-frame 3x3 camera matrices
            (``<stem>.txt``, as ``camera-intrinsics.txt``); a frame with such a file uses
            it instead of ``intrinsics``.

    Raises:
        FileNotFoundError: a sub-folder is missing.
        ValueError: no stems are common to both folders.
    """

    def __init__(self, folder: str | Path, depth_scale: float,
                 intrinsics: CameraIntrinsics, color_dir: str = "color",
                 depth_dir: str = "depth", intrinsics_dir: str | None = None) -> None:
        root = Path(folder)
        color_root, depth_root = root / color_dir, root / depth_dir
        for sub in (color_root, depth_root):
            input_folder(sub, "image folder")
        colors = _stem_map(color_root, IMAGE_SUFFIXES)
        depths = _stem_map(depth_root, _DEPTH_SUFFIXES)
        pairs = [(stem, colors[stem], depths[stem], None) for stem in colors if stem in depths]
        unpaired = sorted(set(colors) ^ set(depths))
        if pairs and unpaired:  # none paired: the base class says so
            warnings.warn(f"{root}: {len(unpaired)} image(s) without a partner of the same "
                          f"name in {color_dir}/ and {depth_dir}/ are left out (e.g. "
                          f"{unpaired[0]!r}); {len(pairs)} pairs are read", stacklevel=2)
        super().__init__(pairs, depth_scale, root)
        height, width = self.image_size
        self.intrinsics = _check_intrinsics(intrinsics, height, width, str(root))
        if intrinsics_dir is not None:
            for stem, _, _, _ in pairs:
                k_file = root / intrinsics_dir / f"{stem}.txt"
                if k_file.exists() or k_file.is_symlink():  # a folder there is refused
                    self.frame_intrinsics[stem] = read_intrinsics_matrix(k_file, height, width)


# ---------------------------------------------------------------------- detection
def detect_layout(folder: str | Path) -> str:
    """Guess a folder's layout: ``"7scenes"``, ``"tum"`` or ``"folder"``.

    Raises:
        FileNotFoundError: the folder does not exist.
        ValueError: no known layout matches.
    """
    root = Path(folder)
    input_folder(root, "RGB-D folder")
    if any(_SEVEN_SCENES_COLOR.match(p.name) for p in root.iterdir()):
        return "7scenes"
    if (root / "associations.txt").is_file() or (
            (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()):
        return "tum"
    if (root / "color").is_dir() and (root / "depth").is_dir():
        return "folder"
    raise ValueError(f"cannot tell the layout of {root}: expected frame-*.color.* files "
                     "(7-Scenes), associations.txt or rgb.txt + depth.txt (TUM), or color/ + "
                     "depth/ folders")


def _read_sidecar(root: Path) -> dict:
    path = root / SIDECAR_NAME
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err
    unknown = set(data) - {"layout", "depth_scale", "intrinsics"} if isinstance(data, dict) \
        else {"<not an object>"}
    if unknown:
        raise ValueError(f"{path}: unknown settings {sorted(unknown)}")
    scale = data.get("depth_scale", 1.0)
    if not (_is_number(scale) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"{path}: depth_scale must be a finite number > 0 of raw depth units "
                         f"per metre (1000 for millimetres), got {scale!r}")
    if data.get("layout", "folder") not in LAYOUTS:
        raise ValueError(f"{path}: layout must be one of {LAYOUTS}, got {data['layout']!r}")
    return data


def open_rgbd(path: str | Path, *, layout: str | None = None, depth_scale: float | None = None,
              intrinsics: CameraIntrinsics | None = None) -> RGBDReader:
    """Open an RGB-D folder with the right reader and its depth scale and intrinsics.

    Settings come from, in order: keyword arguments, the folder's ``deltar_rgbd.json``, then
    the layout's defaults:

    - ``7scenes``: millimetres, ``camera-intrinsics.txt``.
    - ``tum``: a TUM benchmark sequence (has ``rgb.txt`` and ``depth.txt``) uses 5000 units
      per metre; a folder with only ``associations.txt`` is taken as a RealSense/Kinect
      recording in millimetres (1000). Intrinsics: Kinect defaults with a warning.
    - ``folder`` (``color/`` + ``depth/``): millimetres; intrinsics from
      ``camera-intrinsics.txt`` in the folder if present, else Kinect defaults with a
      warning; a frame with its own ``intrinsics/<stem>.txt`` uses that one (unless
      intrinsics are given).

    Args:
        path: dataset folder.
        layout: force a layout instead of detecting it.
        depth_scale: raw depth units per metre.
        intrinsics: camera intrinsics (pixels) at the images' resolution.

    Returns:
        A reader: a sequence of :class:`RGBDFrame`.
    """
    root = Path(path)
    input_folder(root, "RGB-D folder")
    sidecar = _read_sidecar(root)
    layout = layout or sidecar.get("layout") or detect_layout(root)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if depth_scale is None and "depth_scale" in sidecar:
        depth_scale = float(sidecar["depth_scale"])
    if intrinsics is None and "intrinsics" in sidecar:
        height, width = _first_color_size(root, layout)
        intrinsics = _intrinsics_from_dict(sidecar["intrinsics"], height, width,
                                           str(root / SIDECAR_NAME))
    if layout == "7scenes":
        return SevenScenesReader(root, 1000.0 if depth_scale is None else depth_scale,
                                 intrinsics)
    if layout == "tum":
        if depth_scale is None:
            benchmark = (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()
            depth_scale = 5000.0 if benchmark else 1000.0
        return TUMReader(root, depth_scale, intrinsics)
    # Per-frame matrices (intrinsics/<stem>.txt) apply unless intrinsics were given.
    frame_dir = "intrinsics" if intrinsics is None and (root / "intrinsics").is_dir() else None
    if intrinsics is None:
        height, width = _first_color_size(root, layout)
        k_file = root / "camera-intrinsics.txt"
        if k_file.exists() or k_file.is_symlink():  # a folder there is refused, not ignored
            intrinsics = read_intrinsics_matrix(k_file, height, width)
        else:
            warnings.warn(f"no intrinsics given for {root}; assuming the Kinect default "
                          "(fx = fy = 525 px at 640x480)", stacklevel=2)
            intrinsics = default_intrinsics(height, width)
    return FolderReader(root, 1000.0 if depth_scale is None else depth_scale, intrinsics,
                        intrinsics_dir=frame_dir)


def _first_color_size(root: Path, layout: str) -> tuple[int, int]:
    if layout == "7scenes":
        files = sorted(p for p in root.iterdir() if _SEVEN_SCENES_COLOR.match(p.name))
    elif layout == "folder":
        files = sorted(_stem_map(root / "color", IMAGE_SUFFIXES).values())
    else:
        files = [root / row[1] for row in _tum_rows(root)[:1]]
    if not files:
        raise ValueError(f"no colour images found in {root}")
    return color_image_size(files[0])
