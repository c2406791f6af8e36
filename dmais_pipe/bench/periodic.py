"""`dmais bench periodic`: identification on a periodic target, OpenCV's chessboard photographs.

The photographs (640 x 480, a 9 x 6 grid of inner corners, 25 mm squares, a wide-angle lens with
d ~ -0.26: OpenCV's samples left01..left14 and right01..right14 without 10, 26 in all, of which
tests/data/chessboard, the default, holds the ten of the left camera but 12..14) become a dataset: one
camera per side (the file name's letters: left, right) with focal_px 535 and nothing else known of
the lens (principal point at the image centre, no distortion); the board's corners are the control
points, ids `c<col>r<row>` in cv2.findChessboardCorners' order. Each image's pose prior is
cv2.solvePnP with OpenCV's own calibration of the same photographs (cv2.calibrateCamera, its default
model, on the found corners of every photograph of that side), moved by a seeded 5 mm in a random
direction and turned by 0.3 deg about a random axis. Images numbered 09 and 11 are held out (split
eval), the others calibrate.

`dmais markers`' per-image work (markers.extract.process_image with the stage's default settings,
as `dmais markers` runs it) extracts every image; each true corner (findChessboardCorners +
cornerSubPix) is matched to the detection at it (AT_CORNER_FRACTION). Per image: corners, those
identified with their true id, wrong ids (an id on a detection that is not that point's corner),
refused (detected but left without id, counted by reason), off_px (identified more than OFF_PX from
cornerSubPix's corner: at the board's edge in steep views, where cornerSubPix is biased). Then
`dmais intrinsics` (conf ours) beside cv2.calibrateCamera with the same lens model (`model`: radial1,
the one-coefficient model, by default; or opencv, OpenCV's default model) on the same calib split,
once on the true corners (cornerSubPix) and once on our identified corners (the observations): the
focal lengths' difference (%), the principal points' distance (px), the distortion coefficients,
both eps_calib, and with model opencv both eps_eval.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ..calib.intrinsics import OPENCV_FIXED_FLAGS, evaluate, opencv_camera
from ..camera import PARAMETER_NAMES
from ..dataset import Dataset, write_dataset
from ..errors import DmaisError
from ..files import write_csv_atomic
from ..geometry import Rigid3, exp_so3
from ..markers.extract import observation_table, process_image
from ..stages import intrinsics as intrinsics_stage
from ..stages.markers import Conf as MarkersConf
from ..workspace import Workspace

PHOTOS = Path(__file__).resolve().parents[2] / "tests" / "data" / "chessboard"
PATTERN = (9, 6)
SQUARE_M = 0.025
FOCAL_PX = 535.0
SHIFT_M = 0.005
TURN_DEG = 0.3
EVAL_NUMBERS = (9, 11)
#: A detection is at a true corner within this fraction of the corner's distance to its nearest neighbour
#: (23-44 px here): at the board's edge in steep views cornerSubPix's window takes in the board's border
#: and moves its corner by up to ~6 px off the X-junction (where our refined corner lies).
AT_CORNER_FRACTION = 0.3
OFF_PX = 2.0  # an identified corner this far from cornerSubPix's is counted in `off_px`


def board_points() -> np.ndarray:
    """(54, 3) board corners (x = col, y = row, z = 0) in metres, in findChessboardCorners' order."""
    cols, rows = np.meshgrid(np.arange(PATTERN[0]), np.arange(PATTERN[1]))
    return np.column_stack([cols.ravel(), rows.ravel(), np.zeros(cols.size)]) * SQUARE_M


def point_ids() -> np.ndarray:
    """(54,) ids `c<col>r<row>` of board_points."""
    cols, rows = np.meshgrid(np.arange(PATTERN[0]), np.arange(PATTERN[1]))
    return np.array([f"c{c}r{r}" for c, r in zip(cols.ravel(), rows.ravel())], dtype=object)


def true_corners(image: np.ndarray) -> np.ndarray | None:
    """(54, 2) inner corners (findChessboardCorners + cornerSubPix, win 11), or None when not found."""
    found, corners = cv2.findChessboardCorners(image, PATTERN)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    return cv2.cornerSubPix(image, corners, (11, 11), (-1, -1), criteria).reshape(-1, 2).astype(float)


def photographs(folder: Path) -> dict[str, dict]:
    """name -> {path, camera, split, pixels (h, w), corners (54, 2)} of the photographs whose board is found."""
    out = {}
    for path in sorted(Path(folder).glob("*.jpg")):
        camera, number = re.fullmatch(r"([a-zA-Z]+)(\d+)", path.stem).groups()
        pixels = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        corners = true_corners(pixels)
        if corners is not None:
            out[path.stem] = {"path": path, "camera": camera, "pixels": pixels, "corners": corners,
                              "split": "eval" if int(number) in EVAL_NUMBERS else "calib"}
    return out


