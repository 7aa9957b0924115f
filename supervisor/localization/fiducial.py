"""ChArUco fiducial board: its definition, its printable image, and ground-truth
pose detection (`T_cam_board`) for recordings.

Board frame (OpenCV convention): origin at the board's top-left outer corner,
x along the columns, y along the rows, z = x cross y, i.e. *into* the board,
away from a camera that sees the printed side. Units are metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.geometry import make_T

_DICTIONARIES = {
    "4x4_50": cv2.aruco.DICT_4X4_50,
    "4x4_100": cv2.aruco.DICT_4X4_100,
    "5x5_100": cv2.aruco.DICT_5X5_100,
    "6x6_250": cv2.aruco.DICT_6X6_250,
}


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares_x x squares_y squares of `square_m`, markers of `marker_m`."""

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.02
    marker_m: float = 0.015
    dictionary: str = "5x5_100"

    @property
    def size_m(self) -> tuple[float, float]:
        """(width along x, height along y) in metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def to_dict(self) -> dict:
        return {"squares_x": self.squares_x, "squares_y": self.squares_y, "square_m": self.square_m,
                "marker_m": self.marker_m, "dictionary": self.dictionary}

    @classmethod
    def from_dict(cls, d: dict) -> BoardSpec:
        spec = cls(int(d["squares_x"]), int(d["squares_y"]), float(d["square_m"]), float(d["marker_m"]),
                   str(d["dictionary"]))
        if spec.dictionary not in _DICTIONARIES:
            raise ValueError(f"unknown ArUco dictionary {spec.dictionary!r}; known: {', '.join(_DICTIONARIES)}")
        return spec

    def board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(_DICTIONARIES[self.dictionary])
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)

    def image(self, px_per_m: float) -> np.ndarray:
        """The printable board as a mono8 image covering exactly `size_m` (no margin)."""
        w, h = (round(s * px_per_m) for s in self.size_m)
        return self.board().generateImage((w, h), marginSize=0, borderBits=1)


@dataclass(frozen=True)
class BoardPose:
    """A board detection: `T_cam_board`, the corners used and the RMS reprojection error."""

    T_cam_board: np.ndarray
    n_corners: int
    rms_px: float


class BoardDetector:
    """Detects the ChArUco board and solves its pose with iterative PnP."""

    def __init__(self, spec: BoardSpec, intrinsics: Intrinsics, min_corners: int = 6) -> None:
        self.spec = spec
        self.intrinsics = intrinsics
        self.min_corners = min_corners
        self._board = spec.board()
        params = cv2.aruco.CharucoParameters()
        params.cameraMatrix = intrinsics.K
        params.distCoeffs = intrinsics.dist_coeffs
        self._detector = cv2.aruco.CharucoDetector(self._board, params)

    def correspondences(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(board points Nx3 [m, board frame], image points Nx2 [px]) of the detected ChArUco
        corners, or None when fewer than `min_corners` are seen."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _, _ = self._detector.detectBoard(image)
        if corners is None or ids is None or len(corners) < self.min_corners:
            return None
        obj, img = self._board.matchImagePoints(corners, ids)
        if obj is None or len(obj) < self.min_corners:
            return None
        return obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64)

    def detect(self, image: np.ndarray) -> BoardPose | None:
        """The board's pose in the camera frame, or None when too few corners are seen."""
        found = self.correspondences(image)
        if found is None:
            return None
        obj, img = found
        K, dist = self.intrinsics.K, self.intrinsics.dist_coeffs
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
        R, _ = cv2.Rodrigues(rvec)
        return BoardPose(make_T(R, tvec.ravel()), int(len(obj)), rms)
