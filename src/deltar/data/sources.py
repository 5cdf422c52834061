"""Open any supported RGB-D source from one string (used by the CLI)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from deltar.camera import CameraIntrinsics
from deltar.data.flat_wall import WALL_PREFIX, open_wall_source
from deltar.data.nyu import NYU_INTRINSICS, NYUH5Reader, NYULabeledReader
from deltar.data.procedural import ProceduralReader
from deltar.data.rgbd import RGBDFrame, open_rgbd

#: Prefix of procedural sources: ``procedural:<frames>[:<seed>[:<height>x<width>]]``.
PROCEDURAL_PREFIX = "procedural:"


def _procedural(spec: str) -> ProceduralReader:
    parts = spec[len(PROCEDURAL_PREFIX):].split(":")
    try:
        if len(parts) > 3:
            raise ValueError("too many fields")
        frames = int(parts[0])
        seed = int(parts[1]) if len(parts) > 1 else 0
        if seed < 0:
            raise ValueError("a seed is >= 0")
        height, width = (int(v) for v in parts[2].split("x")) if len(parts) > 2 else (480, 640)
    except (ValueError, IndexError) as err:
        raise ValueError(f"procedural source must look like 'procedural:100', "
                         f"'procedural:100:7' or 'procedural:100:7:480x640', got {spec!r}"
                         ) from err
    return ProceduralReader(frames, seed, height, width)


def open_source(spec: str | Path, *, depth_scale: float | None = None,
                intrinsics: CameraIntrinsics | None = None, split: str = "train",
                ) -> Sequence[RGBDFrame]:
    """Open an RGB-D source, detecting its kind.

    Args:
        spec: one of

            - an RGB-D folder (7-Scenes, TUM, ``color/`` + ``depth/``; see
              :func:`deltar.data.rgbd.open_rgbd`);
            - a NYU-Depth V2 labeled ``.mat`` file;
            - a ``.json`` split file of the release's NYU h5 files (``split`` selects the
              list);
            - ``procedural:<frames>[:<seed>[:<height>x<width>]]`` for procedural rooms;
            - ``wall:<metres>[:<frames>[:<height>x<width>]]`` for a textured flat wall
              (:mod:`deltar.data.flat_wall`).
        depth_scale: raw depth units per metre; folder sources only.
        intrinsics: camera intrinsics (pixels) overriding the source's own (not for
            procedural sources, which define their camera).
        split: list to read from a NYU json split file.

    Returns:
        A sequence of :class:`~deltar.data.rgbd.RGBDFrame`.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the source kind cannot be told or its options are invalid.
    """
    text = str(spec)
    for prefix, opener in ((PROCEDURAL_PREFIX, _procedural), (WALL_PREFIX, open_wall_source)):
        if text.startswith(prefix):
            if intrinsics is not None or depth_scale is not None:
                raise ValueError(f"{prefix[:-1]} sources define their own camera and metric "
                                 "depth; intrinsics and depth_scale do not apply")
            return opener(text)
    path = Path(spec)
    if path.is_dir():
        return open_rgbd(path, depth_scale=depth_scale, intrinsics=intrinsics)
    if not path.exists():
        raise FileNotFoundError(f"RGB-D source not found: {path}")
    if depth_scale is not None:
        raise ValueError(f"depth_scale applies to RGB-D folders only; {path} stores metres")
    if path.suffix.lower() == ".mat":
        return NYULabeledReader(path, intrinsics=intrinsics or NYU_INTRINSICS)
    if path.suffix.lower() == ".json":
        return NYUH5Reader(path, split=split, intrinsics=intrinsics or NYU_INTRINSICS)
    raise ValueError(f"cannot tell what {path} is: expected an RGB-D folder, a NYU .mat, a "
                     "NYU split .json, 'procedural:<frames>' or 'wall:<metres>'")