def opencv_poses(photos: dict[str, dict]) -> dict[str, Rigid3]:
    """cam_from_world of every photograph: cv2.solvePnP with cv2.calibrateCamera (default model) of its side."""
    poses = {}
    for camera in sorted({p["camera"] for p in photos.values()}):
        names = [n for n, p in photos.items() if p["camera"] == camera]
        objects = [board_points().astype(np.float32)] * len(names)
        corners = [photos[n]["corners"].astype(np.float32) for n in names]
        size = photos[names[0]]["pixels"].shape[::-1]
        _, K, dist, _, _ = cv2.calibrateCamera(objects, corners, size, None, None)
        for name, points in zip(names, corners):
            _, rvec, tvec = cv2.solvePnP(board_points(), points.astype(float), K, dist)
            poses[name] = Rigid3(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return poses


def perturbed(pose: Rigid3, rng: np.random.Generator, shift_m: float = SHIFT_M, turn_deg: float = TURN_DEG) -> Rigid3:
    """`pose` (cam_from_world) with its centre moved by shift_m and its attitude turned by turn_deg,
    each in a random direction."""
    direction, axis = rng.normal(size=(2, 3))
    R = exp_so3(np.radians(turn_deg) * axis / np.linalg.norm(axis)) @ pose.R
    centre = pose.center + shift_m * direction / np.linalg.norm(direction)
    return Rigid3(R, -R @ centre)


def write_photo_dataset(photos: dict[str, dict], root: Path, seed: int, model: str = "radial1",
                        corners: bool = False) -> Dataset:
    """The dataset of the photographs under `root` (images copied), priors perturbed with `seed`, its
    cameras of lens model `model`; with `corners`, every photograph's true corners (cornerSubPix) are
    the dataset's observations (so that `dmais intrinsics` runs without `dmais markers`)."""
    rng = np.random.default_rng(seed)
    poses = opencv_poses(photos)
    rows = []
    for name, photo in photos.items():
        target = root / "images" / photo["path"].name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(photo["path"], target)
        prior = perturbed(poses[name], rng)
        rows.append({"image": name, "camera": photo["camera"], "stage": "intrinsics", "split": photo["split"],
                     "placement": "", "path": f"images/{target.name}",
                     **dict(zip(("prior_x", "prior_y", "prior_z"), prior.center)),
                     **dict(zip(("prior_qw", "prior_qx", "prior_qy", "prior_qz"), prior.quat))})
    height, width = next(iter(photos.values()))["pixels"].shape
    cameras = {c: {"width": width, "height": height, "focal_px": FOCAL_PX, "model": model}
               for c in dict.fromkeys(p["camera"] for p in photos.values())}
    points = pd.DataFrame(board_points(), columns=["x", "y", "z"], index=pd.Index(point_ids(), name="point_id"))
    points["sigma_m"] = 0.0  # a printed board's corners are exact, as OpenCV takes them (no survey to estimate)
    manifest = {"name": "chessboard", "reference_camera": next(iter(cameras)), "cameras": cameras,
                "marker_size_m": SQUARE_M}
    observations = pd.concat([pd.DataFrame({"image": name, "point_id": point_ids(), "u": photo["corners"][:, 0],
                                            "v": photo["corners"][:, 1]}) for name, photo in photos.items()],
                             ignore_index=True) if corners else None
    write_dataset(root, manifest, points, pd.DataFrame(rows), observations=observations)
    return Dataset.load(root)


def score_image(markers: pd.DataFrame, corners: np.ndarray) -> dict:
    """Counts of one image: its markers (u, v, point_id[, id_refusal]) against the true corners (54, 2).
    A detection's true id is that of the corner it lies at (AT_CORNER_FRACTION); an id anywhere else,
    or another corner's, is wrong."""
    uv = markers[["u", "v"]].to_numpy(dtype=float)
    ids = markers["point_id"].to_numpy(dtype=object)
    reasons = markers["id_refusal"].to_numpy(dtype=object) if "id_refusal" in markers else np.full(len(ids), "")
    truth, distance = np.full(len(uv), "", dtype=object), np.full(len(uv), np.inf)
    if len(uv):
        distance, nearest = cKDTree(corners).query(uv)
        spacing = cKDTree(corners).query(corners, 2)[0][:, 1]
        at = distance <= AT_CORNER_FRACTION * spacing[nearest]
        truth[at] = point_ids()[nearest[at]]
    named, at_corner = ids != "", truth != ""
    refused = at_corner & ~named
    why = Counter(r or "unknown" for r in reasons[refused])
    return {"corners": len(corners), "detected": int(at_corner.sum()),
            "identified": int((named & (ids == truth)).sum()), "wrong": int((named & (ids != truth)).sum()),
            "refused": int(refused.sum()), "off_px": int((named & (ids == truth) & (distance > OFF_PX)).sum()),
            "reasons": "; ".join(f"{r} {n}" for r, n in why.most_common())}


def extract_and_score(dataset: Dataset, workspace: Workspace, photos: dict[str, dict]) -> pd.DataFrame:
    """Every image through `process_image` (the markers stage's defaults), its markers and the
    observations written as `dmais markers` writes them; one row of `score_image` per image."""
    conf, rows, markers = MarkersConf(), [], {}
    for name, photo in photos.items():
        markers[name] = process_image(dataset, name, None, None, conf.prediction_margin_px, conf.verify_gate_px,
                                      conf.identify_gate_px, conf.identify_min_inliers)
        workspace.save_markers(name, markers[name])
        rows.append({"image": name, "camera": photo["camera"], "split": photo["split"],
                     **score_image(markers[name], photo["corners"])})
    workspace.save_observations(observation_table(dataset, list(photos), markers))
    table = pd.DataFrame(rows)
    table.insert(table.columns.get_loc("identified") + 1, "identified_pct",
                 100.0 * table["identified"] / table["corners"])
    return table


def opencv_calibration(corners: list[np.ndarray], ids: list[np.ndarray], size: tuple[int, int],
                       model: str = "radial1") -> dict:
    """cv2.calibrateCamera on corners (n_i, 2) of the board points `ids` (n_i,) with our `model`:
    radial1 k1 alone, opencv its default model. Returns the model's parameters by name, the Camera
    ("camera") and eps_calib_px."""
    flags = OPENCV_FIXED_FLAGS[model]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    objects = [_board_points_of(names).astype(np.float32) for names in ids]
    rms, K, dist, _, _ = cv2.calibrateCamera(objects, [c.astype(np.float32) for c in corners], size, None, None,
                                             flags=flags, criteria=criteria)
    camera = opencv_camera(K, dist, size[0], size[1], model)
    return {**dict(zip(camera.parameter_names, camera.parameters)), "camera": camera, "eps_calib_px": rms}


def _board_points_of(names) -> np.ndarray:
    """(n, 3) the board points of ids `names` (n,)."""
    index = {point: k for k, point in enumerate(point_ids())}
    return board_points()[[index[i] for i in names]]


def compare_intrinsics(workspace: Workspace, photos: dict[str, dict]) -> pd.DataFrame:
    """Per camera and reference: `dmais intrinsics` (conf ours) beside cv2.calibrateCamera of the same
    calib split, with the camera's dataset.yaml model, on the true corners (cornerSubPix) and on our
    identified corners (the observations). Beyond radial1 (whose table stays as it was) both
    eps_eval too, OpenCV's by the same pose-only fit of the held-out images as ours
    (calib.intrinsics.evaluate)."""
    rows, observations = [], workspace.load_observations()
    for camera in dict.fromkeys(p["camera"] for p in photos.values()):
        model = workspace.dataset.cameras[camera].model
        size = next(p["pixels"] for p in photos.values() if p["camera"] == camera).shape[::-1]
        ours = _our_calibration(workspace, camera)
        for reference, split in _references(photos, camera, observations).items():
            corners, ids = split["calib"]
            theirs = opencv_calibration(corners, ids, size, model) if corners else {}
            if theirs and model != "radial1":
                eval_corners, eval_ids = split["eval"]
                theirs["eps_eval_px"] = evaluate(theirs["camera"], [_board_points_of(i) for i in eval_ids],
                                                 eval_corners, camera)
            rows.append({"camera": camera, "opencv_on": reference, **_difference(ours, theirs, model)})
    return pd.DataFrame(rows)


def _references(photos: dict[str, dict], camera: str, observations: pd.DataFrame) -> dict[str, dict]:
    """reference -> split -> (corners [(n_i, 2)], ids [(n_i,)]) of the camera's images: the true
    corners, and our observations (images with at least 6)."""
    out = {"cornerSubPix corners": {}, "our corners": {}}
    for split in ("calib", "eval"):
        names = [n for n, p in photos.items() if p["camera"] == camera and p["split"] == split]
        out["cornerSubPix corners"][split] = ([photos[n]["corners"] for n in names], [point_ids()] * len(names))
        ours = [o for o in (observations[observations["image"] == n] for n in names) if len(o) >= 6]
        out["our corners"][split] = ([o[["u", "v"]].to_numpy(float) for o in ours],
                                     [o["point_id"].to_numpy(object) for o in ours])
    return out


def _our_calibration(workspace: Workspace, camera: str) -> dict:
    """`dmais intrinsics` (conf ours) of one camera: its record, or {"error": the one-line error}."""
    try:
        intrinsics_stage.run_cameras(workspace, [camera], intrinsics_stage.CONFS["ours"])
    except DmaisError as error:
        return {"error": str(error)}
    return workspace.load_intrinsics(camera)[1]


def _difference(ours: dict, theirs: dict, model: str = "radial1") -> dict:
    """Our calibration beside OpenCV's: focal length (%) and principal point (px) apart, each
    distortion coefficient of the model, both eps_calib, and both eps_eval where `theirs` has one."""
    if "error" in ours or not theirs:
        return {"error": ours.get("error", "no observations")}
    row = {"fx": ours["fx"], "fx_opencv": theirs["fx"], "focal_pct": 100.0 * (ours["fx"] / theirs["fx"] - 1.0),
           "principal_px": float(np.hypot(ours["cx"] - theirs["cx"], ours["cy"] - theirs["cy"]))}
    for name in PARAMETER_NAMES[model][4:]:
        row.update({name: ours[name], f"{name}_opencv": theirs[name]})
    row.update(eps_calib_px=ours["eps_calib_px"], eps_calib_opencv_px=theirs["eps_calib_px"])
    if "eps_eval_px" in theirs:
        row.update(eps_eval_px=ours["eps_eval_px"], eps_eval_opencv_px=theirs["eps_eval_px"])
    return {**row, "error": ""}


def bench_periodic(photos_dir: Path | None = None, csv: Path | None = None, seed: int = 0,
                   work: Path | None = None, model: str = "radial1") -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-image table, intrinsics table) of one draw of the priors; written to `csv` and beside it
    (<stem>_intrinsics.csv) when given. photos_dir: default PHOTOS; work: folder for the dataset and
    results (default: a temporary one); model: the cameras' lens model (camera.MODELS)."""
    photos_dir = PHOTOS if photos_dir is None else photos_dir
    photos = photographs(photos_dir)
    if not photos:
        raise DmaisError(f"{photos_dir}: no photograph with a 9 x 6 chessboard found")
    with tempfile.TemporaryDirectory(prefix="dmais_periodic_") as scratch:
        root = Path(work) if work else Path(scratch)
        dataset = write_photo_dataset(photos, root / "dataset", seed, model)
        workspace = Workspace.open(root / "dataset", root / "results")
        images = extract_and_score(dataset, workspace, photos)
        calibration = compare_intrinsics(workspace, photos)
    images.insert(0, "seed", seed)
    calibration.insert(0, "seed", seed)
    if csv is not None:
        csv = Path(csv)
        write_csv_atomic(csv, images.round(3))
        write_csv_atomic(csv.with_name(csv.stem + "_intrinsics.csv"), calibration.round(4))
    return images, calibration


