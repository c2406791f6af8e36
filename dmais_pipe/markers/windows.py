"""Detection in windows of an image: exactly `detect`'s detections there, without the rest of it.

`detect` makes a saddle response over the whole half-resolution level, then tests and fits each of
its candidates on the float image about it. Both are local: a candidate depends on the level within
`detect.RESPONSE_SUPPORT_PX` of it (and the pyramid's 5 taps at full resolution), the tests and fits
of a candidate read the image within `detect.REACH_PX` of it, and a detection lies within
`detect.MOVE_PX` of its candidate. So `detect_in_windows`:

1. takes the image-wide numbers from the same pixels as `detect`: the 16-bit scale (a strided sample
   of the whole image) and the clutter of the level's tiles (`detect.tile_boxes`), each tile's level
   made from a crop about it;
2. groups the windows whose parts of the image would overlap (`groups`), and makes for each
   group one part of the float image (an 8- or 16-bit image's pixels read as float32 where they are
   read, `_raw_parts`; another's converted, `_parts`): READ_PX about its windows (the area whose candidates can give or, 2 px
   apart, remove a detection in a window, AREA_PX, and the reach of their tests and fits), its left
   edge on a multiple of ALIGN_PX and its top on an even row, so that the pyramid's pixels are the
   whole image's and OpenCV's vector loops meet every column as in the whole image (at the right
   edge of an image whose width is no multiple of the vector, its scalar tail falls on the same
   columns): the saddle response there is the whole image's, and so are the candidates;
3. runs `detect.detections` on the candidates of every group together (strongest first, as
   `candidates` orders them) on the parts as `rings.ImageParts`, read in the whole image's
   coordinates: every test and fit computes with the same values at the same coordinates
   (the bilinear samples too: a part's offset is exact in float32);
4. keeps the detections and rejections inside a window.

The result is `detect`'s detections and rejections inside the windows, to the last bit (the
rejections compared as a set), unless the whole image has more than MAX_CANDIDATES saddle peaks
(then `detect` drops its weakest that are no X over rings, which a window may keep). No full-image
float copy is made (an 8- or 16-bit image's parts are views of it; the candidates' crops converted),
and the work is that of the parts' candidates.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pandas as pd

from .detect import (DUPLICATE_PX, MOVE_PX, REACH_PX, RESPONSE_SUPPORT_PX, clutter_of_tiles, contrasts, detect,
                     detections, saddle_peaks, saddle_response, strongest, tile_boxes, uv_of)
from .rings import ImageParts, as_float_image

#: Crops start on a multiple of this many columns (OpenCV's widest vector is 16 floats of the level).
ALIGN_PX = 64
#: Full-resolution px a crop reaches beyond the candidates it gives: the response's support at half
#: resolution, doubled, and the pyramid's 2 px, with room.
CANDIDATE_PAD_PX = 2 * RESPONSE_SUPPORT_PX + 2 + 8
#: px about a window whose candidates can give (or, 2 px apart, remove) a detection in it.
AREA_PX = MOVE_PX + int(np.ceil(DUPLICATE_PX))
#: px about a window that its candidates' tests and fits read.
READ_PX = AREA_PX + REACH_PX
#: px between two groups' windows at least: their parts (READ_PX about them, the left edge moved to
#: the alignment) stay ImageParts.CELL_PX apart.
APART_PX = 2 * READ_PX + ALIGN_PX + ImageParts.CELL_PX


def detect_in_windows(image, boxes: np.ndarray, with_rejected: bool = False, seconds: dict | None = None):
    """`detect(image)`'s detections (and with `with_rejected` its rejections) whose u, v lie in one
    of the windows `boxes` (m, 4): x0, y0, x1, y1 in pixels (OpenCV convention), bounds included.
    image: (h, w) 8/16-bit grayscale. seconds, if given, receives detect_s and refine_s as `detect`'s.
    """
    seconds = {} if seconds is None else seconds
    started = time.perf_counter()
    raw = np.asarray(image)
    as_float_image(raw[:1, :1])  # the shape check of `detect`
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    if min(raw.shape) < 8:
        return _inside(detect(raw, with_rejected=True, seconds=seconds), boxes, with_rejected)
    texture = clutter_of_tiles([_level_tile(raw, box) for box in tile_boxes(_level_shape(raw.shape))])
    contrast, lit_contrast = contrasts(raw, texture)
    members = groups(boxes)
    parts = _raw_parts(raw, members)
    parts = _parts(raw, members) if parts is None else parts
    cand = _candidates(parts, members, max(contrast, lit_contrast))
    found = detections(parts, cand, contrast, lit_contrast, texture, seconds=seconds, started=started)
    return _inside(found, boxes, with_rejected)


def groups(boxes: np.ndarray) -> list[np.ndarray]:
    """The windows boxes (m, 4) in groups (k, 4) that one part of the image serves: those whose
    parts (READ_PX about them) would overlap share one, and the parts of two groups are apart."""
    parts = [box[None] for box in boxes]
    bounds = [tuple(box.tolist()) for box in boxes]  # each part's `_bounds`, as Python floats
    merged = True
    while merged:
        merged = False
        for i, j in ((i, j) for i in range(len(parts)) for j in range(i + 1, len(parts))):
            a, b = bounds[i], bounds[j]
            if a[0] - APART_PX <= b[2] and a[1] - APART_PX <= b[3] and b[0] - APART_PX <= a[2] \
                    and b[1] - APART_PX <= a[3]:
                parts[i] = np.vstack([parts[i], parts.pop(j)])
                bounds[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                bounds.pop(j)
                merged = True
                break
    return parts


def _bounds(boxes: np.ndarray) -> np.ndarray:
    """(4,) the bounding box x0, y0, x1, y1 of boxes (m, 4)."""
    return np.concatenate([boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)])


def _level_shape(shape: tuple[int, int]) -> tuple[int, int]:
    """(h, w) of cv2.pyrDown's level of an image of `shape` (h, w)."""
    return (shape[0] + 1) // 2, (shape[1] + 1) // 2


