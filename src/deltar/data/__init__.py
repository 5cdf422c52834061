"""Datasets and readers: RGB-D folders, ZJU-L5 sets, NYU-Depth V2, simulated L5 and
procedural scenes.

The torch-based modules (``deltar.data.simulated``) are imported on demand.
"""

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
