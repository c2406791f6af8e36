"""The results folder of one dataset: every results path, and a load_*/save_* pair per result.

`Workspace` is the output side's counterpart of `Dataset`: the stages read and write results only
through it, so that each file's name, columns and checks live in one place. The layout is
documented in docs/design.md ("Results directory"). Every write is atomic (`files`); every
results CSV read back is checked with the dataset's CSV reader and a fault raises `ResultsError`
naming the file and line.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

from .camera import Camera
from .dataset import STAGES, Dataset, Table, camera_of_images, read_observation_table, read_table
from .errors import DatasetError, DmaisError
from .files import csv_text, write_csv_atomic, write_json_atomic, write_text_atomic
from .geo import GeoError
from .geometry import Rigid3
from .plan import marker_batches
from .rig import Rig

log = logging.getLogger(__name__)

QUAT = ("qw", "qx", "qy", "qz")
TRANSLATION = ("tx", "ty", "tz")
CENTER = ("x", "y", "z")
#: The columns of poses.csv (docs/design.md); rig_from_world quaternion (w, x, y, z) and translation.
POSE_COLUMNS = ("frame", "group", "cameras", "n_points", *QUAT, *TRANSLATION, *CENTER, "eps_proj_px", "time_ms")
#: poses.csv's attitude and 1-sigma uncertainty columns after `certified` (docs/design.md): heading,
#: pitch, roll (deg) of world_from_rig = Rz Ry Rx, the rig centre's sigma along the world axes (m),
#: the angles' sigma (arc-min), and the per-axis pixel noise behind them. Files before them lack them.
POSE_UNCERTAINTY_COLUMNS = ("heading_deg", "pitch_deg", "roll_deg", "sigma_x_m", "sigma_y_m", "sigma_z_m",
                            "sigma_heading_arcmin", "sigma_pitch_arcmin", "sigma_roll_arcmin", "noise_px")
#: poses.csv's columns after those of a dataset with a `crs` (geo.py, docs/design.md): the rig centre's
#: WGS 84 latitude, longitude (deg) and ellipsoidal height (m); the ZYX Euler angles (deg) of
#: ned_from_rig at the frame's own position; the centre's 1-sigma along north, east, down (m) and the
#: angles' (arc-min).
POSE_GEO_COLUMNS = ("lat_deg", "lon_deg", "h_m", "ned_heading_deg", "ned_pitch_deg", "ned_roll_deg",
                    "sigma_north_m", "sigma_east_m", "sigma_down_m", "sigma_ned_heading_arcmin",
                    "sigma_ned_pitch_arcmin", "sigma_ned_roll_arcmin")
#: One row per observation of a solved frame: whether the pose used it, and its residual (px).
POSE_OBSERVATION_COLUMNS = ("frame", "image", "camera", "point_id", "u", "v", "used", "du", "dv")
#: <poses>.budget.csv: one row per solved frame and error-model component (pose/error_model.py):
#: the group's sigma of the component (unit, and how it was obtained), and its share of the frame's
#: variances of x, y, z (m^2) and heading, pitch, roll (arcmin^2); their sums are the sigmas squared.
POSE_BUDGET_COLUMNS = ("frame", "component", "sigma", "unit", "source", "var_x_m2", "var_y_m2", "var_z_m2",
                       "var_heading_arcmin2", "var_pitch_arcmin2", "var_roll_arcmin2")
#: <poses>.mounting.csv and tables/mounting.csv: per flight group and camera, the rotation of its
#: in-flight cam_from_rig times the calibrated one's inverse (rotation vector in the camera frame,
#: arc-min), its 1-sigma, and whether it is significant; then its focal change and 1-sigma (ppm,
#: empty where the focal length was held; a file of an earlier version has neither) (pose/mounting.py).
MOUNTING_COLUMNS = ("group", "camera", "d_rx_arcmin", "d_ry_arcmin", "d_rz_arcmin", "sigma_rx_arcmin",
                    "sigma_ry_arcmin", "sigma_rz_arcmin", "significant", "d_focal_ppm", "sigma_focal_ppm")
TRUTH_COLUMNS = ("frame", "group", *QUAT, *TRANSLATION, *CENTER)
#: markers/<image>.csv: every detection, its sub-pixel standard deviation per axis and the fit's
#: residual (fraction of the marker's contrast), and its point id ('' when unidentified).
MARKER_COLUMNS = ("u", "v", "score", "sigma_px", "fit_residual", "point_id")
MARKER_REQUIRED = ("u", "v", "score", "point_id")
#: intrinsics/<camera>.residuals.csv: per observation of our calibration, observed minus projected (px).
CALIBRATION_RESIDUAL_COLUMNS = ("image", "split", "point_id", "u", "v", "du", "dv")
SUBSET_FILE = re.compile(r"^poses_(\d+)\.csv$")


def rig_from_world_of(pose_row) -> Rigid3:
    """rig_from_world of a poses.csv row (an itertuples row with qw, qx, qy, qz, tx, ty, tz)."""
    return Rigid3.from_quat([getattr(pose_row, c) for c in QUAT], [getattr(pose_row, c) for c in TRANSLATION])


class ResultsError(DatasetError):
    """A malformed results file (written by an earlier stage or by hand), naming the file and line."""


class Workspace:
    """The results folder `root` of `dataset`. A job's workspace (slices.py) holds the slice of the
    dataset it needs (`Dataset.restricted`) with, as the slice was cut from the whole load, its
    `observations` (those load_observations gives of its images) and its marker `batches`."""

    def __init__(self, dataset: Dataset, root: str | Path, observations: pd.DataFrame | None = None,
                 batches: dict[str, dict] | None = None):
        self.dataset = dataset
        self.root = Path(root)
        self._observations = observations
        self._batches = batches

    @classmethod
    def open(cls, dataset_dir: str | Path, results_dir: str | Path) -> Workspace:
        """The workspace of the dataset folder `dataset_dir` (loaded and validated) at `results_dir`."""
        return cls(Dataset.load(dataset_dir), results_dir)

    def __repr__(self) -> str:
        return f"Workspace({self.dataset.name!r}, root={str(self.root)!r})"

    # -------------------------------------------------------------- paths

    def markers_path(self, image: str) -> Path:
        return self.root / "markers" / f"{image}.csv"

    def marker_batch_path(self, batch: str) -> Path:
        """RESULTS/markers/batches/<batch>.csv: a marker job's images, counts and times (stages.markers)."""
        return self.root / "markers" / "batches" / f"{batch}.csv"

    def observations_path(self, stage: str | None = None) -> Path:
        """RESULTS/observations/<stage>.csv (the workflow's), or RESULTS/observations.csv (None)."""
        return observations_file(self.root, stage)

    def intrinsics_path(self, camera: str) -> Path:
        return self.root / "intrinsics" / f"{camera}.json"

    def methods_path(self, camera: str) -> Path:
        """One camera's rows of tables/intrinsics.csv, every method."""
        return self.root / "intrinsics" / f"{camera}.methods.csv"

    def calibration_residuals_path(self, camera: str) -> Path:
        """Per observation of our intrinsic calibration of `camera`: its residual (calib and eval images)."""
        return self.root / "intrinsics" / f"{camera}.residuals.csv"

    @property
    def rig_path(self) -> Path:
        return self.root / "rig.json"

    @property
    def rig_config_path(self) -> Path:
        """The rig in COLMAP's rig config layout, beside rig.json."""
        return self.root / "rig_config.json"

    @property
    def colmap_dir(self) -> Path:
        """RESULTS/colmap: the COLMAP export (`dmais export-colmap`)."""
        return self.root / "colmap"

    def colmap_model_dir(self, fmt: str) -> Path:
        """RESULTS/colmap/<fmt>: the sparse model as COLMAP text (fmt "text") or binary ("binary") files."""
        return self.colmap_dir / fmt

    def case_rig_path(self, case: str) -> Path:
        """extrinsics/rig_<case>.json: the rig calibrated with (known) or without (unknown) RTK priors."""
        return self.root / "extrinsics" / f"rig_{case}.json"

    @property
    def extrinsics_note_path(self) -> Path:
        """Why the rig calibrated without priors lands where it does, in the run's numbers."""
        return self.table_path("extrinsics_note").with_suffix(".txt")

    @property
    def layout_figure_path(self) -> Path:
        """fig:extrinsics, the rigs with and without priors (SVG)."""
        return self.root / "figures" / "extrinsics_layout.svg"

    def poses_path(self, label: str | None = None) -> Path:
        """poses.csv (the whole rig, label None) or poses_<label>.csv (a camera subset)."""
        return self.root / ("poses.csv" if label is None else f"poses_{label}.csv")

    def evaluation_path(self, label: str | None = None) -> Path:
        return self.root / ("evaluation.csv" if label is None else f"evaluation_{label}.csv")

    def table_path(self, name: str) -> Path:
        return self.root / "tables" / f"{name}.csv"

    def subset_labels(self) -> dict[str, Path]:
        """label -> poses_<label>.csv of the camera subsets solved so far, by length then value."""
        found = {}
        for path in self.root.glob("poses_*.csv"):
            match = SUBSET_FILE.match(path.name)
            if match:
                found[match.group(1)] = path
        return dict(sorted(found.items(), key=lambda item: (len(item[0]), item[0])))

    # -------------------------------------------------------------- markers and observations

    def save_markers(self, image: str, markers: pd.DataFrame) -> Path:
        return write_csv_atomic(self.markers_path(image), markers[list(MARKER_COLUMNS)])

    def load_markers(self, image: str) -> pd.DataFrame:
        """One image's detections: u, v, score, sigma_px, fit_residual (float; the last two NaN where
        a file predates them), point_id (str, '' when unidentified)."""
        path = self.markers_path(image)
        if not path.is_file():
            raise ResultsError(path, f"missing; run `dmais markers --image {image}`")
        with results_errors():
            table = read_table(path, MARKER_REQUIRED)
            columns = {c: table.floats(c, optional=c in ("sigma_px", "fit_residual")) for c in MARKER_COLUMNS[:-1]}
            return pd.DataFrame({**columns, "point_id": table.text("point_id")})

    def save_observations(self, observations: pd.DataFrame, stage: str | None = None) -> Path:
        return write_csv_atomic(self.observations_path(stage), observations)

    def load_observations(self) -> pd.DataFrame:
        """Observations (image, camera, point_id, u, v + extras) used downstream.

        The first source found wins, each validated against the dataset with errors naming its file:
        1. RESULTS/observations/<stage>.csv, the union over the stages that have one (the workflow
           collects each stage's per-image markers there, `dmais markers --collect STAGE`);
        2. RESULTS/observations.csv, written by `dmais markers` over the whole dataset;
        3. the dataset's own observations, with `camera` taken from images.csv.
        A job's workspace gives those of its slice (slices.py).
        """
        if self._observations is not None:
            return self._observations.copy()
        self._check_whole("observations")
        dataset = self.dataset
        *per_stage, whole = observation_files(self.root)
        paths = [p for p in per_stage if p.exists()]
        if paths and whole.exists():
            log.warning("%s is ignored: the per-stage files %s take precedence", whole, [str(p) for p in paths])
        if not paths and whole.exists():
            paths = [whole]
        if paths:
            tables = [read_observation_table(p, dataset) for p in paths]
            return pd.concat(tables, ignore_index=True) if len(tables) > 1 else tables[0]
        observations = dataset.observations.copy()
        camera_of = camera_of_images(dataset.images)
        observations.insert(1, "camera", observations["image"].map(camera_of).astype(str))
        return observations

    def marker_batches(self, per_job: int) -> dict[str, dict]:
        """plan.marker_batches of the dataset with `per_job` images a job; a job's workspace gives
        the batch its slice was cut for (slices.py)."""
        if self._batches is not None:
            return self._batches
        self._check_whole("marker batches")
        return marker_batches(self.dataset, per_job)

    def _check_whole(self, what: str) -> None:
        """A slice's dataset lacks the other images: what is made from all of them is not made from it."""
        if self.dataset.part:
            raise ValueError(f"{self!r} holds only {self.dataset.part} of the dataset, not its {what}")

    # -------------------------------------------------------------- intrinsics and rig

    def save_intrinsics(self, camera: str, record: dict, methods: pd.DataFrame) -> list[Path]:
        """<camera>.json (our calibration, docs/design.md) and <camera>.methods.csv (every method)."""
        return [write_json_atomic(self.intrinsics_path(camera), record),
                write_csv_atomic(self.methods_path(camera), methods)]

    def load_intrinsics(self, camera: str) -> tuple[Camera, dict]:
        """The calibrated Camera of `camera` and its whole record."""
        path = self.intrinsics_path(camera)
        try:
            data = json.loads(path.read_text())
            return Camera.from_dict(data), data
        except FileNotFoundError:
            raise DmaisError(f"{path}: missing; run `dmais intrinsics` first") from None
        except (KeyError, TypeError, ValueError) as error:
            raise DmaisError(f"{path}: not a valid intrinsics file ({error})") from None

    def load_methods(self, camera: str) -> pd.DataFrame:
        path = self.methods_path(camera)
        if not path.is_file():
            raise DmaisError(f"intrinsics table: missing {path}; run `dmais intrinsics --camera {camera}`")
        return pd.read_csv(path, dtype={"method": str, "camera": str})

    def save_calibration_residuals(self, camera: str, residuals: pd.DataFrame) -> Path:
        return write_csv_atomic(self.calibration_residuals_path(camera), residuals[list(CALIBRATION_RESIDUAL_COLUMNS)])

    def load_calibration_residuals(self, camera: str) -> pd.DataFrame | None:
        """image, split, point_id (str), u, v, du, dv (float) of `camera`'s calibration; None when absent."""
        path = self.calibration_residuals_path(camera)
        if not path.is_file():
            return None
        with results_errors():
            table = read_table(path, CALIBRATION_RESIDUAL_COLUMNS)
            return pd.DataFrame({**{c: table.text(c) for c in CALIBRATION_RESIDUAL_COLUMNS[:3]},
                                 **{c: table.floats(c) for c in CALIBRATION_RESIDUAL_COLUMNS[3:]}})

    def save_rig(self, rig: Rig, case: str | None = None, **extra) -> Path:
        """rig.json (case None) or extrinsics/rig_<case>.json; `extra` keys are stored beside the rig."""
        return rig.save(self.rig_path if case is None else self.case_rig_path(case), **extra)

    def save_rig_config(self, config: list[dict]) -> Path:
        return write_json_atomic(self.rig_config_path, config)

    def save_extrinsics_note(self, note: str) -> Path:
        return write_text_atomic(self.extrinsics_note_path, note.strip() + "\n")

    def load_extrinsics_note(self) -> str | None:
        path = self.extrinsics_note_path
        return path.read_text().strip() if path.is_file() else None

    def has_rig(self) -> bool:
        return self.rig_path.is_file()

    def load_rig(self) -> Rig:
        if not self.rig_path.is_file():
            raise DmaisError(f"{self.rig_path}: missing; run `dmais extrinsics` first")
        return Rig.load(self.rig_path)

    # -------------------------------------------------------------- poses

    def save_poses(self, poses: pd.DataFrame, observations: pd.DataFrame, path: Path,
                   budget: pd.DataFrame | None = None, mounting: pd.DataFrame | None = None) -> list[Path]:
        """A poses file (POSE_COLUMNS, then any extra columns) and, beside it, its per-observation file
        and, when given, its error budget (POSE_BUDGET_COLUMNS) and its rig watched in flight
        (MOUNTING_COLUMNS). With the dataset's `crs`, x, y, z are written in it (`centres_in_crs`)."""
        extras = [c for c in poses.columns if c not in POSE_COLUMNS]
        poses = self.centres_in_crs(poses)
        written = [write_text_atomic(path, csv_text(poses[[*POSE_COLUMNS, *extras]])),
                   write_text_atomic(pose_observations_path(path), csv_text(observations[list(POSE_OBSERVATION_COLUMNS)]))]
        if budget is not None:
            written.append(write_text_atomic(pose_file_beside(path, "budget"),
                                             csv_text(budget[list(POSE_BUDGET_COLUMNS)])))
        if mounting is not None:
            written.append(write_text_atomic(pose_file_beside(path, "mounting"),
                                             csv_text(mounting[list(MOUNTING_COLUMNS)])))
        return written

    def load_poses(self, path: Path | None = None, allowed_cameras: Sequence[str] | None = None,
                   empty_ok: bool = False) -> pd.DataFrame:
        """A poses file (default poses.csv) checked against the dataset and the rig.

        Numbers must be finite; frames must be frames of the dataset with the same group; cameras
        (names joined by '+') must be cameras of the rig (and of `allowed_cameras` when given); a
        file without rows is an error unless empty_ok (a per-group part of the workflow).
        Raises ResultsError naming the file and line. Returns typed columns: POSE_UNCERTAINTY_COLUMNS
        and POSE_GEO_COLUMNS as floats (NaN where empty) when the file has them, other extras as
        strings. With the dataset's `crs`, x, y, z are returned in the computation frame.
        """
        path = self.poses_path() if path is None else Path(path)
        if not path.is_file():
            raise ResultsError(path, "missing; run `dmais pose` first")
        rig = self.load_rig()
        with results_errors():
            table = read_table(path, POSE_COLUMNS)
            if len(table) == 0 and not empty_ok:
                raise ResultsError(path, "has no rows; no frame to evaluate")
            frame = _checked_frames(table, self.dataset)
            cameras = _checked_cameras(table, rig, allowed_cameras)
            numbers = {c: table.floats(c) for c in POSE_COLUMNS[3:]}
            n_points = numbers["n_points"]
            table.check((n_points != np.round(n_points)) | (n_points < 0),
                        lambda row: f"column n_points: {n_points[row]:g} is not a count")
            extras = {c: table.floats(c, optional=True) if c in (*POSE_UNCERTAINTY_COLUMNS, *POSE_GEO_COLUMNS)
                      else table.text(c) for c in table.extra_columns(POSE_COLUMNS)}
            geo = self.dataset.geo
            if geo is not None and len(table):
                centres = np.column_stack([numbers[c] for c in CENTER])
                try:
                    centres = geo.enu_from_crs(centres)
                except GeoError as error:
                    raise table.error(f"x, y, z in crs {geo.crs!r}: {error}", error.row) from None
                numbers.update(zip(CENTER, centres.T))
        return pd.DataFrame({"frame": frame, "group": table.text("group"), "cameras": cameras,
                             **numbers, "n_points": n_points.astype(int), **extras})

    def centres_in_crs(self, table: pd.DataFrame) -> pd.DataFrame:
        """A poses or evaluation table with its x, y, z (computation frame) in the dataset's `crs`
        (geo.Geo.crs_from_enu); the table itself without one."""
        geo = self.dataset.geo
        if geo is None or not len(table):
            return table
        out = table.copy()
        out[list(CENTER)] = geo.crs_from_enu(table[list(CENTER)].to_numpy(float))
        return out

    def load_pose_observations(self, path: Path | None = None) -> pd.DataFrame | None:
        """The per-observation file beside a poses file (default poses.csv): frame, image, camera,
        point_id (str), u, v, du, dv (float), used (bool); None when the poses file has none."""
        with results_errors():
            table = self._beside_poses(path, "observations", POSE_OBSERVATION_COLUMNS)
            return None if table is None else pd.DataFrame({
                **{c: table.text(c) for c in ("frame", "image", "camera", "point_id")},
                **{c: table.floats(c, optional=c in ("du", "dv")) for c in ("u", "v", "du", "dv")},
                "used": _flags(table, "used")})

    def load_pose_budget(self, path: Path | None = None) -> pd.DataFrame | None:
        """The error budget beside a poses file (default poses.csv), POSE_BUDGET_COLUMNS typed (frame,
        component, unit, source as text); None when the poses file has none."""
        text = ("frame", "component", "unit", "source")
        with results_errors():
            table = self._beside_poses(path, "budget", POSE_BUDGET_COLUMNS)
            return None if table is None else pd.DataFrame({
                c: table.text(c) if c in text else table.floats(c, optional=True) for c in POSE_BUDGET_COLUMNS})

    def load_pose_mounting(self, path: Path | None = None) -> pd.DataFrame | None:
        """The rig watched in flight beside a poses file (default poses.csv), MOUNTING_COLUMNS (group,
        camera as text, significant as bool); None when the poses file has none."""
        with results_errors():
            table = self._beside_poses(path, "mounting", MOUNTING_COLUMNS[:9])
            return None if table is None else pd.DataFrame({
                "group": table.text("group"), "camera": table.text("camera"),
                **{c: table.floats(c, optional=True) for c in MOUNTING_COLUMNS[2:8]},
                "significant": _flags(table, "significant"),
                **{c: table.floats(c, optional=True) for c in MOUNTING_COLUMNS[9:]}})

    def _beside_poses(self, path: Path | None, kind: str, columns: Sequence[str]) -> Table | None:
        """The `kind` file beside a poses file (default poses.csv) read with `columns`; None when absent."""
        beside = pose_file_beside(self.poses_path() if path is None else Path(path), kind)
        return read_table(beside, columns) if beside.is_file() else None

    def load_truth_frames(self) -> pd.DataFrame | None:
        """truth/frames.csv of a simulated dataset indexed by frame (TRUTH_COLUMNS as floats), None
        without truth."""
        path = self.dataset.truth_dir / "frames.csv"
        if not path.is_file():
            return None
        table = read_table(path, TRUTH_COLUMNS)
        columns = {"frame": table.required_text("frame"), "group": table.text("group")}
        columns.update({c: table.floats(c) for c in TRUTH_COLUMNS[2:]})
        return pd.DataFrame(columns).set_index("frame")

    # -------------------------------------------------------------- evaluation and tables

    def save_evaluation(self, evaluation: pd.DataFrame, label: str | None = None) -> Path:
        """evaluation.csv (or evaluation_<label>.csv); x, y, z in the dataset's `crs` where it has one."""
        return write_csv_atomic(self.evaluation_path(label), self.centres_in_crs(evaluation))

    def load_evaluation(self, label: str | None = None) -> pd.DataFrame | None:
        """evaluation.csv (or evaluation_<label>.csv) as written by the evaluate stage; None when absent."""
        path = self.evaluation_path(label)
        return pd.read_csv(path, dtype={"frame": str, "group": str, "cameras": str}) if path.is_file() else None

    def save_table(self, name: str, table: pd.DataFrame, float_format: str | None = None) -> Path:
        return write_csv_atomic(self.table_path(name), table, float_format=float_format)

    def load_table(self, name: str, keys: Sequence[str] = ()) -> pd.DataFrame | None:
        """tables/<name>.csv with its key columns as text (subset '012' stays '012'); None when absent."""
        path = self.table_path(name)
        return pd.read_csv(path, dtype={k: str for k in keys}) if path.is_file() else None

    def table_paths(self) -> list[Path]:
        """Every tables/*.csv written so far, by name."""
        return sorted((self.root / "tables").glob("*.csv"))


