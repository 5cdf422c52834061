"""Datasets and readers: RGB-D folders, ZJU-L5 sets, NYU-Depth V2, simulated L5 and
procedural scenes.

Every name is imported on first use, so that reading one colour image (as ``deltar
predict`` does) does not load the NYU reader's HDF5 library or the torch-based modules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from deltar.extras import lazy_attributes

if TYPE_CHECKING:
    from deltar.data.nyu import NYU_INTRINSICS, NYUH5Reader, NYULabeledReader
    from deltar.data.procedural import ProceduralReader, render_scene
    from deltar.data.rgbd import (
        FolderReader,
        RGBDFrame,
        SevenScenesReader,
        TUMReader,
        detect_layout,
        open_rgbd,
    )
    from deltar.data.sources import open_source
    from deltar.data.zju_l5 import ZJUL5Dataset, ZJUL5Sample, write_zju_l5

_LAZY = {
    "NYU_INTRINSICS": "deltar.data.nyu",
    "NYUH5Reader": "deltar.data.nyu",
    "NYULabeledReader": "deltar.data.nyu",
    "ProceduralReader": "deltar.data.procedural",
    "render_scene": "deltar.data.procedural",
    "FolderReader": "deltar.data.rgbd",
    "RGBDFrame": "deltar.data.rgbd",
    "SevenScenesReader": "deltar.data.rgbd",
    "TUMReader": "deltar.data.rgbd",
    "detect_layout": "deltar.data.rgbd",
    "open_rgbd": "deltar.data.rgbd",
    "open_source": "deltar.data.sources",
    "ZJUL5Dataset": "deltar.data.zju_l5",
    "ZJUL5Sample": "deltar.data.zju_l5",
    "write_zju_l5": "deltar.data.zju_l5",
}


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = [
    "NYU_INTRINSICS",
    "FolderReader",
    "NYUH5Reader",
    "NYULabeledReader",
    "ProceduralReader",
    "RGBDFrame",
    "SevenScenesReader",
    "TUMReader",
    "ZJUL5Dataset",
    "ZJUL5Sample",
    "detect_layout",
    "open_rgbd",
    "open_source",
    "render_scene",
    "write_zju_l5",
]
