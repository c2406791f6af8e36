"""`dmais bench sigma`: the table's arithmetic on hand-made poses with known errors and sigmas, and
one tiny simulation through the chain and back through a results folder."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.bench.sigma import (
    AXES,
    TABLE_COLUMNS,
    Simulation,
    frame_errors,
    frames_path,
    is_ok,
    sigma_table,
    simulation_grid,
    wrapped_degrees,
)
from dmais_pipe import cli
from dmais_pipe.cli import main
from dmais_pipe.geometry import quat_from_rotation, rotation_from_euler_zyx

#: Truth attitudes (heading, pitch, roll in degrees), among them a heading and rolls next to the wrap.
TRUE_ANGLES = np.array([[359.9, 0.5, 179.95], [10.0, -1.0, -179.9], [120.0, 2.0, 178.0], [200.0, 0.0, -178.0]])
TRUE_CENTRES = np.array([[100.0, 200.0, 400.0], [101.0, 199.0, 401.0], [99.0, 201.0, 399.0], [100.5, 200.5, 400.5]])
#: Sigmas per axis (m, m, m, arc-min x 3); powers of two, so that the position errors are exact.
SIGMAS = np.array([0.25, 0.125, 0.5, 12.0, 6.0, 6.0])
SETTINGS = {"source": "hand-made", "rig": "truth", "pattern": "hover", "seed": "1", "vibration_arcmin": 0.0,
            "mount_arcmin": 0.0,
            "survey_h_m": 0.01, "survey_v_m": 0.01, "pixel_px": 0.25}


def truth_frames() -> pd.DataFrame:
    """truth/frames.csv as Workspace.load_truth_frames gives it, of TRUE_ANGLES and TRUE_CENTRES."""
    world_from_rig = rotation_from_euler_zyx(np.radians(TRUE_ANGLES))
    rig_from_world = np.swapaxes(world_from_rig, 1, 2)
    q = quat_from_rotation(rig_from_world)
    t = -np.einsum("fij,fj->fi", rig_from_world, TRUE_CENTRES)
    columns = {"group": "1", **dict(zip(("qw", "qx", "qy", "qz"), q.T)), **dict(zip(("tx", "ty", "tz"), t.T)),
               **dict(zip("xyz", TRUE_CENTRES.T))}
    return pd.DataFrame(columns, index=pd.Index([f"f{k}" for k in range(len(q))], name="frame"))


def poses_off_by(errors_in_sigmas) -> pd.DataFrame:
    """poses.csv rows whose errors are errors_in_sigmas (F, 6) x SIGMAS: x, y, z moved in m, the
    angles in arc-min (heading taken into [0, 360), roll into (-180, 180] as the pose stage writes)."""
    errors = np.asarray(errors_in_sigmas, dtype=float) * SIGMAS
    angles = TRUE_ANGLES + errors[:, 3:] / 60.0
    angles[:, 0] %= 360.0
    angles[:, 2] = wrapped_degrees(angles[:, 2])
    columns = {"frame": [f"f{k}" for k in range(len(errors))], "group": "1",
               **dict(zip("xyz", (TRUE_CENTRES + errors[:, :3]).T)),
               **dict(zip(("heading_deg", "pitch_deg", "roll_deg"), angles.T)),
               **dict(zip(("sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_heading_arcmin", "sigma_pitch_arcmin",
                           "sigma_roll_arcmin"), np.tile(SIGMAS, (len(errors), 1)).T))}
    return pd.DataFrame(columns)


def table_of(errors_in_sigmas) -> pd.DataFrame:
    """The bench's table of one camera set whose frames are off by errors_in_sigmas, by axis."""
    frames = frame_errors(poses_off_by(errors_in_sigmas), truth_frames()).assign(**SETTINGS, set="01234")
    return sigma_table(frames).set_index("axis")


def test_wrapped_degrees_are_in_the_half_open_interval():
    np.testing.assert_allclose(wrapped_degrees([0.1 - 359.9, 359.9 - 0.1, 180.0, -180.0, 190.0, -540.5]),
                               [0.2, -0.2, 180.0, 180.0, -170.0, 179.5], atol=1e-9)


def test_errors_are_estimate_minus_truth_across_the_wrap():
    signs = np.array([[1, -1, 1, 1, -1, 1], [-1, 1, -1, -1, 1, -1], [1, 1, 1, 1, 1, 1], [-1, -1, -1, -1, -1, -1]])
    errors = frame_errors(poses_off_by(signs), truth_frames())
    np.testing.assert_allclose(errors[[f"error_{a}" for a in AXES]].to_numpy(), signs * SIGMAS, atol=1e-7)
    np.testing.assert_array_equal(errors[[f"sigma_{a}" for a in AXES]].to_numpy(), np.tile(SIGMAS, (4, 1)))
    # frame f0: heading 359.9 -> 0.1 deg is +12', not -21588'; roll 179.95 -> -179.95 is +6'
    assert poses_off_by(signs)["heading_deg"][0] == pytest.approx(0.1)
    assert errors["error_heading"][0] == pytest.approx(12.0) and errors["error_roll"][0] == pytest.approx(6.0)


def test_errors_of_exactly_one_sigma_give_rms_one_and_full_coverage():
    table = table_of(np.where(np.arange(24).reshape(4, 6) % 2, 1.0, -1.0))
    assert sorted(table.reset_index().columns) == sorted(TABLE_COLUMNS)
    for axis in AXES:
        row = table.loc[axis]
        assert row["n_frames"] == 4
        assert row["rms_ratio"] == pytest.approx(1.0)
        assert (row["cover_1sigma"], row["cover_2sigma"]) == (1.0, 1.0)
        assert row["median_sigma"] == pytest.approx(row["median_abs_error"])
        assert not row["ok"]  # all within 1 sigma is 32 points above a Gaussian's 68%