def observation_files(root: Path) -> list[Path]:
    """Every file Workspace.load_observations may read in the results folder `root`: the per-stage
    ones (`observations_file`, in STAGES order), then RESULTS/observations.csv."""
    return [observations_file(root, stage) for stage in STAGES] + [observations_file(root)]


def observations_file(root: Path, stage: str | None = None) -> Path:
    """RESULTS/observations/<stage>.csv (the workflow's), or RESULTS/observations.csv (None)."""
    return root / "observations.csv" if stage is None else root / "observations" / f"{stage}.csv"


def pose_file_beside(poses_path: str | Path, kind: str) -> Path:
    """The `kind` file (observations, budget, mounting) beside a poses file: poses.csv -> poses.<kind>.csv."""
    poses_path = Path(poses_path)
    return poses_path.with_name(f"{poses_path.stem}.{kind}.csv")


def pose_observations_path(poses_path: str | Path) -> Path:
    """The per-observation file beside a poses file: poses.csv -> poses.observations.csv."""
    return pose_file_beside(poses_path, "observations")


def _flags(table: Table, column: str) -> np.ndarray:
    """(n,) bool of a column of True/False cells; another value is an error naming its line."""
    text = table.text(column)
    table.check(~np.isin(text, ("True", "False")), lambda row: f"column {column}: {text[row]!r} is not True/False")
    return text == "True"


