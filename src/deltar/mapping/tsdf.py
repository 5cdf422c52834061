"""A confidence-weighted TSDF map in Open3D's ``VoxelBlockGrid``.

The volume is Open3D's sparse voxel block grid (hashed blocks of
``block_resolution``\\ :sup:`3` voxels, each with a truncated signed distance, an RGB
colour, the number of pixels that observed it and the sum of their weights, all
float32). Open3D allocates the blocks that a frame's depth
touches (``compute_unique_block_coordinates``) and extracts the mesh and points
(marching cubes); the per-voxel update, a weighted running average, is done here with
numpy on the grid's own attribute buffers (shared, not copied) because Open3D's
``integrate`` gives every pixel the weight 1 and the map weights each pixel by its
confidence.

Two quantities per voxel, because they answer different questions: the pixels' weights
(their confidence, :func:`deltar.mapping.frames.confidence_weight`) decide how the
views that see a voxel are averaged, so a confident view outvotes an unsure one where
both look; the number of pixels that observed it (Open3D's ``weight`` attribute, which
its extraction thresholds) decides whether the voxel is on the surface at all, so one
integrated pixel makes a surface whatever its weight, as one pixel of a classical
baseline (weight 1) does. Which pixels are integrated at all is the depth source's
choice (a zero weight skips a pixel).

Memory is bounded: the grid's block capacity doubles as the map grows but never past
the budget (``max_memory_bytes``); once the budget is reached, a frame integrates only
into the blocks that exist (the map stops growing, with a warning).
One block costs :func:`block_bytes` (about 10 KiB at 8\\ :sup:`3` voxels).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from deltar.camera import CameraIntrinsics

#: Voxels per block side.
BLOCK_RESOLUTION = 8
#: Bytes per voxel: tsdf, observation count, RGB and weight sum, float32 each.
VOXEL_BYTES = 4 * (1 + 1 + 3 + 1)
#: Hash map bytes per block beside the voxels (key, index, bookkeeping), measured order.
BLOCK_OVERHEAD_BYTES = 64
#: Least number of integrated pixels that observed a voxel on the extracted surface.
MIN_OBSERVATIONS = 1
#: Blocks a map reserves at first (48 MiB at 8^3 voxels); it doubles as needed.
INITIAL_BLOCKS = 4096
#: Most blocks a map may hold, whatever its memory budget: Open3D 0.20 crashes (a
#: segfault, not an error) extracting the surface of a grid of about 2^18 = 262,144
#: blocks, with dense surfaces from about 250,000. 3 x 2^16 keeps a 20 % margin below
#: that (a surface through every one of them extracted: 49.7 million triangles) and
#: stays above the default budget's 173,857 blocks (2 GiB).
MAX_BLOCKS = 3 * 2**16
_OPEN3D_HINT = 'mapping needs Open3D: pip install "deltar[map]"'


def require_open3d() -> Any:
    """Import ``open3d`` or raise ``ImportError`` naming the extra.

    Open3D's Linux wheel links ``libusb-1.0.so.0`` (for RealSense cameras). Machines
    without the system library use the copy of the ``libusb-package`` wheel (part of
    the ``map`` extra), loaded before Open3D.
    """
    try:
        import open3d
    except ImportError as first:
        if "libusb" not in str(first):
            raise ImportError(f"{_OPEN3D_HINT} ({first})") from first
        try:
            import ctypes

            import libusb_package

            ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
            import open3d
        except (ImportError, OSError) as err:
            raise ImportError(f"{_OPEN3D_HINT}; Open3D needs libusb-1.0 (apt-get install "
                              f"libusb-1.0-0, or pip install libusb-package) ({err})") from err
    return open3d


def _buffer(attribute: Any, channels: int) -> np.ndarray:
    """A grid attribute as a flat (N,) or (N, channels) numpy view of Open3D's memory."""
    array = attribute.numpy()
    flat = array.reshape(-1) if channels == 1 else array.reshape(-1, channels)
    if not np.may_share_memory(flat, array):  # a copy: the update would be lost
        raise RuntimeError("the voxel grid's attribute is not contiguous")
    return flat


