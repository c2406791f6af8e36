"""Pose evaluation: the POS lever arm and INS boresight, eps_pos's two readings, eps_ang conversion,
truth errors, tables and bad inputs."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.evaluate import (
    angular_errors,
    angular_resolution_arcmin,
    cramer_rao_errors,
    group_offsets,
    mean_focal_px,
    position_errors,
    subset_cameras,
    true_errors,
)
from dmais_pipe.geometry import Rigid3, exp_so3, quat_from_rotation, rotation_from_euler_zyx
from dmais_pipe.pos_calibration import attitude_spread, calibration_table, fit_boresight, fit_lever_arm
from dmais_pipe.rig import Rig
from dmais_pipe.sim.config import DEFAULTS
from dmais_pipe.stages import evaluate, pose
from dmais_pipe.workspace import ResultsError, Workspace

from conftest import observation_only

SIM = observation_only("evaluate-small", seed=5, calib_images=2, eval_images=1, frames_per_group=3)
ALL = "C0+C1+C2+C3+C4"
ARCMIN = np.radians(1.0 / 60.0)
SHIFT = np.array([0.03, -0.04, 0.0])  # every estimated centre is off the truth by 5 cm
TILT_ARCMIN = 1.5  # every estimated attitude is off the truth by 1.5'


def poses_from_truth(dataset, cameras: str = ALL, shift=SHIFT, tilt_arcmin: float = TILT_ARCMIN) -> pd.DataFrame:
    """poses.csv rows: the true poses moved by `shift` (m) and turned by `tilt_arcmin` about x."""
    truth = pd.read_csv(dataset / "truth" / "frames.csv", dtype={"frame": str, "group": str})
    turn = rotation_from_euler_zyx([0.0, 0.0, tilt_arcmin * ARCMIN])
    rows = []
    for k, r in enumerate(truth.itertuples(index=False)):
        true = Rigid3.from_quat([r.qw, r.qx, r.qy, r.qz], [r.tx, r.ty, r.tz])
        center = true.center + shift
        R = turn @ true.R
        pose = Rigid3(R, -R @ center)
        rows.append({"frame": r.frame, "group": r.group, "cameras": cameras, "n_points": 40,
                     **dict(zip(("qw", "qx", "qy", "qz"), quat_from_rotation(R))),
                     **dict(zip(("tx", "ty", "tz"), pose.t)), **dict(zip("xyz", center)),
                     "eps_proj_px": 3.0 + 0.1 * k, "time_ms": 0.4 + 0.01 * k})
    return pd.DataFrame(rows)


@pytest.fixture(scope="module")
def dataset(simulated_dataset):
    return simulated_dataset(SIM)


@pytest.fixture()
def results(dataset, tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    shutil.copy(dataset / "truth" / "rig.json", out / "rig.json")
    poses_from_truth(dataset).to_csv(out / "poses.csv", index=False)
    return out


def read(path) -> pd.DataFrame:
    return pd.read_csv(path, dtype={"frame": str, "group": str, "subset": str})


# ------------------------------------------------------------------------------ pure functions


def test_position_errors_remove_the_mean_offset_per_group():
    # A constant lever-arm offset per group plus known per-frame deviations.
    groups = np.array(["a", "a", "b", "b", "b"])
    reference = np.arange(15, dtype=float).reshape(5, 3) * 10.0
    offset = {"a": np.array([0.15, -0.08, 0.32]), "b": np.array([-0.3, 0.2, 0.1])}
    deviation = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.3, 0], [0, 0, 0], [0, 0, 0]])
    estimated = reference + np.array([offset[g] for g in groups]) + deviation
    # by hand: group a's deviations have mean 0 -> 0.1, 0.1; group b's mean is (0, 0.1, 0) -> 0.2, 0.1, 0.1
    np.testing.assert_allclose(position_errors(estimated, reference, groups), [0.1, 0.1, 0.2, 0.1, 0.1], atol=1e-12)
    offsets = group_offsets(estimated, reference, groups)
    np.testing.assert_allclose(offsets["a"], offset["a"], atol=1e-12)
    np.testing.assert_allclose(offsets["b"], offset["b"] + [0, 0.1, 0], atol=1e-12)
    # Given offsets (the full rig's) are used as they are: group a with b's offset removed is off by their difference.
    given = {"a": offset["a"] + [0.0, 0.0, 0.5]}
    np.testing.assert_allclose(position_errors(estimated, reference, groups, given)[:2],
                               np.hypot(0.1, 0.5), atol=1e-12)


LEVER = np.array([0.15, -0.08, 0.32])
POS_SIGMA = np.array([0.02, 0.02, 0.05])  # per world axis: the vertical is the noisier


def hovering_attitudes(rng, n: int, tilt_deg: float = 3.0, heading=None) -> np.ndarray:
    """(n, 3, 3) world_from_rig of a nadir rig (rig z = world down) at random headings (or
    `heading` rad for all), tilted by N(0, tilt_deg) per axis."""
    down = np.diag([1.0, -1.0, -1.0])
    headings = rng.uniform(0, 2 * np.pi, n) if heading is None else np.full(n, heading)
    turns = exp_so3(np.outer(headings, [0.0, 0.0, 1.0]))
    tilts = exp_so3(rng.normal(0.0, np.radians(tilt_deg), (n, 3))) if tilt_deg else np.eye(3)
    return tilts @ turns @ down


def pos_of(rng, centers, world_from_rig, lever=LEVER) -> np.ndarray:
    """POS = centre + R lever + N(0, POS_SIGMA) per world axis."""
    return centers + world_from_rig @ lever + rng.normal(0.0, 1.0, centers.shape) * POS_SIGMA


def test_lever_arm_is_recovered_within_its_uncertainty():
    rng = np.random.default_rng(3)
    n = 40
    R = hovering_attitudes(rng, n)
    centers = rng.uniform(-2000, 2000, (n, 3))
    trials = [fit_lever_arm(centers, pos_of(rng, centers, R), R, np.radians(5.0)) for _ in range(400)]
    first = trials[0]
    assert first.frame == "rig" and first.n_frames == n
    assert np.all(np.abs(first.value - LEVER) < 3 * first.sigma)
    # Independent reference: generalized least squares with the true noise, solved by lstsq on the
    # whitened 3n x 3 system; the fit's own weights come from its residuals and must agree.
    A = (R / POS_SIGMA[None, :, None]).reshape(-1, 3)
    pos = pos_of(np.random.default_rng(3), centers, R)
    gls = np.linalg.lstsq(A, ((pos - centers) / POS_SIGMA).reshape(-1), rcond=None)[0]
    mine = fit_lever_arm(centers, pos, R, np.radians(5.0))
    assert np.all(np.abs(mine.value - gls) < 0.2 * mine.sigma)
    # The sigma is the spread of the estimates over noise draws, and errors / sigma are ~N(0, 1).
    values = np.array([t.value for t in trials])
    sigmas = np.array([t.sigma for t in trials])
    np.testing.assert_allclose(values.std(axis=0), sigmas.mean(axis=0), rtol=0.15)
    assert 0.62 < np.mean(np.abs(values - LEVER) < sigmas) < 0.74
    # The rig z axis points down in every frame, where the POS is noisier (5 cm): its sigma is the largest.
    assert sigmas.mean(axis=0)[2] > 2 * sigmas.mean(axis=0)[:2].max()
    assert np.all(np.abs(values.mean(axis=0) - LEVER) < 3 * sigmas.mean(axis=0) / np.sqrt(len(trials)))


def grouped_flight(rng, groups: int = 5, frames: int = 6):
    """(world_from_rig (n, 3, 3), centres (n, 3), group labels (n,)): each group hovers at its own
    heading, its frames tilted by 0.2 deg."""
    R = np.concatenate([hovering_attitudes(rng, frames, tilt_deg=0.2, heading=h)
                        for h in rng.uniform(0, 2 * np.pi, groups)])
    return R, rng.uniform(-500, 500, (groups * frames, 3)), np.repeat(np.arange(groups), frames)


def test_variance_components_match_a_dense_computation():
    """Henderson-style moments: E[r^T P r] = tr(P (I - H) K (I - H)^T), written out with dense
    3n x 3n matrices, solved by NNLS; the module does it with sparse selectors and 3 x 3 algebra."""
    from scipy.optimize import nnls

    from dmais_pipe.pos_calibration import variance_components

    rng = np.random.default_rng(11)
    R, _, groups = grouped_flight(rng, groups=3, frames=4)
    n = len(R)
    residuals, weights = rng.normal(0.0, [0.02, 0.03, 0.05], (n, 3)), np.array([1.0, 0.5, 0.2])
    A, W = R.reshape(3 * n, 3), np.diag(np.tile(weights, n))
    I_H = np.eye(3 * n) - A @ np.linalg.inv(A.T @ W @ A) @ A.T @ W
    axis = [np.diag(np.tile(np.eye(3)[k], n)) for k in range(3)]
    same_group = (groups[:, None] == groups[None, :]).astype(float)
    shared = [np.kron(same_group, np.diag(np.eye(3)[k])) for k in range(3)]
    means = [np.kron(same_group / np.bincount(groups)[groups][None, :], np.diag(np.eye(3)[k])) for k in range(3)]
    statistics, components = axis + means, axis + shared
    r = residuals.reshape(-1)
    T = np.array([[np.trace(P @ I_H @ K @ I_H.T) for K in components] for P in statistics])
    expected = nnls(T, np.array([r @ P @ r for P in statistics]))[0]
    own, between = variance_components(residuals, R, weights, groups)
    np.testing.assert_allclose(np.concatenate([own, between]), expected, rtol=1e-9, atol=1e-15)


def test_errors_shared_by_a_group_widen_the_lever_arms_sigma():
    """A group's frames share an error (same ground markers): its sigma must follow the spread of
    the estimates, where treating the frames as independent understates it about twofold."""
    rng = np.random.default_rng(8)
    R, centers, groups = grouped_flight(rng)
    shared, own = np.array([0.03, 0.03, 0.04]), np.array([0.02, 0.02, 0.03])
    values, sigmas, independent = [], [], []
    for _ in range(120):
        error = rng.normal(0.0, 1.0, (5, 3))[groups] * shared + rng.normal(0.0, 1.0, (len(R), 3)) * own
        pos = centers + R @ LEVER + error
        fit = fit_lever_arm(centers, pos, R, np.radians(5.0), groups)
        values.append(fit.value)
        sigmas.append(fit.sigma)
        independent.append(fit_lever_arm(centers, pos, R, np.radians(5.0)).sigma)
    spread = np.std(values, axis=0)
    np.testing.assert_allclose(np.sqrt(np.mean(np.square(sigmas), axis=0)), spread, rtol=0.25)
    assert np.all(np.mean(independent, axis=0) < 0.65 * spread)


def test_one_attitude_falls_back_to_a_world_offset(caplog):
    rng = np.random.default_rng(4)
    n = 12
    R = hovering_attitudes(rng, n, tilt_deg=0.0, heading=0.7)
    centers = rng.uniform(-100, 100, (n, 3))
    pos = pos_of(rng, centers, R)
    with caplog.at_level(logging.WARNING):
        fit = fit_lever_arm(centers, pos, R, np.radians(5.0))
    assert fit.frame == "world"
    assert "share one attitude" in caplog.text and "world offset" in caplog.text
    np.testing.assert_allclose(fit.value, (pos - centers).mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(fit.position_errors(centers, pos, R),
                               np.linalg.norm(pos - centers - (pos - centers).mean(axis=0), axis=1), atol=1e-12)
    np.testing.assert_allclose(fit.sigma, POS_SIGMA / np.sqrt(n), rtol=0.5)
    table = calibration_table(fit)
    assert table["parameter"].tolist() == ["world_offset_x", "world_offset_y", "world_offset_z"]
    assert table["unit"].tolist() == ["m"] * 3


def test_headings_about_the_vertical_leave_the_rig_axis_along_it_unseparated(caplog):
    rng = np.random.default_rng(5)
    R = hovering_attitudes(rng, 20, tilt_deg=0.0)
    angles, axes, directions = attitude_spread(R)
    # the rig z axis (the optical axis of C0) always points down; x and y turn with the heading
    assert angles.min() < 1e-6 and np.degrees(np.sort(angles)[1:]).min() > 30
    k = int(np.argmin(angles))
    assert abs(axes[k] @ [0, 0, 1]) > 1 - 1e-9 and abs(directions[k] @ [0, 0, 1]) > 1 - 1e-9
    centers = rng.uniform(-100, 100, (20, 3))
    with caplog.at_level(logging.INFO):
        fit = fit_lever_arm(centers, pos_of(rng, centers, R), R, np.radians(5.0))
    assert fit.frame == "rig" and "keeps world direction" in caplog.text
    assert np.all(np.abs(fit.value - LEVER) < 3 * fit.sigma)
    # a constant POS height bias goes wholly into lever_z, whose sigma cannot show it: the table says so
    biased = fit_lever_arm(centers, pos_of(rng, centers, R) + [0.0, 0.0, 0.1], R, np.radians(5.0))
    assert abs(biased.value[2] - fit.value[2]) > 0.05 and abs(biased.value[2] - LEVER[2]) > 3 * biased.sigma[2]
    notes = calibration_table(biased)["note"].tolist()
    assert notes[2].startswith("not separable from a constant POS offset") and notes[:2] == ["", ""]


def test_boresight_recovers_a_small_rotation():
    rng = np.random.default_rng(6)
    n = 40
    rig_from_world = np.swapaxes(hovering_attitudes(rng, n), -1, -2)
    truth = np.radians([0.3, -0.2, 0.5])
    B = exp_so3(truth)
    exact = fit_boresight(rig_from_world, B @ rig_from_world)
    np.testing.assert_allclose(exact.rotvec, truth, atol=1e-12)
    trials = []
    for _ in range(200):
        noise = exp_so3(rng.normal(0.0, np.radians(0.5), (n, 3)))
        trials.append(fit_boresight(rig_from_world, noise @ B @ rig_from_world))
    assert np.all(np.abs(trials[0].rotvec - truth) < 3 * trials[0].sigma)
    values = np.array([t.rotvec for t in trials])
    sigmas = np.array([t.sigma for t in trials])
    np.testing.assert_allclose(sigmas.mean(axis=0), np.radians(0.5) / np.sqrt(n), rtol=0.1)
    np.testing.assert_allclose(values.std(axis=0), sigmas.mean(axis=0), rtol=0.2)
    world_from_rig = np.swapaxes(rig_from_world, -1, -2)
    lever = fit_lever_arm(np.zeros((n, 3)), pos_of(rng, np.zeros((n, 3)), world_from_rig), world_from_rig, 0.1)
    table = calibration_table(lever, trials[0], {"lever_x": 0.15, "boresight_z": 30.0})
    assert table["parameter"].tolist()[3:] == ["boresight_x", "boresight_y", "boresight_z"]
    assert table.set_index("parameter").loc["boresight_z", "value"] == pytest.approx(
        np.degrees(trials[0].rotvec[2]) * 60)
    assert table["unit"].tolist() == ["m"] * 3 + ["arcmin"] * 3
    assert table["truth"].isna().sum() == 4


def test_angular_resolution_and_eps_ang():
    # One pixel at f = 45000 px is 1/45000 rad = 0.0763944' ; 4 px -> 0.30558'.
    assert angular_resolution_arcmin(45000.0) == pytest.approx(180 * 60 / np.pi / 45000.0)
    assert angular_errors(4.0, 45000.0) == pytest.approx(0.3055775, rel=1e-6)
    np.testing.assert_allclose(angular_errors([1.0, 2.0], [36000.0, 36000.0]),
                               [0.0954930, 0.1909859], rtol=1e-6)


def test_mean_focal_and_subset_labels(dataset):
    rig = Rig.load(dataset / "truth" / "rig.json")
    c0, c1 = rig.cameras["C0"], rig.cameras["C1"]
    assert mean_focal_px(rig, ["C0", "C1"]) == pytest.approx((c0.fx + c0.fy + c1.fx + c1.fy) / 4)
    assert subset_cameras("012", rig) == ["C0", "C1", "C2"]
    assert subset_cameras("1234", rig) == ["C1", "C2", "C3", "C4"]
    with pytest.raises(ValueError, match="0..4"):
        subset_cameras("05", rig)


def test_true_errors():
    R = rotation_from_euler_zyx([0.3, -0.2, 2.0])
    turned = rotation_from_euler_zyx([0.0, 2 * ARCMIN, 0.0]) @ R
    position, attitude = true_errors([quat_from_rotation(turned)], [[1.0, 2.0, 3.0]],
                                     [quat_from_rotation(R)], [[1.3, 2.4, 3.0]])
    np.testing.assert_allclose(position, [0.5])
    np.testing.assert_allclose(attitude, [2.0], rtol=1e-6)


# ------------------------------------------------------------------------------ the stage


def test_evaluate_stage_writes_errors_and_tables(dataset, results):
    written = evaluate.run(Workspace.open(dataset, results))
    assert results / "evaluation.csv" in written and results / "tables" / "pose_methods.csv" in written
    assert not (results / "tables" / "conf.csv").exists()  # no subset file
    evaluation = read(results / "evaluation.csv")
    poses = read(results / "poses.csv")
    assert list(evaluation.columns) == list(poses.columns) + [
        "eps_pos_m", "eps_pos_group_m", "eps_ang_arcmin", "true_pos_err_m", "true_ang_err_arcmin", "crb_pos_m",
        "crb_ang_arcmin"]

    # eps_pos_group by hand: estimate - POS minus its group mean.
    frames = read(dataset / "frames.csv").set_index("frame").loc[evaluation["frame"]]
    delta = evaluation[["x", "y", "z"]].to_numpy() - frames[["pos_x", "pos_y", "pos_z"]].to_numpy()
    expected = np.empty(len(delta))
    for group in evaluation["group"].unique():
        mine = (evaluation["group"] == group).to_numpy()
        expected[mine] = np.linalg.norm(delta[mine] - delta[mine].mean(axis=0), axis=1)
    np.testing.assert_allclose(evaluation["eps_pos_group_m"], expected, atol=1e-9)
    # eps_pos by hand from lever_arm.csv: centre + R^T lever - POS with each pose's own rotation.
    lever = read(results / "tables" / "lever_arm.csv").set_index("parameter")
    assert lever.index.tolist()[:3] == ["lever_x", "lever_y", "lever_z"] and (lever["sigma"] > 0).all()
    R = [Rigid3.from_quat([r.qw, r.qx, r.qy, r.qz], [r.tx, r.ty, r.tz]).R for r in evaluation.itertuples()]
    moved = np.einsum("nji,j->ni", np.array(R), lever.loc[["lever_x", "lever_y", "lever_z"], "value"].to_numpy())
    np.testing.assert_allclose(evaluation["eps_pos_m"], np.linalg.norm(delta + moved, axis=1), atol=1e-9)
    # The lever arm (0.37 m) is gone: what remains is the POS noise (2-3 cm per axis) and the 5 cm SHIFT,
    # which the per-group offsets absorb and the lever arm does not.
    assert np.linalg.norm(delta, axis=1).min() > 0.3
    assert evaluation["eps_pos_m"].max() < 0.15 and evaluation["eps_pos_group_m"].max() < 0.15
    assert evaluation["eps_pos_m"].mean() > evaluation["eps_pos_group_m"].mean() + 0.01

    rig = Rig.load(results / "rig.json")
    focal = np.mean([(c.fx + c.fy) / 2 for c in rig.cameras.values()])
    np.testing.assert_allclose(evaluation["eps_ang_arcmin"], evaluation["eps_proj_px"] / focal / ARCMIN, rtol=1e-9)
    np.testing.assert_allclose(evaluation["true_pos_err_m"], 0.05, atol=1e-6)
    np.testing.assert_allclose(evaluation["true_ang_err_arcmin"], TILT_ARCMIN, rtol=1e-5)

    table = read(results / "tables" / "pose_methods.csv")
    assert table["group"].tolist() == ["1", "2", "3", "4", "5", "all"]
    assert table["n_frames"].tolist() == [3, 3, 3, 3, 3, 15]
    by_group = evaluation.groupby("group")
    np.testing.assert_allclose(table["eps_pos_mean_m"][:5], by_group["eps_pos_m"].mean(), rtol=1e-9)
    np.testing.assert_allclose(table["eps_pos_std_m"][:5], by_group["eps_pos_m"].std(ddof=1), rtol=1e-9)
    np.testing.assert_allclose(table["eps_pos_group_mean_m"][:5], by_group["eps_pos_group_m"].mean(), rtol=1e-9)
    np.testing.assert_allclose(table["eps_pos_group_std_m"][:5], by_group["eps_pos_group_m"].std(ddof=1), rtol=1e-9)
    np.testing.assert_allclose(table["eps_proj_mean_px"][:5], by_group["eps_proj_px"].mean(), rtol=1e-9)
    np.testing.assert_allclose(table["time_mean_ms"].iloc[-1], evaluation["time_ms"].mean(), rtol=1e-9)
    np.testing.assert_allclose(table["true_pos_err_median_m"], 0.05, atol=1e-6)
    # the bound scales with the frame's pixel noise: same geometry, noise doubled -> bound doubled
    doubled = evaluation.assign(eps_proj_px=2 * evaluation["eps_proj_px"])
    truth = read(dataset / "truth" / "frames.csv").set_index("frame").loc[evaluation["frame"]]
    observations = Workspace.open(dataset, results).load_observations()
    position, attitude = cramer_rao_errors(Dataset.load(dataset), rig, doubled, truth, observations)
    np.testing.assert_allclose(position, 2 * evaluation["crb_pos_m"], rtol=1e-6)
    np.testing.assert_allclose(attitude, 2 * evaluation["crb_ang_arcmin"], rtol=1e-6)
    assert (evaluation["crb_pos_m"] > 0).all() and (evaluation["crb_ang_arcmin"] > 0).all()
    assert "crb_pos_median_m" in table and "crb_ang_median_arcmin" in table
    for column in ("eps_ang_std_arcmin", "eps_proj_std_px", "true_ang_err_mean_arcmin"):
        assert column in table


def test_subsets_use_the_full_rigs_lever_arm_and_fill_conf(dataset, results):
    bias = np.array([0.5, 0.0, 0.0])
    poses_from_truth(dataset, cameras="C0", shift=SHIFT + bias).to_csv(results / "poses_0.csv", index=False)
    written = evaluate.run(Workspace.open(dataset, results))
    assert {results / "evaluation_0.csv", results / "tables" / "conf.csv"} <= set(written)
    assert not (results / "evaluation_01234.csv").exists()  # the full rig is evaluation.csv
    full = read(results / "evaluation.csv")
    single = read(results / "evaluation_0.csv")
    # Same frames and attitudes, every estimate moved by `bias`: the full rig's lever arm and group
    # offsets leave the bias in the error.
    frames = read(dataset / "frames.csv").set_index("frame").loc[full["frame"]]
    delta = full[["x", "y", "z"]].to_numpy() - frames[["pos_x", "pos_y", "pos_z"]].to_numpy()
    mean = full.assign(dx=delta[:, 0], dy=delta[:, 1], dz=delta[:, 2]).groupby("group")[["dx", "dy", "dz"]].transform("mean")
    np.testing.assert_allclose(single["eps_pos_group_m"], np.linalg.norm(delta - mean.to_numpy() + bias, axis=1),
                               atol=1e-9)
    lever = read(results / "tables" / "lever_arm.csv").set_index("parameter").loc[["lever_x", "lever_y", "lever_z"],
                                                                                  "value"].to_numpy()
    R = np.array([Rigid3.from_quat([r.qw, r.qx, r.qy, r.qz], [0, 0, 0]).R for r in single.itertuples()])
    np.testing.assert_allclose(single["eps_pos_m"], np.linalg.norm(delta + bias + np.einsum("nji,j->ni", R, lever),
                                                                   axis=1), atol=1e-9)
    assert (single["eps_pos_m"] > 0.35).all()
    rig = Rig.load(results / "rig.json")
    c0 = rig.cameras["C0"]
    np.testing.assert_allclose(single["eps_ang_arcmin"], single["eps_proj_px"] / ((c0.fx + c0.fy) / 2) / ARCMIN)

    conf = read(results / "tables" / "conf.csv")
    assert conf["subset"].tolist()[:2] == ["0", "01234"]
    assert set(conf["group"]) == {"1", "2", "3", "4", "5", "all"}
    assert len(conf) == 12
    assert conf.loc[conf["subset"] == "0", "cameras"].unique().tolist() == ["C0"]
    assert conf.loc[conf["subset"] == "01234", "cameras"].unique().tolist() == [ALL]
    table = read(results / "tables" / "pose_methods.csv").set_index("group")
    everything = conf[conf["subset"] == "01234"].set_index("group")
    np.testing.assert_allclose(everything.loc[table.index, "eps_pos_mean_m"], table["eps_pos_mean_m"], rtol=1e-9)
    np.testing.assert_allclose(everything.loc[table.index, "eps_proj_used_mean_px"], table["eps_proj_mean_px"],
                               rtol=1e-9)
    # tab:conf's eps_proj: the subset's pose reprojected into every camera, checked by a plain loop
    ds = Dataset.load(dataset)
    observations = Workspace(ds, results).load_observations()
    image_frame = ds.images.set_index("image")["placement"]
    for row in single.itertuples(index=False):
        pose = Rigid3.from_quat([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz])
        mine = observations[observations["image"].map(image_frame) == row.frame]
        squared = [np.sum((rig.project(o.camera, pose, ds.points.loc[[o.point_id], ["x", "y", "z"]].to_numpy())[0]
                           - [o.u, o.v]) ** 2) for o in mine.itertuples(index=False)]
        assert row.eps_proj_all_px == pytest.approx(np.sqrt(np.mean(squared)), rel=1e-9)
    # the pose 0.5 m off moves the images by ~f x 0.5 / 350 = 64 px: that, not C0's 3 px, is what shows
    assert (single["eps_proj_all_px"] > 25).all()
    all_focal = np.mean([(c.fx + c.fy) / 2 for c in rig.cameras.values()])
    np.testing.assert_allclose(single["eps_ang_all_arcmin"], single["eps_proj_all_px"] / all_focal / ARCMIN)
    zero = conf[(conf["subset"] == "0") & (conf["group"] == "all")]
    assert zero["eps_proj_mean_px"].iloc[0] == pytest.approx(single["eps_proj_all_px"].mean())

    # A subset file of every camera is tab:conf's #01234 in place of poses.csv.
    poses_from_truth(dataset, shift=SHIFT + bias).to_csv(results / "poses_01234.csv", index=False)
    evaluate.run(Workspace.open(dataset, results))
    conf = read(results / "tables" / "conf.csv")
    everything = conf[conf["subset"] == "01234"].set_index("group")
    assert len(conf) == 12 and (everything["eps_pos_mean_m"] > table["eps_pos_mean_m"] + 0.3).all()

    # Without subset files a rerun leaves no stale conf table behind.
    (results / "poses_0.csv").unlink()
    (results / "poses_01234.csv").unlink()
    evaluate.run(Workspace.open(dataset, results))
    assert not (results / "tables" / "conf.csv").exists()


def test_solved_flight_recovers_the_simulators_lever_arm_and_boresight(dataset, tmp_path):
    """End to end: the pose stage's poses of the simulated flight, then evaluate. The simulator puts
    the POS at centre + R^T lever (lever_arm_m) and the INS attitude at boresight @ rig_from_world
    (ins_boresight_deg); lever_arm.csv's truth column holds both, and the estimates must lie within
    3 sigma of them."""
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(dataset / "truth" / "rig.json", results / "rig.json")
    pose.run(Workspace.open(dataset, results), pose.Conf())
    evaluate.run(Workspace.open(dataset, results))
    table = read(results / "tables" / "lever_arm.csv").set_index("parameter")
    simulated = DEFAULTS["flight"]
    np.testing.assert_allclose(table.loc[["lever_x", "lever_y", "lever_z"], "truth"], simulated["lever_arm_m"])
    np.testing.assert_allclose(table.loc[["boresight_x", "boresight_y", "boresight_z"], "truth"],
                               np.multiply(simulated["ins_boresight_deg"], 60.0))
    assert np.all(np.abs(table["value"] - table["truth"]) < 3 * table["sigma"]), table
    # 15 frames: the lever arm to a few centimetres, the boresight to a few arc-minutes of its ~30'
    assert table["sigma"].iloc[:3].max() < 0.05 and table["sigma"].iloc[3:].max() < 15.0


def test_stage_settings_boresight_and_attitude_spread(dataset, results, caplog):
    evaluate.run(Workspace.open(dataset, results), evaluate.Conf(boresight=False))
    assert read(results / "tables" / "lever_arm.csv")["parameter"].tolist() == ["lever_x", "lever_y", "lever_z"]
    with_lever_arm = read(results / "evaluation.csv")["eps_pos_m"].mean()
    # Every frame within 200 deg of one attitude "is" one attitude: the named fallback, a world offset.
    with caplog.at_level(logging.WARNING):
        evaluate.run(Workspace.open(dataset, results), evaluate.Conf(min_attitude_spread_deg=200.0))
    assert "share one attitude" in caplog.text
    table = read(results / "tables" / "lever_arm.csv")
    assert table["parameter"].tolist()[:3] == ["world_offset_x", "world_offset_y", "world_offset_z"]
    evaluation = read(results / "evaluation.csv")
    frames = read(dataset / "frames.csv").set_index("frame").loc[evaluation["frame"]]
    offset = frames[["pos_x", "pos_y", "pos_z"]].to_numpy() - evaluation[["x", "y", "z"]].to_numpy()
    np.testing.assert_allclose(table["value"].iloc[:3], offset.mean(axis=0), atol=1e-9)
    # the lever arm's horizontal 0.17 m, turned with the heading, is now error
    assert evaluation["eps_pos_m"].mean() > with_lever_arm + 0.05


def test_extra_poses_columns_are_carried_through(dataset, results):
    poses = read(results / "poses.csv")
    poses.assign(heading_deg=12.5, heading_sigma_deg=0.01).to_csv(results / "poses.csv", index=False)
    evaluate.run(Workspace.open(dataset, results))
    evaluation = read(results / "evaluation.csv")
    assert (evaluation["heading_deg"] == 12.5).all() and evaluation["eps_pos_m"].notna().all()
    assert read(results / "tables" / "lever_arm.csv")["value"].notna().all()


# ------------------------------------------------------------------------------ bad inputs


def test_missing_poses(dataset, results):
    (results / "poses.csv").unlink()
    with pytest.raises(ResultsError, match=r"poses\.csv: missing"):
        evaluate.run(Workspace.open(dataset, results))


def test_missing_rig(dataset, results):
    (results / "rig.json").unlink()
    with pytest.raises(DmaisError, match="rig.json"):
        evaluate.run(Workspace.open(dataset, results))


@pytest.mark.parametrize("column, value, message", [
    ("frame", "nope", r"line 3: frame 'nope' is not a frame of"),
    ("eps_proj_px", "nan", r"line 3: column eps_proj_px: 'nan' is not a finite number"),
    ("x", "", r"line 3: column x is empty"),
    ("group", "9", r"line 3: frame '\w+': group '9', frames.csv says"),
    ("cameras", "C0+C9", r"line 3: cameras 'C0\+C9': not all are cameras of the rig"),
    ("n_points", "2.5", r"line 3: column n_points: 2.5 is not a count"),
])
def test_bad_poses_name_file_and_line(dataset, results, column, value, message):
    poses = pd.read_csv(results / "poses.csv", dtype=str, keep_default_na=False)
    poses.loc[1, column] = value
    poses.to_csv(results / "poses.csv", index=False)
    with pytest.raises(ResultsError, match=rf"poses\.csv, {message}"):
        evaluate.run(Workspace.open(dataset, results))


def test_duplicate_and_empty_poses(dataset, results):
    poses = pd.read_csv(results / "poses.csv", dtype=str)
    pd.concat([poses, poses.iloc[:1]]).to_csv(results / "poses.csv", index=False)
    with pytest.raises(ResultsError, match="duplicate frame"):
        evaluate.run(Workspace.open(dataset, results))
    poses.iloc[:0].to_csv(results / "poses.csv", index=False)
    with pytest.raises(ResultsError, match="has no rows"):
        evaluate.run(Workspace.open(dataset, results))


def test_bad_subset_files(dataset, results):
    poses_from_truth(dataset, cameras="C0+C1").to_csv(results / "poses_0.csv", index=False)
    with pytest.raises(ResultsError, match=r"poses_0\.csv, line 2: cameras 'C0\+C1': this subset file may use only C0"):
        evaluate.run(Workspace.open(dataset, results))
    (results / "poses_0.csv").unlink()
    poses_from_truth(dataset, cameras="C0").to_csv(results / "poses_07.csv", index=False)
    with pytest.raises(ResultsError, match=r"poses_07\.csv: subset label '07'"):
        evaluate.run(Workspace.open(dataset, results))


def test_robust_outliers_leave_the_errors_and_the_bound(dataset, tmp_path):
    """With --robust, evaluation sees only the observations each pose was solved from: point ids
    swapped in 30% of the flight observations make the rejected ones hundreds of pixels off, and
    neither eps_proj_all nor the Cramer-Rao bound may count them."""
    from dmais_pipe.evaluate import every_camera_eps_proj, used_observations

    copy = tmp_path / "data"
    shutil.copytree(dataset, copy)
    observations = pd.read_csv(copy / "observations.csv", dtype=str, keep_default_na=False)
    flight = observations.index[observations["image"].str.startswith("flight")].to_numpy()
    rows = np.random.default_rng(1).choice(flight, size=int(0.3 * len(flight)), replace=False)
    observations.loc[rows, "point_id"] = np.roll(observations.loc[rows, "point_id"].to_numpy(), 1)
    observations.drop_duplicates(["image", "point_id"]).to_csv(copy / "observations.csv", index=False)
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(copy / "truth" / "rig.json", results / "rig.json")
    robust = pose.Conf(robust=True)
    pose.run(Workspace.open(copy, results), robust)
    pose.run(Workspace.open(copy, results), robust, cameras=["C0", "C1", "C2"])
    evaluate.run(Workspace.open(copy, results))

    workspace = Workspace.open(copy, results)
    whole = workspace.load_pose_observations()
    assert (~whole["used"]).sum() >= 0.2 * len(flight)  # RANSAC rejected the swapped ids
    everything = workspace.load_observations()
    used = used_observations(everything, whole, workspace.load_pose_observations(workspace.poses_path("012")))
    subset = read(results / "evaluation_012.csv")
    rig = workspace.load_rig()
    np.testing.assert_allclose(subset["eps_proj_all_px"], every_camera_eps_proj(workspace.dataset, rig, subset, used))
    with_outliers = every_camera_eps_proj(workspace.dataset, rig, subset, everything)
    assert (with_outliers > 3 * subset["eps_proj_all_px"]).all(), (with_outliers, subset["eps_proj_all_px"])
    evaluation = read(results / "evaluation.csv")
    assert evaluation["crb_pos_m"].notna().all() and (evaluation["crb_pos_m"] < 0.5).all()
    # tab:conf's full rig (#01234, from poses.csv) is reprojected from the observations its own poses used
    conf = read(results / "tables" / "conf.csv").set_index(["group", "subset"])
    assert set(conf.index.get_level_values("subset")) == {"012", "01234"}
    assert (evaluation["cameras"] == ALL).all()
    assert conf.loc[("all", "01234"), "eps_proj_mean_px"] == pytest.approx(evaluation["eps_proj_px"].mean(), rel=1e-6)


def test_error_budget_table_shares_and_totals():
    from dmais_pipe.evaluate import error_budget_table

    frames = ["f1", "f2"]
    rows = []
    for frame, scale in zip(frames, (1.0, 3.0)):
        for component, position, attitude in (("pixel", 1e-4, 0.5), ("jitter", 3e-4, 1.5)):
            rows.append({"frame": frame, "component": component, "sigma": 0.3, "unit": "px", "source": "estimated",
                         "var_x_m2": position * scale, "var_y_m2": 0.0, "var_z_m2": 0.0,
                         "var_heading_arcmin2": attitude * scale, "var_pitch_arcmin2": 0.0, "var_roll_arcmin2": 0.0})
    budget = pd.DataFrame(rows)
    evaluation = pd.DataFrame({"frame": frames, "true_pos_err_m": [0.02, 0.04], "true_ang_err_arcmin": [1.0, 2.0],
                               "eps_pos_m": [9.0, 9.0], "eps_ang_arcmin": [9.0, 9.0]})
    table = error_budget_table({"01": evaluation}, {"01": budget, "0": None})
    shares = table[table["component"] != "total"].set_index("component")
    assert shares.loc["pixel", "position_share_pct"] == pytest.approx(25.0)
    assert shares.loc["jitter", "attitude_share_pct"] == pytest.approx(75.0)
    total = table[table["component"] == "total"].iloc[0]
    assert total["rms_sigma_position_m"] == pytest.approx(np.sqrt((4e-4 + 12e-4) / 2))
    assert total["rms_error_position_m"] == pytest.approx(np.sqrt((0.02**2 + 0.04**2) / 2))
    assert total["error_measure"] == "truth"
    # without the simulator's truth the error beside the sigmas is eps_pos
    real = error_budget_table({"01": evaluation.drop(columns=["true_pos_err_m", "true_ang_err_arcmin"])},
                              {"01": budget})
    assert real.iloc[-1]["error_measure"] == "eps_pos" and real.iloc[-1]["rms_error_position_m"] == 9.0
