"""Rings of samples about a point: the primitives of the X-corner tests and starts.

An X-corner seen on a ring of samples about its centre is point symmetric, two-valued and changes
level exactly four times, at the same angles on every radius (its edges are straight lines
through the centre). `detect`, `refine` and `shadow` test candidates, choose windows and start
their fits with these.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from . import _rings

RING_SAMPLES = 48
RADII = 3.0 * 1.35 ** np.arange(14)  # ring radii probed by clean_radius: 3 ... ~150 px
#: `clean_radius` samples this many rings (points x radii) at once at most.
CLEAN_BLOCK_RINGS = 400


class ImageParts:
    """Parts of a float32 image, read in the whole image's pixel coordinates: part k (h_k, w_k) holds
    the rows tops[k].. and columns lefts[k].. of an image of `shape` (h, w), all parts in one flat
    buffer (float32 pixels the caller writes), or views of the 8- or 16-bit image itself (`raw`: its
    pixels read as float32, which is exact, where they are read, and none converted before). Indexing
    with integer arrays (`parts[ys, xs]`) and `sample` give the whole image's float32 values (the same
    arithmetic, to the last bit) wherever a part has them; a position beyond every part reads the
    nearest part's border (replicated)."""

    dtype = np.dtype(np.float32)
    ndim = 2
    #: px: the cells of the map of which part holds a position; parts must lie further apart.
    CELL_PX = 64

    def __init__(self, bounds: list[tuple[int, int, int, int]], shape: tuple[int, int], raw: np.ndarray | None = None):
        """bounds: per part (left, top, right, bottom), its columns left..right - 1 and rows top..bottom - 1.
        The pixels are written by the caller into `pixels[k]` (views of one buffer), or with raw, a
        C-ordered uint8 or uint16 image of `shape`, they are its own (`pixels[k]` views of it)."""
        self.shape = tuple(shape)
        box = np.array(bounds, dtype=int).reshape(-1, 4)
        self.lefts, self.tops = box[:, 0], box[:, 1]
        self.widths, self.heights = box[:, 2] - box[:, 0], box[:, 3] - box[:, 1]
        if raw is None:
            self.bases = np.concatenate([[0], np.cumsum(self.widths * self.heights)])
            self.buffer = np.empty(int(self.bases[-1]), dtype=np.float32)
            self.pixels = [self.buffer[b:b + h * w].reshape(h, w)
                           for b, h, w in zip(self.bases, self.heights, self.widths)]
            self.strides = self.widths  # each part's rows' stride (pixels)
        else:
            if raw.shape != self.shape or raw.dtype not in (np.uint8, np.uint16) or not raw.flags.c_contiguous:
                raise ValueError("parts of a raw image: a C-ordered uint8 or uint16 image of the parts' shape")
            self.bases = self.tops * self.shape[1] + self.lefts
            self.buffer = raw.reshape(-1)
            self.pixels = [raw[t:t + h, x:x + w] for t, x, h, w in zip(self.tops, self.lefts, self.heights, self.widths)]
            self.strides = np.full(len(box), self.shape[1], dtype=int)
        self._cells = self._owner_map() if len(box) > 1 else None

    def _owner_map(self) -> np.ndarray:
        """(h / CELL_PX, w / CELL_PX) the part that holds each cell's pixels (parts CELL_PX apart
        never share a cell), or the part nearest the cell."""
        rows, cols = (-(-np.asarray(self.shape) // self.CELL_PX)).tolist()
        centre_y, centre_x = np.meshgrid((np.arange(rows) + 0.5) * self.CELL_PX, (np.arange(cols) + 0.5) * self.CELL_PX,
                                         indexing="ij")
        reach = 0.5 * self.CELL_PX  # a cell's centre this near a part (per axis): the cell has pixels of it
        rights, bottoms = self.lefts + self.widths - 1, self.tops + self.heights - 1
        dx = np.maximum(np.maximum(self.lefts - reach - centre_x[..., None], centre_x[..., None] - rights - reach), 0)
        dy = np.maximum(np.maximum(self.tops - reach - centre_y[..., None], centre_y[..., None] - bottoms - reach), 0)
        return np.argmin(dx + dy, axis=2)

    def owners(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """(n,) the part that holds each position xs, ys (n,), or the nearest."""
        if self._cells is None:
            return np.zeros(len(xs), dtype=int)
        rows, cols = self._cells.shape
        row = np.minimum(np.maximum(np.floor_divide(ys, self.CELL_PX).astype(int), 0), rows - 1)
        return self._cells[row, np.minimum(np.maximum(np.floor_divide(xs, self.CELL_PX).astype(int), 0), cols - 1)]

    def __getitem__(self, key):
        ys, xs = np.broadcast_arrays(*key)
        if self._cells is None:  # one part
            return self.pixels[0][np.clip(ys - self.tops[0], 0, self.heights[0] - 1),
                                  np.clip(xs - self.lefts[0], 0, self.widths[0] - 1)].astype(np.float32, copy=False)
        if ys.dtype.kind in "iu" and xs.dtype.kind in "iu":  # the same pixels, by one compiled loop
            return _rings.parts_gather(self.buffer, self.bases, self.lefts, self.tops, self.widths, self.heights,
                                       self.strides, self._cells, self.CELL_PX, ys.ravel(), xs.ravel()
                                       ).reshape(xs.shape)
        return self._gathered(ys, xs)

    def _gathered(self, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """`__getitem__` of several parts in numpy (the reference of tests/test_marker_sampling.py)."""
        owner = self.owners(xs.ravel(), ys.ravel()).reshape(xs.shape)
        height, width = self.heights[owner], self.widths[owner]
        row = np.minimum(np.maximum(ys - self.tops[owner], 0), height - 1)
        column = np.minimum(np.maximum(xs - self.lefts[owner], 0), width - 1)
        return self.buffer[self.bases[owner] + row * self.strides[owner] + column].astype(np.float32, copy=False)

    def sample(self, xy: np.ndarray) -> np.ndarray:
        """`sample` at float32 positions xy (n, 2): each position's part (`owners`) sampled at its
        own coordinates x - left, y - top (exact in float32 wherever x >= left, |x| < 2^24), as
        the whole image is at x, y."""
        if self._cells is None:
            owner = np.zeros(len(xy), dtype=np.intp)
        else:
            owner = _rings.owners(xy[:, 0], xy[:, 1], self._cells, self.CELL_PX)
        return _rings.parts_sample(self.buffer, self.bases, self.lefts, self.tops, self.widths, self.heights,
                                   self.strides, owner, xy)


def as_float_image(image) -> np.ndarray | ImageParts:
    """(h, w) float32 copy/view of an 8- or 16-bit (or float) grayscale image (ImageParts as they are)."""
    if isinstance(image, ImageParts):
        return image
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"expected a (height, width) grayscale image, got shape {image.shape}")
    return image.astype(np.float32, copy=False)


def sample(image: np.ndarray | ImageParts, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of float32 `image` (or ImageParts) at pixel positions xy (..., 2);
    replicated border."""
    xy = np.asarray(xy, dtype=np.float32)
    flat = xy.reshape(-1, 2)
    values = image.sample(flat) if isinstance(image, ImageParts) else _bilinear(image, flat)
    return values.reshape(xy.shape[:-1])


def ring_sample(image: np.ndarray | ImageParts, centres: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(..., k) `sample(image, centres[..., None, :] + offsets)` at centres (..., 2) and offsets (k, 2),
    to the last bit: the positions made and sampled in one compiled loop (`_rings.ring_samples`) for a
    float32 image or ImageParts."""
    centres = np.asarray(centres, dtype=float)
    offsets = np.asarray(offsets, dtype=float)
    flat = _flat(image)
    if flat is None:
        return sample(image, centres[..., None, :] + offsets)
    out = _rings.ring_samples(*flat, centres.reshape(-1, 2), offsets.reshape(-1, 2))
    return out.reshape(centres.shape[:-1] + (len(offsets),))


def _bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n,) bilinear samples of `image` (h, w) at float32 positions xy (n, 2): cv2.remap's
    (INTER_LINEAR, BORDER_REPLICATE), in one compiled loop (`_rings.sample`) for a float32 image."""
    if image.dtype != np.float32:
        return _remap(image, xy)
    return _rings.sample(image, xy)


def _remap(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n,) float32: cv2.remap's bilinear samples of `image` (h, w) (not float32) at float32 positions xy (n, 2)."""
    flat = xy.reshape(-1, 1, 2)
    # cv2.remap is limited to SHRT_MAX rows per call.
    out = np.empty(len(flat), dtype=np.float32)
    for s in range(0, len(flat), 30000):
        out[s:s + 30000] = cv2.remap(image, flat[s:s + 30000, :, 0].copy(), flat[s:s + 30000, :, 1].copy(),
                                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
    return out


def ring_quality(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quality (m,) in [0, 1] and contrast (m,) of rings of samples (m, k) as an X-corner.

    An X-corner ring is point symmetric (opposite samples equal), two-valued, and changes level
    exactly four times. Quality = bimodality (between-class / total variance of the two levels split
    at the ring mean) x point symmetry, 0 unless there are exactly 4 transitions.
    """
    quality, high_level, low_level, _ = ring_stats(values)
    return quality, high_level - low_level


def ring_stats(values: np.ndarray):
    """quality (m,), bright level (m,), dark level (m,), bright mask (m, k) of rings (m, k):
    `_ring_stats` (numpy) to the last bit, in one compiled pass (`_rings.ring_stats`)."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape[1] == 0:
        return _ring_stats(values)
    return _rings.ring_stats(values)


def _ring_stats(values: np.ndarray):
    """`ring_stats` in numpy (the reference of tests/test_marker_sampling.py)."""
    values = np.asarray(values, dtype=np.float64)
    k = values.shape[1]
    mean = values.mean(axis=1, keepdims=True)
    high = values > mean
    transitions = np.count_nonzero(high[:, 1:] != high[:, :-1], axis=1) + (high[:, 0] != high[:, -1])
    n_high = high.sum(axis=1)
    total = ((values - mean) ** 2).sum(axis=1) + 1e-9
    mean_high = np.where(high, values, 0).sum(axis=1) / np.maximum(n_high, 1)
    mean_low = np.where(~high, values, 0).sum(axis=1) / np.maximum(k - n_high, 1)
    within = (np.where(high, values - mean_high[:, None], values - mean_low[:, None]) ** 2).sum(axis=1)
    bimodal = np.clip(1.0 - within / total, 0.0, 1.0)
    opposite = np.concatenate([values[:, k - k // 2:], values[:, :k - k // 2]], axis=1)  # np.roll by k // 2
    symmetric = np.clip(1.0 - ((values - opposite) ** 2).sum(axis=1) / (2.0 * total), 0.0, 1.0)
    quality = np.where(transitions == 4, bimodal * symmetric, 0.0)
    return quality, mean_high, mean_low, high


def half_turn(values: np.ndarray) -> np.ndarray:
    """np.roll(values, k // 2, axis=1) of rings (m, k): each ring's samples half a turn on (the same values)."""
    k = values.shape[1]
    return np.concatenate([values[:, k - k // 2:], values[:, :k - k // 2]], axis=1)


def ring_offsets(radius: float, k: int = RING_SAMPLES) -> np.ndarray:
    """(k, 2) offsets of k samples on a circle of `radius` px, half a step off the x axis."""
    return radius * _unit_ring(k)


@lru_cache(maxsize=16)
def _unit_ring(k: int) -> np.ndarray:
    """(k, 2) `ring_offsets` of radius 1 (read-only: shared by every call)."""
    angle = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    unit = np.column_stack([np.cos(angle), np.sin(angle)])
    unit.flags.writeable = False
    return unit


def clean_radius(image: np.ndarray, uv: np.ndarray, min_quality: float = 0.6,
                 radii: np.ndarray = RADII, max_first: float = 8.0) -> np.ndarray:
    """(n,) largest radius of `radii` up to which the rings around uv (n, 2) stay the same clean
    X-corner: quality >= min_quality, the same bright/dark sectors (edges are straight lines through
    the centre, so the pattern does not change with the radius) and the same two levels as the
    previous ring (the pattern: as the first clean ring, at most `max_first` px); 0 where no ring
    qualifies. Compiled per point and ring (`_rings.clean_radius`, `_clean_radius`'s numbers) for a
    float32 image or ImageParts."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    flat = _flat(image)
    if flat is None:
        return _clean_radius(image, uv, min_quality, radii, max_first)
    return _rings.clean_radius(*flat, uv, np.asarray(radii, dtype=float), _unit_ring(RING_SAMPLES),
                               float(min_quality), float(max_first))


def _flat(image) -> tuple | None:
    """(flat float32 buffer, per part its offset, left, top, width, height, row and column strides,
    the parts' cell map or None for one part, its cell px) of ImageParts or a C-ordered float32 image;
    None for other images."""
    if isinstance(image, ImageParts):
        return (image.buffer, image.bases, image.lefts, image.tops, image.widths, image.heights, image.strides,
                np.ones(len(image.widths), dtype=np.intp), image._cells, image.CELL_PX)
    image = np.asarray(image)
    if image.dtype != np.float32 or not image.flags.c_contiguous or image.size == 0:
        return None
    height, width = image.shape
    zero, size = np.zeros(1, dtype=np.intp), np.array([width, height])
    return image.reshape(-1), zero, zero, zero, size[:1], size[1:], size[:1], np.ones(1, dtype=np.intp), None, \
        ImageParts.CELL_PX


def _clean_radius(image, uv: np.ndarray, min_quality: float, radii: np.ndarray, max_first: float) -> np.ndarray:
    """`clean_radius` in numpy (the reference of tests/test_marker_sampling.py)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    result = np.zeros(n)
    started = np.zeros(n, dtype=bool)
    alive = np.ones(n, dtype=bool)
    ref_high, ref_low = np.zeros(n), np.zeros(n)
    ref_mask = np.zeros((n, RING_SAMPLES), dtype=bool)
    radii = np.asarray(radii, dtype=float)
    at = 0
    while at < len(radii) and alive.any():
        # Several radii per sampling and per `ring_stats` where the points are few: each ring's
        # numbers are its own (row by row), and the calls' overhead, not the samples, is the cost.
        block = radii[at:at + max(1, min(len(radii) - at, CLEAN_BLOCK_RINGS // int(alive.sum())))]
        at += len(block)
        rows = np.nonzero(alive)[0]
        offsets = np.concatenate([ring_offsets(radius) for radius in block])  # (b k, 2)
        values = sample(image, uv[rows, None, :] + offsets[None]).reshape(len(rows) * len(block), RING_SAMPLES)
        stats = [a.reshape((len(rows), len(block)) + a.shape[1:]) for a in ring_stats(values)]
        for j, radius in enumerate(block):
            live = alive[rows]
            idx = rows[live]
            if len(idx) == 0:
                break
            quality, high, low, mask = (a[live, j] for a in stats)
            ok = quality >= min_quality
            was = started[idx]
            contrast = np.maximum(ref_high[idx] - ref_low[idx], 1e-9)
            same = ((np.mean(mask == ref_mask[idx], axis=1) >= 0.9)
                    & (high >= ref_high[idx] - 0.25 * contrast) & (low <= ref_low[idx] + 0.25 * contrast))
            ok = np.where(was, ok & same, ok)
            first = ok & ~was
            ref_mask[idx[first]] = mask[first]
            # Levels, ring to ring: blur lets them spread with the radius, but a ring leaving the
            # board (background, outline) pulls a level back.
            ref_high[idx[ok]], ref_low[idx[ok]] = high[ok], low[ok]
            started[idx[first]] = True
            result[idx[ok]] = radius
            stop = np.where(was, ~ok, ~ok & (radius >= max_first))
            alive[idx[stop]] = False
    return result


def ring_params(start: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Model parameters (n, 7) from rings of samples values (n, k) (`ring_offsets` order) about
    start (n, 2): edge normals from its four level changes, blur 1 px, levels from the ring; NaN
    rows where the ring does not change level exactly four times."""
    params = np.full((len(start), 7), np.nan)
    k = values.shape[1]
    mean = values.mean(axis=1, keepdims=True)
    high = values > mean
    nxt = np.roll(values, -1, axis=1)
    change = high != np.roll(high, -1, axis=1)
    ok = change.sum(axis=1) == 4
    if not ok.any():
        return params
    # Sub-sample angle of each level change (the crossing of the ring mean between samples j, j+1).
    j = np.nonzero(change[ok])[1].reshape(-1, 4)
    rows = np.arange(ok.sum())[:, None]
    v0, v1 = values[ok][rows, j], nxt[ok][rows, j]
    t = np.clip((v0 - mean[ok]) / np.where(v0 == v1, 1.0, v0 - v1), 0.0, 1.0)
    angle = 2.0 * np.pi * (j + 0.5 + t) / k
    # An edge line runs through changes 0 and 2, the other through 1 and 3; normals = direction + 90 deg.
    d1 = _mean_direction(angle[:, 0], angle[:, 2] - np.pi)
    d2 = _mean_direction(angle[:, 1], angle[:, 3] - np.pi)
    params[ok] = np.column_stack([start[ok], d1 + 0.5 * np.pi, d2 + 0.5 * np.pi, np.ones(ok.sum()), mean[ok, 0],
                                  0.5 * (values[ok].max(axis=1) - values[ok].min(axis=1))])
    return params


def _mean_direction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(a) + np.sin(b), np.cos(a) + np.cos(b))
