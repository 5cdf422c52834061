"""Procedural scenes: determinism, sizes, depth ranges and hand-checked ray hits."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.data import procedural
from deltar.data.procedural import ProceduralReader, render_scene, scene_intrinsics


def test_same_seed_same_frame_and_seeds_differ():
    a, b, c = render_scene(3, 48, 64), render_scene(3, 48, 64), render_scene(4, 48, 64)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert not np.array_equal(a.depth_m, c.depth_m)


@pytest.mark.parametrize(("height", "width"), [(48, 64), (30, 90)])
def test_shapes_types_and_room_scale_depth(height, width):
    for seed in range(5):
        frame = render_scene(seed, height, width)
        assert frame.image.shape == (height, width, 3) and frame.image.dtype == np.uint8
        assert frame.depth_m.shape == (height, width) and frame.depth_m.dtype == np.float32
        assert np.all(np.isfinite(frame.depth_m))
        # Indoor ranges: nothing closer than the camera's clearance, nothing beyond a room.
        assert 0.3 < frame.depth_m.min() and frame.depth_m.max() < 10.0
        assert frame.intrinsics == scene_intrinsics(height, width)
        assert frame.image.std() > 5  # shaded and textured, not one flat colour


def test_reader_is_a_sequence_of_seeded_frames():
    reader = ProceduralReader(3, seed=10, height=24, width=32)
    assert len(reader) == 3
    np.testing.assert_array_equal(reader[2].depth_m, render_scene(12, 24, 32).depth_m)
    assert reader[-1].name == "procedural-12"
    with pytest.raises(IndexError):
        reader[3]
    with pytest.raises(ValueError, match="num_frames"):
        ProceduralReader(0)


def _prim(kind, **shape):
    return procedural._Primitive(kind, np.ones(3), "plain", 1.0, **shape)


def test_intersections_match_hand_computed_distances():
    origin = np.zeros(3)
    # Rays with unit z component: straight ahead, and 45 degrees to the right.
    rays = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]).T  # (3, N)
    with np.errstate(divide="ignore", invalid="ignore"):
        sphere = procedural._hit_sphere(_prim("sphere", center=np.array([0, 0, 3.0]),
                                              radius=0.5), origin, rays)
        box = procedural._hit_box(_prim("box", lo=np.array([-1, -1, 2.0]),
                                        hi=np.array([1, 1, 4.0])), origin, rays)
        room = procedural._hit_room(_prim("room", lo=np.array([-2, -1, -1.0]),
                                          hi=np.array([2, 2, 5.0])), origin, rays)
        cyl = procedural._hit_cylinder(_prim("cylinder", center=np.array([0, -1, 2.0]),
                                             radius=0.25, height=2.0), origin, rays)
    np.testing.assert_allclose(sphere, [2.5, np.inf])
    # The 45-degree ray reaches x = 1 at z = 1, before the box starts at z = 2: a miss.
    np.testing.assert_allclose(box, [2.0, np.inf])
    np.testing.assert_allclose(room, [5.0, 2.0])  # far wall z = 5; side wall x = 2
    np.testing.assert_allclose(cyl, [1.75, np.inf])
    # Looking down onto the cylinder's top cap (y = 1) from above.
    with np.errstate(divide="ignore", invalid="ignore"):
        cap = procedural._hit_cylinder(_prim("cylinder", center=np.array([0, -1, 0.0]),
                                             radius=0.25, height=2.0),
                                       np.array([0, 3.0, 0]), np.array([[0.0], [-1.0], [1e-3]]))
    np.testing.assert_allclose(cap, [2.0], rtol=1e-5)


def test_shadow_rays_by_hand():
    # A 2 m box floating 1-2 m above a floor point, light straight above: shadowed; light
    # off to the side (the segment passes x = 1.7..3.3 m at the box's height): lit.
    box = _prim("box", lo=np.array([-1.0, 1.0, -1.0]), hi=np.array([1.0, 2.0, 1.0]))
    room = _prim("room", lo=np.array([-9.0, 0.0, -9.0]), hi=np.array([9.0, 4.0, 9.0]))
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    normals = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])  # the second faces away
    above = procedural._in_shadow([room, box], points, normals, np.array([0.0, 3.0, 0.0]))
    side = procedural._in_shadow([room, box], points, normals, np.array([5.0, 3.0, 0.0]))
    assert above.tolist() == [True, False]  # a point facing away is unlit, not "shadowed"
    assert side.tolist() == [False, False]
