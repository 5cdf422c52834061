"""Pairing readings with images: one reading per image.

Shared by the recording and bag readers' users (``deltar replay`` and ``deltar map``),
so both keep the same reading of an image and warn in the same words.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

Pair = TypeVar("Pair")


def one_per_image(pairs: list[Pair], image_of: Callable[[Pair], Any],
                  distance_of: Callable[[Pair], float], source: str | os.PathLike,
                  what: str = "zone frame") -> list[Pair]:
    """Keep one pair per image, the reading nearest it in time (the first of a tie).

    A sensor faster than the camera pairs several readings with one image: writing that
    image's outputs twice makes two results under one name (the second replaces the
    first), and fusing it twice weighs it double and repeats its time in a trajectory.

    Args:
        pairs: the pairs, in time order.
        image_of: the pair's image (anything hashable that is equal for one image).
        distance_of: how far the reading is from its image, seconds (after any time
            offset the pairing applied).
        source: the recording or bag, for the warning.
        what: what a reading is called in the warning (singular).

    Returns:
        The kept pairs, in their order; a warning counts the others.
    """
    # image -> index of its nearest pair: by index, as two equal pairs are two readings
    best: dict[Any, int] = {}
    for i, pair in enumerate(pairs):
        key = image_of(pair)
        if key not in best or distance_of(pair) < distance_of(pairs[best[key]]):
            best[key] = i
    kept = set(best.values())
    if len(kept) < len(pairs):
        warnings.warn(f"{source}: {len(pairs) - len(kept)} of {len(pairs)} {what}s share "
                      f"a colour image with a {what} nearer to it in time and are left out "
                      f"(one {what} per image)", stacklevel=3)
    return [pair for i, pair in enumerate(pairs) if i in kept]
