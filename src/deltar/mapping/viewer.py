"""The growing map in rerun: camera, its path and the mesh, frame by frame.

Beside what :class:`~deltar.capture.viewer.RerunLogger` logs for a frame (image,
zones, depth under ``world/camera``), ``world/camera`` is placed at the frame's pose,
``world/path`` is the camera path so far (a line strip) and ``world/map`` the map's mesh,
re-extracted every ``mesh_every`` frames and after the last.
"""

from __future__ import annotations

import os

import numpy as np

from deltar.mapping.frames import MapFrame
from deltar.mapping.tsdf import TSDFMap


class MapViewer:
    """Log a map being built to rerun (spawned viewer, or an ``.rrd`` file).

    Args:
        save_path: write an ``.rrd`` file instead of spawning the viewer.
        mesh_every: frames between mesh updates (extraction costs ~0.1-1 s).
    """

    def __init__(self, save_path: str | os.PathLike | None = None, mesh_every: int = 10) -> None:
        from deltar.capture.viewer import RerunLogger

        self.logger = RerunLogger(save_path, application_id="deltar map")
        self.rr = self.logger.rr
        self.mesh_every = max(1, int(mesh_every))
        self.path: list[np.ndarray] = []

    def log(self, frame: MapFrame, pose: np.ndarray, volume: TSDFMap,
            depth_m: np.ndarray | None = None) -> None:
        """One integrated frame: camera at ``pose`` (4x4 camera-to-world), path, mesh."""
        rr, stream = self.rr, self.logger.stream
        stream.set_time("frame", sequence=self.logger.frames)
        stream.set_time("time", duration=float(frame.time_s))
        stream.log("world/camera", rr.Transform3D(translation=pose[:3, 3].astype(np.float32),
                                                  mat3x3=pose[:3, :3].astype(np.float32)))
        rects = frame.calibration.zone_rects_for(frame.zone_frame, frame.image.shape[:2])
        self.logger.log_frame(frame.image, frame.zone_frame, rects,
                              frame.calibration.intrinsics, time_s=frame.time_s,
                              extrinsics=frame.calibration.extrinsics,
                              fov_deg=frame.calibration.fov_deg, depth_m=depth_m)
        self.path.append(pose[:3, 3].astype(np.float32))
        stream.log("world/path", rr.LineStrips3D([np.stack(self.path)], radii=0.01))
        if len(self.path) % self.mesh_every == 0:
            self.log_mesh(volume)

    def log_mesh(self, volume: TSDFMap) -> None:
        """The map's current mesh as ``world/map``."""
        mesh = volume.mesh()
        if len(mesh.triangles) == 0:
            return
        colors = np.asarray(mesh.vertex_colors)
        self.logger.stream.log("world/map", self.rr.Mesh3D(
            vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
            triangle_indices=np.asarray(mesh.triangles, dtype=np.uint32),
            vertex_colors=(np.clip(colors, 0, 1) * 255).astype(np.uint8) if len(colors)
            else None))

    def close(self, volume: TSDFMap | None = None) -> None:
        """Log the final mesh (when ``volume`` is given) and finish the recording."""
        if volume is not None:
            self.log_mesh(volume)
        self.logger.close()
