"""Refinement per regime against cv2.cornerSubPix, uncertainty, rejection, aerial effects and real photographs."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.special import ndtr

from dmais_pipe.markers import detect
from dmais_pipe.bench.marker_photos import PHOTOS, SUITE_PHOTOS, board_corners
from dmais_pipe.bench.marker_regimes import corner_sub_pix
from dmais_pipe.markers.refine import refine_corners
from dmais_pipe.bench.marker_scenes import marker_scene, regime_settings, starts
from dmais_pipe.sim import effects
from dmais_pipe.sim.effects import disc_kernel, motion_kernel


def errors(size, tilt, blur, noise, seed, images=2):
    """Our and cornerSubPix's (best of window half-sizes 3, 5, 11) errors (n,) and our corners."""
    rng = np.random.default_rng(seed)
    ours, theirs, fits = [], {h: [] for h in (3, 5, 11)}, []
    for _ in range(images):
        image, truth, _ = marker_scene(rng, size, tilt, regime_settings(blur, noise))
        start = starts(truth, rng)
        corners = refine_corners(image, start)
        ours.append(np.linalg.norm(corners.uv - truth, axis=1))
        fits.append(corners)
        for h in theirs:
            theirs[h].append(np.linalg.norm(corner_sub_pix(image, start, h) - truth, axis=1))
    best = min(np.sqrt(np.mean(np.concatenate(v) ** 2)) for v in theirs.values())
    return np.concatenate(ours), best, fits


@pytest.mark.parametrize("size, tilt, blur, noise", [(28, 60, 1.5, 5.0), (20, 0, 2.0, 5.0), (120, 0, 1.5, 5.0),
                                                     (40, 65, 2.0, 1.0)])
def test_refinement_beats_corner_sub_pix_in_hard_regimes(size, tilt, blur, noise):
    """The issue's cases: a 28 px marker at 60 deg (0.88 px off before), 100-180 px under 1.5 px blur."""
    ours, best, _ = errors(size, tilt, blur, noise, seed=size + tilt)
    kept = ours[np.isfinite(ours)]
    assert len(kept) >= 0.9 * len(ours)
    assert np.sqrt(np.mean(kept**2)) <= best
    assert kept.max() < 0.3


def test_uncertainty_predicts_the_error():
    """sigma_px from the fit's residual is the size of the actual error: the normalized errors of
    many corners (noise 5 DN, blur 1.3 px) have an RMS near 1 per axis."""
    ours, _, fits = errors(40, 45, 1.3, 5.0, seed=3, images=4)
    sigma = np.concatenate([c.sigma_px for c in fits])
    ok = np.isfinite(ours)
    normalized = ours[ok] / (np.sqrt(2.0) * sigma[ok])  # distance over per-axis sigma of 2D error
    assert 0.5 < np.sqrt(np.mean(normalized**2)) < 2.0
    # less noise, smaller uncertainty
    _, _, quiet = errors(40, 45, 1.3, 1.0, seed=3, images=1)
    assert np.nanmedian(quiet[0].sigma_px) < 0.5 * np.nanmedian(sigma)
    blur = np.concatenate([c.blur_px for c in fits])
    assert np.all(np.abs(blur[ok] - np.hypot(1.3, 0.29)) < 0.4)  # the fitted blur: PSF and pixel area


def test_rejects_what_is_not_an_x_with_a_reason():
    image = np.full((120, 120), 100, np.uint8)
    image[:, 60:] = 200  # a straight edge
    cv2.rectangle(image, (20, 20), (40, 40), 30, -1)  # an L-corner at (40, 40)
    corners = refine_corners(image, [[60.0, 60.0], [40.0, 40.0], [90.0, 20.0]])
    assert np.isnan(corners.uv).all()
    assert all(reason != "" for reason in corners.reason)


def test_poor_fit_is_rejected_not_returned():
    """An occluder over the corner itself (a blob through the centre) spoils the X: rejected."""
    rng = np.random.default_rng(4)
    image, truth, _ = marker_scene(rng, 60, 0, regime_settings(1.0, 2.0))
    for u, v in truth[:3]:
        cv2.circle(image, (int(round(u + 2)), int(round(v))), 4, 120, -1)
    corners = refine_corners(image, starts(truth, rng))
    assert np.all(np.isnan(corners.uv[:3])) and all(r for r in corners.reason[:3])
    assert np.linalg.norm(corners.uv[3:] - truth[3:], axis=1).max() < 0.1


def test_detect_returns_uncertainty_and_fit_quality():
    rng = np.random.default_rng(8)
    image, truth, _ = marker_scene(rng, 50, 30, regime_settings(1.0, 3.0))
    frame = detect(image)
    assert len(frame) == len(truth)
    assert (frame["sigma_px"] > 0).all() and (frame["sigma_px"] < 0.1).all()
    assert (frame["fit_residual"] > 0).all() and (frame["fit_residual"] < 0.08).all()


# ------------------------------------------------------------------------------ aerial effects


