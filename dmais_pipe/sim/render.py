"""Synthetic 8-bit camera images of planar checkerboard marker boards, geometrically exact.

Rendering is by inverse mapping: pixel corners (and, where needed, sample points inside pixels)
are undistorted with the camera's own model (`Camera.undistort_normalized`), turned into rays,
intersected with the board plane and coloured by the checkerboard cell they hit. A pixel's value
is its area coverage, so edges and X-corners sit exactly where `Camera.project` puts them.

Work is limited to each board's projected bounding box (the visible outline projected densely,
with distortion, padded by 2 px). Inside it a first pass evaluates the pattern at every pixel
corner. Pixels whose four corners agree are uniform: a straight edge crossing a pixel always
separates one of its corners from the others, and the pixels around every projected pattern vertex
are examined regardless (a narrow wedge of an X-corner can slip between corners). The mixed pixels
are then split by the lines of the pattern's grid (cell lines and outline) that cross them:

- one line, or one line of each direction (edges, X-corners, T-junctions, outline corners): the
  exact area on each side, computed from the lines, which are straight in undistorted normalized
  coordinates; the only approximation is the distortion's curvature over one pixel (< 1e-3 px even
  for a strong wide-angle model);
- anything else (several parallel lines in one pixel, cells smaller than a few pixels, the
  horizon of a board crossing the camera plane, where a lens model folds): s x s rays per pixel
  (`RenderSettings.supersampling`) in a multi-jittered pattern, area within ~1 / s^2.

`coverage_image` is the noise-free, blur-free, vignetting-free rendering on a flat background;
`render_image` paints the same boards over a fractal texture and adds illumination jitter, optical
blur, vignetting, shot and read noise, and optionally the effects of real aerial photographs
(`effects.py`: ground texture, cast shadows, occluders, motion blur, defocus, JPEG, 12-bit data).
Pixel coordinates follow OpenCV (centre of the top-left
pixel is (0, 0); pixel (i, j) covers [j - 0.5, j + 0.5] x [i - 0.5, i + 0.5]).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import Camera
from ..geometry import Rigid3
from . import effects

# Coverage codes of one sample.
_BACKGROUND, _BLACK, _WHITE = 0, 1, 2

_MAX_CHUNK_POINTS = 1 << 19  # sample points per vectorized chunk (~ tens of MB of temporaries)
_MIN_COS = 0.05  # boards seen more edge-on than this are skipped
_BBOX_PAD_PX = 2
_VERTEX_RADIUS_PX = 1  # examine the (2r+1)^2 pixels around every projected pattern vertex
_MIN_CELL_PX = 3.0  # below this projected cell size every pixel of the bounding box is examined


@dataclass(frozen=True, eq=False)
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
            value = np.array(getattr(self, name), dtype=float).reshape(3)
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    def _key(self) -> tuple:
        return (tuple(self.origin), tuple(self.axis_u), tuple(self.axis_v), self.cols, self.rows,
                self.cell_u, self.cell_v, self.polarity, self.margin)

    def __eq__(self, other) -> bool:
        return isinstance(other, MarkerBoard) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

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

    supersampling: int = 4  # s x s rays per pixel where the exact area split does not apply
    blur_sigma_px: float = 0.8  # Gaussian optical PSF
    black_level: float = 35.0  # DN of black cells (before vignetting/noise)
    white_level: float = 205.0  # DN of white cells
    background_mean: float = 110.0
    background_contrast: float = 25.0  # std of the fractal texture in DN
    background_roughness: float = 0.5  # octave amplitude ~ spacing**roughness: 1 smooth clouds, 0 white noise
    vignetting: float = 0.15  # relative falloff at the farthest image corner
    read_noise_dn: float = 1.5  # Gaussian read noise
    shot_noise_gain: float = 0.05  # shot-noise variance per DN: var = gain * signal
    illumination_jitter: float = 0.1  # per-board random scale of the levels (shadow/sun)
    # Effects of real aerial photographs (`effects.py`), all off by default:
    ground_texture_dn: float = 0.0  # std of band-limited ground texture (grass, gravel, asphalt) added
    ground_grain_px: float = 1.0  # its grain: the scale of the band (difference of Gaussians)
    shadow_fraction: float = 0.0  # share of boards crossed by a cast shadow's edge
    shadow_depth: float = 0.6  # relative loss of light in the shadow
    shadow_penumbra_px: float = 0.3  # width (std) of the shadow edge
    occlusion_fraction: float = 0.0  # share of boards with a third of one cell hidden by an occluder
    motion_blur_px: float = 0.0  # length of a linear motion blur
    motion_direction_deg: float = 0.0  # its direction in the image (flight direction), from +u toward +v
    defocus_px: float = 0.0  # radius of a disc (defocus) PSF
    jpeg_quality: int = 0  # 1-100: JPEG-compress the 8-bit output; 0: none
    bit_depth: int = 8  # 8: uint8 output; 9-16: uint16 with levels scaled to 2**bit_depth - 1 (e.g. 12-bit data)


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


@functools.lru_cache(maxsize=64)
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
        # The model folds inside the image: nothing beyond the radius where it stops being
        # one-to-one is ever seen.
        r_turn = camera.max_projectable_radius
        return -r_turn, r_turn, -r_turn, r_turn
    x_min, y_min = xy.min(axis=0)
    x_max, y_max = xy.max(axis=0)
    # A little slack: the border is sampled, and bounding boxes are padded anyway.
    sx, sy = 4.0 / camera.fx, 4.0 / camera.fy
    return float(x_min - sx), float(x_max + sx), float(y_min - sy), float(y_max + sy)


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
    """Distorted pixels (m, 2) of undistorted normalized points (m, 2); points beyond a folding
    model's `max_projectable_radius` are first pulled radially onto it."""
    xy = np.array(xy, dtype=float)
    r_turn = camera.max_projectable_radius
    if np.isfinite(r_turn):
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
    """(m, s*s, 2) sample offsets from the centres of pixels (px, py), in (-0.5, 0.5).

    Multi-jittered sampling (Chiu, Shirley, Wang 1994): one sample per s x s sub-cell and all s^2
    abscissae (and ordinates) in distinct 1/s^2 strips, so an axis-aligned edge is resolved to
    1/s^2; the pattern is shuffled per pixel by a hash of its coordinates, so errors do not
    correlate between pixels and the image stays a deterministic function of the scene.
    """
    n = s * s
    i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    i, j = i.ravel(), j.ravel()
    u = _pixel_uniforms(px, py, 4 * n).reshape(len(px), 4, s, s)
    fine_x = np.argsort(u[:, 0], axis=2)  # fine_x[m, i] permutation over j
    fine_y = np.argsort(u[:, 1], axis=2)  # fine_y[m, j] permutation over i
    jitter_x = u[:, 2].reshape(len(px), n)
    jitter_y = u[:, 3].reshape(len(px), n)
    ox = (i + (fine_x[:, i, j] + jitter_x) / s) / s - 0.5
    oy = (j + (fine_y[:, j, i] + jitter_y) / s) / s - 0.5
    return np.stack([ox, oy], axis=2)


