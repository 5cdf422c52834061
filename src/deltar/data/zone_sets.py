"""Open a set of real (or simulated) zone readings by kind: ZJU-L5 or THDR3K.

Both kinds read as sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample` (image,
ground-truth depth, zone readings and rectangles, optional histograms), so every
consumer of ZJU-L5 sets (``deltar evaluate``, fine-tuning) reads THDR3K sets too.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

#: Kinds :func:`open_zone_set` reads (``"auto"`` picks one from the files).
ZONE_SET_KINDS: tuple[str, ...] = ("zju_l5", "thdr3k")


def open_zone_set(path: str | Path, split: str = "test", kind: str = "auto") -> Sequence:
    """Open a ZJU-L5-layout or THDR3K-layout set.

    Args:
        path: a ZJU-L5 ``data.json`` (or its folder), or a THDR3K file list JSON.
        split: the list to read (``"test"``, ``"train"``...).
        kind: ``"zju_l5"``, ``"thdr3k"`` or ``"auto"``: THDR3K when the list's first
            entry has a ``<root>_tof.json`` beside it, else ZJU-L5.

    Returns:
        A :class:`~deltar.data.zju_l5.ZJUL5Dataset` or
        :class:`~deltar.data.thdr3k.THDR3KDataset`.

    Raises:
        FileNotFoundError / ValueError: missing or corrupt list, unknown split or kind.
    """
    from deltar.data.thdr3k import THDR3KDataset, is_thdr3k_list
    from deltar.data.zju_l5 import ZJUL5Dataset

    if kind not in (*ZONE_SET_KINDS, "auto"):
        raise ValueError(f"kind must be one of {(*ZONE_SET_KINDS, 'auto')}, got {kind!r}")
    path = Path(path)
    if kind == "auto":
        kind = "thdr3k" if path.is_file() and is_thdr3k_list(path, split) else "zju_l5"
    if kind == "thdr3k":
        return THDR3KDataset(path, split=split)
    return ZJUL5Dataset(path, split=split)