def test_effect_kernels_are_centred_and_normalized():
    for kernel in (motion_kernel(3.0, 20.0), motion_kernel(1.0, 0.0), disc_kernel(2.0)):
        assert kernel.sum() == pytest.approx(1.0, abs=1e-5)
        k = kernel.shape[0] // 2
        ys, xs = np.mgrid[-k:k + 1, -k:k + 1]
        assert abs((kernel * xs).sum()) < 1e-5 and abs((kernel * ys).sum()) < 1e-5  # no shift of the image
    moving = motion_kernel(3.0, 0.0)
    assert np.count_nonzero(moving.sum(axis=1) > 1e-6) == 1  # horizontal motion: one row


@pytest.mark.parametrize("options", [{"motion_blur_px": 3.0, "motion_direction_deg": 20.0}, {"jpeg_quality": 60},
                                     {"ground_texture_dn": 25.0, "ground_grain_px": 1.0}, {"bit_depth": 12},
                                     {"occlusion_fraction": 1.0}, {"defocus_px": 2.0}, {"vignetting": 0.3}])
def test_detection_under_aerial_effects(options):
    """Every marker found, no false detection, sub-pixel accuracy kept, under each effect."""
    rng = np.random.default_rng(11)
    settings = replace(regime_settings(1.2, 3.0), **options)
    image, truth, _ = marker_scene(rng, 45, 35, settings)
    assert image.dtype == (np.uint16 if options.get("bit_depth", 8) > 8 else np.uint8)
    frame = detect(image)
    uv = frame[["u", "v"]].to_numpy()
    distance, _ = cKDTree(uv).query(truth)
    assert len(uv) == len(truth) and distance.max() < 0.15


def test_effects_are_off_by_default_and_seeded():
    rng = lambda: np.random.default_rng(5)  # noqa: E731
    base = regime_settings(1.0, 2.0)
    plain = marker_scene(rng(), 40, 20, base)[0]
    assert np.array_equal(plain, marker_scene(rng(), 40, 20, base)[0])
    shadowed = marker_scene(rng(), 40, 20, replace(base, shadow_fraction=1.0))[0]
    assert np.array_equal(shadowed, marker_scene(rng(), 40, 20, replace(base, shadow_fraction=1.0))[0])
    assert not np.array_equal(plain, shadowed)
    assert shadowed.mean() < plain.mean()  # shadows only take light away
    textured = marker_scene(rng(), 40, 20, replace(base, ground_texture_dn=25.0))[0].astype(float)
    high = lambda im: im - cv2.GaussianBlur(im, (0, 0), 3.0)  # noqa: E731
    assert high(textured)[:20].std() > 1.5 * high(plain.astype(float))[:20].std()  # after the 1 px optical blur


def test_overlapping_shadows_darken_once():
    """Two shadows over the same ground take the direct sun once: nowhere less than 1 - depth of
    the light (large markers, whose shadows overlap their neighbours'; no noise)."""
    settings = regime_settings(1.0, 0.0)
    plain = marker_scene(np.random.default_rng(2), 150, 10, settings)[0].astype(float)
    shaded = marker_scene(np.random.default_rng(2), 150, 10, replace(settings, shadow_fraction=1.0))[0].astype(float)
    lit = plain > 60  # where rounding to 8 bits leaves the ratio meaningful
    ratio = shaded[lit] / plain[lit]
    assert ratio.min() > 1.0 - settings.shadow_depth - 0.03
    assert np.mean(ratio < 0.5) > 0.1  # and there is shade


@pytest.mark.parametrize("edge_x", [10.2, 10.3, 10.45])
def test_shadow_edge_pixels_are_its_area_mean(edge_x):
    """A pixel of the shade map is the mean of the shade over its area, as a camera integrates it,
    not the shade at its centre (which, for a penumbra narrower than a pixel, moves the edge with
    its sub-pixel phase): a vertical edge at edge_x against a fine quadrature of each pixel."""
    settings = regime_settings(1.0, 0.0)
    shade = np.zeros((20, 30), np.float32)
    effects._shadow(shade, np.array([edge_x, 10.0]), 0.0, 40.0, settings)
    x = np.arange(30)[:, None] + np.linspace(-0.5, 0.5, 2001)[None]  # (30, 2001) within each pixel
    exact = ndtr((x - edge_x) / settings.shadow_penumbra_px).mean(axis=1)
    assert np.abs(shade[10] - exact).max() < 0.01