@contextmanager
def results_errors():
    """Turn a DatasetError of the shared CSV reader into a ResultsError (same file, line, message)."""
    try:
        yield
    except ResultsError:
        raise
    except DatasetError as error:
        raise ResultsError(error.path, error.message, error.line) from None


def _checked_frames(table: Table, dataset: Dataset) -> np.ndarray:
    frame = table.required_text("frame")
    table.first_rows(["frame"], "frame")
    group_of = dict(zip(dataset.frames["frame"], dataset.frames["group"]))
    table.check([f not in group_of for f in frame],
                lambda row: f"frame {frame[row]!r} is not a frame of {dataset.root / 'frames.csv'}")
    group = table.text("group")
    table.check([group_of[f] != g for f, g in zip(frame, group)],
                lambda row: f"frame {frame[row]!r}: group {group[row]!r}, frames.csv says {group_of[frame[row]]!r}")
    return frame


def _checked_cameras(table: Table, rig: Rig, allowed: Sequence[str] | None) -> np.ndarray:
    cameras = table.required_text("cameras")
    names = [c.split("+") for c in cameras]
    table.check([any(n not in rig.cameras for n in row) for row in names],
                lambda row: f"cameras {cameras[row]!r}: not all are cameras of the rig ({', '.join(rig.camera_names)})")
    if allowed is not None:
        table.check([any(n not in allowed for n in row) for row in names],
                    lambda row: f"cameras {cameras[row]!r}: this subset file may use only {'+'.join(allowed)}")
    return cameras
