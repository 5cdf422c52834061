"""Pair the image files and zone-frame files of two folders by file stem."""

from __future__ import annotations

import os
from pathlib import Path

#: Image files taken from an images folder (suffix, any case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm")
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
        FileNotFoundError: a folder is missing; the message names it.
    """
    images_dir, zones_dir = Path(images_dir), Path(zones_dir)
    for folder, kind in ((images_dir, "image"), (zones_dir, "zone")):
        if not folder.is_dir():
            raise FileNotFoundError(f"{kind} folder not found: {folder}")
    images = {p.stem: p for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    zones = {p.stem: p for p in zones_dir.iterdir() if p.suffix.lower() in ZONE_SUFFIXES}
    stems = sorted(images.keys() & zones.keys())
    unpaired = sorted(images.keys() ^ zones.keys())
    return [(images[s], zones[s]) for s in stems], unpaired