def in_the_shade(sharp, truth, offset, angle_deg, depth=0.6, noise=3.0, seed=2):
    """The unblurred image sharp (h, w) with a straight shadow edge (penumbra 0.3 px, `depth`)
    `offset` px beyond each true corner (n, 2), at `angle_deg`, within 40 px of it, then blurred
    by 1.2 px (the shadow is cast before the optical blur, as in the simulator and in the sky)
    and `noise` DN added; uint8."""
    ys, xs = np.mgrid[0:sharp.shape[0], 0:sharp.shape[1]].astype(float)
    light = np.ones(sharp.shape)
    normal = np.radians(angle_deg)
    for u, v in truth:
        near = np.hypot(xs - u, ys - v) < 40
        beyond = np.cos(normal) * (xs - u) + np.sin(normal) * (ys - v) - offset
        light[near] = 1.0 - depth * ndtr(beyond[near] / 0.3)
    blurred = cv2.GaussianBlur(sharp * light, (0, 0), 1.2, borderType=cv2.BORDER_REFLECT)
    noisy = blurred + np.random.default_rng(seed).normal(0.0, noise, sharp.shape)
    return np.clip(noisy + 0.5, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def quiet_scene():
    """Six 45 px markers foreshortened by 30 deg, blur 1.2 px, no noise (each test adds its own)."""
    image, truth, _ = marker_scene(np.random.default_rng(4), 45, 30, regime_settings(1.2, 0.0))
    return image.astype(float), truth


@pytest.fixture(scope="module")
def sharp_scene(quiet_scene):
    """The quiet scene unblurred (`in_the_shade` blurs it after casting its shadows)."""
    image, truth, _ = marker_scene(np.random.default_rng(4), 45, 30, regime_settings(0.0, 0.0))
    assert np.array_equal(truth, quiet_scene[1])
    return image.astype(float), truth


@pytest.mark.parametrize("light", [0.4, 0.3])
def test_markers_wholly_in_the_shade_are_detected(quiet_scene, light):
    """A marker in the shade keeps ~40% of its contrast: below the fixed 50 DN of before, above
    the threshold set from the quiet image's clutter."""
    image, truth = quiet_scene
    shaded = np.clip(image * light + np.random.default_rng(1).normal(0, 3.0, image.shape) + 0.5, 0, 255)
    frame = detect(shaded.astype(np.uint8))
    distance, _ = cKDTree(frame[["u", "v"]].to_numpy()).query(truth)
    assert len(frame) == len(truth) and distance.max() < 0.15


def test_contrast_threshold_follows_the_clutter():
    """Quiet ground: the floor; gravel (20 DN at 2.5 px grain, which forms X-like blobs of 40-50
    DN): the full threshold."""
    import importlib

    detection = importlib.import_module("dmais_pipe.markers.detect")
    quiet = marker_scene(np.random.default_rng(3), 40, 20, regime_settings(1.0, 3.0))[0]
    gravel = marker_scene(np.random.default_rng(3), 40, 20, replace(regime_settings(1.0, 3.0), ground_texture_dn=20.0,
                                                                     ground_grain_px=2.5))[0]
    threshold = [detection.contrast_threshold(cv2.pyrDown(im.astype(np.float32)), 1.0) for im in (quiet, gravel)]
    assert threshold == [detection.MIN_CONTRAST_FLOOR, detection.MIN_CONTRAST]


@pytest.mark.parametrize("offset", [0.0, 2.0, 4.0])
def test_shadow_edge_at_the_corner_is_fitted_or_rejected_not_shifted(sharp_scene, offset):
    """A shadow edge within 4 px of the corner: `detect` fits the corner with the edge
    (`markers.shadow`) and returns half of them or more within 0.1 px (the ring tests fail them
    all; 2, 5 and 10 of 18 at offsets 0, 2 and 4 px with the product of the blurred X and the
    blurred light as the final model, 9, 17 and 11 with the blurred product), none shifted, every
    other one rejected with a reason; `refine_corners` from starts near the truth returns each
    within 0.1 px or rejects it with a reason."""
    image, truth = sharp_scene
    found_near = rejected_near = 0
    for angle in (10.0, 70.0, 150.0):
        shaded = in_the_shade(image, truth, offset, angle)
        frame, rejected = detect(shaded, with_rejected=True)
        found = frame[["u", "v"]].to_numpy()
        if len(found):
            distance = cKDTree(truth).query(found)[0]
            assert np.all((distance < 0.1) | (distance > 5.0))  # nothing shifted, nothing new nearby
            found_near += int(np.count_nonzero(distance < 0.1))
        if len(rejected):
            rejected_near += int(np.count_nonzero(cKDTree(rejected[["u", "v"]].to_numpy()).query(truth)[0] < 3.0))
        corners = refine_corners(shaded, starts(truth, np.random.default_rng(int(angle))))
        error = np.linalg.norm(corners.uv - truth, axis=1)
        assert np.all(np.where(np.isnan(error), corners.reason != "", error < 0.1))
        assert np.count_nonzero(np.isnan(error)) >= 4
    assert found_near >= 9 and found_near + rejected_near == 18


def test_every_shadowed_marker_is_found_or_rejected_with_a_reason():
    """The effects benchmark's shadow row on a fresh seed (6 images of 6 markers, a hard shadow
    edge through each, `sim.effects`): every true corner detected within 0.1 px or rejected with a
    reason near it, none missed without a trace (before: 11 of 36 missed, recall 0.64; now 0 missed,
    recall 0.83), no wrong identification, no false detection."""
    from dmais_pipe.bench.marker_effects import EFFECTS, measure_effect

    row = measure_effect("shadow", EFFECTS["shadow"], 6, 5)
    assert row["missed"] == 0 and row["accounted"] == 1.0
    assert row["recall"] >= 0.75 and row["max_px"] < 0.1
    assert row["wrong_ids"] == 0 and row["false_per_image"] == 0.0


def test_virtual_corner_of_an_outline_and_a_shadow_edge_is_not_returned():
    """`dmais bench markers --suite effects --seed 2`, shadow row: a marker's T-junction with a
    shadow edge along its stem looks like an X (ground x 0.4 ~ the dark cell) and passed the ring
    tests; identified as the undetected marker beside it once the shadowed markers of that image
    were found. Its fit is uncertain (sigma 0.16 px; true detections <= 0.08): rejected, with the
    reason. No false detection, no wrong id in the row (2 false detections, 1 wrong id before)."""
    from dmais_pipe.bench.marker_effects import EFFECTS, measure_effect, row_seed
    from dmais_pipe.markers.detect import UNCERTAIN

    row = measure_effect("shadow", EFFECTS["shadow"], 10, row_seed(2, list(EFFECTS).index("shadow")))
    assert row["false_per_image"] == 0.0 and row["wrong_ids"] == 0 and row["recall"] >= 0.75
    assert UNCERTAIN not in row["reasons_true"]  # no true corner rejected for its uncertainty


def test_marker_outlines_are_not_taken_for_shadowed_corners():
    """Unshadowed markers on textured ground: the outline's L- and T-junctions fail the ring tests,
    and the start of the fit with a shadow edge (`shadow._best_step`: a step whose line crosses the
    X's sectors and leaves both levels on both sides in the same ratio) takes none of them: no
    rejection says a shadow edge is at a corner, and every marker is returned within 0.1 px."""
    from dmais_pipe.markers.shadow import SHADOW_REASON

    rng = np.random.default_rng(8)
    for size, tilt in ((30, 10), (60, 40), (120, 55)):
        settings = replace(regime_settings(1.1, 3.0), ground_texture_dn=20.0, ground_grain_px=1.5)
        image, truth, _ = marker_scene(rng, size, tilt, settings)
        frame, rejected = detect(image, with_rejected=True)
        assert not (rejected["reason"] == SHADOW_REASON).any()
        distance, _ = cKDTree(frame[["u", "v"]].to_numpy()).query(truth)
        assert len(frame) == len(truth) and distance.max() < 0.1


def _supersampled_x(t1_deg, t2_deg, shade_deg=None, offset=0.0, corner=(30.3, 30.15), n=61, blur=1.2, s=8):
    """(n, n) float32 render of an X-corner (levels 50 and 190, edge normals t1, t2) at `corner`,
    its light cut by 60% beyond a straight edge (normal `shade_deg`, `offset` px from the corner)
    if given: sharp X x sharp shade supersampled s x s, Gaussian blur, pixel areas (the simulator's
    order: the shadow before the optics)."""
    fine = (np.arange(n * s) + 0.5) / s - 0.5
    yy, xx = np.meshgrid(fine - corner[1], fine - corner[0], indexing="ij")
    t1, t2 = np.radians([t1_deg, t2_deg])
    sharp = 120.0 + 70.0 * np.sign(np.cos(t1) * xx + np.sin(t1) * yy) * np.sign(np.cos(t2) * xx + np.sin(t2) * yy)
    if shade_deg is not None:
        t3 = np.radians(shade_deg)
        sharp *= 1.0 - 0.6 * (np.cos(t3) * xx + np.sin(t3) * yy > offset)
    return cv2.GaussianBlur(sharp, (0, 0), blur * s).reshape(n, s, n, s).mean(axis=(1, 3)).astype(np.float32)


@pytest.mark.parametrize("name", ["shaded_model", "product_shaded_model"])
def test_shaded_model_jacobian_matches_differences(name):
    from dmais_pipe.markers import xfit

    model = getattr(xfit, name)
    rng = np.random.default_rng(0)
    params = np.array([[0.3, -0.2, 0.4, 2.0, 1.1, 100.0, 60.0, 0.7, 1.5, 0.9, 0.55]])
    # Pixels on one integer lattice about a sub-pixel centre (the product model's grid needs it).
    x, y = (rng.integers(-6, 7, (2, 1, 60)) - np.array([0.37, -0.21])[:, None, None])
    _, jac = model(params, x, y)
    for i in range(xfit.N_SHADED):
        step = np.zeros_like(params)
        step[0, i] = 1e-6
        numeric = (model(params + step, x, y, False)[0] - model(params - step, x, y, False)[0])
        assert np.allclose(jac[..., i], numeric / 2e-6, atol=1e-5 * 160.0)


@pytest.mark.parametrize("shade_deg, offset", [(70.0, 1.5), (40.0, 0.0), (160.0, 3.0)])
def test_product_shaded_model_matches_an_independent_render(shade_deg, offset):
    """`xfit.product_shaded_model` with the render's parameters (blur 1.2 px and the pixel area's
    1/12 px^2, penumbra 0.2 px for the render's sharp one) is within 0.8 DN of the supersampled
    render of `_supersampled_x` in a window of 8 px (0.2-0.63 DN measured, 0.2 of it the render's
    pixel area, no Gaussian, with no shadow at all); the product of the blurred factors
    (`shaded_model`) is ~10 DN off where the shadow edge crosses the X's edges."""
    from dmais_pipe.markers import xfit

    image = _supersampled_x(20.0, 110.0, shade_deg, offset)
    corner = np.array([[30.3, 30.15]])
    x, y, values, weights = xfit.window(image, corner, 8.0)
    x, y, inside = x - corner[:, :1], y - corner[:, 1:], weights > 0
    blur = np.hypot(1.2, np.sqrt(1.0 / 12.0))
    params = np.array([[0.0, 0.0, np.radians(20.0), np.radians(110.0), blur, 120.0, 70.0, np.radians(shade_deg),
                        offset, 0.2, 0.6]])
    product = xfit.product_shaded_model(params, x, y, False)[0]
    assert np.abs(product - values)[inside].max() < 0.8
    params[0, 9] = np.hypot(blur, 0.2)  # shaded_model's index 9: the edge's blur in the image
    assert np.abs(xfit.shaded_model(params, x, y, False)[0] - values)[inside].max() > 8.0


def test_product_fit_converges_with_the_penumbra_at_its_floor():
    """Fits of `xfit.product_shaded_model` to renders of a sharp shadow (its penumbra at the
    floor, MIN_BLUR) converge within 20 iterations, the corner within 0.06 px: the blur held at its
    floor while the step would push it below (11 of 15 converged when it was clamped instead)."""
    from dmais_pipe.markers import xfit

    noise = np.random.default_rng(7).normal(0.0, 2.0, (61, 61)).astype(np.float32)
    corner = np.array([[30.3, 30.15]])
    for shade_deg in (40.0, 70.0, 160.0, 250.0, 340.0):
        for offset in (0.0, 1.5, 3.0):
            x, y, values, weights = xfit.window(_supersampled_x(20.0, 110.0, shade_deg, offset) + noise, corner, 8.0)
            start = np.array([[0.5, -0.4, np.radians(25.0), np.radians(105.0), 1.5, 115.0, 65.0,
                               np.radians(shade_deg + 10.0), offset + 0.5, 1.0, 0.5]])
            params, _, _, converged = xfit.fit(start, x - corner[:, :1], y - corner[:, 1:], values, weights, 20,
                                               model=xfit.product_shaded_model)
            assert converged[0] and np.hypot(*params[0, :2]) < 0.06


def test_shadowed_corner_fit_on_an_independent_render():
    """`shadow.shadowed_corners` on supersampled renders of an X whose light a straight edge cuts
    0-3 px from the corner (5 directions x 3 offsets, 2 DN noise), started 1 px off: every corner
    it returns within 0.1 px, at least 9 of the 15 returned (10 measured, 6 with the product of the
    blurred factors as the final model; the ring tests of `detect` take none of them), the rest
    rejected with the reason or not started (the start, which must see both levels of the X on
    both sides of the step and its line cross the X's sectors, takes no marker outline but misses
    5 of these, the edge 1.5-3 px off); no corner from the same X unshadowed (the ring tests'
    job) nor from a straight shadow edge alone."""
    import importlib

    shadow = importlib.import_module("dmais_pipe.markers.shadow")
    noise = np.random.default_rng(7).normal(0.0, 2.0, (61, 61)).astype(np.float32)
    start = np.array([[31.0, 29.5]])
    found = 0
    for shade_deg in (40.0, 70.0, 160.0, 250.0, 340.0):
        for offset in (0.0, 1.5, 3.0):
            image = _supersampled_x(20.0, 110.0, shade_deg, offset) + noise
            uv, radius, sigma, _, reason = shadow.shadowed_corners(image, start, 25.0, 0.7, 4.0)
            if reason[0] == "":
                assert np.hypot(*(uv[0] - [30.3, 30.15])) < 0.1 and radius[0] >= 7.0 and sigma[0] < 0.1
            found += reason[0] == ""
            assert reason[0] in ("", shadow.SHADOW_REASON, None)
    assert found >= 9
    plain = _supersampled_x(20.0, 110.0) + noise
    assert shadow.shadowed_corners(plain, start, 25.0, 0.7, 4.0)[4][0] != ""
    ys, xs = np.mgrid[0:61, 0:61]
    edge = 150.0 * (1.0 - 0.6 * ndtr((np.cos(1.0) * (xs - 30.3) + np.sin(1.0) * (ys - 30.15)) / 1.2)) + noise
    assert shadow.shadowed_corners(edge.astype(np.float32), start, 25.0, 0.7, 4.0)[4][0] != ""


def test_refinement_refits_a_corner_beside_a_shadow_edge(sharp_scene):
    """`refine_corners` from starts near the truth, a shadow edge 3-5 px beyond the corners: the
    corners it returns (15 of 54; the rest rejected as asymmetric) are all within 0.05 px, their
    plain fits replaced by the fit with the edge in the model (0.05-0.14 px off before)."""
    image, truth = sharp_scene
    returned = 0
    for offset in (3.0, 4.0, 5.0):
        for angle in (35.0, 100.0, 160.0):
            corners = refine_corners(in_the_shade(image, truth, offset, angle),
                                     starts(truth, np.random.default_rng(int(angle))))
            error = np.linalg.norm(corners.uv - truth, axis=1)
            assert np.all(np.where(np.isnan(error), corners.reason != "", error < 0.05))
            returned += int(np.count_nonzero(np.isfinite(error)))
    assert returned >= 12


def test_shadow_edge_off_the_corner_does_not_shift_it(sharp_scene):
    """A shadow edge 6 px from the corner, inside the window the marker allows: the window is cut
    to the part that is point symmetric about the corner; every corner within 0.1 px (0.15-0.2 px
    off before)."""
    image, truth = sharp_scene
    for angle in (35.0, 100.0):
        shaded = in_the_shade(image, truth, 6.0, angle)
        distance, _ = cKDTree(detect(shaded)[["u", "v"]].to_numpy()).query(truth)
        assert distance.max() < 0.1
        corners = refine_corners(shaded, starts(truth, np.random.default_rng(int(angle))))
        assert np.linalg.norm(corners.uv - truth, axis=1).max() < 0.1


# ------------------------------------------------------------------------------ real photographs


@pytest.fixture(scope="module")
def photos():
    return [cv2.imread(str(PHOTOS / name), cv2.IMREAD_GRAYSCALE) for name in SUITE_PHOTOS]


def test_detection_recall_on_real_x_junctions(photos):
    """OpenCV's chessboard photographs: the 54 inner corners (findChessboardCorners + cornerSubPix)
    of each are detected, within 0.5 px of OpenCV's, and they score higher than anything else found."""
    found = total = 0
    for image in photos:
        corners = board_corners(image)
        corners = corner_sub_pix(image, corners, 5)
        frame = detect(image)
        uv = frame[["u", "v"]].to_numpy()
        distance, index = cKDTree(uv).query(corners)
        hit = distance < 0.5
        found += hit.sum()
        total += len(corners)
        others = cKDTree(corners).query(uv)[0] >= 1.5  # clutter: keyboards, stripes, window frames
        if others.any():
            assert frame["score"].to_numpy()[others].max() < frame["score"].to_numpy()[index[hit]].min()
    assert len(photos) == 10 and found >= 0.99 * total


def test_real_photo_corners_fit_the_camera_better_than_corner_sub_pix():
    from dmais_pipe.bench.marker_photos import bench_photos

    table = bench_photos().set_index("method")
    assert table.loc["refine", "corners"] >= 530
    for other in ("cornerSubPix win 11", "cornerSubPix win 23"):
        assert table.loc["refine", "median_px"] < table.loc[other, "median_px"]
        assert table.loc["refine", "p95_px"] < table.loc[other, "p95_px"]


def test_symmetric_centre_of_a_shadowed_x_from_a_far_candidate():
    """`shadow.symmetric_centre` (where a shadowed X is rejected) from candidates 3-4 px off the
    corner of independent renders of an X whose light a straight edge cuts 0-3 px from the corner:
    within 1.5 px of the corner (0.15-1.4 px measured; the benchmark counts a rejection within 3 px
    of a true corner, and the candidates and fits of its misses were 3.2-4.2 px off): the shade adds
    little more than a constant to the log ring's point-symmetric part."""
    import importlib

    shadow = importlib.import_module("dmais_pipe.markers.shadow")
    noise = np.random.default_rng(9).normal(0.0, 2.0, (61, 61)).astype(np.float32)
    corner = np.array([30.3, 30.15])
    rng = np.random.default_rng(3)
    for shade_deg in (40.0, 160.0, 250.0):
        for offset in (0.0, 1.5, 3.0):
            image = _supersampled_x(20.0, 110.0, shade_deg, offset) + noise
            angle = rng.uniform(0.0, 2.0 * np.pi, 4)
            far = corner + rng.uniform(3.0, 4.0, (4, 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
            centre = shadow.symmetric_centre(image, far)
            assert np.hypot(*(centre - corner).T).max() < 1.5


def test_shadowed_x_from_far_candidates_is_fitted_or_rejected_near_it():
    """`shadow.shadowed_corners` from candidates 2-3.5 px off the corner of independent renders of
    a shadowed X (5 directions x 3 offsets of the edge, 4 candidates each): every corner returned
    within 0.1 px, every rejection within 3 px of the corner (at its symmetric centre), and 34 of
    the 60 traced (measured; 24 before the start about the symmetric centre, which rejects without
    a fit where neither the candidate nor its centring starts one)."""
    import importlib

    shadow = importlib.import_module("dmais_pipe.markers.shadow")
    noise = np.random.default_rng(9).normal(0.0, 2.0, (61, 61)).astype(np.float32)
    corner = np.array([30.3, 30.15])
    rng = np.random.default_rng(3)
    traced = 0
    for shade_deg in (40.0, 70.0, 160.0, 250.0, 340.0):
        for offset in (0.0, 1.5, 3.0):
            image = _supersampled_x(20.0, 110.0, shade_deg, offset) + noise
            angle = rng.uniform(0.0, 2.0 * np.pi, 4)
            far = corner + rng.uniform(2.0, 3.5, (4, 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
            uv, _, _, _, reason = shadow.shadowed_corners(image, far, 25.0, 0.7, 4.0)
            distance = np.hypot(*(uv - corner).T)
            fitted, rejected = reason == "", reason == shadow.SHADOW_REASON
            assert np.all(distance[fitted] < 0.1) and np.all(distance[rejected] < 3.0)
            traced += int(np.count_nonzero(fitted | rejected))
    assert traced >= 34


def _shadow_row_scene(seed: int, index: int, noise_free: bool = False):
    """(image, truth) of image `index` of the shadow row of `dmais bench markers --suite effects
    --seed seed` (of its noise-free twin if `noise_free`)."""
    from itertools import islice

    from dmais_pipe.bench.marker_effects import EFFECTS, effect_scenes, row_seed

    options = {**EFFECTS["shadow"], "read_noise_dn": 0.0} if noise_free else EFFECTS["shadow"]
    scenes = effect_scenes(options, index + 1, row_seed(seed, list(EFFECTS).index("shadow")))
    image, truth, _, _ = next(islice(scenes, index, None))
    return image, truth


def test_window_stops_before_a_shadow_edge_whose_misfit_inflates_the_noise():
    """`dmais bench markers --suite effects --seed 107`, the shadow row's noise-free twin, image 9,
    corner 0: a shadow edge 14 px from a low-contrast corner (68 DN) crossed its 25 px window. The
    symmetry test allowed 2 x the fit's residual for noise, and that residual was the edge's misfit
    (0.079 of the contrast on a noise-free image): the corner came out 0.118 px off, with a sigma
    of 0.028. With the noise taken from the most symmetric ring the window stops
    before the edge: within 0.02 px (0.005 measured)."""
    from dmais_pipe.markers.refine import symmetric_radius

    image, truth = _shadow_row_scene(107, 9, noise_free=True)
    corners = refine_corners(image, truth[:1] + 0.3)
    assert np.linalg.norm(corners.uv[0] - truth[0]) < 0.02 and corners.window_px[0] < 14.0
    # The fit's residual over the 25 px window, 5.4 DN, let the asymmetry of the rings past the edge pass.
    centre = truth[:1].astype(float)
    assert symmetric_radius(image.astype(np.float32), centre, np.array([68.0]), np.array([5.4]), np.array([25.0]))[0] < 14.0


def test_noise_free_shadow_row_is_the_shadow_rows_scenes_and_its_own_target(monkeypatch):
    """The effects table's last row repeats the shadow row's scenes without read noise (the same
    markers: same truth, images apart by noise only), stays out of the 'all' totals, and is `ok`
    only with no error beyond MAX_SHIFT_PX."""
    from itertools import islice

    from dmais_pipe.bench import marker_effects as bench_effects
    from dmais_pipe.bench.marker_effects import EFFECTS, NOISE_FREE_SHADOW, bench_effects as table, effect_scenes

    noisy = next(islice(effect_scenes(EFFECTS["shadow"], 1, 3), 0, None))
    clean = next(islice(effect_scenes({**EFFECTS["shadow"], "read_noise_dn": 0.0}, 1, 3), 0, None))
    np.testing.assert_array_equal(noisy[1], clean[1])
    assert 1.0 < np.std(noisy[0].astype(float) - clean[0]) < 6.0
    effects = {"none": EFFECTS["none"], "shadow": EFFECTS["shadow"]}
    frame = table(images=2, seed=4, effects=effects).set_index("effect")
    assert list(frame.index) == ["none", "shadow", "all", NOISE_FREE_SHADOW]
    assert frame.loc["all", "n_true"] == frame.loc["none", "n_true"] + frame.loc["shadow", "n_true"]
    assert frame.loc[NOISE_FREE_SHADOW, "max_px"] < 0.1
    monkeypatch.setattr(bench_effects, "MAX_SHIFT_PX", 0.0)
    strict = table(images=2, seed=4, effects=effects).set_index("effect")
    assert not strict.loc[NOISE_FREE_SHADOW, "ok_with_reasons"]
    assert (strict.drop(NOISE_FREE_SHADOW)["ok_with_reasons"] == frame.drop(NOISE_FREE_SHADOW)["ok_with_reasons"]).all()


def test_shadowed_corner_beside_the_edge_is_fitted_not_shifted():
    """`dmais bench markers --suite effects --seed 53`, shadow row, image 6, corner 0: a shadow edge
    0.7 px from the corner of a small marker (blur 1.4 px, a 10 px window). The fit of the X
    beside the shadow edge leaves out a band that covers the corner and extrapolates it (0.21 px
    off, and the product of the blurred factors agreed with it); the fit of the blurred product
    finds it 0.05 px off, which the final fit in a smaller window confirms: returned by `detect`
    within 0.1 px (rejected with the reason before); every other corner of the image is returned
    (within 0.11 px: corner 4 is the ordinary fit's, 0.101 px) or rejected with a reason near it."""
    from dmais_pipe.bench.marker_effects import REJECTED_PX
    from dmais_pipe.markers.shadow import SHADOW_REASON, shadowed_corners

    image, truth = _shadow_row_scene(53, 6)
    uv, _, _, _, reason = shadowed_corners(image.astype(float), truth[:1] + 0.5, 20.0, 0.5, 4.0)
    assert reason[0] == SHADOW_REASON or np.linalg.norm(uv[0] - truth[0]) < 0.1
    frame, rejected = detect(image, with_rejected=True)
    found, _ = cKDTree(frame[["u", "v"]].to_numpy()).query(truth)
    near = cKDTree(rejected[["u", "v"]].to_numpy(dtype=float)).query(truth)[0]
    assert found[0] < 0.1
    assert np.all((found < 0.11) | (near < REJECTED_PX))


@pytest.mark.parametrize("seed, image_index, corner", [(1, 9, 5), (2, 7, 5)])
def test_corner_the_plain_fit_calls_asymmetric_is_fitted_with_the_shadow_edge(monkeypatch, seed, image_index, corner):
    """Effects bench shadow row (`--seed 1` image 9, `--seed 2` image 7): a corner whose rings pass
    the ring tests but whose plain fit `refine_corners` rejects as asymmetric (a shadow edge near
    it) is fitted with the edge in the model by `detect` and returned within 0.05 px (0.015 and
    0.019 measured); without that second chance it is only rejected."""
    import importlib

    from dmais_pipe.markers.refine import ASYMMETRIC

    detection = importlib.import_module("dmais_pipe.markers.detect")
    image, truth = _shadow_row_scene(seed, image_index)
    found = detect(image)
    assert cKDTree(found[["u", "v"]].to_numpy()).query(truth[corner])[0] < 0.05
    monkeypatch.setattr(detection, "ASYMMETRIC_REASONS", ())
    found, rejected = detect(image, with_rejected=True)
    assert cKDTree(found[["u", "v"]].to_numpy()).query(truth[corner])[0] > 2.0
    near, which = cKDTree(rejected[["u", "v"]].to_numpy(dtype=float)).query(truth[corner])
    assert near < 3.0 and rejected["reason"].iloc[which] == ASYMMETRIC


@pytest.mark.parametrize("seed, image_index, corner", [(211, 2, 2), (213, 3, 0)])
def test_shadowed_x_whose_wide_check_ring_fails_starts_on_a_narrower_one(monkeypatch, seed, image_index, corner):
    """The shadow row's noise-free twin of `dmais bench markers --suite effects --seed 211` image 2
    (a 69 px marker; the shadow edge 3 px from the corner meets an edge of the X near the check
    ring) and `--seed 213` image 3 (a 29 px marker foreshortened by 39 deg: the check ring of
    CHECK_RING_PX reaches past its outline). The start's step is not found on that ring, and the
    corner was missed without a trace; confirmed on the ring of INNER_RING_PX instead, the fit
    starts and `detect` returns the corner within 0.03 px (0.003 and 0.013 measured)."""
    import importlib

    shadow = importlib.import_module("dmais_pipe.markers.shadow")
    image, truth = _shadow_row_scene(seed, image_index, noise_free=True)
    found = detect(image)
    assert cKDTree(found[["u", "v"]].to_numpy()).query(truth[corner])[0] < 0.03
    monkeypatch.setattr(shadow, "INNER_RING_PX", shadow.CHECK_RING_PX)
    found, rejected = detect(image, with_rejected=True)
    assert cKDTree(found[["u", "v"]].to_numpy()).query(truth[corner])[0] > 2.0
    assert len(rejected) == 0 or cKDTree(rejected[["u", "v"]].to_numpy(dtype=float)).query(truth[corner])[0] > 3.0


def test_starts_only_the_narrower_ring_confirms_blame_no_shadow_on_gravel():
    """Gravel (20 DN, 2.5 px grain) forms X-like blobs whose log rings show a straight step on the
    narrower check ring: such starts whose fits fail are no shadowed X, so they are not rejected
    as one (the effects benchmark's gravel row, `--seed 202`: 13 such rejections away from every
    marker in its 10 images when they were, 1 now; 12 and 2 with `--seed 203`)."""
    from dmais_pipe.bench.marker_effects import EFFECTS, effect_scenes, row_seed
    from dmais_pipe.markers.shadow import SHADOW_REASON

    blamed = 0
    for image, truth, _, _ in effect_scenes(EFFECTS["gravel"], 10, row_seed(202, list(EFFECTS).index("gravel"))):
        frame, rejected = detect(image, with_rejected=True)
        shadowed = rejected.loc[rejected["reason"] == SHADOW_REASON, ["u", "v"]].to_numpy(dtype=float)
        if len(shadowed):
            blamed += int(np.count_nonzero(cKDTree(truth).query(shadowed)[0] >= 3.0))
        assert cKDTree(frame[["u", "v"]].to_numpy()).query(truth)[0].max() < 0.1
    assert blamed <= 2
