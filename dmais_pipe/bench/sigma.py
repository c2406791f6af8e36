"""`dmais bench sigma`: whether poses.csv's 1-sigma columns describe the true errors (issue 29).

Per camera set (poses_<label>.csv; poses.csv under the full rig's label, 01234) and per axis of
the pose, against the simulator's truth (truth/frames.csv), over the set's frames:

- error: estimate - truth. x, y, z: the rig centre in the world (m); heading, pitch, roll:
  poses.csv's angles minus the truth's (`heading_pitch_roll` of its rig_from_world), wrapped to
  (-180, 180] deg, in arc-min. sigma: the frame's column sigma_x_m ... sigma_roll_arcmin;
- rms_ratio = sqrt(mean((error / sigma)^2)): 1 where the sigmas are honest;
- cover_1sigma, cover_2sigma: the share of frames with |error| <= sigma, <= 2 sigma (68.27% and
  95.45% for Gaussian errors of that sigma);
- median_sigma, median_abs_error (m or arc-min); n_frames: the frames with a finite sigma;
- ok: rms_ratio within RATIO_BOUNDS and both coverages within COVERAGE_TOLERANCE of the Gaussian's.

Two summary axes per set, `position` and `attitude`: the norm of the three errors over the root
sum of the three sigmas squared (the issue's "true error over the predicted 3-D sigma"). Its RMS
is 1 for honest sigmas whatever the correlation between the axes (E |e|^2 = trace cov); its
coverage has no Gaussian 68/95 target and is left empty, so its ok is the ratio's alone.

Sources:

- `results_frames(DIR)`: a workflow run on a simulated dataset (results/demo, results/paper),
  its dataset in DIR/dataset, where the workflow simulates it.
- `simulation_frames`: per `Simulation` (flight vibration_sigma_arcmin, an isotropic ground-survey
  sigma, the flight's marker noise in px, the per-group mounting change, a seed) an
  observation-only dataset of `groups` flight groups of `frames_per_group` frames (the simulator's
  sites A and B in turns) with a demo-sized calibration (6 + 2 images per camera), simulated into
  WORK/<name>/dataset; then its chain as the workflow runs it with its default settings, into
  WORK/<name>: intrinsics (the paper's procedure alone, `ours`: the same calibration without the
  baselines' table rows), extrinsics, the pose of every set of CAMERA_SETS; then the rows of that
  folder as of a workflow run. With `truth_rig` the simulator's rig replaces the calibration.
  With several seeds, `pooled` rows gather the seeds' frames per setting.

  Many short groups rather than few long ones: a group's frames share its ground points' survey
  errors and its mounting change, so the group, not the frame, is the independent draw of those
  errors; 6 groups x 10 frames weigh them three times better than 2 x 30 at the same cost.
  One simulation takes 9-16 s on 2 shared cores (simulating 4-5 s, intrinsics and extrinsics
  3-6 s, five pose runs 1-2 s; with `truth_rig` about 8 s), the default grid of 3 x 3 settings x 3
  seeds about 5 minutes.

The rig column says whether the poses were solved with a calibrated rig (`calibrated`: a
workflow's run, the chain) or the simulator's (`truth`). The settings behind every row (seed,
vibration, per-group mounting change, survey sigma
horizontal / vertical, flight marker noise; the last empty when the flight images were rendered,
whose noise is the detector's) come from the dataset's truth/simulation.yaml, for both sources.
The CSV has one row per source, setting, seed, set and axis; the per-frame errors and sigmas are
written beside it (<stem>_frames.csv).
"""

from __future__ import annotations

import logging
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ..dataset import CONTROL_POINTS, GROUND_POINTS, POINT_SIGMA, POINT_SIGMA_Z
from ..errors import DmaisError
from ..evaluate import subset_cameras
from ..files import copy_atomic, write_csv_atomic, write_yaml_atomic
from ..geometry import rotation_from_quat
from ..pose.uncertainty import heading_pitch_roll
from ..sim.config import DEFAULTS
from ..sim.simulate import simulate
from ..stages import extrinsics, intrinsics, pose
from ..workspace import CENTER, POSE_UNCERTAINTY_COLUMNS, QUAT, ResultsError, Workspace