def _forced_mask(camera: Camera, cam_from_world: Rigid3, board: MarkerBoard, bbox) -> np.ndarray | bool:
    """Pixels of the bbox (ny, nx) to treat as mixed regardless of the corner test, or True for all."""
    x0, y0, x1, y1 = bbox
    vertices = board.vertex_coordinates()
    uv = camera.project(cam_from_world.apply(board.to_world(vertices)))
    # Small projected cells could hide a whole cell between pixel corners: examine everything.
    grid = uv[: (board.cols + 1) * (board.rows + 1)].reshape(board.rows + 1, board.cols + 1, 2)
    edges = np.concatenate([
        np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
        np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
    ])
    edges = edges[np.isfinite(edges)]
    if len(edges) and edges.min() < _MIN_CELL_PX:
        return True
    mask = np.zeros((y1 - y0, x1 - x0), dtype=bool)
    uv = uv[(np.abs(uv) < 1e9).all(axis=1)]  # finite and castable: a vertex near the camera plane projects to ~1e20
    centre = np.floor(uv + 0.5).astype(np.int64) - np.array([x0, y0])
    r = _VERTEX_RADIUS_PX
    for cx, cy in centre:
        if -r <= cx < mask.shape[1] + r and -r <= cy < mask.shape[0] + r:
            mask[max(cy - r, 0): cy + r + 1, max(cx - r, 0): cx + r + 1] = True
    return mask


