"""Calibration boards: the spec (anipose keys, TOML), 3D corner positions and rendering.

A board spec uses the keys of anipose (top level or in a ``[calibration]`` table)::

    board_type = "charuco"              # or "checkerboard"
    board_size = [7, 5]                 # squares in x and y
    board_square_side_length = 25.0     # any length unit; the calibration uses it
    board_marker_length = 18.75         # ChArUco only
    board_marker_bits = 4               # ChArUco only: DICT_<bits>X<bits>_<number>
    board_marker_dict_number = 50       # ChArUco only
    legacy_pattern = false              # ChArUco only: OpenCV < 4.6 board layout

sleap-anipose's ``board.toml`` (``sleap_anipose.calibration.write_board``) is read too: its
keys ``board_x``, ``board_y``, ``square_length``, ``marker_length``, ``marker_bits`` and
``dict_size`` stand for ``board_size``, ``board_square_side_length``, ``board_marker_length``,
``board_marker_bits`` and ``board_marker_dict_number``; it names no board type, and, as
sleap-anipose's ``read_board`` does, a file with ``marker_length`` is a ChArUco board and one
without a checkerboard.

``board_points`` are the corners OpenCV reports, in board units with ``z = 0``:

* checkerboard: the ``(sx - 1) (sy - 1)`` inner corners, row by row (x fastest), corner
  ``(c, r)`` at ``(c s, r s, 0)``;
* ChArUco: the inner chessboard corners in ChArUco id order, as
  ``cv2.aruco.CharucoBoard.getChessboardCorners`` (origin at the board's outer corner).
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

BOARD_TYPES = ("checkerboard", "charuco")


#: sleap-anipose's board.toml keys (``write_board``) -> anipose's.
SLEAP_ANIPOSE_KEYS = {
    "square_length": "board_square_side_length",
    "marker_length": "board_marker_length",
    "marker_bits": "board_marker_bits",
    "dict_size": "board_marker_dict_number",
}


def _from_sleap_anipose(d: dict) -> dict:
    """sleap-anipose's board keys as anipose's (board type from ``marker_length``, as
    ``sleap_anipose.calibration.read_board`` decides)."""
    if "board_x" not in d or "board_y" not in d:
        raise ValueError("a sleap-anipose board needs both board_x and board_y")
    mixed = [k for k in ("board_size", *SLEAP_ANIPOSE_KEYS.values()) if k in d]
    if mixed:
        raise ValueError(f"board spec mixes sleap-anipose keys (board_x, board_y) with {mixed}")
    out = {k: v for k, v in d.items() if k not in ("board_x", "board_y", *SLEAP_ANIPOSE_KEYS)}
    out["board_size"] = [d["board_x"], d["board_y"]]
    out.update({new: d[old] for old, new in SLEAP_ANIPOSE_KEYS.items() if old in d})
    out.setdefault("board_type", "charuco" if "marker_length" in d else "checkerboard")
    return out


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard or ChArUco board.

    Parameters
    ----------
    board_type : {"checkerboard", "charuco"}
    squares : (int, int)
        Number of squares in x and y (anipose ``board_size``), each >= 2.
    square_length : float
        Side of one square in the length unit of the calibration (e.g. mm), > 0.
    marker_length : float, optional
        ChArUco marker side (same unit), ``0 < marker_length < square_length``.
    marker_bits : int
        ChArUco dictionary bits (4, 5, 6 or 7).
    dict_number : int
        ChArUco dictionary size (50, 100, 250 or 1000).
    legacy_pattern : bool
        ChArUco layout of OpenCV < 4.6 (boards printed with old tools need this).
    """

    board_type: str
    squares: tuple[int, int]
    square_length: float
    marker_length: float | None = None
    marker_bits: int = 4
    dict_number: int = 50
    legacy_pattern: bool = False

    def __post_init__(self) -> None:
        if self.board_type not in BOARD_TYPES:
            raise ValueError(f"board_type must be one of {BOARD_TYPES}, got {self.board_type!r}")
        sq = tuple(int(v) for v in self.squares)
        if len(sq) != 2 or min(sq) < 2:
            raise ValueError(f"board_size must be two integers >= 2, got {self.squares}")
        object.__setattr__(self, "squares", sq)
        if not np.isfinite(self.square_length) or self.square_length <= 0:
            raise ValueError(f"square length must be > 0, got {self.square_length}")
        if self.board_type == "charuco":
            if self.marker_length is None or not 0 < self.marker_length < self.square_length:
                raise ValueError(
                    "a ChArUco board needs 0 < board_marker_length < board_square_side_length, "
                    f"got {self.marker_length} and {self.square_length}"
                )
            n_markers = sq[0] * sq[1] // 2
            if n_markers > self.dict_number:
                raise ValueError(
                    f"a {sq[0]}x{sq[1]} ChArUco board has {n_markers} markers but dictionary "
                    f"DICT_{self.marker_bits}X{self.marker_bits}_{self.dict_number} only "
                    f"{self.dict_number}"
                )
            self.dictionary_id  # noqa: B018  (validates bits/number)

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: dict) -> BoardSpec:
        """Board from anipose keys (a ``[calibration]`` sub-table is looked into too)."""
        if "calibration" in d and isinstance(d["calibration"], dict):
            d = {**d, **d["calibration"]}
        if "board_x" in d or "board_y" in d:
            d = _from_sleap_anipose(d)
        missing = [
            k for k in ("board_type", "board_size", "board_square_side_length") if k not in d
        ]
        if missing:
            raise ValueError(f"board spec lacks {missing} (anipose keys, see docs/calibration.md)")
        return cls(
            board_type=str(d["board_type"]).lower(),
            squares=tuple(d["board_size"]),
            square_length=float(d["board_square_side_length"]),
            marker_length=(float(d["board_marker_length"]) if "board_marker_length" in d else None),
            marker_bits=int(d.get("board_marker_bits", 4)),
            dict_number=int(d.get("board_marker_dict_number", 50)),
            legacy_pattern=bool(d.get("legacy_pattern", False)),
        )

    @classmethod
    def load(cls, path: str | Path) -> BoardSpec:
        """Read a board spec TOML file (anipose keys, or sleap-anipose's ``board.toml``)."""
        p = Path(path)
        try:
            doc = tomllib.loads(p.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{p}: invalid TOML: {exc}") from None
        try:
            return cls.from_dict(doc)
        except ValueError as exc:
            raise ValueError(f"{p}: {exc}") from None

    def to_dict(self) -> dict:
        """Anipose keys of this board."""
        d: dict = {
            "board_type": self.board_type,
            "board_size": list(self.squares),
            "board_square_side_length": self.square_length,
        }
        if self.board_type == "charuco":
            d.update(
                board_marker_length=self.marker_length,
                board_marker_bits=self.marker_bits,
                board_marker_dict_number=self.dict_number,
                legacy_pattern=self.legacy_pattern,
            )
        return d

    def key(self) -> str:
        """Canonical text of the spec (used to validate detection caches)."""
        return json.dumps(asdict(self), sort_keys=True)

    # -- geometry -------------------------------------------------------------------------
    @property
    def inner_corners(self) -> tuple[int, int]:
        """Inner corners in x and y, ``(sx - 1, sy - 1)``."""
        return self.squares[0] - 1, self.squares[1] - 1

    @property
    def n_points(self) -> int:
        """Number of detectable corners."""
        nx, ny = self.inner_corners
        return nx * ny

    @property
    def board_points(self) -> np.ndarray:
        """(n_points, 3) corner positions in board units, ``z = 0`` (order: module docs)."""
        if self.board_type == "charuco":
            return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64)
        nx, ny = self.inner_corners
        c, r = np.meshgrid(np.arange(nx), np.arange(ny))
        pts = np.stack([c.ravel(), r.ravel(), np.zeros(nx * ny)], axis=1)
        return pts * self.square_length

    def grid_neighbours(self) -> np.ndarray:
        """(n_pairs, 2) indices of corners one square apart (for scale checks)."""
        nx, ny = self.inner_corners
        idx = np.arange(nx * ny).reshape(ny, nx)
        pairs = [np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)]
        pairs.append(np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1))
        return np.concatenate(pairs)

    # -- OpenCV ---------------------------------------------------------------------------
    @property
    def dictionary_id(self) -> int:
        """OpenCV predefined dictionary id, e.g. ``cv2.aruco.DICT_4X4_50``."""
        import cv2

        name = f"DICT_{self.marker_bits}X{self.marker_bits}_{self.dict_number}"
        if not hasattr(cv2.aruco, name):
            raise ValueError(
                f"unknown ArUco dictionary {name} (board_marker_bits in 4..7, "
                "board_marker_dict_number in 50, 100, 250, 1000)"
            )
        return int(getattr(cv2.aruco, name))

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` of a ChArUco spec."""
        import cv2

        if self.board_type != "charuco":
            raise ValueError("cv_board() is only defined for ChArUco boards")
        board = cv2.aruco.CharucoBoard(
            self.squares,
            float(self.square_length),
            float(self.marker_length),
            cv2.aruco.getPredefinedDictionary(self.dictionary_id),
        )
        board.setLegacyPattern(bool(self.legacy_pattern))
        return board

    def render(
        self, pixels_per_square: int = 60, margin: int = 40
    ) -> tuple[np.ndarray, np.ndarray]:
        """Draw the board (uint8 grey image) for printing or synthetic tests.

        Returns
        -------
        image : numpy.ndarray, shape (h, w), uint8
        to_pixels : numpy.ndarray, shape (3, 3)
            Affine map from board coordinates ``(x, y, 1)`` (board units) to OpenCV pixel
            coordinates of ``image`` (pixel centres at integers).
        """
        sx, sy = self.squares
        w, h = sx * pixels_per_square + 2 * margin, sy * pixels_per_square + 2 * margin
        k = pixels_per_square / self.square_length
        if self.board_type == "charuco":
            img = self.cv_board().generateImage((w, h), marginSize=margin, borderBits=1)
            # getChessboardCorners: origin at the board's outer corner.
            off = margin - 0.5
        else:
            cells = (np.add.outer(np.arange(sy), np.arange(sx)) % 2 == 0).astype(np.uint8)
            img = np.full((h, w), 255, np.uint8)
            block = np.kron(1 - cells, np.ones((pixels_per_square, pixels_per_square), np.uint8))
            img[margin : h - margin, margin : w - margin] = block * 255
            # board_points origin: the first inner corner, one square in.
            off = margin + pixels_per_square - 0.5
        to_px = np.array([[k, 0.0, off], [0.0, k, off], [0.0, 0.0, 1.0]])
        return img, to_px
