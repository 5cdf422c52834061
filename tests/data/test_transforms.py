"""Image augmentation: rotation geometry, photometric ranges, seeding."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.camera import CameraIntrinsics
from deltar.data.transforms import ImageAugmentation, flip_intrinsics

INTR = CameraIntrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)


def _inputs():
    image = np.full((48, 64, 3), 128, np.uint8)
    depth = np.full((48, 64), 2.0, np.float32)
    return image, depth


def test_rotation_leaves_invalid_corners_and_keeps_depth_values():
    aug = ImageAugmentation(max_rotation_deg=2.5, flip_prob=0.0, photometric_prob=0.0)
    image, depth = _inputs()
    out = aug.apply(image, depth, INTR, np.random.default_rng(0))
    # Nearest-neighbour depth: only the original value or the invalid border marker.
    assert set(np.unique(out.depth_m)) <= {0.0, 2.0}
    assert out.depth_m[24, 32] == 2.0
    # A rotation of up to 2.5 degrees about the centre moves a corner of a 64x48 image by
    # at most 32 * sin(2.5 deg) + 24 * (1 - cos(2.5 deg)) < 1.5 px: at most a thin border.
    assert np.count_nonzero(out.depth_m == 0) < 2 * (48 + 64) * 2
    assert out.intrinsics == INTR
    # Some rotation does happen: the rotated-in corners are marked invalid.
    assert any(np.count_nonzero(aug.apply(image, depth, INTR, np.random.default_rng(s))
                                .depth_m == 0) > 0 for s in range(5))


def test_photometric_jitter_stays_in_the_documented_range():
    aug = ImageAugmentation(max_rotation_deg=0.0, flip_prob=0.0, photometric_prob=1.0)
    image, depth = _inputs()
    x = 128 / 255
    # Extremes of gamma, brightness and colour factors.
    low, high = x**1.1 * 0.75 * 0.9, min(1.0, x**0.9 * 1.25 * 1.1)
    for seed in range(20):
        out = aug.apply(image, depth, INTR, np.random.default_rng(seed))
        assert low - 1e-6 <= out.image.min() and out.image.max() <= high + 1e-6
        # One gamma and brightness for the image, one factor per channel: flat per channel.
        assert np.ptp(out.image.reshape(-1, 3), axis=0).max() < 1e-6


def test_same_generator_state_same_output():
    aug = ImageAugmentation(crop_size=(32, 40))
    image = np.random.default_rng(3).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = np.random.default_rng(4).uniform(0.5, 4, (48, 64)).astype(np.float32)
    a = aug.apply(image, depth, INTR, np.random.default_rng(9))
    b = aug.apply(image, depth, INTR, np.random.default_rng(9))
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert (a.crop_top, a.crop_left, a.flipped) == (b.crop_top, b.crop_left, b.flipped)


def test_flip_intrinsics_by_hand():
    flipped = flip_intrinsics(CameraIntrinsics(50.0, 51.0, 30.0, 20.0, 64, 48))
    assert (flipped.cx, flipped.cy, flipped.fx, flipped.fy) == (33.0, 20.0, 50.0, 51.0)


def test_bad_augmentation_settings():
    with pytest.raises(ValueError, match="crop_size"):
        ImageAugmentation(crop_size=(0, 10))
    with pytest.raises(ValueError, match="flip_prob"):
        ImageAugmentation(flip_prob=1.5)



def test_zoom_multiplies_the_focal_lengths_and_keeps_the_size():
    image, depth = _inputs()
    depth[:, 32:] = 3.0
    intrinsics = CameraIntrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
    aug = ImageAugmentation(max_rotation_deg=0.0, flip_prob=0.0, photometric_prob=0.0,
                            max_zoom=2.0)
    out = aug.apply(image, depth, intrinsics, np.random.default_rng(3))
    assert out.image.shape[:2] == depth.shape and out.depth_m.shape == depth.shape
    zoom = out.intrinsics.fx / intrinsics.fx
    assert 1.0 < zoom <= 2.0
    assert out.intrinsics.fy / intrinsics.fy == pytest.approx(zoom, rel=0.05)
    # Depth values are resampled by nearest neighbour: no new distances appear.
    assert set(np.unique(out.depth_m)) <= set(np.unique(depth))
    with pytest.raises(ValueError, match="max_zoom"):
        ImageAugmentation(max_zoom=0.5)
