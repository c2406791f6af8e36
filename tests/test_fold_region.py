"""An OpenCV-model calibration whose polynomial folds back inside the image but beyond its
observations (issue 42, item 1): accepted with its one-to-one region (warning, JSON, report), refused
only where observations reach within Plausibility.fold_margin of the fold. The lens is the issue's
(OpenCV's stereo sample, left camera: k1 -0.3162, k2 0.2226, k3 -0.1626), seen by a seeded 3-D field
out to a chosen share of its fold's undistorted radius."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.calib.intrinsics import Plausibility, calibrate_camera, check_plausible
from dmais_pipe.camera import Camera
from dmais_pipe.dataset import write_dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3
from dmais_pipe.report.html import intrinsics_table
from dmais_pipe.stages import intrinsics
from dmais_pipe.workspace import Workspace

LENS = Camera(535.0, 535.4, 330.0, 240.0, -0.3162, 640, 480, "opencv", k2=0.2226, p1=0.0011, p2=0.0002, k3=-0.1626)


def views_within(reach: float, n_views: int, seed: int, noise: float = 0.1):
    """A 3-D field (150, 3) and per view {image: (rows (n,), pixels (n, 2))} of the points LENS images
    2 px or more inside the image whose rays lie within `reach` of the fold's radius (Camera.fold_reach)."""
    rng = np.random.default_rng(seed)
    field = rng.uniform([-1.5, -1.0, -0.75], [1.5, 1.0, 0.75], size=(150, 3))
    views = {}
    while len(views) < n_views:
        pose = Rigid3(Rotation.from_euler("xyz", rng.uniform(-0.4, 0.4, 3)).as_matrix(),
                      np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(1.6, 2.6)]))
        points = pose.apply(field)
        xy = points[:, :2] / points[:, 2:]
        uv = LENS.project(points)
        seen = np.flatnonzero((points[:, 2] > 0) & (LENS.fold_reach(xy) <= reach)
                              & LENS.in_image(np.nan_to_num(uv, nan=-1e9), margin=2))
        if len(seen) >= 40:
            uv = uv[seen]
            views[f"view{len(views)}"] = (seen, uv + rng.normal(scale=noise, size=uv.shape))
    return field, views


def calibrated(reach: float, seed: int, n_eval: int = 2):
    field, views = views_within(reach, 10, seed)
    names = list(views)
    calib, held = names[:-n_eval], names[-n_eval:]
    return calibrate_camera({k: field[views[k][0]] for k in calib}, {k: views[k][1] for k in calib}, 640, 480,
                            eval_points_world_per_image={k: field[views[k][0]] for k in held},
                            eval_uv_per_image={k: views[k][1] for k in held}, name="left", model="opencv")


def test_the_issues_lens_folds_in_the_image_corners():
    region = LENS.one_to_one_region()
    assert LENS.folds_in_image and 1.0 < region.undistorted_radius < 1.01  # the issue: 1.006
    assert 0.99 < region.image_fraction < 1.0 and 390 < region.radius_px < 400  # distorted radius 0.744 x 535 = 398
    assert LENS.fold_reach(np.array([[0.0, region.undistorted_radius * 0.9]]))[0] == pytest.approx(0.9, rel=1e-12)
    assert LENS.fold_reach(np.array([[0.0, 1.1]]))[0] > 1 and LENS.fold_reach(np.zeros((1, 2)))[0] == 0.0
    assert Camera(535.0, 535.0, 320.0, 240.0, 0.1, 640, 480, "opencv").fold_reach(np.ones((1, 2)))[0] == 0.0


def test_a_calibration_folding_beyond_its_observations_is_accepted_with_its_region(caplog):
    """Rays out to 60% of the fold's radius (the issue's photographs: distorted radius 0.525 of 0.744,
    undistorted 0.575 of 1.006): the fitted model folds in the corners as the lens does, and is
    accepted with a warning naming the region in pixels and per cent of the image."""
    result = calibrated(0.6, seed=4211)
    assert result.camera.folds_in_image and result.eps_calib_px < 0.16
    assert 0.5 < max(result.fold_reach.values()) <= 0.7
    with caplog.at_level("WARNING"):
        check_plausible(result, 535.0, Plausibility())
    region = result.one_to_one
    assert f"one-to-one within {region.radius_px:.0f} px of the principal point, {region.image_fraction:.1%} of " \
           "the image" in caplog.text and "beyond its observations" in caplog.text
    assert result.to_dict()["one_to_one"] == {**region.to_dict(), "observed_reach": max(result.fold_reach.values())}
    assert abs(region.undistorted_radius / LENS.one_to_one_region().undistorted_radius - 1) < 0.05


def test_a_calibration_whose_observations_reach_near_the_fold_is_refused():
    """Rays out to 97% of the fold's radius: within the 10% margin, refused naming the reach."""
    result = calibrated(0.97, seed=4212)
    assert result.camera.folds_in_image and max(result.fold_reach.values()) > 0.9
    with pytest.raises(DmaisError, match=r"^camera left: calibration refused, its opencv distortion \(k1 -0\.3\d+ .*\) "
                                         r"folds back inside the image at the observations \(one-to-one within \d+ px "
                                         r".*the farthest observation's ray at 9\d% of the fold's radius, .*limit 90%\)"):
        check_plausible(result, 535.0, Plausibility())
    check_plausible(result, 535.0, Plausibility(fold_margin=0.0))  # the margin is what refused it


def test_the_stage_writes_the_region_and_the_report_shows_it(tmp_path):
    field, views = views_within(0.6, 10, seed=4211)
    images = [{"image": k, "camera": "left", "stage": "intrinsics", "split": "calib" if i < 8 else "eval", "path": ""}
              for i, k in enumerate(views)]
    observations = pd.concat([pd.DataFrame({"image": k, "point_id": [f"p{r}" for r in rows], "u": uv[:, 0],
                                            "v": uv[:, 1]}) for k, (rows, uv) in views.items()])
    points = pd.DataFrame(field, columns=["x", "y", "z"],
                          index=pd.Index([f"p{k}" for k in range(len(field))], name="point_id"))
    manifest = {"name": "fold", "reference_camera": "left",
                "cameras": {"left": {"width": 640, "height": 480, "focal_px": 535.0, "model": "opencv"}}}
    write_dataset(tmp_path / "dataset", manifest, points, pd.DataFrame(images), observations=observations)
    workspace = Workspace.open(tmp_path / "dataset", tmp_path / "results")
    intrinsics.run_cameras(workspace, ["left"], intrinsics.CONFS["ours"])
    camera, record = workspace.load_intrinsics("left")
    assert record["one_to_one"]["radius_px"] == pytest.approx(camera.one_to_one_region().radius_px)
    row = intrinsics_table([record]).iloc[0]
    assert row["one_to_one"] == (f"{record['one_to_one']['radius_px']:.0f} px, "
                                 f"{record['one_to_one']['image_fraction']:.1%} of the image, observations to "
                                 f"{record['one_to_one']['observed_reach']:.0%} of the fold's radius")
    assert np.isnan(camera.undistort(np.array([[-0.5, -0.5]]))).all()  # the corner farthest from (cx, cy)
    assert np.isfinite(camera.undistort(np.array([[camera.cx - 0.95 * record["one_to_one"]["radius_px"],
                                                   camera.cy]]))).all()