log = logging.getLogger(__name__)

AXES = ("x", "y", "z", "heading", "pitch", "roll")
UNITS = dict.fromkeys(AXES[:3], "m") | dict.fromkeys(AXES[3:], "arcmin")
SUMMARIES = {"position": AXES[:3], "attitude": AXES[3:]}
ANGLE_COLUMNS = list(POSE_UNCERTAINTY_COLUMNS[:3])
SIGMA_COLUMNS = list(POSE_UNCERTAINTY_COLUMNS[3:9])
RATIO_BOUNDS = (0.7, 1.4)
GAUSSIAN_COVERAGE = (0.6827, 0.9545)
COVERAGE_TOLERANCE = 0.10
#: An error of exactly k sigma counts as within k sigma despite the rounding of the angle conversions.
COVERAGE_ROUNDING = 1e-9
#: The workflow's camera sets (config/config.yaml's subsets) and the full rig.
CAMERA_SETS = ("0", "01", "012", "1234", "01234")
SETTING_COLUMNS = ["source", "rig", "pattern", "seed", "vibration_arcmin", "mount_arcmin", "survey_h_m", "survey_v_m",
                   "pixel_px"]
STATISTIC_COLUMNS = ["n_frames", "rms_ratio", "cover_1sigma", "cover_2sigma", "median_sigma", "median_abs_error"]
TABLE_COLUMNS = [*SETTING_COLUMNS, "set", "axis", "unit", *STATISTIC_COLUMNS, "ok"]
#: Printed names of the setting columns.
SHORT_NAMES = {"vibration_arcmin": "vib'", "mount_arcmin": "mount'", "survey_h_m": "survey_h",
               "survey_v_m": "survey_v", "pixel_px": "px"}
DEFAULT_SEEDS = (1001, 1002, 1003)
DEFAULT_VIBRATION_ARCMIN = (0.0, 0.3, 1.0)
DEFAULT_SURVEY_M = (0.01, 0.02, 0.03)


# ------------------------------------------------------------------------------ the arithmetic


def wrapped_degrees(difference) -> np.ndarray:
    """Angle differences (any shape, degrees) wrapped to (-180, 180]."""
    return 180.0 - np.mod(180.0 - np.asarray(difference, dtype=float), 360.0)


