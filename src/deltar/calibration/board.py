"""Printed calibration boards (ChArUco or checkerboard): specification, detection, pose.

A board is given as text, the same on every command::

    charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]   e.g. charuco:7x5:0.04:0.03:DICT_5X5_100
    checkerboard:COLSxROWS:SQUARE_M              e.g. checkerboard:9x6:0.025

For ChArUco, COLS x ROWS counts squares (OpenCV's ``CharucoBoard((COLS, ROWS), ...)``);
for a checkerboard it counts *inner* corners (OpenCV's ``patternSize``), so a 9x6 board
has 10 x 7 squares. Lengths are metres. The board frame has x along the columns, y
along the rows and z out of the printed side's back (OpenCV's board frame), origin at
the board's top-left outer corner; the board lies in its z = 0 plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltar.camera import CameraIntrinsics

#: Dictionary used when a ChArUco spec names none.
DEFAULT_DICTIONARY = "DICT_5X5_100"
#: Fewest corners accepted for one view's pose (ChArUco corners or checkerboard corners).
MIN_BOARD_CORNERS = 6
#: Dictionaries tried when the spec's finds nothing, to say which one the board uses.
COMMON_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_5X5_50",
                       "DICT_5X5_100", "DICT_5X5_250", "DICT_6X6_50", "DICT_6X6_250",
                       "DICT_7X7_50", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11")


@dataclass(frozen=True)
class BoardSpec:
    """A printed board.

    Attributes:
        kind: ``"charuco"`` or ``"checkerboard"``.
        cols, rows: ChArUco: squares across and down; checkerboard: inner corners.
        square_m: side of one square, metres.
        marker_m: ChArUco marker side, metres (None for a checkerboard).
        dictionary: ChArUco ArUco dictionary name (e.g. ``"DICT_5X5_100"``).
    """

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float | None = None
    dictionary: str = DEFAULT_DICTIONARY

    @property
    def squares(self) -> tuple[int, int]:
        """(across, down) number of squares printed."""
        if self.kind == "charuco":
            return self.cols, self.rows
        return self.cols + 1, self.rows + 1

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the printed pattern, metres."""
        across, down = self.squares
        return across * self.square_m, down * self.square_m

    @property
    def marker_count(self) -> int:
        """ArUco markers on a ChArUco board (on the white squares), 0 for a checkerboard."""
        return self.cols * self.rows // 2 if self.kind == "charuco" else 0

    def text(self) -> str:
        """The spec as it is written on the command line."""
        if self.kind == "charuco":
            return (f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:"
                    f"{self.dictionary}")
        return f"checkerboard:{self.cols}x{self.rows}:{self.square_m:g}"

    def opencv_board(self):
        """The ``cv2.aruco.CharucoBoard`` of a ChArUco spec."""
        import cv2

        if self.kind != "charuco":
            raise ValueError("only a ChArUco spec has an OpenCV board object")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m,
                                      dictionary)

    def texture(self, pixels_per_square: int = 64) -> np.ndarray:
        """The printed pattern as a grey image, exactly ``squares`` x ``pixels_per_square``.

        Returns:
            (rows * p, cols * p) uint8 image (0 black, 255 white), pixel (0, 0) at the
            board's top-left outer corner.
        """
        across, down = self.squares
        p = int(pixels_per_square)
        if self.kind == "charuco":
            return self.opencv_board().generateImage((across * p, down * p), marginSize=0,
                                                     borderBits=1)
        cells = (np.add.outer(np.arange(down), np.arange(across)) % 2) * 255
        return np.kron(cells, np.ones((p, p))).astype(np.uint8)


