"""`dmais bench stereo`: OpenCV's stereo chessboard photographs through intrinsics, extrinsics and
pose, against cv2.calibrateCamera + cv2.stereoCalibrate + cv2.solvePnP.

The photographs (tests/data/chessboard, `bench.periodic`: 640 x 480, a wide-angle lens, pairs
leftNN / rightNN taken together) become a two-camera rig dataset (`write_stereo_dataset`): cameras
left (the reference) and right of the given model, and the board corners found by
findChessboardCorners + cornerSubPix as observations.csv, so that the comparison measures the
calibration chain rather than the corner detector:

- intrinsics: every photograph, images 09 and 11 held out (periodic's split);
- extrinsics: each pair found on both sides is one placement, each image's prior pose OpenCV's
  solvePnP moved by 5 mm and turned by 0.3 deg (periodic.perturbed), its centre the RTK prior;
- flight: each pair again, as a frame, its POS position the left camera's solvePnP centre.

OpenCV's reference: calibrateCamera per side on the same calib split and model (periodic's
`opencv_calibration`), stereoCalibrate over all pairs with those intrinsics fixed (right_from_left),
and solvePnP per photograph; a frame's rig_from_world is the left camera's cam_from_world, or the
right camera's turned into the rig by stereoCalibrate's extrinsics.

Compared (`compare`): each camera's intrinsics (focal %, principal point px, eps_eval of both, OpenCV's
by our same pose-only fit of the held-out images); the rig's right_from_left (baseline mm,
rotation arc-min); per frame, `dmais pose --refine` with left alone, right alone and both cameras
against solvePnP of each side (position mm, rotation arc-min), beside the two solvePnP apart.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from ..dataset import Dataset, write_dataset
from ..files import write_csv_atomic
from ..geometry import Rigid3, rotation_angle
from ..stages import extrinsics as extrinsics_stage
from ..stages import intrinsics as intrinsics_stage
from ..stages import pose as pose_stage
from ..workspace import Workspace
from ..calib.intrinsics import evaluate
from .periodic import FOCAL_PX, PHOTOS, SQUARE_M, board_points, opencv_calibration, perturbed, photographs, point_ids
from .sigma import _stages_quiet

log = logging.getLogger(__name__)

SIDES = ("left", "right")
SEED = 38
SUBSETS = {"left": ["left"], "right": ["right"], "both": ["left", "right"]}
ARCMIN_PER_RAD = 60.0 * 180.0 / np.pi


def pairs_of(photos: dict[str, dict]) -> list[str]:
    """The photograph numbers ("01", ...) found on both sides."""
    numbers = sorted({name[-2:] for name in photos})
    return [k for k in numbers if all(f"{side}{k}" in photos for side in SIDES)]


def opencv_reference(photos: dict[str, dict], model: str) -> dict:
    """OpenCV's calibration of the photographs: per side the calibrateCamera result (periodic's
    `opencv_calibration` on the calib split), stereoCalibrate's right_from_left (Rigid3) and its RMS,
    and every photograph's cam_from_world by solvePnP."""
    calibrations, size = {}, (640, 480)
    for side in SIDES:
        names = [n for n, p in photos.items() if p["camera"] == side and p["split"] == "calib"]
        size = photos[names[0]]["pixels"].shape[::-1]
        calibrations[side] = opencv_calibration([photos[n]["corners"] for n in names], [point_ids()] * len(names),
                                                size, model)
    K = {side: calibrations[side]["camera"].K for side in SIDES}
    D = {side: np.array(calibrations[side]["camera"].distortion) for side in SIDES}
    pairs = pairs_of(photos)
    board = board_points().astype(np.float32)
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        [board] * len(pairs), *([photos[f"{side}{k}"]["corners"].astype(np.float32) for k in pairs] for side in SIDES),
        K["left"], D["left"], K["right"], D["right"], size, flags=cv2.CALIB_FIX_INTRINSIC)
    poses = {}
    for name, photo in photos.items():
        _, rvec, tvec = cv2.solvePnP(board_points(), photo["corners"], K[photo["camera"]], D[photo["camera"]])
        poses[name] = Rigid3(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return {"calibrations": calibrations, "right_from_left": Rigid3(R, T.ravel()), "stereo_rms_px": float(rms),
            "poses": poses}


def write_stereo_dataset(photos: dict[str, dict], poses: dict[str, Rigid3], root: Path, model: str,
                         seed: int = SEED) -> Dataset:
    """The two-camera dataset of the module docstring under `root` (no image files: the corners are
    its observations); poses: OpenCV's cam_from_world per photograph, for the priors."""
    rng = np.random.default_rng(seed)
    images, observations, frames = [], [], []

    def add(image: str, photo: str, stage: str, split: str, placement: str) -> None:
        prior = perturbed(poses[photo], rng)
        images.append({"image": image, "camera": photos[photo]["camera"], "stage": stage, "split": split,
                       "placement": placement, "path": "",
                       **dict(zip(("prior_x", "prior_y", "prior_z"), prior.center)),
                       **dict(zip(("prior_qw", "prior_qx", "prior_qy", "prior_qz"), prior.quat))})
        observations.extend({"image": image, "point_id": point, "u": u, "v": v}
                            for point, (u, v) in zip(point_ids(), photos[photo]["corners"]))

    for name, photo in photos.items():
        add(name, name, "intrinsics", photo["split"], "")
    for k in pairs_of(photos):
        for side in SIDES:
            add(f"x{side}{k}", f"{side}{k}", "extrinsics", "", f"p{k}")
            add(f"f{side}{k}", f"{side}{k}", "flight", "", f"f{k}")
        frames.append({"frame": f"f{k}", "group": "", **dict(zip(("pos_x", "pos_y", "pos_z"), poses[f"left{k}"].center))})
    height, width = next(iter(photos.values()))["pixels"].shape
    cameras = {side: {"width": width, "height": height, "focal_px": FOCAL_PX, "model": model} for side in SIDES}
    points = pd.DataFrame(board_points(), columns=["x", "y", "z"], index=pd.Index(point_ids(), name="point_id"))
    manifest = {"name": "stereo", "reference_camera": "left", "cameras": cameras, "marker_size_m": SQUARE_M}
    write_dataset(root, manifest, points, pd.DataFrame(images), frames=pd.DataFrame(frames),
                  observations=pd.DataFrame(observations))
    return Dataset.load(root)


def run_stages(workspace: Workspace) -> dict[str, pd.DataFrame]:
    """intrinsics (conf ours), extrinsics, then the pose (refined) of every frame with each of
    SUBSETS; returns poses.csv's table per subset."""
    with _stages_quiet():
        intrinsics_stage.run(workspace, intrinsics_stage.CONFS["ours"])
        extrinsics_stage.run(workspace)
        solved = {}
        for label, cameras in SUBSETS.items():
            out = workspace.root / f"poses_stereo_{label}.csv"
            pose_stage.run(workspace, pose_stage.Conf(refine=True), cameras=cameras, out=out)
            solved[label] = pd.read_csv(out, dtype={"frame": str})
    return solved


def compare(photos: dict[str, dict], reference: dict, workspace: Workspace, solved: dict[str, pd.DataFrame]
            ) -> pd.DataFrame:
    """The comparison table of the module docstring: one row per quantity, with its median and
    maximum where it has one per frame."""
    rows = [_intrinsics_row(photos, reference, workspace, side) for side in SIDES]
    ours = workspace.load_rig().cam_from_rig["right"]
    theirs = reference["right_from_left"]
    rows.append({"what": "rig right_from_left vs stereoCalibrate", "position_mm": 1000 * np.linalg.norm(ours.t - theirs.t),
                 "rotation_arcmin": float(rotation_angle(ours.R @ theirs.R.T)) * ARCMIN_PER_RAD})
    references = {k: {"left": reference["poses"][f"left{k}"],
                      "right": theirs.inverse() * reference["poses"][f"right{k}"]} for k in pairs_of(photos)}
    for label, table in solved.items():
        for side in SIDES:
            errors = [_apart(_rig_from_world(row), references[row.frame[1:]][side]) for row in table.itertuples()]
            rows.append(_per_frame(f"pose {label} vs solvePnP {side}", errors))
    rows.append(_per_frame("solvePnP left vs solvePnP right", [_apart(r["left"], r["right"]) for r in references.values()]))
    return pd.DataFrame(rows)


def _intrinsics_row(photos: dict[str, dict], reference: dict, workspace: Workspace, side: str) -> dict:
    ours = workspace.load_intrinsics(side)[1]
    theirs = reference["calibrations"][side]
    held_out = [n for n, p in photos.items() if p["camera"] == side and p["split"] == "eval"]
    eps_eval = evaluate(theirs["camera"], [board_points()] * len(held_out), [photos[n]["corners"] for n in held_out],
                        side)
    return {"what": f"intrinsics {side} vs calibrateCamera", "focal_pct": 100.0 * (ours["fx"] / theirs["fx"] - 1.0),
            "principal_px": float(np.hypot(ours["cx"] - theirs["cx"], ours["cy"] - theirs["cy"])),
            "eps_eval_px": ours["eps_eval_px"], "eps_eval_opencv_px": eps_eval}


def _rig_from_world(row) -> Rigid3:
    return Rigid3.from_quat([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz])


def _apart(a: Rigid3, b: Rigid3) -> tuple[float, float]:
    """(mm, arc-min) between two rig_from_world: their centres' distance and the rotation between them."""
    return 1000 * float(np.linalg.norm(a.center - b.center)), float(rotation_angle(a.R @ b.R.T)) * ARCMIN_PER_RAD


def _per_frame(what: str, errors: list[tuple[float, float]]) -> dict:
    position, rotation = np.array(errors).reshape(-1, 2).T
    return {"what": what, "frames": len(position), "position_mm": float(np.median(position)),
            "position_max_mm": float(position.max()), "rotation_arcmin": float(np.median(rotation)),
            "rotation_max_arcmin": float(rotation.max())}


def bench_stereo(photos_dir: Path | None = None, csv: Path | None = None, model: str = "opencv",
                 work: Path | None = None) -> pd.DataFrame:
    """Run the comparison on the photographs of `photos_dir` (default: tests/data/chessboard) in
    `work` (default: a temporary folder); write `csv` if given; returns the table."""
    photos = photographs(photos_dir or PHOTOS)
    reference = opencv_reference(photos, model)
    with tempfile.TemporaryDirectory(prefix="dmais-stereo-") as scratch:
        root = Path(work) if work else Path(scratch)
        dataset = write_stereo_dataset(photos, reference["poses"], root / "dataset", model)
        workspace = Workspace(dataset, root / "results")
        table = compare(photos, reference, workspace, run_stages(workspace))
    table.attrs["stereo_rms_px"] = reference["stereo_rms_px"]
    if csv:
        write_csv_atomic(Path(csv), table)
    return table


def print_table(table: pd.DataFrame) -> None:
    print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}", na_rep=""))
