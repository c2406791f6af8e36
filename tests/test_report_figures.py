"""The report's figures of the paper: fields of view on the ground, marker overlays, calibration residuals,
and the paper comparison's erratum and method labels."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3, rotation_from_euler_zyx
from dmais_pipe.report.calibration import image_eps_table
from dmais_pipe.report.footprint import angular_extent_deg, ground_footprints
from dmais_pipe.report.overlays import crop_size_px, marker_montage, pick_markers
from dmais_pipe.report.paper import PAPER_DIR, PAPER_TABLES, paper_comparisons, read_table
from dmais_pipe.rig import Rig

W, H, F = 4096, 3000, 45000.0


def pinhole(d: float = 0.0) -> Camera:
    return Camera(fx=F, fy=F, cx=(W - 1) / 2, cy=(H - 1) / 2, d=d, width=W, height=H)


def about_y(degrees: float) -> np.ndarray:
    """Rotation about the y axis (x towards z) by `degrees`."""
    return rotation_from_euler_zyx(np.radians([0.0, degrees, 0.0]))


def rig_of(rotations: dict[str, np.ndarray]) -> Rig:
    """cam_from_rig rotations, centres 10 cm apart along x."""
    cams = {name: Rigid3(R, -R @ np.array([0.1 * k, 0.0, 0.0])) for k, (name, R) in enumerate(rotations.items())}
    return Rig({name: pinhole() for name in rotations}, cams, next(iter(rotations)))


def test_angular_extent_of_a_fan_of_cameras():
    half_width = np.degrees(np.arctan((W / 2) / F))
    rig = rig_of({"C0": np.eye(3), "C1": about_y(45.0), "C2": about_y(-45.0)})
    horizontal, vertical = angular_extent_deg(rig)
    # A rotation about y shifts every ray's azimuth atan2(x, z) by the same angle.
    assert horizontal == pytest.approx(90.0 + 2 * half_width, abs=1e-9)
    assert vertical >= 2 * np.degrees(np.arctan((H / 2) / F)) - 1e-9
    single = angular_extent_deg(rig_of({"C0": np.eye(3)}))
    assert single == pytest.approx((2 * half_width, 2 * np.degrees(np.arctan((H / 2) / F))), abs=1e-9)


def test_ground_footprints_project_back_onto_the_image_corners():
    rig = rig_of({"C0": np.eye(3), "C1": about_y(40.0), "UP": rotation_from_euler_zyx(np.radians([0.0, 0.0, 120.0]))})
    looking_down = np.diag([1.0, -1.0, -1.0])  # rig z (the optical axis of C0) = world -z
    centre = np.array([10.0, 20.0, 400.0])
    rig_from_world = Rigid3(looking_down, -looking_down @ centre)
    footprints = ground_footprints(rig, rig_from_world, ground_z=25.0)
    assert footprints["UP"] is None  # looks above the horizon
    corners = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [W - 0.5, H - 0.5], [-0.5, H - 0.5]])
    for camera in ("C0", "C1"):
        ground = np.column_stack([footprints[camera], np.full(4, 25.0)])
        np.testing.assert_allclose(rig.project(camera, rig_from_world, ground), corners, atol=1e-6)
    # C0 looks straight down: its footprint is the image scaled by height / focal length around the nadir.
    np.testing.assert_allclose(footprints["C0"].mean(axis=0), centre[:2], atol=1e-6)
    width_m = np.ptp(footprints["C0"][:, 0])
    assert width_m == pytest.approx(W / F * (400.0 - 25.0), rel=1e-9)


def markers_table(points: list[tuple[float, float, str]]) -> pd.DataFrame:
    return pd.DataFrame({"u": [p[0] for p in points], "v": [p[1] for p in points], "score": 0.9,
                         "sigma_px": 0.01, "fit_residual": 0.02, "point_id": [p[2] for p in points]})


def test_crops_centre_on_the_markers_and_show_both_kinds():
    rng = np.random.default_rng(3)
    points = [(200.0 + 300.0 * k, 150.0 + 40.0 * k, f"P{k}") for k in range(6)] + [(1900.0, 1400.0, "")]
    markers = markers_table(points)
    chosen = pick_markers(markers, 3)
    assert len(chosen) == 3 and (chosen["point_id"] == "").sum() == 1
    identified = chosen[chosen["point_id"] != ""]["u"].tolist()
    assert identified == [200.0, 1700.0]  # the extremes of the identified markers, spread by u
    assert crop_size_px(markers) == int(0.8 * np.percentile(np.full(6, np.hypot(300.0, 40.0)).tolist()
                                                             + [np.hypot(1900.0 - 1700.0, 1400.0 - 350.0)], 75))
    assert crop_size_px(markers.iloc[:1]) == 400
    pixels = rng.integers(0, 4000, size=(1500, 2000), dtype=np.uint16)
    fig = marker_montage([("cam", pixels, markers)], crops=3)
    axes = fig.axes
    assert len(axes) == 4
    for ax, (_, marker) in zip(axes[1:], chosen.iterrows()):
        left, right, bottom, top = ax.images[0].get_extent()
        assert left < marker["u"] < right and top < marker["v"] < bottom
        assert ax.get_title() == (marker["point_id"] or "unidentified")


def test_per_image_eps_table_has_calibration_and_held_out_images():
    records = [{"camera": "C0", "image_eps_calib_px": {"a": 0.2, "b": 0.3}, "image_eps_eval_px": {"c": 0.4}},
               {"camera": "C1", "image_eps_calib_px": {"d": 0.1}}]
    table = image_eps_table(records)
    assert table.values.tolist() == [["C0", "a", "calib", 0.2], ["C0", "b", "calib", 0.3],
                                     ["C0", "c", "eval", 0.4], ["C1", "d", "calib", 0.1]]


def test_paper_misprint_is_corrected_and_methods_are_labelled():
    published = read_table(PAPER_DIR / "pose_methods.csv", PAPER_TABLES["pose_methods"].keys)
    assert published.set_index("group").loc["5", "eps_proj_mean_px"] == 5.148  # transcribed as printed
    conf = read_table(PAPER_DIR / "conf.csv", PAPER_TABLES["conf"].keys).set_index(["group", "subset"])
    # tab:conf's value, and the eps_ang / eps_proj ratio of groups 1-4, support 5.418.
    assert conf.loc[("5", "01234"), "eps_proj_mean_px"] == 5.418
    ratios = published["eps_ang_mean_arcmin"] / published["eps_proj_mean_px"]
    assert np.ptp(ratios[:4]) < 1e-4 and abs(0.425 / 5.418 - ratios[:4].mean()) < 2e-4 < abs(ratios[4] - ratios[:4].mean())
    ours = published.assign(eps_proj_mean_px=published["eps_proj_mean_px"] * 1.1)
    intrinsics = pd.DataFrame({"method": ["ours", "dlt_lm", "opencv"], "camera": "C0", "fx": 45000.0})
    comparisons = paper_comparisons({"pose_methods": ours, "intrinsics": intrinsics})
    rows = comparisons["pose_methods"].set_index(["group", "quantity"])
    assert rows.loc[("5", "eps_proj_mean_px"), "paper"] == 5.418
    assert "5.148" in rows.loc[("5", "eps_proj_mean_px"), "note"]
    assert (rows.drop(index=("5", "eps_proj_mean_px"))["note"] == "").all()
    labels = comparisons["intrinsics"].drop_duplicates("method").set_index("method")["ours_is"]
    assert labels["bouguet"].startswith("dlt_lm") and "not run" in labels["bouguet"]
    assert labels["babelcalib"].startswith("nothing") and labels["opencv"].startswith("opencv")
    babel = comparisons["intrinsics"][comparisons["intrinsics"]["method"] == "babelcalib"]
    assert babel["ours"].isna().all() and babel["paper"].notna().all()