def frame_errors(poses: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Per frame of `poses` (F rows with poses.csv's columns, the uncertainty ones included):
    frame, group, then error_<axis> and sigma_<axis> for every axis of AXES (units in UNITS).
    truth: `Workspace.load_truth_frames()`, indexed by frame, with a row for every frame of poses."""
    true = truth.loc[poses["frame"]]
    position = poses[list(CENTER)].to_numpy(dtype=float) - true[list(CENTER)].to_numpy(dtype=float)
    true_angles = heading_pitch_roll(rotation_from_quat(true[list(QUAT)].to_numpy(dtype=float)))
    attitude = wrapped_degrees(poses[ANGLE_COLUMNS].to_numpy(dtype=float) - true_angles) * 60.0
    errors, sigmas = np.column_stack([position, attitude]), poses[SIGMA_COLUMNS].to_numpy(dtype=float)
    columns = {"frame": poses["frame"].to_numpy(), "group": poses["group"].to_numpy()}
    for k, axis in enumerate(AXES):
        columns |= {f"error_{axis}": errors[:, k], f"sigma_{axis}": sigmas[:, k]}
    return pd.DataFrame(columns)


def axis_statistics(error, sigma, gaussian: bool = True) -> dict:
    """STATISTIC_COLUMNS and ok of one axis: error (F,), sigma (F,) in one unit; frames without a
    finite error and sigma are left out. gaussian: whether the coverages have the Gaussian targets
    (else they are NaN)."""
    error, sigma = np.asarray(error, dtype=float), np.asarray(sigma, dtype=float)
    kept = np.isfinite(error) & np.isfinite(sigma)
    error, sigma = error[kept], sigma[kept]
    if not len(error):
        return {"n_frames": 0, **dict.fromkeys(STATISTIC_COLUMNS[1:], np.nan), "ok": False}
    ratio = np.abs(error) / sigma
    covers = [np.mean(ratio <= k * (1.0 + COVERAGE_ROUNDING)) if gaussian else np.nan for k in (1, 2)]
    rms_ratio = float(np.sqrt(np.mean(ratio**2)))
    return {"n_frames": len(error), "rms_ratio": rms_ratio, "cover_1sigma": covers[0],
            "cover_2sigma": covers[1], "median_sigma": float(np.median(sigma)),
            "median_abs_error": float(np.median(np.abs(error))), "ok": is_ok(rms_ratio, covers)}


def is_ok(rms_ratio: float, covers) -> bool:
    """rms_ratio within RATIO_BOUNDS and every coverage (1 and 2 sigma; NaN: no target) within
    COVERAGE_TOLERANCE of the Gaussian's."""
    coverage_ok = all(np.isnan(c) or abs(c - g) <= COVERAGE_TOLERANCE for c, g in zip(covers, GAUSSIAN_COVERAGE))
    return bool(RATIO_BOUNDS[0] <= rms_ratio <= RATIO_BOUNDS[1] and coverage_ok)


def set_rows(frames: pd.DataFrame) -> list[dict]:
    """One row per axis of AXES and SUMMARIES (axis, unit, STATISTIC_COLUMNS, ok) over `frames`
    (`frame_errors` rows of one camera set)."""
    rows = [{"axis": axis, "unit": UNITS[axis], **axis_statistics(frames[f"error_{axis}"], frames[f"sigma_{axis}"])}
            for axis in AXES]
    for name, axes in SUMMARIES.items():
        error = np.linalg.norm(frames[[f"error_{a}" for a in axes]].to_numpy(dtype=float), axis=1)
        sigma = np.linalg.norm(frames[[f"sigma_{a}" for a in axes]].to_numpy(dtype=float), axis=1)
        rows.append({"axis": name, "unit": UNITS[axes[0]], **axis_statistics(error, sigma, gaussian=False)})
    return rows


def sigma_table(frames: pd.DataFrame) -> pd.DataFrame:
    """TABLE_COLUMNS, one row per source, setting, seed, camera set and axis, from per-frame rows
    (SETTING_COLUMNS, set, then `frame_errors`' columns); with `pooled` seeds where a source has
    several seeds."""
    keys = [*SETTING_COLUMNS, "set"]
    rows = [{**dict(zip(keys, key)), **row}
            for key, part in with_pooled_seeds(frames).groupby(keys, sort=False, dropna=False)
            for row in set_rows(part)]
    return pd.DataFrame(rows, columns=TABLE_COLUMNS)


def with_pooled_seeds(frames: pd.DataFrame) -> pd.DataFrame:
    """`frames`, and again with seed `pooled` the frames of every source that has several seeds."""
    several = frames.groupby("source")["seed"].transform("nunique") > 1
    return pd.concat([frames, frames[several].assign(seed="pooled")], ignore_index=True)


# ------------------------------------------------------------------------------ a results folder


def results_frames(results_dir: Path, source: str | None = None, rig: str = "calibrated") -> pd.DataFrame:
    """Per-frame rows (SETTING_COLUMNS, set, `frame_errors`) of every camera set solved in a
    workflow's results folder, its simulated dataset in results_dir/dataset. source: the rows'
    source (default: the folder as given); rig: how its rig.json came about (calibrated, truth)."""
    results_dir = Path(results_dir)
    workspace = Workspace.open(results_dir / "dataset", results_dir)
    truth = workspace.load_truth_frames()
    if truth is None:
        raise DmaisError(f"{results_dir}: its dataset has no truth/frames.csv; the sigma bench needs a simulated "
                         "dataset")
    settings = {"source": str(source or results_dir), "rig": rig, **simulation_settings(workspace.dataset.truth_dir)}
    parts = [frame_errors(checked_poses(workspace, path, truth), truth).assign(**settings, set=label)
             for label, path in camera_set_files(workspace).items()]
    frames = pd.concat(parts, ignore_index=True)
    return frames[[*SETTING_COLUMNS, "set", *[c for c in frames.columns if c not in (*SETTING_COLUMNS, "set")]]]


def camera_set_files(workspace: Workspace) -> dict[str, Path]:
    """label -> poses file of every camera set solved: the subsets, and poses.csv under the full
    rig's label unless a subset file of that label exists (as tables/conf.csv)."""
    files = workspace.subset_labels()
    full_rig = pose.subset_label(workspace.load_rig(), workspace.load_rig().camera_names)
    if workspace.poses_path().is_file():
        files.setdefault(full_rig, workspace.poses_path())
    if not files:
        raise ResultsError(workspace.poses_path(), "missing; run `dmais pose` first")
    return files


def checked_poses(workspace: Workspace, path: Path, truth: pd.DataFrame) -> pd.DataFrame:
    """The poses file, which must have the sigma columns and only frames of the truth."""
    poses = workspace.load_poses(path)
    absent = [c for c in [*ANGLE_COLUMNS, *SIGMA_COLUMNS] if c not in poses.columns]
    if absent:
        raise ResultsError(path, f"has no column(s) {', '.join(absent)}: solved before poses.csv had its 1-sigma "
                                 "columns; run `dmais pose` again")
    missing = sorted(set(poses["frame"]) - set(truth.index))
    if missing:
        raise ResultsError(workspace.dataset.truth_dir / "frames.csv",
                           f"has no row for frame(s) {', '.join(missing[:5])}")
    return poses


def simulation_settings(truth_dir: Path) -> dict:
    """SETTING_COLUMNS but source and rig, from truth/simulation.yaml: the flight's pattern, seed
    (text), vibration and mounting change (arc-min), ground survey horizontal and vertical sigma (m),
    the flight's marker noise (px; NaN when the flight images were rendered)."""
    config = yaml.safe_load((truth_dir / "simulation.yaml").read_text())
    flight = config["flight"]
    survey = np.broadcast_to(np.asarray(flight["survey_sigma_m"], dtype=float), 3)
    rendered = config.get("render", {}).get("flight", False)
    return {"pattern": str(flight.get("pattern", DEFAULTS["flight"]["pattern"])), "seed": str(config["seed"]),
            "vibration_arcmin": float(flight["vibration_sigma_arcmin"]),
            "mount_arcmin": float(flight["mount_sigma_arcmin"]), "survey_h_m": float(survey[0]),
            "survey_v_m": float(survey[2]), "pixel_px": np.nan if rendered else float(flight["pixel_sigma_px"])}


# ------------------------------------------------------------------------------ simulations


@dataclass(frozen=True)
class Simulation:
    """One observation-only flight of the grid and its calibration (module docstring). truth_rig:
    solve with the simulator's rig (truth/rig.json) instead of calibrating one, which tells the
    calibration's share of the errors from the flight's. pattern: the simulator's flight.pattern
    (hover, line)."""

    vibration_arcmin: float
    survey_m: float
    seed: int
    pixel_px: float = 0.25
    mount_arcmin: float = DEFAULTS["flight"]["mount_sigma_arcmin"]
    groups: int = 6
    frames_per_group: int = 10
    calib_images: int = 6
    eval_images: int = 2
    truth_rig: bool = False
    pattern: str = DEFAULTS["flight"]["pattern"]
    #: the calibration field's survey sigma per axis (m; None: the simulator's), and whether the
    #: dataset gives the survey sigmas (sigma_m) or the calibration and the flight estimate them
    field_survey_m: float | None = None
    sigma_given: bool = True

    @property
    def name(self) -> str:
        pattern = "" if self.pattern == DEFAULTS["flight"]["pattern"] else f"-{self.pattern}"
        field = "" if self.field_survey_m is None else f"-field{self.field_survey_m:g}"
        return (f"vib{self.vibration_arcmin:g}-mount{self.mount_arcmin:g}-survey{self.survey_m:g}{field}"
                f"-px{self.pixel_px:g}-{self.groups}x{self.frames_per_group}{pattern}-seed{self.seed}"
                f"{'-truthrig' if self.truth_rig else ''}{'' if self.sigma_given else '-nosigma'}")

    def config(self) -> dict:
        """Its simulator settings (a mapping over sim.config.DEFAULTS); flight.pattern only when not the default."""
        pattern = {} if self.pattern == DEFAULTS["flight"]["pattern"] else {"pattern": self.pattern}
        field = {} if self.field_survey_m is None else {"field": {"survey_sigma_m": self.field_survey_m}}
        return {"name": self.name, "seed": self.seed, **field,
                "intrinsics": {"calib_images_per_camera": self.calib_images,
                               "eval_images_per_camera": self.eval_images},
                "flight": {"frames_per_group": self.frames_per_group, "sites": alternating_sites(self.groups),
                           "vibration_sigma_arcmin": self.vibration_arcmin, "mount_sigma_arcmin": self.mount_arcmin,
                           "survey_sigma_m": [self.survey_m] * 3, "pixel_sigma_px": self.pixel_px, **pattern},
                "render": {"intrinsics": False, "extrinsics": False, "flight": False}}


def alternating_sites(groups: int) -> dict:
    """The simulator's sites A and B with groups 1..groups taken in turns (A: 1, 3, ...; B: 2, 4, ...)."""
    sites = DEFAULTS["flight"]["sites"]
    return {name: {**sites[name], "groups": list(range(1 + k, groups + 1, 2))}
            for k, name in enumerate(("A", "B")) if k < groups}


def simulation_grid(seeds=DEFAULT_SEEDS, vibrations=DEFAULT_VIBRATION_ARCMIN, surveys=DEFAULT_SURVEY_M,
                    patterns=("hover",), **options) -> list[Simulation]:
    """Every flight pattern x vibration x survey x seed (seeds innermost); options: Simulation's other
    fields."""
    return [Simulation(v, s, seed, pattern=pattern, **options)
            for pattern in patterns for v in vibrations for s in surveys for seed in seeds]


def calibrated_workspace(simulation: Simulation, folder: Path) -> Workspace:
    """Simulate into folder/dataset and calibrate the rig into `folder` (the simulator's with truth_rig)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_yaml_atomic(folder / "simulation.yaml", simulation.config())
    dataset = simulate(folder / "simulation.yaml", folder / "dataset")
    if not simulation.sigma_given:
        _without_survey_sigmas(dataset)
    workspace = Workspace.open(dataset, folder)
    if simulation.truth_rig:
        copy_atomic(dataset / "truth" / "rig.json", workspace.rig_path)
    else:
        intrinsics.run(workspace, intrinsics.CONFS["ours"])
        extrinsics.run(workspace)
    return workspace


def _without_survey_sigmas(dataset: Path) -> None:
    """The bench's simulated `dataset` with its points' survey sigma columns taken out: a survey
    whose sigma the user does not know."""
    for name in (CONTROL_POINTS, GROUND_POINTS):
        table = pd.read_csv(dataset / name, dtype={"point_id": str})
        write_csv_atomic(dataset / name, table.drop(columns=[POINT_SIGMA, POINT_SIGMA_Z], errors="ignore"))


def run_simulation(simulation: Simulation, folder: Path) -> Path:
    """Simulate into folder/dataset and run the chain into `folder` (module docstring); the folder."""
    workspace = calibrated_workspace(simulation, folder)
    rig = workspace.load_rig()
    for label in CAMERA_SETS:
        pose.run(workspace, cameras=subset_cameras(label, rig))
    return folder


def simulation_frames(simulations: list[Simulation], work: Path | None = None) -> pd.DataFrame:
    """Per-frame rows (as `results_frames`, source `simulation`) of every simulation, each run in
    work/<name> (default: a temporary folder, removed after)."""
    if not simulations:
        return pd.DataFrame()
    with tempfile.TemporaryDirectory(prefix="dmais-bench-sigma-") as scratch:
        root = Path(work) if work is not None else Path(scratch)
        parts, start = [], time.perf_counter()
        for k, simulation in enumerate(simulations):
            began = time.perf_counter()
            with _stages_quiet():
                folder = run_simulation(simulation, root / simulation.name)
            parts.append(results_frames(folder, "simulation", "truth" if simulation.truth_rig else "calibrated"))
            log.info("sigma bench: simulation %d/%d %s in %.1f s", k + 1, len(simulations), simulation.name,
                     time.perf_counter() - began)
    log.info("sigma bench: %d simulations in %.0f s", len(simulations), time.perf_counter() - start)
    return pd.concat(parts, ignore_index=True)


@contextmanager
def _stages_quiet():
    """The simulator's and the stages' INFO lines held back (warnings pass) while a simulation runs."""
    loggers = [logging.getLogger(f"dmais_pipe.{name}") for name in ("sim", "stages", "calib", "pose", "dataset")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


# ------------------------------------------------------------------------------ the bench


def bench_sigma(csv: Path, results: list[Path] = (), simulations: list[Simulation] = (),
                work: Path | None = None) -> pd.DataFrame:
    """The table (TABLE_COLUMNS) of every results folder and simulation, written to `csv`, the
    per-frame rows beside it (<stem>_frames.csv)."""
    if not results and not simulations:
        raise DmaisError("bench sigma: give --results DIR and/or --simulate")
    parts = [results_frames(folder) for folder in results]
    if simulations:
        parts.append(simulation_frames(list(simulations), work))
    frames = pd.concat(parts, ignore_index=True)
    table = sigma_table(frames)
    write_csv_atomic(csv, table)
    write_csv_atomic(frames_path(csv), frames)
    return table


def frames_path(csv: Path) -> Path:
    """The per-frame table beside the bench's CSV."""
    return Path(csv).with_name(f"{Path(csv).stem}_frames.csv")


def print_table(table: pd.DataFrame, csv: Path) -> None:
    """Three blocks, a line per source, setting, seed and set: RMS(error / sigma) per axis (with
    the 3-D summaries and how many of the six axes are ok), then the 1- and 2-sigma coverage (%)."""
    keys = [*SETTING_COLUMNS, "set"]
    sets = [(_shown_keys(dict(zip(keys, key)), part), part.set_index("axis"))
            for key, part in table.groupby(keys, sort=False, dropna=False)]
    blocks = {"RMS(error / sigma); target [0.7, 1.4]": ("rms_ratio", [*AXES, *SUMMARIES], 1.0),
              "share within 1 sigma (%); target 68 +- 10": ("cover_1sigma", AXES, 100.0),
              "share within 2 sigma (%); target 95 +- 10": ("cover_2sigma", AXES, 100.0)}
    for title, (statistic, axes, scale) in blocks.items():
        rows = []
        for shown, by_axis in sets:
            rows.append({**shown, **{axis: by_axis.at[axis, statistic] * scale for axis in axes}})
            if statistic == "rms_ratio":
                rows[-1]["ok"] = f"{int(by_axis.loc[list(AXES), 'ok'].sum())}/{len(AXES)}"
        digits = ("{:.2f}" if scale == 1.0 else "{:.0f}").format
        print(f"\n{title}")
        print(pd.DataFrame(rows).to_string(index=False, formatters=dict.fromkeys(axes, digits),
                                           float_format="{:g}".format, na_rep="-"))
    print(f"\ntable: {csv}; per frame: {frames_path(csv)}")


def _shown_keys(keys: dict, part: pd.DataFrame) -> dict:
    """A printed line's keys: the source's folder name (sim for the simulations), the settings, the
    set and its frames."""
    source = "sim" if keys["source"] == "simulation" else Path(keys["source"]).name
    shown = {SHORT_NAMES.get(key, key): value for key, value in keys.items()}
    return {**shown, "source": source, "n": int(part["n_frames"].max())}
