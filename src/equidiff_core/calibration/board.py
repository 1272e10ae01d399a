"""The ChArUco board: its geometry, a printable image of exact size, and detection with OpenCV's aruco.

Board frame (OpenCV's): origin at the board's top-left outer corner, x along the rows to the
right, y down the printed page, z into the board (so a camera facing the printed side sees
+z pointing away from it). Corner ``k`` of ``CharucoBoard.getChessboardCorners()`` is inner
corner ``k``; detection returns the ids of the corners it found.

OpenCV 5's aruco API: ``cv2.aruco.CharucoBoard((cols, rows), square, marker, dictionary)``,
``CharucoDetector(board).detectBoard(gray)`` -> (corners, ids, marker corners, marker ids),
``board.generateImage((w, h), marginSize, borderBits)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

MM_PER_INCH = 25.4


class CalibrationError(RuntimeError):
    """Calibration cannot go on (no detections, too few poses, a file would be overwritten)."""


def _cv2():
    try:
        import cv2
    except ImportError as err:  # an optional extra: say how to get it
        raise CalibrationError(
            "camera calibration needs OpenCV's aruco module: pip install -e '.[calib]' (opencv-contrib-python-headless)"
        ) from err
    return cv2


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board. Defaults: 5 x 4 squares of 45 mm (225 x 180 mm): with its margin it fits A4 landscape."""

    squares_x: int = 5  # columns
    squares_y: int = 4  # rows
    square_length: float = 0.045  # m, as printed
    marker_length: float = 0.034  # m, the ArUco marker inside each white square
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self):
        if self.squares_x < 3 or self.squares_y < 3:
            raise ValueError("a ChArUco board needs at least 3 x 3 squares")
        if not 0 < self.marker_length < self.square_length:
            raise ValueError(f"marker_length {self.marker_length} must be in (0, square_length {self.square_length})")

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_length, self.squares_y * self.square_length

    def cv_board(self):
        cv2 = _cv2()
        if not hasattr(cv2.aruco, self.dictionary):
            raise CalibrationError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50)")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )

    def corners(self) -> np.ndarray:
        """(N, 3) inner corners in the board frame (m), indexed by ChArUco corner id."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def image(self, px_per_square: int = 200) -> np.ndarray:
        """The board (no margin) as a grayscale image, ``px_per_square`` pixels per square."""
        w, h = self.squares_x * px_per_square, self.squares_y * px_per_square
        return self.cv_board().generateImage((w, h), marginSize=0, borderBits=1)


@dataclass(frozen=True)
class PrintedBoard:
    path: Path
    dpi: int
    page_mm: tuple[float, float]
    board_mm: tuple[float, float]
    square_mm: float
    marker_mm: float

    def instructions(self) -> str:
        return (
            f"{self.path}: print at 100 % scale (no 'fit to page'); the page is "
            f"{self.page_mm[0]:.1f} x {self.page_mm[1]:.1f} mm at {self.dpi} dpi, the board "
            f"{self.board_mm[0]:.1f} x {self.board_mm[1]:.1f} mm, each square {self.square_mm:.2f} mm, "
            f"each marker {self.marker_mm:.2f} mm. Measure a square after printing: if it is not "
            f"{self.square_mm:.2f} mm, pass the measured size with --square-mm."
        )


def write_printable(spec: BoardSpec, path: str | Path, dpi: int = 508, margin_mm: float = 10.0) -> PrintedBoard:
    """Write the board as a PDF (page = board + white margin, exact size at 100 %) or a PNG with its dpi."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() not in (".pdf", ".png"):
        raise CalibrationError(f"{path}: the board is written as .pdf or .png")
    px_per_m = dpi / (MM_PER_INCH / 1000)
    px_per_square = spec.square_length * px_per_m
    if abs(px_per_square - round(px_per_square)) > 1e-6:
        # a non-integer square would be rounded by the renderer and the print would be off size
        raise CalibrationError(
            f"square {spec.square_length * 1000:.3f} mm is not a whole number of "
            f"pixels at {dpi} dpi; pick another dpi or square size"
        )
    board = spec.image(round(px_per_square))
    margin = round(margin_mm / 1000 * px_per_m)
    page = np.full((board.shape[0] + 2 * margin, board.shape[1] + 2 * margin), 255, np.uint8)
    page[margin : margin + board.shape[0], margin : margin + board.shape[1]] = board
    path.parent.mkdir(parents=True, exist_ok=True)
    image = Image.fromarray(page)
    if path.suffix.lower() == ".pdf":
        image.save(path, resolution=float(dpi))
    else:
        image.save(path, dpi=(dpi, dpi))
    to_mm = MM_PER_INCH / dpi
    return PrintedBoard(
        path,
        dpi,
        (page.shape[1] * to_mm, page.shape[0] * to_mm),
        (board.shape[1] * to_mm, board.shape[0] * to_mm),
        spec.square_length * 1000,
        spec.marker_length * 1000,
    )


@dataclass(frozen=True)
class Detection:
    """The board's inner corners found in one image."""

    ids: np.ndarray  # (N,) int corner ids
    pixels: np.ndarray  # (N, 2) float64 subpixel image coordinates (OpenCV: pixel centre = integer)

    def __len__(self) -> int:
        return len(self.ids)


class BoardDetector:
    """ChArUco corners in RGB or grayscale images (one detector per board, reused across images)."""

    def __init__(self, spec: BoardSpec, min_corners: int = 6):
        cv2 = _cv2()
        self.spec = spec
        self.min_corners = min_corners
        self._cv2 = cv2
        self._board = spec.cv_board()
        self._detector = cv2.aruco.CharucoDetector(self._board)

    def detect(self, image: np.ndarray) -> Detection | None:
        """The corners in ``image``, or None when fewer than ``min_corners`` (or collinear ones) are seen."""
        cv2 = self._cv2
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if ids is None or len(ids) < self.min_corners:
            return None
        if self._board.checkCharucoCornersCollinear(ids):
            return None  # a single row of corners does not fix a pose
        return Detection(ids.reshape(-1).astype(int), corners.reshape(-1, 2).astype(np.float64))


def board_pose(
    spec: BoardSpec, det: Detection, K: np.ndarray, dist: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """(T_cam_board 4x4, RMS reprojection px) from one detection by PnP (IPPE for a plane, then LM)."""
    cv2 = _cv2()
    obj = spec.corners()[det.ids]
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, det.pixels, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("solvePnP failed on a board detection")
    rvec, tvec = cv2.solvePnPRefineLM(obj, det.pixels, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - det.pixels) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, rms
