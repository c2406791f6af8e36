"""Synthetic 8-bit camera images of planar checkerboard marker boards, geometrically exact.

Rendering is by inverse mapping: every sample point of a pixel is undistorted with the camera's
own model (`Camera.undistort_normalized`), turned into a ray, intersected with the board plane and
coloured by the checkerboard cell it hits. A pixel's value is the mean of its samples, i.e. its
area coverage, so edges and X-corners sit exactly where `Camera.project` puts them (up to the
1 / supersampling^2 quantization of the coverage).

Work is limited to each board's projected bounding box. Inside it a coarse pass evaluates the
pattern at the pixel corners only; pixels whose four corners disagree, and the pixels around every
projected vertex of the pattern (cell corners, X-corners, outline corners), are supersampled with
an s x s "n-rooks" pattern (all s^2 sample abscissae distinct and all ordinates distinct, so even an
axis-aligned edge is resolved to 1 / s^2 of a pixel). A straight edge crossing a pixel always
separates at least one of its corners from the others, so away from vertices the corner test misses
nothing; boards whose cells are smaller than a few pixels are supersampled everywhere.

`coverage_image` is the noise-free, blur-free, vignetting-free rendering on a flat background;
`render_image` paints the same boards over a fractal texture and adds illumination jitter, optical
blur, vignetting, shot and read noise. Pixel coordinates follow OpenCV (centre of the top-left
pixel is (0, 0); pixel (i, j) covers [j - 0.5, j + 0.5] x [i - 0.5, i + 0.5]).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import Camera
from ..geometry import Rigid3

# Coverage codes of one sample.
_BACKGROUND, _BLACK, _WHITE = 0, 1, 2

_MAX_CHUNK_POINTS = 1 << 19  # sample points per vectorized chunk (~ tens of MB of temporaries)
_MIN_COS = 0.05  # boards seen more edge-on than this are skipped
_BBOX_PAD_PX = 2
_VERTEX_RADIUS_PX = 1  # supersample the (2r+1)^2 pixels around every projected pattern vertex
_MIN_CELL_PX = 3.0  # below this projected cell size the whole bounding box is supersampled


@dataclass(frozen=True)
class MarkerBoard:
    """A planar board of cols x rows checkerboard cells in the world; its X-corners are the inner corners.

    Board coordinates (a, b) are metres along `axis_u` / `axis_v` from `origin`, the board centre.
    Cell (i, j) (column i along u, row j along v, (0, 0) at min u, min v) is black when i + j is
    even for polarity +1, odd for polarity -1. A white border `margin` metres wide surrounds the
    cells. The pattern is printed on both faces (seen mirrored from behind).
    """

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    cols: int
    rows: int
    cell_u: float
    cell_v: float
    polarity: int = 1
    margin: float = 0.0

    def __post_init__(self):
        for name in ("origin", "axis_u", "axis_v"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float).reshape(3))

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal axis_u x axis_v (world)."""
        n = np.cross(self.axis_u, self.axis_v)
        return n / np.linalg.norm(n)

    @property
    def half_size(self) -> tuple[float, float]:
        """Half extents (a, b) of the cell area, metres."""
        return 0.5 * self.cols * self.cell_u, 0.5 * self.rows * self.cell_v

    def to_world(self, ab) -> np.ndarray:
        """World points (n, 3) of board coordinates (n, 2)."""
        ab = np.asarray(ab, dtype=float).reshape(-1, 2)
        return self.origin + ab[:, :1] * self.axis_u + ab[:, 1:] * self.axis_v

    def corner_coordinates(self) -> np.ndarray:
        """Board coordinates (n, 2) of the (cols-1)*(rows-1) inner corners, row-major (rows along v)."""
        half_u, half_v = self.half_size
        a = -half_u + self.cell_u * np.arange(1, self.cols)
        b = -half_v + self.cell_v * np.arange(1, self.rows)
        bb, aa = np.meshgrid(b, a, indexing="ij")
        return np.column_stack([aa.ravel(), bb.ravel()])

    def corners(self) -> np.ndarray:
        """World points (n, 3) of the (cols-1)*(rows-1) inner X-corners, row-major: index = row*(cols-1)+col."""
        return self.to_world(self.corner_coordinates())

    def vertex_coordinates(self) -> np.ndarray:
        """Board coordinates (m, 2) of every vertex of the pattern: the (cols+1)*(rows+1) cell grid
        points and, with a margin, the 4 outline corners."""
        half_u, half_v = self.half_size
        a = -half_u + self.cell_u * np.arange(self.cols + 1)
        b = -half_v + self.cell_v * np.arange(self.rows + 1)
        bb, aa = np.meshgrid(b, a, indexing="ij")
        points = [np.column_stack([aa.ravel(), bb.ravel()])]
        if self.margin > 0:
            points.append(self.outline_coordinates())
        return np.concatenate(points)

    def outline_coordinates(self) -> np.ndarray:
        """Board coordinates (4, 2) of the outer outline (cells plus margin), counter-clockwise in (a, b)."""
        half_u, half_v = self.half_size
        a, b = half_u + self.margin, half_v + self.margin
        return np.array([[-a, -b], [a, -b], [a, b], [-a, b]])