def _linear_area_fraction(c: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Fraction of the pixel square [-0.5, 0.5]^2 where the linear function c + p x + q y < 0.

    The distribution of p X + q Y for X, Y uniform is trapezoidal; this is its CDF at -c.
    """
    h1 = np.minimum(np.abs(p), np.abs(q))
    h2 = np.maximum(np.maximum(np.abs(p), np.abs(q)), 1e-300)
    t = -c
    half_sum, half_diff = 0.5 * (h1 + h2), 0.5 * (h2 - h1)
    with np.errstate(divide="ignore", invalid="ignore"):
        low = (t + half_sum) ** 2 / (2.0 * h1 * h2)
        high = 1.0 - (half_sum - t) ** 2 / (2.0 * h1 * h2)
    fraction = np.where(t < -half_diff, low, np.where(t > half_diff, high, 0.5 + t / h2))
    return np.clip(np.where(t <= -half_sum, 0.0, np.where(t >= half_sum, 1.0, fraction)), 0.0, 1.0)


def _line_function(h: np.ndarray, plane: _BoardInCamera, line: np.ndarray, x4: np.ndarray, y4: np.ndarray):
    """(c, p, q), each (m,): g = c + p x + q y over the pixel square [-0.5, 0.5]^2 (x right, y down),
    negative on the low side of the board line {a = line} (h = ha) or {b = line} (h = hb).

    The line is exactly straight in normalized coordinates, where g(r) = sign(n.o) (h - line n) . r;
    x4, y4 (4, m) are the normalized coordinates of the pixel corners (top-left, top-right,
    bottom-left, bottom-right), and g is linear over the pixel up to the distortion's curvature.
    """
    hh = h[None, :] - line[:, None] * plane.n[None, :]
    g4 = np.sign(plane.no) * (hh[:, 0] * x4 + hh[:, 1] * y4 + hh[:, 2])
    c = g4.mean(axis=0)
    p = 0.5 * ((g4[1] - g4[0]) + (g4[3] - g4[2]))
    q = 0.5 * ((g4[2] - g4[0]) + (g4[3] - g4[1]))
    return c, p, q


def _clipped_square_area(half_planes) -> np.ndarray:
    """Area (m,) of the pixel square [-0.5, 0.5]^2 where every c + p x + q y < 0 (vectorized
    Sutherland-Hodgman; polygons are padded by repeating their first vertex)."""
    c0 = half_planes[0][0]
    m = len(c0)
    poly = np.broadcast_to(np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]), (m, 4, 2)).copy()
    rows = np.arange(m)[:, None]
    for c, p, q in half_planes:
        value = c[:, None] + p[:, None] * poly[:, :, 0] + q[:, None] * poly[:, :, 1]
        nxt = np.roll(poly, -1, axis=1)
        value_next = np.roll(value, -1, axis=1)
        inside, inside_next = value < 0, value_next < 0
        crossing = inside != inside_next
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(crossing, value / (value - value_next), 0.0)
        cut = poly + t[:, :, None] * (nxt - poly)
        candidates = np.stack([poly, cut], axis=2).reshape(m, -1, 2)
        keep = np.stack([inside, crossing], axis=2).reshape(m, -1)
        order = np.argsort(~keep, axis=1, kind="stable")
        candidates = candidates[rows, order]
        count = keep.sum(axis=1)
        pad = np.arange(candidates.shape[1])[None, :] >= count[:, None]
        poly = np.where(pad[:, :, None], candidates[:, :1], candidates)
    x, y = poly[:, :, 0], poly[:, :, 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))


def _paint_board(image: np.ndarray, camera: Camera, cam_from_world: Rigid3, plane: _BoardInCamera,
                 bbox, black: float, white: float, supersampling: int) -> None:
    """Composite one board over `image` (float32, in place) by area coverage within `bbox`.

    Pass 1 maps every pixel corner to board coordinates (a, b). Pixels whose corners all have the
    same colour (and that are not next to a pattern vertex) are uniform. Mixed pixels crossed by
    one line of the pattern's grid, or by one a-line and one b-line (X-corners, T-junctions, outline
    corners), get their exact area split: the lines are straight in undistorted normalized
    coordinates, whose map from the pixel is affine up to the distortion's curvature over one pixel
    (< 1e-3 px even for strong wide-angle distortion); one line's area is closed-form, two lines'
    is a clipped square. The remaining mixed pixels (several parallel lines in one pixel, the
    horizon, where the lens model folds) are supersampled with s x s rays.
    """
    x0, y0, x1, y1 = bbox
    nx, ny = x1 - x0, y1 - y0
    forced = _forced_mask(camera, cam_from_world, plane.board, bbox)
    s = max(int(supersampling), 1)
    n_samples = s * s
    lines_a, lines_b = plane.edge_lines()
    delta = 1e-6 * min(np.diff(lines_a).min(), np.diff(lines_b).min())
    xs = np.arange(x0, x1 + 1, dtype=float) - 0.5  # pixel-corner abscissae
    rows_per_chunk = max(1, _MAX_CHUNK_POINTS // (nx + 1))
    pixels_per_chunk = max(1, _MAX_CHUNK_POINTS // n_samples)
    for r0 in range(0, ny, rows_per_chunk):
        r1 = min(ny, r0 + rows_per_chunk)
        ys = np.arange(y0 + r0, y0 + r1 + 1, dtype=float) - 0.5
        gu, gv = np.meshgrid(xs, ys)
        xy = camera.undistort_normalized(np.column_stack([gu.ravel(), gv.ravel()]))
        a, b, valid = plane.board_coordinates(xy)
        grid_shape = (len(ys), len(xs))
        codes = plane.codes_ab(a, b, valid).reshape(grid_shape)
        a, b, valid = a.reshape(grid_shape), b.reshape(grid_shape), valid.reshape(grid_shape)
        gx, gy = xy[:, 0].reshape(grid_shape), xy[:, 1].reshape(grid_shape)
        c00 = codes[:-1, :-1]
        mixed = (c00 != codes[:-1, 1:]) | (c00 != codes[1:, :-1]) | (c00 != codes[1:, 1:])
        if forced is True:
            mixed[:] = True
        else:
            mixed |= forced[r0:r1]
        black_fraction = (c00 == _BLACK).astype(np.float32)
        white_fraction = (c00 == _WHITE).astype(np.float32)
        iy, ix = np.nonzero(mixed)
        if len(iy):
            # Corner values, order: top-left, top-right, bottom-left, bottom-right.
            a4 = np.stack([a[iy, ix], a[iy, ix + 1], a[iy + 1, ix], a[iy + 1, ix + 1]])
            b4 = np.stack([b[iy, ix], b[iy, ix + 1], b[iy + 1, ix], b[iy + 1, ix + 1]])
            v4 = valid[iy, ix] & valid[iy, ix + 1] & valid[iy + 1, ix] & valid[iy + 1, ix + 1]
            a4 = np.where(v4, a4, 0.0)
            b4 = np.where(v4, b4, 0.0)
            a_lo, a_hi = a4.min(axis=0), a4.max(axis=0)
            b_lo, b_hi = b4.min(axis=0), b4.max(axis=0)
            first_a = np.searchsorted(lines_a, a_lo, side="right")
            first_b = np.searchsorted(lines_b, b_lo, side="right")
            count_a = np.searchsorted(lines_a, a_hi, side="left") - first_a
            count_b = np.searchsorted(lines_b, b_hi, side="left") - first_b
            # Exact areas where one line, or one a-line and one b-line, cross the pixel; no line
            # at all (a pixel examined because it is near a vertex) leaves it uniform.
            exact = v4 & (count_a <= 1) & (count_b <= 1) & (count_a + count_b >= 1)
            uniform = v4 & (count_a == 0) & (count_b == 0)
            k = np.nonzero(exact)[0]
            if len(k):
                py, px = iy[k], ix[k]
                x4 = np.stack([gx[py, px], gx[py, px + 1], gx[py + 1, px], gx[py + 1, px + 1]])
                y4 = np.stack([gy[py, px], gy[py, px + 1], gy[py + 1, px], gy[py + 1, px + 1]])
                has_a, has_b = count_a[k] == 1, count_b[k] == 1
                line_a = lines_a[np.minimum(first_a[k], len(lines_a) - 1)]
                line_b = lines_b[np.minimum(first_b[k], len(lines_b) - 1)]
                g_a = _line_function(plane.ha, plane, line_a, x4, y4)
                g_b = _line_function(plane.hb, plane, line_b, x4, y4)
                low_a = np.where(has_a, _linear_area_fraction(*g_a), 1.0)
                low_b = np.where(has_b, _linear_area_fraction(*g_b), 1.0)
                low_ab = low_a * low_b
                both = np.nonzero(has_a & has_b)[0]
                if len(both):
                    low_ab[both] = _clipped_square_area([tuple(g[both] for g in g_a), tuple(g[both] for g in g_b)])
                # The (up to) four regions: low/high side of the a-line x low/high side of the b-line.
                a_mid, b_mid = a4[:, k].mean(axis=0), b4[:, k].mean(axis=0)
                side_a = [np.where(has_a, line_a - delta, a_mid), np.where(has_a, line_a + delta, a_mid)]
                side_b = [np.where(has_b, line_b - delta, b_mid), np.where(has_b, line_b + delta, b_mid)]
                areas = {(0, 0): low_ab, (1, 0): low_b - low_ab, (0, 1): low_a - low_ab,
                         (1, 1): 1.0 - low_a - low_b + low_ab}
                black_k = np.zeros(len(k))
                white_k = np.zeros(len(k))
                ones = np.ones(len(k), dtype=bool)
                for (ia, ib), area in areas.items():
                    code = plane.codes_ab(side_a[ia], side_b[ib], ones)
                    area = np.clip(area, 0.0, 1.0)
                    black_k += area * (code == _BLACK)
                    white_k += area * (code == _WHITE)
                black_fraction[py, px] = black_k
                white_fraction[py, px] = white_k
            k = np.nonzero(uniform)[0]
            if len(k):
                # Its corners may still disagree when one lies exactly on a line: use the centre.
                code = plane.codes_ab(a4[:, k].mean(axis=0), b4[:, k].mean(axis=0), np.ones(len(k), dtype=bool))
                black_fraction[iy[k], ix[k]] = code == _BLACK
                white_fraction[iy[k], ix[k]] = code == _WHITE
            rest = np.nonzero(~exact & ~uniform)[0]
            iy, ix = iy[rest], ix[rest]
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
                       finest_px: int = 4, roughness: float = 1.0) -> np.ndarray:
    """(height, width) float32 multi-octave value noise, mean `mean`, std ~`contrast`.

    Octave amplitudes grow as spacing**roughness: 1 gives 1/f smooth clouds, smaller values keep
    more fine detail (grass, gravel, field edges) for detectors to cope with.

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
        octave = rng.standard_normal(shape, dtype=np.float32) * np.float32((spacing / spacings[0]) ** roughness)
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
    """Synthetic grayscale image (height, width) of `boards` seen by the camera: uint8, or uint16
    holding `settings.bit_depth`-bit data.

    Deterministic for a given rng state. One integer is drawn from `rng` and seeds three
    independent streams (illumination factors, background texture, noise), so adding a board that
    is not visible changes nothing else in the image.
    """
    boards = list(boards)
    key = int(rng.integers(0, 2**63 - 1))
    # Streams by index: the effects' streams (3, 4) leave the first three unchanged.
    jitter_rng, texture_rng, noise_rng, effect_rng, ground_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(key).spawn(5))
    factors = np.clip(1.0 + settings.illumination_jitter * jitter_rng.standard_normal(len(boards)), 0.7, 1.3)
    levels = np.column_stack([settings.black_level * factors, settings.white_level * factors])
    image = fractal_background(camera.height, camera.width, texture_rng, settings.background_mean,
                               settings.background_contrast, roughness=settings.background_roughness)
    if settings.ground_texture_dn > 0:
        image += effects.band_limited_noise(image.shape, ground_rng, settings.ground_texture_dn, settings.ground_grain_px)
    _paint_boards(image, camera, cam_from_world, boards, levels, settings)
    effects.occlude_and_shadow(image, camera, cam_from_world, boards, effect_rng, settings)
    if settings.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), settings.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    image = effects.blur_motion_and_defocus(image, settings)
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
    return effects.quantize(image, settings)
