"""The confidence-weighted TSDF: surfaces where they are, weights, memory budget, files."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.mapping.tsdf import MapSettings, TSDFMap, block_bytes, estimate_blocks
from tests.mapping.conftest import SMALL, WALL_Z_M, pose_at, render_wall

COARSE = MapSettings(voxel_size_m=0.04, truncation_voxels=3, max_depth_m=4.0)


def _wall_map(settings=COARSE, weight=None, poses=None):
    volume = TSDFMap(settings)
    for pose in poses or [pose_at(0.0), pose_at(0.1), pose_at(-0.1, yaw_deg=5)]:
        image, depth = render_wall(pose)
        volume.integrate(depth, image, weight, SMALL, pose)
    return volume


def test_a_wall_integrates_into_a_mesh_on_the_wall():
    volume = _wall_map()
    mesh = volume.mesh()
    vertices = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 100
    # Every vertex on the plane (marching cubes interpolates: well within a voxel).
    assert np.abs(vertices[:, 2] - WALL_Z_M).max() < 0.01
    # It spans the wall the cameras saw: about +-1.3 m at 2 m for this camera.
    assert vertices[:, 0].min() < -1.0 and vertices[:, 0].max() > 1.0
    assert np.abs(vertices[:, 1]).max() == pytest.approx(1.0, abs=0.15)
    colors = np.asarray(mesh.vertex_colors)
    assert colors.min() >= 0 and colors.max() <= 1 and colors.std() > 0.05


def test_a_box_corner_lands_on_both_faces():
    # A step: the left half of the image sees a nearer face (z = 1.5 m).
    pose = pose_at(0.0)
    image, depth = render_wall(pose)
    depth[:, :40] *= 1.5 / WALL_Z_M
    volume = TSDFMap(COARSE)
    volume.integrate(depth, image, None, SMALL, pose)
    xyz, rgb = volume.points()
    near = xyz[xyz[:, 0] < -0.2]
    far = xyz[xyz[:, 0] > 0.2]
    assert np.abs(near[:, 2] - 1.5).max() < 0.02
    assert np.abs(far[:, 2] - WALL_Z_M).max() < 0.02
    assert rgb.dtype == np.uint8 and rgb.shape == xyz.shape


def test_zero_weight_pixels_are_skipped_and_weights_average():
    weight = np.ones((SMALL.height, SMALL.width), np.float32)
    weight[:, 40:] = 0.0  # the right half (x > 0 in the world) is not integrated
    vertices = np.asarray(_wall_map(weight=weight, poses=[pose_at(0.0)]).mesh().vertices)
    assert vertices[:, 0].max() < 0.1
    # Weighted mean: a frame at weight 3 pulls the surface 3x as hard as one at weight 1.
    volume = TSDFMap(COARSE)
    pose = pose_at(0.0)
    image, depth = render_wall(pose)
    volume.integrate(depth, image, np.ones_like(depth), SMALL, pose)
    volume.integrate(depth + 0.04, image, np.full_like(depth, 3.0), SMALL, pose)
    z = np.asarray(volume.mesh().vertices)[:, 2]
    assert np.median(z) == pytest.approx(WALL_Z_M + 0.03, abs=0.006)


def test_depth_beyond_the_limit_is_not_integrated():
    settings = MapSettings(voxel_size_m=0.04, truncation_voxels=3, max_depth_m=1.5)
    volume = _wall_map(settings)
    assert volume.block_count == 0
    with pytest.raises(ValueError, match="no surface"):
        volume.write("unused")


def test_the_budget_bounds_the_blocks_and_warns_once():
    settings = MapSettings(voxel_size_m=0.04, truncation_voxels=3,
                           max_memory_bytes=60 * block_bytes())
    poses = [pose_at(0.5 * i) for i in range(6)]  # the camera keeps seeing new wall
    with pytest.warns(RuntimeWarning, match="memory budget") as record:
        volume = _wall_map(settings, poses=poses)
    assert len(record) == 1
    assert volume.block_count <= 60 and volume.capacity_blocks <= 60
    assert volume.full_frames >= 1


def test_the_capacity_doubles_as_the_map_grows():
    volume = TSDFMap(COARSE, capacity_blocks=8)
    image, depth = render_wall(pose_at(0.0))
    volume.integrate(depth, image, None, SMALL, pose_at(0.0))
    assert volume.capacity_blocks >= volume.block_count > 8
    assert volume.memory_bytes == volume.capacity_blocks * block_bytes()


def test_write_makes_both_files_and_refuses_to_overwrite(tmp_path):
    from deltar.io.ply import read_ply
    from deltar.mapping.tsdf import require_open3d

    paths = _wall_map().write(tmp_path)
    mesh = require_open3d().io.read_triangle_mesh(str(paths["mesh"]))
    assert len(mesh.triangles) > 100 and mesh.has_vertex_colors()
    cloud = read_ply(paths["points"])
    assert cloud.colors is not None and np.abs(cloud.points[:, 2] - WALL_Z_M).max() < 0.01
    with pytest.raises(FileExistsError):
        _wall_map().write(tmp_path)
    assert not list(tmp_path.glob(".*tmp*"))


def test_estimate_takes_the_smaller_bound():
    still = np.zeros((10, 3))
    box = estimate_blocks(COARSE, still, first_frame_blocks=10_000, frames=10)
    assert box < 10 * 15_000
    assert estimate_blocks(COARSE, None, first_frame_blocks=100, frames=10) == 1500


def test_settings_refuse_bad_numbers():
    with pytest.raises(ValueError, match="voxel_size_m"):
        MapSettings(voxel_size_m=0)
    with pytest.raises(ValueError, match="truncation_voxels"):
        MapSettings(truncation_voxels=0.5)
    with pytest.raises(ValueError, match="max_memory_bytes"):
        MapSettings(max_memory_bytes=10)


def test_integrate_takes_a_float32_pose_and_names_bad_frames():
    rgb, depth = render_wall(pose_at(0.0))
    volume = TSDFMap(COARSE)
    assert volume.integrate(depth, rgb, None, SMALL, pose_at(0.0).astype(np.float32)) > 0
    for pose, message in ((np.eye(3), "a pose must be a 4x4 matrix"),
                          (np.full((4, 4), np.nan), "NaN or infinite"),
                          (np.diag([2.0, 2.0, 2.0, 1.0]), "not a rotation")):
        with pytest.raises(ValueError, match=f"camera_to_world: .*{message}"):
            volume.integrate(depth, rgb, None, SMALL, pose)
    with pytest.raises(ValueError, match=r"color_rgb must be an \(H, W, 3\) uint8 RGB image"):
        volume.integrate(depth, None, None, SMALL, pose_at(0.0))


def test_a_large_memory_budget_is_capped_below_open3ds_crash():
    """Open3D segfaults extracting a surface from about 2^18 blocks: the volume never
    holds that many, whatever --max-memory (nothing is allocated here)."""
    from deltar.mapping.tsdf import MAX_BLOCKS

    assert MAX_BLOCKS < 250_000
    huge = MapSettings(max_memory_bytes=64 * 2**30)
    assert huge.max_blocks == MAX_BLOCKS and huge.memory_clipped
    default = MapSettings()
    assert default.max_blocks == 2 * 2**30 // block_bytes() and not default.memory_clipped
