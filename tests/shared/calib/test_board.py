"""board.json validation and board corner detection on rendered boards with known geometry."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from shared.calib.board import Board, detect_board, load_board, parse_board
from shared.core.errors import InputError

CHESS = {"kind": "chessboard", "inner_corners": [9, 7], "square_size": 75.0}
CHARUCO = {
    "kind": "charuco",
    "squares": [8, 6],
    "square_size": 40.0,
    "marker_size": 30.0,
    "dictionary": "DICT_5X5_100",
}


def test_parse_valid_boards() -> None:
    b = parse_board(CHESS)
    assert (b.kind, b.inner_corners, b.square_size, b.n_corners) == ("chessboard", (9, 7), 75.0, 63)
    pts = b.object_points()
    assert pts.shape == (63, 3) and pts.dtype == np.float32
    # Corner id j * nx + i sits at (i, j) squares.
    assert np.allclose(pts[9 + 2], [2 * 75.0, 75.0, 0.0])
    c = parse_board(CHARUCO)
    assert c.inner_corners == (7, 5) and c.squares == (8, 6) and c.n_corners == 35
    assert parse_board(c.to_json()) == c
    assert parse_board(b.to_json()) == b


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        ([1, 2], "JSON object"),
        ({**CHESS, "kind": "circles"}, '"kind"'),
        ({**CHESS, "inner_corners": [9]}, '"inner_corners"'),
        ({**CHESS, "inner_corners": [9, 1]}, '"inner_corners"'),
        ({**CHESS, "inner_corners": [9.0, 7]}, '"inner_corners"'),
        ({**CHESS, "inner_corners": [7, 7]}, '"inner_corners"'),
        ({**CHESS, "square_size": 0}, '"square_size"'),
        ({**CHESS, "square_size": 1e308}, '"square_size" must be a positive number up to'),
        ({**CHESS, "inner_corners": [9, 10**12]}, '"inner_corners" must be two integers in 2..200'),
        ({**CHESS, "square_size": "75"}, '"square_size"'),
        ({**CHESS, "square_size": True}, '"square_size"'),
        ({**CHESS, "marker_size": 5.0}, '"marker_size"'),
        ({**CHESS, "units": ""}, '"units"'),
        ({k: v for k, v in CHESS.items() if k != "square_size"}, '"square_size"'),
        ({**CHARUCO, "marker_size": 40.0}, '"marker_size"'),
        ({**CHARUCO, "dictionary": "DICT_NOPE"}, '"dictionary"'),
        ({**CHARUCO, "dictionary": 5}, '"dictionary"'),
        ({**CHARUCO, "squares": [30, 30], "dictionary": "DICT_4X4_50"}, '"dictionary"'),
        ({**CHARUCO, "inner_corners": [9, 7]}, '"inner_corners"'),
    ],
)
def test_parse_rejects_bad_fields(doc: object, field: str) -> None:
    with pytest.raises(InputError) as e:
        parse_board(doc, "session/board.json")
    assert "session/board.json" in str(e.value) and field in str(e.value)
    assert "\n" not in str(e.value)


def test_load_board_errors(tmp_path) -> None:
    with pytest.raises(InputError, match="board.json"):
        load_board(tmp_path)
    p = tmp_path / "board.json"
    p.write_text("{not json", encoding="utf-8")
    with pytest.raises(InputError, match="malformed JSON"):
        load_board(p)
    p.write_text(json.dumps(CHESS), encoding="utf-8")
    assert load_board(tmp_path).inner_corners == (9, 7)


def _view(
    board: Board, H_board_to_image: np.ndarray, size: tuple[int, int], ppu: float
) -> tuple[np.ndarray, np.ndarray]:
    """Warp the printed board into an image; returns the image and the true corner pixels."""
    printed, to_board = board.render(ppu)
    H = H_board_to_image @ to_board
    img = cv2.warpPerspective(printed, H, size, flags=cv2.INTER_AREA, borderValue=255)
    obj = board.object_points()[:, :2].astype(np.float64)
    truth = cv2.perspectiveTransform(obj.reshape(-1, 1, 2), H_board_to_image).reshape(-1, 2)
    return img, truth


def _homography(angle_deg: float, scale: float, shift: tuple[float, float], tilt: float = 2e-4) -> np.ndarray:
    a = np.radians(angle_deg)
    return np.array(
        [
            [scale * np.cos(a), -scale * np.sin(a), shift[0]],
            [scale * np.sin(a), scale * np.cos(a), shift[1]],
            [tilt, -tilt / 2, 1.0],
        ]
    )


def test_detect_chessboard_subpixel() -> None:
    board = Board("chessboard", (9, 7), 20.0)
    img, truth = _view(board, _homography(8.0, 3.2, (180.0, 140.0)), (1000, 800), ppu=12.0)
    det = detect_board(board, img)
    assert det is not None and len(det) == 63
    # A half-turned labelling is equally valid: compare with whichever order the truth matches.
    err = np.linalg.norm(det.image_points - truth, axis=1)
    err_rev = np.linalg.norm(det.image_points - truth[::-1], axis=1)
    err = err if err.mean() < err_rev.mean() else err_rev
    assert err.max() < 0.15, err.max()
    # Board absent: a blank image.
    assert detect_board(board, np.full((600, 800), 200, np.uint8)) is None
    # The wrong corner count is not found.
    assert detect_board(Board("chessboard", (10, 8), 20.0), img) is None


def test_detect_charuco_partial_view() -> None:
    board = parse_board(CHARUCO)
    img, truth = _view(board, _homography(-5.0, 3.0, (150.0, 120.0)), (1100, 900), ppu=10.0)
    det = detect_board(board, img)
    assert det is not None and len(det) == board.n_corners
    assert np.abs(det.image_points - truth[det.ids]).max() < 0.3
    # Hide the left third of the board: fewer corners, with the right ids.
    covered = img.copy()
    covered[:, : int(truth[:, 0].min() + (truth[:, 0].max() - truth[:, 0].min()) / 3)] = 255
    part = detect_board(board, covered)
    assert part is not None and 8 <= len(part) < board.n_corners
    assert np.abs(part.image_points - truth[part.ids]).max() < 0.3
