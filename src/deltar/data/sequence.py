"""What the dataset readers share as ``Sequence`` s: the index check of ``__getitem__``."""

from __future__ import annotations


def checked_index(index: int, length: int, item: str = "frame") -> int:
    """``index`` unchanged when a sequence of ``length`` items has it (negative indices
    count from the end, as in a list).

    Raises:
        IndexError: ``"<item> index <index> out of range for <length> <item>s"``.
    """
    if not -length <= index < length:
        raise IndexError(f"{item} index {index} out of range for {length} {item}s")
    return index
