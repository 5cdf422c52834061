"""Pair the image files and zone-frame files of two folders by file stem."""

from __future__ import annotations

import os
from pathlib import Path

from deltar.io.input_file import input_folder

#: Image files taken from an images folder (suffix, any case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".webp")
#: Zone-frame files taken from a zones folder (:mod:`deltar.io.zone_file`).
ZONE_SUFFIXES = (".json", ".npz")


def pair_by_stem(images_dir: str | os.PathLike, zones_dir: str | os.PathLike
                 ) -> tuple[list[tuple[Path, Path]], list[str]]:
    """Pair image files and zone files by file stem (``a.png`` with ``a.json``).

    Args:
        images_dir: folder of images (:data:`IMAGE_SUFFIXES`).
        zones_dir: folder of zone frames (:data:`ZONE_SUFFIXES`); may be the same folder.

    Returns:
        (``(image, zone file)`` pairs sorted by stem, the stems that have only an image
        or only a zone file, sorted).

    Raises:
        FileNotFoundError / NotADirectoryError: a folder is missing or a file; the
            message names it.
        ValueError: two files of one folder share a stem (``a.png`` and ``a.jpg``): which
            one is meant is unknown, so neither is dropped silently.
    """
    images_dir = input_folder(images_dir, "image folder")
    zones_dir = input_folder(zones_dir, "zone folder")
    images = _by_stem(images_dir, IMAGE_SUFFIXES, "images")
    zones = _by_stem(zones_dir, ZONE_SUFFIXES, "zone files")
    stems = sorted(images.keys() & zones.keys())
    unpaired = sorted(images.keys() ^ zones.keys())
    return [(images[s], zones[s]) for s in stems], unpaired


def _by_stem(folder: Path, suffixes: tuple[str, ...], what: str) -> dict[str, Path]:
    """The files of ``folder`` with one of ``suffixes`` by stem; refuses shared stems.
    Hidden files (a leading dot: editors' and atomic writes' temporaries) are no frames."""
    found: dict[str, Path] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() not in suffixes or path.name.startswith(".") or \
                not path.is_file():
            continue
        if path.stem in found:
            raise ValueError(f"{found[path.stem]} and {path} are {what} with the same stem "
                             f"{path.stem!r}; frames pair by stem, so keep only one of them")
        found[path.stem] = path
    return found
