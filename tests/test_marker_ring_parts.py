"""The compiled ring samplers' one look-up of a ring's part (`_rings.pyx`, DMAIS_RING: a ring whose
positions lie in one cell of the parts' map reads that cell's part for all of them) against the samples
made position by position (`rings.sample`: `_rings.owners`, then `_rings.parts_sample`), bit for bit:
small rings about the cells' edges, the parts' edges and the image's, rings across them, positions that
are not finite or far beyond the image."""

import numpy as np
import pytest

from dmais_pipe.markers.rings import RADII, ImageParts, _clean_radius, clean_radius, ring_offsets, ring_sample, sample


def _parts(image: np.ndarray) -> ImageParts:
    parts = ImageParts([(0, 0, 192, 180), (448, 300, 900, 700), (256, 0, 384, 64)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    return parts


@pytest.mark.parametrize("seed", range(4))
def test_small_rings_about_cell_and_part_edges_are_sampled_as_position_by_position(seed):
    rng = np.random.default_rng(100 + seed)
    image = rng.normal(100.0, 30.0, (700, 900)).astype(np.float32)
    parts = _parts(image)
    edges = np.array([0.0, 64.0, 128.0, 180.0, 192.0, 256.0, 300.0, 384.0, 448.0, 640.0, 699.0, 899.0])
    near = rng.choice(edges, (400, 2)) + rng.uniform(-4.0, 4.0, (400, 2))
    centres = np.vstack([near, rng.uniform(-10.0, 910.0, (400, 2)), np.round(near[:100])])
    centres[5] = [np.nan, 3.0]
    centres[6] = [2.0, np.inf]
    centres[7] = [1e12, 5.0]
    centres[8] = [-3e9, 64.0]
    for radius, k in ((0.5, 8), (1.0, 24), (3.5, 24), (4.0, 48), (7.5, 48), (40.0, 48)):
        offsets = ring_offsets(radius, k)
        for img in (image, parts):
            want = sample(img, centres[:, None, :] + offsets[None])
            np.testing.assert_array_equal(ring_sample(img, centres, offsets), want)


def test_clean_radius_about_cell_edges_is_numpys():
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:700, 0:900]
    image = (100.0 + rng.normal(0.0, 4.0, (700, 900)) + 60.0 * np.sign((xx - 64.3) * (yy - 128.6))).astype(np.float32)
    parts = _parts(image)
    uv = np.vstack([[[64.3, 128.6], [63.9, 127.8], [64.0, 128.0], [191.5, 179.5]],
                    [64.3, 128.6] + rng.normal(0.0, 1.0, (60, 2)), rng.uniform(0.0, 900.0, (60, 2)) * [1.0, 0.78]])
    for img in (image, parts):
        for min_quality, radii in ((0.6, RADII), (0.7, RADII[RADII < 8.0])):
            want = _clean_radius(img, uv, min_quality, radii, 8.0)
            np.testing.assert_array_equal(clean_radius(img, uv, min_quality, radii), want)
    assert _clean_radius(parts, uv[:1], 0.6, RADII, 8.0)[0] > 30.0