def test_a_known_mix_of_errors():
    in_sigmas = np.tile([[0.5], [-1.5], [2.5], [-0.5]], (1, 6))
    table = table_of(in_sigmas)
    for axis in AXES:
        row = table.loc[axis]
        assert row["rms_ratio"] == pytest.approx(1.5)  # sqrt((0.25 + 2.25 + 6.25 + 0.25) / 4)
        assert (row["cover_1sigma"], row["cover_2sigma"]) == (0.5, 0.75)
        assert row["median_abs_error"] == pytest.approx(SIGMAS[AXES.index(axis)])  # median of 0.5, 0.5, 1.5, 2.5
    # the 3-D summaries, |error| / sqrt(sum sigma^2) per frame: k sigma on every axis is k; no coverage target
    assert table.loc["position", "rms_ratio"] == pytest.approx(1.5)
    assert np.isnan(table.loc["attitude", "cover_1sigma"]) and table.loc["attitude", "unit"] == "arcmin"


def test_frames_without_a_finite_sigma_are_left_out():
    poses = poses_off_by(np.ones((4, 6)) * 0.5)
    poses.loc[1, "sigma_pitch_arcmin"] = np.nan
    frames = frame_errors(poses, truth_frames()).assign(**SETTINGS, set="0")
    table = sigma_table(frames).set_index("axis")
    assert table.loc["pitch", "n_frames"] == 3 and table.loc["roll", "n_frames"] == 4
    assert table.loc["pitch", "rms_ratio"] == pytest.approx(0.5)


def test_ok_needs_the_ratio_and_both_coverages_near_a_gaussians():
    assert is_ok(1.0, (0.68, 0.95)) and is_ok(0.7, (0.59, 0.86)) and is_ok(1.4, (0.77, 1.0))
    assert not is_ok(0.69, (0.68, 0.95)) and not is_ok(1.41, (0.68, 0.95))
    assert not is_ok(1.0, (0.57, 0.95)) and not is_ok(1.0, (0.68, 0.84))
    assert is_ok(1.2, (np.nan, np.nan)) and not is_ok(np.nan, (0.68, 0.95))


def test_several_seeds_add_pooled_rows():
    one = frame_errors(poses_off_by(np.ones((4, 6))), truth_frames()).assign(**SETTINGS, set="0")
    two = frame_errors(poses_off_by(3 * np.ones((4, 6))), truth_frames()).assign(**{**SETTINGS, "seed": "2"}, set="0")
    table = sigma_table(pd.concat([one, two], ignore_index=True))
    pooled = table[(table["seed"] == "pooled") & (table["axis"] == "x")].iloc[0]
    assert pooled["n_frames"] == 8 and pooled["rms_ratio"] == pytest.approx(np.sqrt(5.0))
    assert len(table) == 3 * 8


def test_the_grid_and_the_command_take_the_flight_pattern():
    grid = simulation_grid([3], [0.3], [0.02], patterns=["hover", "line"])
    assert [s.pattern for s in grid] == ["hover", "line"] and grid[0].name != grid[1].name
    assert grid[1].config()["flight"]["pattern"] == "line" and "pattern" not in grid[0].config()["flight"]
    parser = cli._parser()
    assert parser.parse_args(["bench", "sigma", "--pattern", "line"]).pattern == ["line"]
    assert parser.parse_args(["bench", "sigma"]).pattern == ["hover"]


def test_a_tiny_simulation_and_its_results_folder(tmp_path, capsys):
    common = ["--csv", str(tmp_path / "simulated.csv")]
    assert main(["bench", "sigma", "--simulate", "--seeds", "5", "--vibration", "0.3", "--survey", "0.02",
                 "--groups", "2", "--frames-per-group", "2", "--calib-images", "3", "--work", str(tmp_path / "work"),
                 *common]) == 0
    assert "RMS(error / sigma)" in capsys.readouterr().out
    simulated = pd.read_csv(tmp_path / "simulated.csv", dtype={"seed": str, "set": str})
    assert list(simulated.columns) == TABLE_COLUMNS and len(simulated) == 5 * 8
    assert set(simulated["set"]) == {"0", "01", "012", "1234", "01234"}
    assert (simulated["n_frames"] == 4).all() and np.isfinite(simulated["rms_ratio"]).all()
    settings = simulated[["pattern", "vibration_arcmin", "survey_h_m", "survey_v_m", "pixel_px"]].iloc[0]
    assert settings.tolist() == ["hover", 0.3, 0.02, 0.02, 0.25]
    assert frames_path(tmp_path / "simulated.csv").is_file()

    folder = tmp_path / "work" / Simulation(0.3, 0.02, 5, groups=2, frames_per_group=2, calib_images=3).name
    assert main(["bench", "sigma", "--results", str(folder), "--csv", str(tmp_path / "results.csv")]) == 0
    again = pd.read_csv(tmp_path / "results.csv", dtype={"seed": str, "set": str})
    columns = [c for c in TABLE_COLUMNS if c != "source"]
    pd.testing.assert_frame_equal(again[columns], simulated[columns])
    assert set(again["source"]) == {str(folder)} and set(simulated["source"]) == {"simulation"}

    shutil.copytree(folder, tmp_path / "no-truth")
    shutil.rmtree(tmp_path / "no-truth" / "dataset" / "truth")
    capsys.readouterr()
    assert main(["bench", "sigma", "--results", str(tmp_path / "no-truth"), *common]) == 2
    assert "no truth/frames.csv" in capsys.readouterr().err
