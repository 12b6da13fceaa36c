"""Calibration boards: the ``board.json`` contract and corner detection.

``board.json`` describes the printed target of a calibration session, either a plain
chessboard::

    {"kind": "chessboard", "inner_corners": [9, 7], "square_size": 75.0}

(inner corners along the board's width, then its height; the square size in the rig's
units, millimetres unless the session says otherwise) or a ChArUco board::

    {"kind": "charuco", "squares": [10, 8], "square_size": 40.0, "marker_size": 30.0,
     "dictionary": "DICT_5X5_100"}

(squares along the width, then the height; ``marker_size`` < ``square_size``;
``dictionary`` one of OpenCV's predefined ArUco dictionaries). An optional ``"units"``
string (default ``"mm"``) names the unit of the sizes.

:func:`detect_board` finds the inner corners in a grey ``uint8`` image with sub-pixel
precision; corners come with integer ids indexing :meth:`Board.object_points`, so a
partly hidden ChArUco board still yields usable corners.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.core.files import read_json
from shared.core.jsonsafe import finite_number

log = logging.getLogger(__name__)

BOARD_FILE = "board.json"
KINDS = ("chessboard", "charuco")
#: Fewest ChArUco corners we accept in one view: fewer do not pin down a homography robustly.
MIN_CHARUCO_CORNERS = 8


@dataclass(frozen=True)
class Board:
    """A planar calibration target.

    ``inner_corners`` is (corners along the width, corners along the height). For a
    ChArUco board it is derived from ``squares`` (one less each way).
    """

    kind: str
    inner_corners: tuple[int, int]
    square_size: float
    marker_size: float | None = None
    dictionary: str | None = None
    units: str = "mm"

    @property
    def n_corners(self) -> int:
        return self.inner_corners[0] * self.inner_corners[1]

    @property
    def squares(self) -> tuple[int, int]:
        """Squares along the width and height."""
        return (self.inner_corners[0] + 1, self.inner_corners[1] + 1)

    def object_points(self) -> np.ndarray:
        """Inner corner positions on the board plane (z = 0), in ``units``.

        Returns
        -------
        (N, 3) float32, row-major: corner id ``j * nx + i`` is at ``((i + 1) s, (j + 1) s, 0)``
        for a ChArUco board (OpenCV's convention) and ``(i s, j s, 0)`` for a chessboard.
        """
        nx, ny = self.inner_corners
        ij = np.mgrid[0:nx, 0:ny].T.reshape(-1, 2).astype(np.float32)
        if self.kind == "charuco":
            ij += 1.0
        pts = np.zeros((nx * ny, 3), np.float32)
        pts[:, :2] = ij * np.float32(self.square_size)
        return pts

    def grid_neighbours(self) -> np.ndarray:
        """Pairs of corner ids one square apart (horizontally and vertically): (M, 2) int64."""
        nx, ny = self.inner_corners
        ids = np.arange(nx * ny).reshape(ny, nx)
        horiz = np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], axis=1)
        vert = np.stack([ids[:-1, :].ravel(), ids[1:, :].ravel()], axis=1)
        return np.concatenate([horiz, vert]).astype(np.int64)

    def to_json(self) -> dict[str, Any]:
        if self.kind == "chessboard":
            doc: dict[str, Any] = {
                "kind": "chessboard",
                "inner_corners": list(self.inner_corners),
                "square_size": self.square_size,
            }
        else:
            doc = {
                "kind": "charuco",
                "squares": list(self.squares),
                "square_size": self.square_size,
                "marker_size": self.marker_size,
                "dictionary": self.dictionary,
            }
        if self.units != "mm":
            doc["units"] = self.units
        return doc

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ChArUco board object (ChArUco boards only)."""
        if self.kind != "charuco":
            raise ValueError("not a ChArUco board")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, str(self.dictionary)))
        return cv2.aruco.CharucoBoard(self.squares, float(self.square_size), float(self.marker_size), dictionary)

    def render(self, pixels_per_unit: float, margin_squares: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
        """A printable image of the board (white margin around it), for printing and simulation.

        Returns
        -------
        image : (H, W) uint8, black squares 0 and white 255.
        to_board : (3, 3) float64 homography from image pixel coordinates to board coordinates
            (the frame of :meth:`object_points`).
        """
        # Whole pixels per square keep the pixel-to-board mapping exact for both board kinds.
        sq = max(4, int(round(self.square_size * pixels_per_unit)))
        margin = int(round(margin_squares * sq))
        w = int(round(self.squares[0] * sq)) + 2 * margin
        h = int(round(self.squares[1] * sq)) + 2 * margin
        if self.kind == "charuco":
            img = self.charuco_board().generateImage((w, h), marginSize=margin, borderBits=1)
            # generateImage fits the board into the image keeping its aspect ratio; recover where it put it.
            inner_w = w - 2 * margin
            inner_h = h - 2 * margin
            scale = min(inner_w / self.squares[0], inner_h / self.squares[1])
            x0 = margin + (inner_w - scale * self.squares[0]) / 2
            y0 = margin + (inner_h - scale * self.squares[1]) / 2
            # pixel (x, y) -> board: origin at the board's outer corner, ChArUco ids start one square in.
            k = self.square_size / scale
            to_board = np.array([[k, 0, -(x0 - 0.5) * k], [0, k, -(y0 - 0.5) * k], [0, 0, 1]])
        else:
            yy, xx = np.mgrid[0:h, 0:w]
            i = np.floor((xx + 0.5 - margin) / sq).astype(int)
            j = np.floor((yy + 0.5 - margin) / sq).astype(int)
            inside = (i >= 0) & (j >= 0) & (i < self.squares[0]) & (j < self.squares[1])
            black = inside & ((i + j) % 2 == 0)
            img = np.where(black, 0, 255).astype(np.uint8)
            # chessboard corner (0, 0) is the first inner corner, one square in from the outer edge.
            k = self.square_size / sq
            off = margin + sq - 0.5
            to_board = np.array([[k, 0, -off * k], [0, k, -off * k], [0, 0, 1]])
        return img, to_board


#: Most squares or corners along a board side, and the largest square (board units): beyond
#: these a board.json is a typing error that would otherwise allocate or fail deep in OpenCV.
MAX_BOARD_COUNT = 200
MAX_BOARD_SIZE = 1e6


def _positive_int_pair(doc: dict[str, Any], key: str, where: Path | str, minimum: int) -> tuple[int, int]:
    v = doc.get(key)
    if (
        not isinstance(v, list)
        or len(v) != 2
        or not all(isinstance(x, int) and not isinstance(x, bool) for x in v)
        or min(v) < minimum
        or max(v) > MAX_BOARD_COUNT
    ):
        raise InputError(where, f'field "{key}" must be two integers in {minimum}..{MAX_BOARD_COUNT} [width, height], '
                                f"got {str(v)[:60]}")
    return (int(v[0]), int(v[1]))


def _positive_number(doc: dict[str, Any], key: str, where: Path | str) -> float:
    v = doc.get(key)
    # finite_number: np.isfinite raised a bare TypeError on an integer of 2^63 (19 digits: a file may hold it)
    if not finite_number(v) or not 0 < v <= MAX_BOARD_SIZE:
        raise InputError(where, f'field "{key}" must be a positive number up to {MAX_BOARD_SIZE:g}, got {str(v)[:40]}')
    return float(v)


def parse_board(doc: Any, where: Path | str = BOARD_FILE) -> Board:
    """Validate a ``board.json`` document; raises :class:`InputError` naming ``where`` and the field."""
    if not isinstance(doc, dict):
        raise InputError(where, "must be a JSON object")
    kind = doc.get("kind")
    if kind not in KINDS:
        raise InputError(where, f'field "kind" must be "chessboard" or "charuco", got {kind!r}')
    units = doc.get("units", "mm")
    if not isinstance(units, str) or not units:
        raise InputError(where, f'field "units" must be a string such as "mm", got {units!r}')
    if kind == "chessboard":
        known = {"kind", "inner_corners", "square_size", "units"}
        unknown = sorted(set(doc) - known)
        if unknown:
            raise InputError(where, f'unknown field "{unknown[0]}" for a chessboard (expected {sorted(known)})')
        inner = _positive_int_pair(doc, "inner_corners", where, 2)
        if inner[0] == inner[1]:
            # A square grid of corners has a 90-degree ambiguity OpenCV cannot resolve.
            raise InputError(where, f'field "inner_corners" is {list(inner)}: use a board with different counts along its sides')
        return Board("chessboard", inner, _positive_number(doc, "square_size", where), units=units)
    known = {"kind", "squares", "square_size", "marker_size", "dictionary", "units"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise InputError(where, f'unknown field "{unknown[0]}" for a ChArUco board (expected {sorted(known)})')
    squares = _positive_int_pair(doc, "squares", where, 3)
    square = _positive_number(doc, "square_size", where)
    marker = _positive_number(doc, "marker_size", where)
    if marker >= square:
        raise InputError(where, f'field "marker_size" ({marker}) must be smaller than "square_size" ({square})')
    dictionary = doc.get("dictionary")
    if not isinstance(dictionary, str) or not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise InputError(where, f'field "dictionary" must name an OpenCV ArUco dictionary such as "DICT_5X5_100", got {dictionary!r}')
    board = Board("charuco", (squares[0] - 1, squares[1] - 1), square, marker, dictionary, units)
    n_markers = (squares[0] * squares[1]) // 2
    dict_size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    if n_markers > dict_size:
        raise InputError(where, f'field "dictionary": {dictionary} has {dict_size} markers, the board needs {n_markers}')
    return board


def load_board(path: str | os.PathLike[str]) -> Board:
    """Read and validate ``board.json`` (a file, or a folder holding one)."""
    p = Path(path)
    if p.is_dir():
        p = p / BOARD_FILE
    doc = read_json(p, "board description not found (a calibration session needs a board.json)")
    return parse_board(doc, p)


@dataclass(frozen=True)
class Detection:
    """Board corners found in one image.

    ``ids`` (N,) int64 index :meth:`Board.object_points`; ``image_points`` (N, 2) float64
    are sub-pixel camera coordinates (OpenCV convention: pixel centres at integers).
    """

    ids: np.ndarray
    image_points: np.ndarray

    def object_points(self, board: Board) -> np.ndarray:
        """(N, 3) float32 board coordinates of the detected corners."""
        return board.object_points()[self.ids]

    def __len__(self) -> int:
        return int(self.ids.size)


def _as_grey_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.shape[2] == 3 else img[..., 0]
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating):
            hi = float(np.nanmax(img)) if img.size else 1.0
            img = np.clip(img / (hi if hi > 1.5 else 1.0) * (255.0 if hi <= 1.5 else 1.0), 0, 255).astype(np.uint8)
        else:
            img = (img.astype(np.float64) * (255.0 / max(1, np.iinfo(img.dtype).max))).astype(np.uint8)
    return np.ascontiguousarray(img)


def _normalise_order(points: np.ndarray) -> np.ndarray:
    """Reverse a chessboard corner list so that corner 0 is the one nearer the image origin.

    Any rectangular grid is unchanged by a half turn, so both orders are valid labellings;
    picking one makes detections of the same board comparable from image to image.
    """
    if points[0].sum() > points[-1].sum():
        return points[::-1].copy()
    return points


#: The quick search for the board's region runs on an image of at most this many pixels per side.
_ROUGH_SIDE = 1024


def _sector_corners(grey: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    # NORMALIZE_IMAGE (histogram equalisation) measurably worsens the sub-pixel corners: leave it out.
    found, corners = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def _find_chessboard(grey: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    """(N, 2) sub-pixel corners in OpenCV's order, or None.

    The sector-based detector with its accuracy option gives the best corners but costs
    seconds on a large image, so the board is first looked for on a reduced image (the
    classic detector, then the sector-based one without its accuracy option) and the
    accurate one runs on a crop around it. No board on the reduced image: not found.
    """
    h, w = grey.shape
    scale = min(1.0, _ROUGH_SIDE / max(h, w))
    small = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else grey
    found, rough = cv2.findChessboardCorners(
        small, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    )
    if not found:
        found, rough = cv2.findChessboardCornersSB(small, size, flags=0)
        if not found:
            return None
    pts = (rough.reshape(-1, 2).astype(np.float64) + 0.5) / scale - 0.5
    grid = pts.reshape(size[1], size[0], 2)
    square = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    pad = 2.0 * square + 8
    x0, y0 = (max(0, int(v)) for v in np.floor(pts.min(axis=0) - pad))
    x1, y1 = int(min(w, np.ceil(pts[:, 0].max() + pad))), int(min(h, np.ceil(pts[:, 1].max() + pad)))
    crop = np.ascontiguousarray(grey[y0:y1, x0:x1])
    corners = _sector_corners(crop, size)
    if corners is not None:
        return corners + np.array([x0, y0], np.float64)
    # The accurate detector missed (strong blur, low contrast): refine the rough corners instead.
    win = int(np.clip(square / 6, 3, 11))
    refined = cv2.cornerSubPix(
        grey, pts.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1),
        (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4),
    )
    return refined.reshape(-1, 2).astype(np.float64)


def detect_board(board: Board, image: np.ndarray) -> Detection | None:
    """Find the board's inner corners in an image.

    Parameters
    ----------
    board : the target.
    image : (H, W) or (H, W, 3) image, any integer or float dtype.

    Returns
    -------
    A :class:`Detection`, or ``None`` if the board is not found (a chessboard must be
    found whole; a ChArUco board needs at least ``MIN_CHARUCO_CORNERS`` corners).
    """
    grey = _as_grey_u8(image)
    if board.kind == "chessboard":
        corners = _find_chessboard(grey, board.inner_corners)
        if corners is None:
            return None
        pts = _normalise_order(corners)
        return Detection(ids=np.arange(board.n_corners, dtype=np.int64), image_points=pts)
    detector = cv2.aruco.CharucoDetector(board.charuco_board())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or corners is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids = np.asarray(ids, dtype=np.int64).ravel()
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(ids)
    return Detection(ids=ids[order], image_points=pts[order])