def summary(images: pd.DataFrame) -> dict:
    """Totals of a per-image table: images, corners, identified, wrong, refused, median and min identified %."""
    return {"images": len(images), "corners": int(images["corners"].sum()),
            "identified": int(images["identified"].sum()), "wrong": int(images["wrong"].sum()),
            "refused": int(images["refused"].sum()), "images_with_wrong": int((images["wrong"] > 0).sum()),
            "images_without_ids": int((images["identified"] == 0).sum()),
            "median_identified_pct": float(images["identified_pct"].median()),
            "min_identified_pct": float(images["identified_pct"].min())}


def print_tables(images: pd.DataFrame, calibration: pd.DataFrame, csv: Path | None = None) -> None:
    """The per-image table, its totals and the intrinsics table, as `dmais bench periodic` prints them."""
    with pd.option_context("display.width", 250, "display.max_rows", 1000, "display.max_colwidth", 200):
        print(images.drop(columns=["seed"]).to_string(index=False, float_format=lambda x: f"{x:.1f}"))
        print(", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in summary(images).items()))
        print(calibration.drop(columns=["seed"]).to_string(index=False, float_format=lambda x: f"{x:.4g}"))
    if csv is not None:
        print(f"CSV: {csv} and {Path(csv).with_name(Path(csv).stem + '_intrinsics.csv')}")