@dataclass(frozen=True)
class RenderSettings:
    """Image formation parameters; levels and noise in DN of the 8-bit output."""

    supersampling: int = 4  # s x s samples per pixel on pixels whose footprint crosses an edge
    blur_sigma_px: float = 0.8  # Gaussian optical PSF
    black_level: float = 35.0  # DN of black cells (before vignetting/noise)
    white_level: float = 205.0  # DN of white cells
    background_mean: float = 110.0
    background_contrast: float = 25.0  # std of the fractal texture in DN
    vignetting: float = 0.15  # relative falloff at the farthest image corner
    read_noise_dn: float = 1.5  # Gaussian read noise
    shot_noise_gain: float = 0.05  # shot-noise variance per DN: var = gain * signal
    illumination_jitter: float = 0.1  # per-board random scale of the levels (shadow/sun)


# ------------------------------------------------------------------------------ board geometry


@dataclass(frozen=True)
class _BoardInCamera:
    """A board's plane as homographies from normalized image coordinates to board coordinates.

    For the ray r = (x, y, 1): a = (ha . r) / (n . r), b = (hb . r) / (n . r); the ray hits the
    plane in front of the camera when (n . o) / (n . r) > 0.
    """

    board: MarkerBoard
    o: np.ndarray  # origin in the camera frame
    n: np.ndarray  # unit normal in the camera frame
    ha: np.ndarray
    hb: np.ndarray
    no: float  # n . o

    @classmethod
    def build(cls, board: MarkerBoard, cam_from_world: Rigid3) -> "_BoardInCamera | None":
        """None when the board is seen edge-on (|cos| < _MIN_COS) or the camera is in its plane."""
        R = cam_from_world.R
        o = R @ board.origin + cam_from_world.t
        u = R @ board.axis_u
        v = R @ board.axis_v
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        distance = np.linalg.norm(o)
        no = float(n @ o)
        if distance == 0 or abs(no) < _MIN_COS * distance:
            return None
        ha = no * u - (u @ o) * n
        hb = no * v - (v @ o) * n
        return cls(board, o, n, ha, hb, no)

    def board_coordinates(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Board coordinates a, b (m,) of normalized image points (m, 2), and whether the ray hits
        the plane in front of the camera (False for NaN points)."""
        x, y = xy[:, 0], xy[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            den = self.n[0] * x + self.n[1] * y + self.n[2]
            inv = 1.0 / den
            a = (self.ha[0] * x + self.ha[1] * y + self.ha[2]) * inv
            b = (self.hb[0] * x + self.hb[1] * y + self.hb[2]) * inv
            valid = ((self.no * den) > 0) & np.isfinite(a) & np.isfinite(b)
        return a, b, valid

    def codes_ab(self, a: np.ndarray, b: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Coverage codes (m,) int8 of board coordinates (m,); invalid points are background."""
        board = self.board
        half_u, half_v = board.half_size
        a = np.where(valid, a, np.inf)
        b = np.where(valid, b, np.inf)
        abs_a, abs_b = np.abs(a), np.abs(b)
        on_board = (abs_a < half_u + board.margin) & (abs_b < half_v + board.margin)
        in_cells = on_board & (abs_a < half_u) & (abs_b < half_v)
        code = np.where(on_board, np.int8(_WHITE), np.int8(_BACKGROUND))
        i = np.floor((np.where(in_cells, a, 0.0) + half_u) / board.cell_u).astype(np.int64)
        j = np.floor((np.where(in_cells, b, 0.0) + half_v) / board.cell_v).astype(np.int64)
        parity = (i + j) & 1
        black = in_cells & (parity == (0 if board.polarity >= 0 else 1))
        code[black] = _BLACK
        return code

    def codes(self, xy: np.ndarray) -> np.ndarray:
        """Coverage codes (m,) int8 of normalized image points (m, 2); NaN points are background."""
        return self.codes_ab(*self.board_coordinates(xy))

    def edge_lines(self) -> tuple[np.ndarray, np.ndarray]:
        """Sorted a and b values of every line of the pattern's grid (cell lines and outline)."""
        board = self.board
        half_u, half_v = board.half_size
        a = -half_u + board.cell_u * np.arange(board.cols + 1)
        b = -half_v + board.cell_v * np.arange(board.rows + 1)
        if board.margin > 0:
            a = np.concatenate([[-half_u - board.margin], a, [half_u + board.margin]])
            b = np.concatenate([[-half_v - board.margin], b, [half_v + board.margin]])
        return a, b


def _image_normalized_bounds(camera: Camera) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the undistorted normalized coordinates of the whole image."""
    n = 257
    xs = np.linspace(-0.5, camera.width - 0.5, n)
    ys = np.linspace(-0.5, camera.height - 0.5, n)
    border = np.concatenate([
        np.column_stack([xs, np.full(n, -0.5)]),
        np.column_stack([xs, np.full(n, camera.height - 0.5)]),
        np.column_stack([np.full(n, -0.5), ys]),
        np.column_stack([np.full(n, camera.width - 0.5), ys]),
        [[camera.cx, camera.cy]],
    ])
    xy = camera.undistort_normalized(border)
    if np.isnan(xy).any():
        # The model folds inside the image: nothing beyond the turning radius is ever seen.
        r_turn = 1.0 / np.sqrt(-3.0 * camera.d)
        return -r_turn, r_turn, -r_turn, r_turn
    x_min, y_min = xy.min(axis=0)
    x_max, y_max = xy.max(axis=0)
    # A little slack: the border is sampled, and bounding boxes are padded anyway.
    sx, sy = 4.0 / camera.fx, 4.0 / camera.fy
    return x_min - sx, x_max + sx, y_min - sy, y_max + sy


def _clip_polygon(polygon: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of a convex polygon (k, dim) where polygon @ normal >= offset."""
    if len(polygon) == 0:
        return polygon
    side = polygon @ normal - offset
    out = []
    for k in range(len(polygon)):
        p, q = polygon[k], polygon[(k + 1) % len(polygon)]
        sp, sq = side[k], side[(k + 1) % len(polygon)]
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            out.append(p + (q - p) * (sp / (sp - sq)))
    return np.array(out).reshape(-1, polygon.shape[1])


def _visible_outline(camera: Camera, cam_from_world: Rigid3, board: MarkerBoard) -> np.ndarray | None:
    """Undistorted normalized points (m, 2) densely along the outline of the part of the board that
    is in front of the camera and within the image's normalized bounds; None if there is none."""
    corners_cam = cam_from_world.apply(board.to_world(board.outline_coordinates()))
    scale = float(np.abs(corners_cam).max())
    polygon = _clip_polygon(corners_cam, np.array([0.0, 0.0, 1.0]), 1e-9 * scale)
    if len(polygon) < 3:
        return None
    polygon = polygon[:, :2] / polygon[:, 2:]
    x_min, x_max, y_min, y_max = _image_normalized_bounds(camera)
    for normal, offset in (([1, 0], x_min), ([-1, 0], -x_max), ([0, 1], y_min), ([0, -1], -y_max)):
        polygon = _clip_polygon(polygon, np.array(normal, dtype=float), offset)
        if len(polygon) < 3:
            return None
    # Densely along each edge: the distorted image of a straight edge is curved.
    f = max(camera.fx, camera.fy)
    points = []
    for k in range(len(polygon)):
        p, q = polygon[k], polygon[(k + 1) % len(polygon)]
        count = int(np.clip(np.hypot(*(q - p)) * f / 8.0, 2, 2048))
        t = np.linspace(0.0, 1.0, count, endpoint=False)[:, None]
        points.append(p + (q - p) * t)
    return np.concatenate(points)


def _distort_normalized_to_pixels(camera: Camera, xy: np.ndarray) -> np.ndarray:
    """Distorted pixels (m, 2) of undistorted normalized points (m, 2); points beyond the turning
    radius of a folding (d < 0) model are first pulled radially onto it."""
    xy = np.array(xy, dtype=float)
    if camera.d < 0:
        r_turn = 1.0 / np.sqrt(-3.0 * camera.d)
        r = np.hypot(xy[:, 0], xy[:, 1])
        far = r > r_turn
        xy[far] *= (r_turn / r[far])[:, None]
    return camera.project(np.column_stack([xy, np.ones(len(xy))]))


def _bbox_of(camera: Camera, cam_from_world: Rigid3, board: MarkerBoard):
    """(x0, y0, x1, y1) half-open pixel bounding box clipped to the image, or None."""
    outline = _visible_outline(camera, cam_from_world, board)
    if outline is None:
        return None
    uv = _distort_normalized_to_pixels(camera, outline)
    uv = uv[np.isfinite(uv).all(axis=1)]
    if len(uv) == 0:
        return None
    # Pixel j covers [j - 0.5, j + 0.5].
    x0 = max(int(np.floor(uv[:, 0].min() + 0.5)) - _BBOX_PAD_PX, 0)
    y0 = max(int(np.floor(uv[:, 1].min() + 0.5)) - _BBOX_PAD_PX, 0)
    x1 = min(int(np.floor(uv[:, 0].max() + 0.5)) + _BBOX_PAD_PX + 1, camera.width)
    y1 = min(int(np.floor(uv[:, 1].max() + 0.5)) + _BBOX_PAD_PX + 1, camera.height)
    if x0 >= x1 or y0 >= y1:
        return None
    return x0, y0, x1, y1


def board_pixel_bbox(camera: Camera, cam_from_world: Rigid3, board: MarkerBoard) -> tuple[int, int, int, int] | None:
    """Pixel bounding box (x0, y0, x1, y1) of a board's image, padded by 2 px and clipped to the image.

    Half-open: the board's pixels are `image[y0:y1, x0:x1]`. None when the board is entirely behind
    the camera, outside the view, or seen edge-on (the cases `render_image` skips).
    """
    if _BoardInCamera.build(board, cam_from_world) is None:
        return None
    return _bbox_of(camera, cam_from_world, board)


# ------------------------------------------------------------------------------ coverage


SAMPLING_MODE = "multijitter"


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """Vectorized splitmix64 finalizer of uint64 values."""
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _pixel_uniforms(px: np.ndarray, py: np.ndarray, count: int) -> np.ndarray:
    """(m, count) uniforms in [0, 1) that depend only on the absolute pixel (px, py)."""
    key = (py.astype(np.uint64) << np.uint64(32)) | (px.astype(np.int64) & 0xFFFFFFFF).astype(np.uint64)
    key = _splitmix64(key)[:, None] + np.arange(count, dtype=np.uint64)[None, :] * np.uint64(0xD1B54A32D192ED03)
    return (_splitmix64(key) >> np.uint64(11)).astype(np.float64) * (1.0 / 2**53)


def _sample_offsets(px: np.ndarray, py: np.ndarray, s: int) -> np.ndarray:
    """(m, s*s, 2) sample offsets from the centres of pixels (px, py), in (-0.5, 0.5)."""
    n = s * s
    i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    i, j = i.ravel(), j.ravel()
    if SAMPLING_MODE == "lattice":
        ox = (i * s + j + 0.5) / n - 0.5
        oy = (j * s + i + 0.5) / n - 0.5
        return np.broadcast_to(np.stack([ox, oy], axis=1), (len(px), n, 2))
    if SAMPLING_MODE == "korobov":
        a = {4: 7}.get(s, 1)
        k = np.arange(n)
        ox = (k + 0.5) / n - 0.5
        oy = ((k * 5) % n + 0.5) / n - 0.5
        return np.broadcast_to(np.stack([ox, oy], axis=1), (len(px), n, 2))
    u = _pixel_uniforms(px, py, 4 * n).reshape(len(px), 4, s, s)
    fine_x = np.argsort(u[:, 0], axis=2)  # fine_x[m, i] permutation over j
    fine_y = np.argsort(u[:, 1], axis=2)  # fine_y[m, j] permutation over i
    jitter_x = u[:, 2].reshape(len(px), n)
    jitter_y = u[:, 3].reshape(len(px), n)
    ox = (i + (fine_x[:, i, j] + jitter_x) / s) / s - 0.5
    oy = (j + (fine_y[:, j, i] + jitter_y) / s) / s - 0.5
    return np.stack([ox, oy], axis=2)


def _forced_mask(camera: Camera, cam_from_world: Rigid3, board: MarkerBoard, bbox) -> np.ndarray | bool:
    """Pixels of the bbox (ny, nx) to supersample regardless of the corner test, or True for all."""
    x0, y0, x1, y1 = bbox
    vertices = board.vertex_coordinates()
    uv = camera.project(cam_from_world.apply(board.to_world(vertices)))
    # Small projected cells could hide a whole cell between pixel corners: supersample everything.
    half_u, half_v = board.half_size
    grid = uv[: (board.cols + 1) * (board.rows + 1)].reshape(board.rows + 1, board.cols + 1, 2)
    edges = np.concatenate([
        np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
        np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
    ])
    edges = edges[np.isfinite(edges)]
    if len(edges) and edges.min() < _MIN_CELL_PX:
        return True
    mask = np.zeros((y1 - y0, x1 - x0), dtype=bool)
    uv = uv[np.isfinite(uv).all(axis=1)]
    centre = np.floor(uv + 0.5).astype(np.int64) - np.array([x0, y0])
    r = _VERTEX_RADIUS_PX
    for cx, cy in centre:
        if -r <= cx < mask.shape[1] + r and -r <= cy < mask.shape[0] + r:
            mask[max(cy - r, 0): cy + r + 1, max(cx - r, 0): cx + r + 1] = True
    return mask


def _paint_board(image: np.ndarray, camera: Camera, cam_from_world: Rigid3, plane: _BoardInCamera,
                 bbox, black: float, white: float, supersampling: int) -> None:
    """Composite one board over `image` (float32, in place) by area coverage within `bbox`."""
    x0, y0, x1, y1 = bbox
    nx, ny = x1 - x0, y1 - y0
    forced = _forced_mask(camera, cam_from_world, plane.board, bbox)
    s = max(int(supersampling), 1)
    n_samples = s * s
    xs = np.arange(x0, x1 + 1, dtype=float) - 0.5  # pixel-corner abscissae
    rows_per_chunk = max(1, _MAX_CHUNK_POINTS // (nx + 1))
    pixels_per_chunk = max(1, _MAX_CHUNK_POINTS // n_samples)
    for r0 in range(0, ny, rows_per_chunk):
        r1 = min(ny, r0 + rows_per_chunk)
        ys = np.arange(y0 + r0, y0 + r1 + 1, dtype=float) - 0.5
        gu, gv = np.meshgrid(xs, ys)
        codes = plane.codes(camera.undistort_normalized(np.column_stack([gu.ravel(), gv.ravel()])))
        codes = codes.reshape(len(ys), len(xs))
        c00 = codes[:-1, :-1]
        mixed = (c00 != codes[:-1, 1:]) | (c00 != codes[1:, :-1]) | (c00 != codes[1:, 1:])
        if forced is True:
            mixed[:] = True
        else:
            mixed |= forced[r0:r1]
        black_fraction = (c00 == _BLACK).astype(np.float32)
        white_fraction = (c00 == _WHITE).astype(np.float32)
        iy, ix = np.nonzero(mixed)
        for p0 in range(0, len(iy), pixels_per_chunk):
            py, px = iy[p0: p0 + pixels_per_chunk], ix[p0: p0 + pixels_per_chunk]
            offsets = _sample_offsets(px + x0, py + y0 + r0, s)
            su = (px + x0)[:, None] + offsets[:, :, 0]
            sv = (py + y0 + r0)[:, None] + offsets[:, :, 1]
            sample_codes = plane.codes(camera.undistort_normalized(np.column_stack([su.ravel(), sv.ravel()])))
            sample_codes = sample_codes.reshape(len(py), n_samples)
            black_fraction[py, px] = np.count_nonzero(sample_codes == _BLACK, axis=1) / n_samples
            white_fraction[py, px] = np.count_nonzero(sample_codes == _WHITE, axis=1) / n_samples
        if not (black_fraction.any() or white_fraction.any()):
            continue
        patch = image[y0 + r0: y0 + r1, x0:x1]
        patch *= 1.0 - black_fraction - white_fraction
        patch += np.float32(black) * black_fraction + np.float32(white) * white_fraction


def _paint_boards(image: np.ndarray, camera: Camera, cam_from_world: Rigid3, boards, levels: np.ndarray,
                  settings: RenderSettings) -> None:
    """Composite all visible boards over `image` in place, farthest first (painter's algorithm)."""
    todo = []
    for index, board in enumerate(boards):
        plane = _BoardInCamera.build(board, cam_from_world)
        if plane is None:
            continue
        bbox = _bbox_of(camera, cam_from_world, board)
        if bbox is None:
            continue
        todo.append((-float(np.linalg.norm(plane.o)), index, plane, bbox))
    for _, index, plane, bbox in sorted(todo, key=lambda item: item[:2]):
        black, white = levels[index]
        _paint_board(image, camera, cam_from_world, plane, bbox, black, white, settings.supersampling)


def _levels_array(levels, n_boards: int, settings: RenderSettings) -> np.ndarray:
    if levels is None:
        return np.tile([settings.black_level, settings.white_level], (n_boards, 1))
    levels = np.asarray(levels, dtype=float)
    if levels.shape == (2,):
        return np.tile(levels, (n_boards, 1))
    if levels.shape != (n_boards, 2):
        raise ValueError(f"levels must have shape (2,) or ({n_boards}, 2), got {levels.shape}")
    return levels


def coverage_image(camera: Camera, cam_from_world: Rigid3, boards, settings: RenderSettings = RenderSettings(),
                   levels=None) -> np.ndarray:
    """Noise-free, blur-free, vignetting-free rendering (height, width) float32.

    The background is flat `settings.background_mean`; each board's pixels are the area-weighted
    mean of black, white and background. `levels`: (black, white) DN for all boards (2,) or per
    board (n_boards, 2); default the settings' levels.
    """
    boards = list(boards)
    image = np.full((camera.height, camera.width), settings.background_mean, dtype=np.float32)
    _paint_boards(image, camera, cam_from_world, boards, _levels_array(levels, len(boards), settings), settings)
    return image


# ------------------------------------------------------------------------------ image formation


def fractal_background(height: int, width: int, rng: np.random.Generator, mean: float, contrast: float,
                       finest_px: int = 4) -> np.ndarray:
    """(height, width) float32 multi-octave value noise with 1/f amplitudes, mean `mean`, std ~`contrast`.

    Built coarse to fine: each octave's random grid is added to the cubic upsampling of the sum of
    the coarser ones, so only the last step works at full size.
    """
    if contrast <= 0:
        return np.full((height, width), mean, dtype=np.float32)
    spacings = []
    spacing = max(finest_px, 1)
    while spacing < max(height, width):
        spacings.append(spacing)
        spacing *= 2
    spacings = spacings[::-1] or [max(finest_px, 1)]
    texture = None
    for spacing in spacings:
        shape = (height // spacing + 2, width // spacing + 2)
        octave = rng.standard_normal(shape, dtype=np.float32) * np.float32(spacing / spacings[0])
        if texture is None:
            texture = octave
        else:
            texture = cv2.resize(texture, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC) + octave
    low_mean, low_std = float(texture.mean()), float(texture.std())
    texture = cv2.resize(texture, (width, height), interpolation=cv2.INTER_CUBIC)
    gain = contrast / max(low_std, 1e-12)
    texture *= np.float32(gain)
    texture += np.float32(mean - gain * low_mean)
    return texture


def vignetting_profile(camera: Camera, vignetting: float) -> np.ndarray:
    """(height, width) float32 multiplier 1 - vignetting * (r / r_corner)^2 about the principal point,
    r_corner the distance to the farthest corner pixel centre."""
    dx = np.arange(camera.width, dtype=np.float32) - np.float32(camera.cx)
    dy = np.arange(camera.height, dtype=np.float32) - np.float32(camera.cy)
    r2_corner = max(float(np.max(dx**2)) + float(np.max(dy**2)), 1e-12)
    k = np.float32(vignetting / r2_corner)
    return (1.0 - k * dx**2)[None, :] - (k * dy**2)[:, None]


def render_image(camera: Camera, cam_from_world: Rigid3, boards, rng: np.random.Generator,
                 settings: RenderSettings = RenderSettings()) -> np.ndarray:
    """Synthetic 8-bit grayscale image (height, width) uint8 of `boards` seen by the camera.

    Deterministic for a given rng state. One integer is drawn from `rng` and seeds three
    independent streams (illumination factors, background texture, noise), so adding a board that
    is not visible changes nothing else in the image.
    """
    boards = list(boards)
    key = int(rng.integers(0, 2**63 - 1))
    jitter_rng, texture_rng, noise_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(key).spawn(3))
    factors = np.clip(1.0 + settings.illumination_jitter * jitter_rng.standard_normal(len(boards)), 0.7, 1.3)
    levels = np.column_stack([settings.black_level * factors, settings.white_level * factors])
    image = fractal_background(camera.height, camera.width, texture_rng, settings.background_mean,
                               settings.background_contrast)
    _paint_boards(image, camera, cam_from_world, boards, levels, settings)
    if settings.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), settings.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    if settings.vignetting != 0:
        image *= vignetting_profile(camera, settings.vignetting)
    if settings.read_noise_dn > 0 or settings.shot_noise_gain > 0:
        sigma = np.maximum(image, np.float32(0.0))
        sigma *= np.float32(settings.shot_noise_gain)
        sigma += np.float32(settings.read_noise_dn**2)
        np.sqrt(sigma, out=sigma)
        sigma *= noise_rng.standard_normal(image.shape, dtype=np.float32)
        image += sigma
        del sigma
    np.clip(image, 0.0, 255.0, out=image)
    image += np.float32(0.5)
    return image.astype(np.uint8)