def block_bytes(block_resolution: int = BLOCK_RESOLUTION) -> int:
    """Memory of one voxel block in bytes (voxels + hash map entry)."""
    return block_resolution ** 3 * VOXEL_BYTES + BLOCK_OVERHEAD_BYTES


@dataclass(frozen=True)
class MapSettings:
    """How the map is built.

    Attributes:
        voxel_size_m: voxel side, metres.
        truncation_voxels: TSDF truncation distance in voxels (the band around the
            surface that a pixel updates: ``truncation_voxels * voxel_size_m`` metres).
        max_depth_m: depth beyond this is not integrated, metres.
        max_memory_bytes: the volume's block capacity is sized to this; it never grows.
        block_resolution: voxels per block side.
    """

    voxel_size_m: float = 0.02
    truncation_voxels: float = 4.0
    max_depth_m: float = 4.0
    max_memory_bytes: int = 2 * 1024 ** 3
    block_resolution: int = BLOCK_RESOLUTION

    def __post_init__(self) -> None:
        for name in ("voxel_size_m", "truncation_voxels", "max_depth_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if self.truncation_voxels < 1:
            raise ValueError(f"truncation_voxels must be >= 1, got {self.truncation_voxels}")
        if self.max_memory_bytes < block_bytes(self.block_resolution):
            raise ValueError(f"max_memory_bytes must hold at least one block "
                             f"({block_bytes(self.block_resolution)} B), got "
                             f"{self.max_memory_bytes}")

    @property
    def truncation_m(self) -> float:
        """The truncation distance in metres."""
        return self.truncation_voxels * self.voxel_size_m

    @property
    def block_size_m(self) -> float:
        """A block's side in metres."""
        return self.voxel_size_m * self.block_resolution

    @property
    def max_blocks(self) -> int:
        """Blocks that fit into ``max_memory_bytes``, at most :data:`MAX_BLOCKS`."""
        return min(self._budget_blocks, MAX_BLOCKS)

    @property
    def memory_clipped(self) -> bool:
        """Whether ``max_memory_bytes`` holds more blocks than :data:`MAX_BLOCKS` (the
        volume is capped there)."""
        return self._budget_blocks > MAX_BLOCKS

    @property
    def _budget_blocks(self) -> int:
        return int(self.max_memory_bytes // block_bytes(self.block_resolution))


def estimate_blocks(settings: MapSettings, positions_m: np.ndarray | None,
                    first_frame_blocks: int, frames: int) -> int:
    """An upper estimate of the blocks a map will allocate.

    Every block lies within ``max_depth_m`` (+ truncation) of a camera centre, so the
    blocks of the box around the camera path widened by that distance bound the map;
    and no frame allocates more than the first one did (times a margin of 1.5 for
    views that see more), so ``frames x`` that bounds it too. The smaller bound is
    returned.

    Args:
        settings: map settings.
        positions_m: (N, 3) camera centres in metres, or None when unknown (odometry).
        first_frame_blocks: blocks the first frame touches.
        frames: number of frames.
    """
    per_frames = math.ceil(1.5 * first_frame_blocks) * max(frames, 1)
    if positions_m is None or len(positions_m) == 0:
        return per_frames
    reach = settings.max_depth_m + settings.truncation_m
    extent = np.ptp(np.asarray(positions_m), axis=0) + 2 * reach
    box = int(np.prod(np.ceil(extent / settings.block_size_m) + 1))
    return min(box, per_frames)


class TSDFMap:
    """A growing confidence-weighted TSDF map.

    Args:
        settings: voxel size, truncation, depth limit, memory budget.
        capacity_blocks: block capacity to allocate first (default
            :data:`INITIAL_BLOCKS`); it doubles when full, never past the budget
            (``settings.max_blocks``).
        device: Open3D device, ``"CPU:0"``.
    """

    def __init__(self, settings: MapSettings, capacity_blocks: int | None = None,
                 device: str = "CPU:0") -> None:
        o3d = require_open3d()
        import open3d.core as o3c

        self.settings = settings
        self.max_blocks = settings.max_blocks
        capacity = min(INITIAL_BLOCKS, self.max_blocks) if capacity_blocks is None else \
            int(min(max(capacity_blocks, 1), self.max_blocks))
        self.capacity_blocks = capacity
        self.device = o3c.Device(device)
        self._o3d, self._o3c = o3d, o3c
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            # "weight" is what Open3D's extraction thresholds: here the observation
            # count; "confidence" is the sum of the pixels' weights (the running mean's).
            attr_names=("tsdf", "weight", "color", "confidence"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3), (1)), voxel_size=settings.voxel_size_m,
            block_resolution=settings.block_resolution, block_count=capacity,
            device=self.device)
        self.frames = 0
        self.full_frames = 0  # frames whose new blocks did not fit
        self._warned_full = False

    # ------------------------------------------------------------------ sizes
    @property
    def block_count(self) -> int:
        """Allocated blocks."""
        return int(self.grid.hashmap().size())

    @property
    def memory_bytes(self) -> int:
        """Memory reserved by the volume (its capacity), bytes."""
        return self.capacity_blocks * block_bytes(self.settings.block_resolution)

    @property
    def used_bytes(self) -> int:
        """Memory of the allocated blocks, bytes."""
        return self.block_count * block_bytes(self.settings.block_resolution)

    def bounds_m(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(min, max) (3,) corners of the allocated blocks in metres, or None when empty."""
        if self.block_count == 0:
            return None
        keys = self.grid.hashmap().key_tensor().numpy()
        active = self.grid.hashmap().active_buf_indices().numpy()
        coords = keys[active].astype(np.float64) * self.settings.block_size_m
        return coords.min(0), coords.max(0) + self.settings.block_size_m

    # ------------------------------------------------------------------ integration
    def frame_blocks(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                     camera_to_world: np.ndarray) -> Any:
        """Block coordinates (Open3D int32 tensor (B, 3)) a depth map touches."""
        o3d, o3c = self._o3d, self._o3c
        depth = np.ascontiguousarray(depth_m, dtype=np.float32)
        extrinsic = o3c.Tensor(np.linalg.inv(camera_to_world))
        return self.grid.compute_unique_block_coordinates(
            o3d.t.geometry.Image(o3c.Tensor(depth)), o3c.Tensor(intrinsics.matrix),
            extrinsic, 1.0, self.settings.max_depth_m, self.settings.truncation_voxels)

    def integrate(self, depth_m: np.ndarray, color_rgb: np.ndarray, weight: np.ndarray | None,
                  intrinsics: CameraIntrinsics, camera_to_world: np.ndarray) -> int:
        """Fuse one frame.

        Args:
            depth_m: (H, W) float depth in metres along the optical axis; 0, NaN or
                beyond ``max_depth_m`` are not integrated.
            color_rgb: (H, W, 3) uint8 RGB image registered with the depth.
            weight: (H, W) float per-pixel weight >= 0 (0: skipped), or None for 1. Only
                ratios matter: it sets how much the pixel pulls a voxel's mean against
                the other pixels that observed it; any positive weight counts as one
                observation for the extraction.
            intrinsics: the camera's intrinsics at (H, W) pixels.
            camera_to_world: (4, 4) pose, metres.

        Returns:
            Number of voxels updated.
        """
        from deltar.camera import check_image
        from deltar.io.pose_file import check_pose

        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.ndim != 2:
            raise ValueError(f"depth_m must be (H, W) metres, got shape {depth.shape}")
        height, width = depth.shape
        color_rgb = check_image(color_rgb, "color_rgb", (height, width))
        # A rigid float64 transform whatever the caller's dtype (Open3D takes only that).
        camera_to_world = check_pose(camera_to_world, "camera_to_world")
        if (intrinsics.height, intrinsics.width) != (height, width):
            raise ValueError(f"intrinsics are for {intrinsics.height}x{intrinsics.width}, "
                             f"the depth is {height}x{width}")
        usable = np.isfinite(depth) & (depth > 0) & (depth <= self.settings.max_depth_m)
        if weight is not None:
            weight = np.asarray(weight, dtype=np.float32)
            if weight.shape != depth.shape:
                raise ValueError(f"weight must be {depth.shape}, got {weight.shape}")
            usable &= np.isfinite(weight) & (weight > 0)
        depth = np.where(usable, depth, 0.0).astype(np.float32)
        self.frames += 1
        if not usable.any():
            return 0
        coords = self.frame_blocks(depth, intrinsics, camera_to_world)
        hashmap = self.grid.hashmap()
        _, found = hashmap.find(coords)
        new = int(coords.shape[0]) - int(found.to(self._o3c.int64).sum().item())
        needed = int(hashmap.size()) + new
        if new and needed > self.max_blocks:
            self.full_frames += 1
            if not self._warned_full:
                self._warned_full = True
                budget_mib = self.max_blocks * block_bytes(self.settings.block_resolution) \
                    / 2**20
                warnings.warn(f"the map reached its memory budget ({self.max_blocks} blocks, "
                              f"{budget_mib:.0f} MiB): from frame {self.frames} on, frames "
                              "update only the existing blocks (raise --max-memory or "
                              "--voxel to map more)",
                              RuntimeWarning, stacklevel=2)
            coords = coords[found]
            if coords.shape[0] == 0:
                return 0
        elif new:
            if needed > self.capacity_blocks:
                # Grow by doubling, never past the budget (Open3D's own growth could).
                self.capacity_blocks = min(max(2 * self.capacity_blocks, needed),
                                           self.max_blocks)
                hashmap.reserve(self.capacity_blocks)
            hashmap.activate(coords)
        buf_indices, _ = hashmap.find(coords)
        return self._update(buf_indices, depth, weight, color_rgb, intrinsics, camera_to_world)

    def _update(self, buf_indices: Any, depth: np.ndarray, weight: np.ndarray | None,
                color_rgb: np.ndarray, intrinsics: CameraIntrinsics,
                camera_to_world: np.ndarray) -> int:
        """The weighted running average over the voxels of ``buf_indices``' blocks.

        Each voxel's distance and colour move to the new pixel's by the share
        ``w / (W + w)`` of its weight ``w`` in the weight sum ``W`` (stored as
        "confidence"); its observation count (Open3D's "weight") grows by one.
        """
        height, width = depth.shape
        voxel_coords, voxel_indices = self.grid.voxel_coordinates_and_flattened_indices(
            buf_indices)
        points = voxel_coords.numpy()
        indices = voxel_indices.numpy()
        # Camera coordinates and pixel of every voxel (elementwise: faster than a matmul
        # on (N, 3) for a 3x3 rotation).
        world_to_camera = np.linalg.inv(camera_to_world).astype(np.float32)
        px, py, pz = np.ascontiguousarray(points.T)
        x, y, z = (r[0] * px + r[1] * py + r[2] * pz + r[3] for r in world_to_camera[:3])
        in_front = z > 1e-6
        safe_z = np.where(in_front, z, np.float32(1.0))
        u = np.round(x * (np.float32(intrinsics.fx) / safe_z)
                     + np.float32(intrinsics.cx)).astype(np.int64)
        v = np.round(y * (np.float32(intrinsics.fy) / safe_z)
                     + np.float32(intrinsics.cy)).astype(np.int64)
        inside = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        # One gather with a clamped pixel index, then one selection (boolean indexing is
        # what costs here).
        pixel = np.clip(v, 0, height - 1) * width + np.clip(u, 0, width - 1)
        observed = depth.reshape(-1)[pixel]
        sdf = observed - z
        truncation = float(self.settings.truncation_m)
        selected = np.flatnonzero(inside & (observed > 0) & (sdf >= -truncation))
        if selected.size == 0:
            return 0
        pixel, indices = pixel[selected], indices[selected]
        tsdf_new = np.minimum(sdf[selected] * np.float32(1.0 / truncation), np.float32(1.0))
        w_new = np.ones_like(tsdf_new) if weight is None else \
            np.asarray(weight, dtype=np.float32).reshape(-1)[pixel]
        color_new = np.asarray(color_rgb).reshape(-1, 3)[pixel].astype(np.float32)
        tsdf, weights, counts = (_buffer(self.grid.attribute(name), 1)
                                 for name in ("tsdf", "confidence", "weight"))
        colors = _buffer(self.grid.attribute("color"), 3)
        w_old = weights[indices]
        total = w_old + w_new
        share = w_new / total  # running weighted mean: old + share * (new - old)
        tsdf_old = tsdf[indices]
        tsdf[indices] = tsdf_old + share * (tsdf_new - tsdf_old)
        color_old = colors[indices]
        colors[indices] = color_old + share[:, None] * (color_new - color_old)
        weights[indices] = total
        counts[indices] += 1.0  # voxel indices are unique: one observation each
        return int(indices.size)

    # ------------------------------------------------------------------ outputs
    def mesh(self, min_observations: int = MIN_OBSERVATIONS) -> Any:
        """The map's surface as an Open3D legacy ``TriangleMesh`` (metres, RGB 0..1).

        Voxels observed by fewer than ``min_observations`` integrated pixels are left out.
        """
        if self.block_count == 0:
            return self._o3d.geometry.TriangleMesh()
        mesh = self.grid.extract_triangle_mesh(
            weight_threshold=_open3d_threshold(min_observations)).to_legacy()
        if mesh.has_vertex_colors():  # float rounding can leave 1 + 1e-7
            mesh.vertex_colors = self._o3d.utility.Vector3dVector(
                np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0))
        return mesh

    def points(self, min_observations: int = MIN_OBSERVATIONS
               ) -> tuple[np.ndarray, np.ndarray]:
        """Surface points of the map: ((N, 3) float64 metres, (N, 3) uint8 RGB).

        Voxels observed by fewer than ``min_observations`` integrated pixels are left out.
        """
        if self.block_count == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
        cloud = self.grid.extract_point_cloud(
            weight_threshold=_open3d_threshold(min_observations))
        if "positions" not in cloud.point or cloud.point.positions.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
        xyz = cloud.point.positions.numpy().astype(np.float64)
        rgb = cloud.point.colors.numpy() if "colors" in cloud.point else np.zeros_like(xyz)
        # Open3D's extraction gives colours scaled to 0..1.
        return xyz, np.clip(np.round(255 * rgb), 0, 255).astype(np.uint8)

    def write(self, out_dir: str | Path, *, overwrite: bool = False,
              min_observations: int = MIN_OBSERVATIONS) -> dict[str, Path]:
        """Write ``mesh.ply`` (coloured triangle mesh) and ``points.ply`` atomically.

        Raises:
            FileExistsError: an output exists and ``overwrite`` is False.
            ValueError: the map is empty (nothing was integrated).
        """
        from deltar.io.atomic import atomic_path
        from deltar.io.ply import write_ply

        out = Path(out_dir)
        paths = {"mesh": out / "mesh.ply", "points": out / "points.ply"}
        if not overwrite:
            for path in paths.values():
                if path.exists():
                    raise FileExistsError(f"refusing to overwrite existing file: {path}")
        mesh = self.mesh(min_observations)
        if len(mesh.triangles) == 0:
            raise ValueError("the map has no surface: no frame's depth was integrated "
                             "(check the depth limit, the poses and the confidence threshold)")
        with atomic_path(paths["mesh"], overwrite=overwrite) as tmp:
            if not self._o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
                raise ValueError(f"{paths['mesh']}: Open3D could not write the mesh")
        xyz, rgb = self.points(min_observations)
        write_ply(paths["points"], xyz, rgb, overwrite=overwrite,
                  comments=[f"deltar map: {len(xyz)} surface points, metres, world frame"])
        return paths


def _open3d_threshold(min_observations: int) -> float:
    """Open3D keeps voxels whose weight is above its threshold: half a count below."""
    if not (isinstance(min_observations, (int, np.integer)) and min_observations >= 1):
        raise ValueError(f"min_observations must be an integer >= 1, got {min_observations!r}")
    return float(min_observations) - 0.5