def _crop_bounds(shape, x0: float, y0: float, x1: float, y1: float, pad: int) -> tuple[int, int, int, int]:
    """(X0, Y0, X1, Y1): the columns X0..X1 - 1 and rows Y0..Y1 - 1 of an image of `shape` (h, w) that
    reach `pad` px beyond x0..x1, y0..y1 (px), X0 on a multiple of ALIGN_PX and Y0 even."""
    height, width = shape
    left = max(0, (int(np.floor(x0)) - pad) // ALIGN_PX * ALIGN_PX)
    top = max(0, (int(np.floor(y0)) - pad) // 2 * 2)
    return left, top, min(width, int(np.ceil(x1)) + pad + 1), min(height, int(np.ceil(y1)) + pad + 1)


def _level_tile(raw: np.ndarray, tile: tuple[int, int, int, int]) -> np.ndarray:
    """The level's pixels (y1 - y0, x1 - x0) of `tile` (y0, y1, x0, x1: level px) of the image raw (h, w),
    as cv2.pyrDown of the whole image has them."""
    y0, y1, x0, x1 = tile
    left, top, right, bottom = _crop_bounds(raw.shape, 2 * x0, 2 * y0, 2 * x1, 2 * y1, 4)
    level = cv2.pyrDown(raw[top:bottom, left:right].astype(np.float32))
    return level[y0 - top // 2:y1 - top // 2, x0 - left // 2:x1 - left // 2]


def _raw_parts(raw: np.ndarray, members: list[np.ndarray]) -> ImageParts | None:
    """`_parts` of an 8- or 16-bit C-ordered image raw (h, w) read where its pixels are read: the parts
    views of it, each pixel read as float32 (exact), the same boxes; none is converted before (the tests
    and fits read a small share of the parts: ~2.9 Mpx were converted for a survey-grade 12 MP image's
    8 windows, ~3 ms, a tenth of what followed its decode). None for other images."""
    if raw.dtype not in (np.uint8, np.uint16) or not raw.flags.c_contiguous:
        return None
    return ImageParts([_crop_bounds(raw.shape, *_bounds(boxes), READ_PX) for boxes in members], raw.shape, raw=raw)


def _parts(raw: np.ndarray, members: list[np.ndarray]) -> ImageParts:
    """The float image of raw (h, w) READ_PX about each group of windows (k, 4): ImageParts, each part
    the bounding box of its group's. Only the pixels READ_PX about one of the windows are converted
    (`_union`: where windows far apart share a part, much of its box lies beyond), for no test or fit
    reads beyond them (the bound at which the parts of two groups end); the rest stays unwritten."""
    parts = ImageParts([_crop_bounds(raw.shape, *_bounds(boxes), READ_PX) for boxes in members], raw.shape)
    for pixels, top, left, boxes in zip(parts.pixels, parts.tops, parts.lefts, members):
        for x0, y0, x1, y1 in _union([_crop_bounds(raw.shape, *box, READ_PX) for box in boxes]):
            pixels[y0 - top:y1 - top, x0 - left:x1 - left] = raw[y0:y1, x0:x1]
    return parts


def _union(rects: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Disjoint rectangles (x0, y0, x1, y1: columns x0..x1 - 1, rows y0..y1 - 1) that cover the union of
    rects: per band between their rows' ends, its columns' runs."""
    rows = sorted({r[1] for r in rects} | {r[3] for r in rects})
    out = []
    for top, bottom in zip(rows[:-1], rows[1:]):
        runs = sorted((r[0], r[2]) for r in rects if r[1] <= top and r[3] >= bottom)
        for x0, x1 in runs:
            if out and out[-1][1] == top and out[-1][3] == bottom and x0 <= out[-1][2]:
                out[-1] = (out[-1][0], top, max(out[-1][2], x1), bottom)
            else:
                out.append((x0, top, x1, bottom))
    return out


def _candidates(parts: ImageParts, members: list[np.ndarray], min_contrast: float) -> np.ndarray:
    """(k, 2) `detect.candidates` within AREA_PX of the windows (each group's (k_i, 4) served by its
    part), strongest first: each window's from the part's pixels CANDIDATE_PAD_PX about that area,
    where the saddle response is the whole image's."""
    xs, ys, strengths = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros(0, np.float32)]
    for pixels, top, left, boxes in zip(parts.pixels, parts.tops, parts.lefts, members):
        for x0, y0, x1, y1 in boxes + [-AREA_PX, -AREA_PX, AREA_PX, AREA_PX]:
            a, b, c, d = _crop_bounds(parts.shape, x0, y0, x1, y1, CANDIDATE_PAD_PX)  # within the part
            crop = pixels[b - top:d - top, a - left:c - left].astype(np.float32, copy=False)  # raw parts: converted
            y, x, strength = saddle_peaks(saddle_response(cv2.pyrDown(crop)), min_contrast)
            x, y = a + 2 * x, b + 2 * y
            keep = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            xs.append(x[keep]), ys.append(y[keep]), strengths.append(strength[keep])
    x, y, strength = np.concatenate(xs), np.concatenate(ys), np.concatenate(strengths)
    _, first = np.unique(y * parts.shape[1] + x, return_index=True)  # windows overlap
    return strongest(x[first], y[first], strength[first])


def _inside(found: tuple[pd.DataFrame, pd.DataFrame], boxes: np.ndarray, with_rejected: bool):
    """The detections (and rejections) of `found` whose u, v lie in one of the windows boxes (m, 4)."""
    kept = []
    for frame in found:
        uv = uv_of(frame)
        inside = ((uv[:, None, 0] >= boxes[None, :, 0]) & (uv[:, None, 1] >= boxes[None, :, 1])
                  & (uv[:, None, 0] <= boxes[None, :, 2]) & (uv[:, None, 1] <= boxes[None, :, 3])).any(axis=1)
        kept.append(frame[inside].reset_index(drop=True))
    return tuple(kept) if with_rejected else kept[0]