def parse_board_spec(text: str, option: str = "--target") -> BoardSpec:
    """Parse ``charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]`` or ``checkerboard:COLSxROWS:SQUARE_M``.

    Raises:
        ValueError: a malformed spec; the message names ``option`` and shows the format.
    """
    import cv2

    usage = (f"{option} must be charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT] (e.g. "
             "charuco:7x5:0.04:0.03:DICT_5X5_100) or checkerboard:COLSxROWS:SQUARE_M "
             f"(inner corners, e.g. checkerboard:9x6:0.025), got {text!r}")
    parts = str(text).strip().split(":")
    kind = parts[0].lower()
    if kind not in ("charuco", "checkerboard") or len(parts) < 3:
        raise ValueError(usage)
    expected = (4, 5) if kind == "charuco" else (3,)
    if len(parts) not in expected:
        raise ValueError(usage)
    try:
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        lengths = [float(v) for v in parts[2:4 if kind == "charuco" else 3]]
    except ValueError:
        raise ValueError(usage) from None
    if not all(np.isfinite(v) and 0 < v < 1.0 for v in lengths):
        raise ValueError(f"{option}: square and marker sizes are metres in (0, 1), got "
                         f"{parts[2:4]} (e.g. 0.04 for 4 cm)")
    if kind == "checkerboard":
        if cols < 2 or rows < 2 or cols == rows == 2:
            raise ValueError(f"{option}: a checkerboard needs at least 3x2 inner corners "
                             f"(one fewer than its squares), got {cols}x{rows}")
        return BoardSpec("checkerboard", cols, rows, lengths[0])
    if cols < 3 or rows < 3:
        raise ValueError(f"{option}: a ChArUco board needs at least 3x3 squares, got "
                         f"{cols}x{rows}")
    square, marker = lengths
    if marker >= square:
        raise ValueError(f"{option}: the marker ({marker} m) must be smaller than the "
                         f"square ({square} m)")
    dictionary = parts[4].upper() if len(parts) == 5 else DEFAULT_DICTIONARY
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"{option}: unknown ArUco dictionary {parts[4]!r} (e.g. "
                         "DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")
    spec = BoardSpec("charuco", cols, rows, square, marker, dictionary)
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    if spec.marker_count > size:
        raise ValueError(f"{option}: a {cols}x{rows} ChArUco board has {spec.marker_count} "
                         f"markers but {dictionary} holds only {size}")
    return spec


@dataclass(frozen=True)
class BoardDetection:
    """The board's corners found in one image.

    Attributes:
        image_points: (N, 2) float32 corner positions in pixels.
        object_points: (N, 3) float32 the same corners in the board frame, metres (z = 0).
    """

    image_points: np.ndarray
    object_points: np.ndarray


@dataclass(frozen=True)
class BoardPose:
    """The board's pose in the camera frame and its plane.

    Attributes:
        rotation: (3, 3) board-to-camera rotation.
        translation_m: (3,) board origin in the camera frame, metres.
        normal_cam: (3,) unit plane normal in the camera frame, pointing at the camera.
        offset_cam_m: plane offset d (``n . p + d = 0``, d > 0 = the camera's distance to
            the plane), metres.
        reprojection_rms_px: RMS corner reprojection error, pixels.
        corners: number of corners used.
        normal_std_rad: standard deviation of the normal's direction (radians), and
        offset_std_m: of the offset (metres), propagated from the corners' reprojection
            error (at least 0.1 px) through the pose's Jacobian; views of a small or
            distant board are uncertain and count less.
    """

    rotation: np.ndarray
    translation_m: np.ndarray
    normal_cam: np.ndarray
    offset_cam_m: float
    reprojection_rms_px: float
    corners: int
    normal_std_rad: float = 0.0
    offset_std_m: float = 0.0


def _grey(image: np.ndarray) -> np.ndarray:
    import cv2

    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image.astype(np.uint8), cv2.COLOR_RGB2GRAY)
    if image.ndim == 2:
        return image.astype(np.uint8)
    raise ValueError(f"image must be (H, W, 3) RGB or (H, W) grey, got shape {image.shape}")


class BoardDetector:
    """Finds one board in images (OpenCV's ``CharucoDetector`` or ``findChessboardCornersSB``).

    Args:
        spec: the board.
    """

    def __init__(self, spec: BoardSpec) -> None:
        import cv2

        self.spec = spec
        if spec.kind == "charuco":
            self.board = spec.opencv_board()
            self._detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, image: np.ndarray) -> BoardDetection | None:
        """The board's corners in an (H, W, 3) RGB (or (H, W) grey) uint8 image, or None
        when fewer than ``MIN_BOARD_CORNERS`` corners (or only collinear ones) are found."""
        import cv2

        grey = _grey(image)
        if self.spec.kind == "checkerboard":
            found, corners = cv2.findChessboardCornersSB(
                grey, (self.spec.cols, self.spec.rows), flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
            if not found:
                return None
            grid = np.mgrid[0:self.spec.rows, 0:self.spec.cols].reshape(2, -1)[::-1].T
            # Inner corner (i, j) sits one square in from the outer edge.
            obj = np.column_stack([(grid + 1) * self.spec.square_m,
                                   np.zeros(len(grid))]).astype(np.float32)
            return BoardDetection(corners.reshape(-1, 2).astype(np.float32), obj)
        corners, ids, _, _ = self._detector.detectBoard(grey)
        if corners is None or ids is None or len(ids) < MIN_BOARD_CORNERS:
            return None
        if self.board.checkCharucoCornersCollinear(ids):
            return None
        obj, img = self.board.matchImagePoints(corners, ids)
        return BoardDetection(img.reshape(-1, 2).astype(np.float32),
                              obj.reshape(-1, 3).astype(np.float32))

    def refuse_few_views(self, recording, found: int, searched: int, needed: int,
                         paired: bool = False) -> None:
        """Refuse a recording where the board is found in too few images, saying why.

        Args:
            recording: the recording (its ``color_paths`` are sampled for the hint).
            found: images with the board; searched: images looked at; needed: fewest.
            paired: whether the images counted are those paired with a zone frame.

        Raises:
            ValueError: ``found < needed``, with a hint (a spec mismatch, or advice).
        """
        if found >= needed:
            return
        import cv2

        sample = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
                  for p in recording.color_paths[::max(1, len(recording.color_paths) // 8)][:8]]
        # Found in none: the spec may not be what is printed; found in some: it is.
        hint = self.diagnose([s for s in sample if s is not None]) if found == 0 else ""
        where = "paired with a zone frame" if paired else "of the recording"
        zone_frames = len(recording.zone_frames()) if paired else 0
        if found and found == searched and zone_frames > searched:
            # The board is in every image looked at: too few images were paired.
            advice = (f"only {searched} of the {zone_frames} zone frames have a colour image "
                      "within --tolerance after --time-offset: check both, or record more "
                      "views")
        elif found and found == searched:  # found in every view there is: too few views
            advice = "record more views (15-25, docs/calibration.md)"
        else:
            advice = (f"the board spec {self.spec.text()} does not match what is detected: "
                      f"{hint}" if hint else "keep the whole board in view, sharp and evenly "
                      "lit, 0.4-1.5 m from the camera, and check --target")
        raise ValueError(f"too few views with the board: found in {found} of the {searched} "
                         f"images {where} (need at least {needed}): {advice}")

    def diagnose(self, images: list[np.ndarray]) -> str:
        """Why the board is not found in ``images``: a hint about a spec mismatch, or ""."""
        import cv2

        if self.spec.kind == "checkerboard":
            for cols, rows in {(self.spec.rows, self.spec.cols),
                               (self.spec.cols + 1, self.spec.rows + 1),
                               (self.spec.cols - 1, self.spec.rows - 1)}:
                if min(cols, rows) < 2:
                    continue
                for image in images:
                    found, _ = cv2.findChessboardCornersSB(_grey(image), (cols, rows))
                    if found:
                        return (f"a checkerboard with {cols}x{rows} inner corners is in the "
                                f"images, the spec says {self.spec.cols}x{self.spec.rows} "
                                "(count inner corners: one fewer than the squares)")
            return ""
        params = cv2.aruco.DetectorParameters()
        seen = []
        for image in images:
            grey = _grey(image)
            _, ids, _ = cv2.aruco.ArucoDetector(self.board.getDictionary(),
                                                params).detectMarkers(grey)
            if ids is not None:
                seen.extend(int(i) for i in ids.ravel())
        if seen:
            top = max(seen)
            if top >= self.spec.marker_count:
                return (f"markers with ids up to {top} are in the images, but a "
                        f"{self.spec.cols}x{self.spec.rows} ChArUco board has only "
                        f"{self.spec.marker_count} (ids 0-{self.spec.marker_count - 1}): "
                        "check COLSxROWS")
            return (f"{self.spec.dictionary} markers are found ({len(set(seen))} ids) but no "
                    "ChArUco corners between them: check COLSxROWS, SQUARE_M:MARKER_M and "
                    "whether the board was made with OpenCV < 4.6 (legacy pattern)")
        for name in COMMON_DICTIONARIES:
            if name == self.spec.dictionary:
                continue
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
            detector = cv2.aruco.ArucoDetector(dictionary, params)
            counts = [0 if (ids := detector.detectMarkers(_grey(im))[1]) is None else len(ids)
                      for im in images]
            if max(counts, default=0) >= 3:
                return (f"markers of {name} are in the images, the spec says "
                        f"{self.spec.dictionary}")
        return ""


def estimate_board_pose(detection: BoardDetection, intrinsics: CameraIntrinsics,
                        distortion: np.ndarray | tuple = ()) -> BoardPose:
    """The board's pose (``cv2.solvePnP``, planar IPPE then iterative refinement).

    Args:
        detection: corners of one view.
        intrinsics: camera intrinsics (pixels).
        distortion: OpenCV distortion coefficients (k1, k2, p1, p2[, k3]) or empty.

    Returns:
        ``BoardPose`` in the camera frame (metres).
    """
    import cv2

    K = intrinsics.matrix
    dist = np.asarray(distortion, dtype=np.float64).reshape(-1) if len(distortion) else None
    obj = detection.object_points.astype(np.float64)
    img = detection.image_points.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("the board's pose could not be solved from its corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    projected, jacobian = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1))))
    rotation = cv2.Rodrigues(rvec)[0]
    translation = tvec.reshape(3)
    normal = rotation[:, 2].copy()
    offset = -float(normal @ translation)
    sign = -1.0 if offset < 0 else 1.0
    normal, offset = sign * normal, sign * offset
    # Pose covariance sigma^2 (J^T J)^-1, then the plane's by numerical differentiation.
    sigma = max(rms, 0.1)
    pose_cov = sigma ** 2 * np.linalg.pinv(jacobian[:, :6].T @ jacobian[:, :6])
    x0 = np.concatenate([rvec.ravel(), translation])

    def plane(x: np.ndarray) -> np.ndarray:
        n = sign * cv2.Rodrigues(x[:3])[0][:, 2]
        return np.concatenate([n, [-float(n @ x[3:])]])

    step = 1e-6
    dplane = np.stack([(plane(x0 + step * e) - plane(x0 - step * e)) / (2 * step)
                       for e in np.eye(6)], axis=1)
    plane_cov = dplane @ pose_cov @ dplane.T
    return BoardPose(rotation, translation, normal, offset, rms, len(obj),
                     float(np.sqrt(max(np.trace(plane_cov[:3, :3]), 0.0))),
                     float(np.sqrt(max(plane_cov[3, 3], 0.0))))


def board_points_in_view(pose_normal: np.ndarray, pose_offset_m: float,
                         sensor_to_cam_rotation: np.ndarray, sensor_to_cam_translation: np.ndarray,
                         fov_deg: tuple[float, float], samples: int) -> np.ndarray:
    """Points of a camera-frame plane where the sensor's rays (a regular grid over its
    field of view) meet it.

    Args:
        pose_normal: (3,) unit plane normal, camera frame.
        pose_offset_m: plane offset d (``n . p + d = 0``), metres.
        sensor_to_cam_rotation, sensor_to_cam_translation: (3, 3) and (3,) the sensor's
            pose in the camera frame (metres).
        fov_deg: sensor field of view (degrees).
        samples: rays per side.

    Returns:
        (M, 3) float64 camera-frame points (rays that miss the plane are left out).
    """
    tx, ty = (np.tan(np.deg2rad(f / 2)) for f in fov_deg)
    u, v = np.meshgrid(np.linspace(-tx, tx, samples), np.linspace(-ty, ty, samples))
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ sensor_to_cam_rotation.T
    origin = np.asarray(sensor_to_cam_translation, dtype=np.float64)
    normal = np.asarray(pose_normal, dtype=np.float64)
    denom = rays @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(normal @ origin + pose_offset_m) / denom
    hit = np.isfinite(s) & (s > 0)
    return origin + s[hit, None] * rays[hit]
