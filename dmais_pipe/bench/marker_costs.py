"""Marker extraction's cost per phase at 12 MP and 140 MP, windowed beside the whole image (issue 40).

`dmais bench campaign`'s marker-phase table (`marker_phase_table`), in-process on rendered flight images:

- `rendered_flight`: a simulator preset (config/simulate/demo.yaml: the DMAIS, 4096 x 3000 = 12 MP;
  oblique.yaml: 14000 x 10000 = 140 MP) with one flight group of `frames` frames rendered (the
  calibration stages observation-only), simulated once into the cache and reused;
- `encoded`: that dataset with its flight images as JPEG (quality 95) or uncompressed 16-bit TIFF
  (the 8-bit values x 257), once into the cache;
- three priors of the same images: the simulator's INS (0.5 deg per axis beside a 0.5 deg boresight,
  frames.csv as simulated) with the markers stage's default bounds; a survey-grade INS
  (`survey_ins`: the true attitude turned by SURVEY_INS_DEG per axis, the boresight calibrated away)
  with the bound SURVEY_BOUND_DEG and the default position bound (the POS's lever arm not given);
  and that INS with the POS's lever arm given (the simulator's, as surveyed) and the position bound
  SURVEY_POSITION_M (the POS's own 2-3 cm);
- per image, the windowed search and the whole image's (`markers.extract.process_image`) one after
  the other, each phase's seconds (decode, detect, refine, identify, write: the markers file), the
  lowest total of `repeats` runs; whether the ids and positions are the same (to 1e-6 px) and the
  detections in the windows the whole image's there (exactly); each in a process set up as a marker
  job's (`dataset.keep_freed_image_memory`); the total over the image's own decode time
  (`reference_decodes`: cv2.imread of the file in a plain process, the least of `repeats`) beside the
  total over the job's own decode phase (`Dataset.read_image`, the memory of the image before reused);
- a marker job's peak memory (`peak_memory`): one image in a fresh process, its peak resident size
  beside its size before decoding (the interpreter and the imports: the constant) and the decoded image.

The simulator's truth rig stands for the calibrated rig.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import yaml

from ..dataset import FRAMES, IMAGES, Dataset, keep_freed_image_memory
from ..errors import DmaisError
from ..files import write_csv_atomic
from ..geometry import Rigid3
from ..markers.extract import PRIOR_ATTITUDE_DEG, PRIOR_POSITION_M, _prediction_model, process_image, search_windows
from ..rig import Rig
from ..sim.scene import small_rotation
from ..sim.simulate import simulate, stream
from ..workspace import Workspace

log = logging.getLogger(__name__)

PRESETS = {"12MP": "demo.yaml", "140MP": "oblique.yaml"}
FORMATS = {"jpeg": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]), "tiff16": (".tif", [cv2.IMWRITE_TIFF_COMPRESSION, 1])}
#: A survey-grade INS (post-processed, its boresight to the rig calibrated): deg per axis, and the bound searched.
SURVEY_INS_DEG = 0.01
SURVEY_BOUND_DEG = 0.05
#: The position bound searched with the POS's lever arm given: the simulator's POS, 2-3 cm per axis.
SURVEY_POSITION_M = 0.1
PHASES = ("decode_s", "detect_s", "refine_s", "identify_s", "write_s")
SAME_PX = 1e-6


# ------------------------------------------------------------------------------ the images


def rendered_flight(preset: Path, cache: Path, frames: int = 1) -> Path:
    """The dataset (in `cache`) of the simulator preset with one flight group of `frames` frames rendered."""
    config = yaml.safe_load(preset.read_text())
    flight = {**config.get("flight", {}), "frames_per_group": frames,
              "sites": {"A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1]}}}
    config = {**config, "flight": flight, "render": {**config.get("render", {}), "intrinsics": False,
                                                      "extrinsics": False, "flight": True}}
    folder = cache / f"{config['name']}_{frames}"
    text = yaml.safe_dump(config, sort_keys=True)
    done = folder / "dataset" / "truth" / "simulation.yaml"
    if not (done.is_file() and (folder / "sim.yaml").is_file() and (folder / "sim.yaml").read_text() == text):
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "sim.yaml").write_text(text)
        log.info("markers bench: rendering %s's flight once into %s", preset.name, folder)
        simulate(folder / "sim.yaml", folder / "dataset", jobs=os.cpu_count() or 1)
    return folder / "dataset"


def encoded(source: Path, fmt: str) -> Path:
    """The dataset `source` beside it with its flight images encoded as FORMATS[fmt] (made once)."""
    suffix, flags = FORMATS[fmt]
    out = source.with_name(f"{source.name}_{fmt}")
    if (out / IMAGES).is_file():
        return out
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    images = pd.read_csv(source / IMAGES, dtype=str, keep_default_na=False)
    for path in images.loc[images["path"] != "", "path"]:
        pixels = cv2.imread(str(source / path), cv2.IMREAD_UNCHANGED)
        pixels = pixels.astype(np.uint16) * 257 if fmt == "tiff16" else pixels
        target = staging / Path(path).with_suffix(suffix)
        target.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(target), pixels, flags):
            raise DmaisError(f"markers bench: cannot write {target}")
    images.loc[images["path"] != "", "path"] = [str(Path(p).with_suffix(suffix)) for p in images["path"] if p]
    images.to_csv(staging / IMAGES, index=False)
    for item in source.iterdir():
        if item.is_file() and item.name != IMAGES:
            shutil.copy2(item, staging / item.name)
    shutil.copytree(source / "truth", staging / "truth")
    staging.rename(out)
    return out


def survey_ins(source: Path, seed: int = 40) -> Path:
    """The dataset `source` beside it, its images linked, with frames.csv's INS attitudes those of a
    survey-grade INS: the true rig_from_world turned by SURVEY_INS_DEG per axis (seeded)."""
    out = source.with_name(f"{source.name}_survey_ins")
    if (out / FRAMES).is_file():
        return out
    out.mkdir()
    for item in source.iterdir():
        (out / item.name).symlink_to(Path("..") / source.name / item.name)  # the cache may move
    (out / FRAMES).unlink()
    frames = pd.read_csv(source / FRAMES, dtype={"frame": str, "group": str}, keep_default_na=False)
    truth = pd.read_csv(source / "truth" / FRAMES, dtype={"frame": str}).set_index("frame")
    rng = stream(seed, "survey_ins")
    for k, frame in enumerate(frames["frame"]):
        R = Rigid3.from_quat(truth.loc[frame, ["qw", "qx", "qy", "qz"]].to_numpy(float), np.zeros(3)).R
        turned = Rigid3(small_rotation(rng, np.radians(SURVEY_INS_DEG)) @ R, np.zeros(3))
        frames.loc[k, ["prior_qw", "prior_qx", "prior_qy", "prior_qz"]] = turned.quat
    frames.to_csv(out / FRAMES, index=False)
    return out


# ------------------------------------------------------------------------------ the costs


def image_costs(dataset: Dataset, image: str, rig: Rig, attitude_deg: float | None, position_m: float,
                results: Workspace, repeats: int, lever_arm: np.ndarray | None = None) -> dict:
    """One image's phases (seconds, the run of least total of `repeats`), its markers frame
    (`found`), the windows searched and whether the whole image was."""
    best = None
    for _ in range(repeats):
        seconds = {}
        found = process_image(dataset, image, rig, seconds=seconds, attitude_deg=attitude_deg,
                              position_m=position_m, lever_arm=lever_arm)
        started = time.perf_counter()
        results.save_markers(image, found)
        seconds["write_s"] = time.perf_counter() - started
        total = sum(seconds[phase] for phase in PHASES)
        if best is None or total < best[0]:
            best = (total, {**seconds, "found": found})
    return best[1]


def same_results(windowed: pd.DataFrame, whole: pd.DataFrame, windows: np.ndarray | None) -> tuple[bool, bool]:
    """(the same ids at the same positions to SAME_PX, the whole image's detections inside the windows
    (m, 4) exactly the windowed ones) of two markers frames of one image."""
    ids = [frame[frame["point_id"] != ""].sort_values("point_id") for frame in (windowed, whole)]
    same_ids = (ids[0]["point_id"].tolist() == ids[1]["point_id"].tolist() and bool(np.all(
        np.abs(ids[0][["u", "v"]].to_numpy() - ids[1][["u", "v"]].to_numpy()) <= SAME_PX)))
    if windows is None:
        return same_ids, windowed.equals(whole)
    uv = whole[["u", "v"]].to_numpy(dtype=float)
    inside = ((uv[:, None] >= windows[None, :, :2]) & (uv[:, None] <= windows[None, :, 2:])).all(axis=2).any(axis=1)
    return same_ids, windowed.reset_index(drop=True).equals(whole[inside].reset_index(drop=True))


def path_rows(root: Path, attitude_deg: float, position_m: float, repeats: int,
              lever_arm: np.ndarray | None = None) -> tuple[list[dict], list[dict]]:
    """Per flight image of the dataset `root`: a row of the windowed search and one of the whole image,
    run in a process of its own as a marker job runs (`_job_rows`), with each image's own decode time
    from another, a plain one (`reference_decodes`)."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(1) as pool:
        reference = pool.apply(reference_decodes, (str(root), repeats))
    with context.Pool(1) as pool:
        return pool.apply(_job_rows, (str(root), attitude_deg, position_m, repeats, lever_arm, reference))


def _job_rows(root: str, attitude_deg: float, position_m: float, repeats: int, lever_arm: np.ndarray | None,
              reference: dict[str, float]) -> tuple[list[dict], list[dict]]:
    """`path_rows` in a process set up as `dmais markers` sets up its own (`keep_freed_image_memory`)."""
    keep_freed_image_memory()
    dataset = Dataset.load(root)
    rig = Rig.load(Path(root) / "truth" / "rig.json")
    rows = {"windowed": [], "whole": []}
    with tempfile.TemporaryDirectory() as scratch:
        results = Workspace(dataset, Path(scratch))
        for image in dataset.images_of("flight")["image"]:
            dataset.read_image(image)  # the file in the page cache for both
            runs = {path: image_costs(dataset, image, rig, bound, position_m, results, repeats, lever_arm)
                    for path, bound in (("windowed", attitude_deg), ("whole", None))}
            model = _prediction_model(dataset, image, rig, lever_arm=lever_arm)
            windows = None if runs["windowed"]["whole_image"] else search_windows(model, attitude_deg, position_m)
            same_ids, same_found = same_results(runs["windowed"]["found"], runs["whole"]["found"], windows)
            for path, run in runs.items():
                rows[path].append({"image": image, **{phase: run[phase] for phase in PHASES},
                                   "reference_decode_s": reference[image],
                                   "windows": run["windows"], "whole_image": run["whole_image"],
                                   "detected": len(run["found"]), "identified": int((run["found"]["point_id"] != "").sum()),
                                   "same_ids": same_ids, "same_detections": same_found})
    return rows["windowed"], rows["whole"]


def reference_decodes(root: str, repeats: int) -> dict[str, float]:
    """Each flight image's own decode time, image -> the least wall seconds of `repeats` cv2.imread of
    its file (unchanged), each result dropped before the next; `path_rows` runs it in a process of its
    own whose allocator is as Python leaves it."""
    dataset = Dataset.load(root)
    best = {}
    for image in dataset.images_of("flight")["image"]:
        path = str(dataset.image_path(image))
        best[image] = np.inf
        for _ in range(repeats + 1):  # the first: the file into the page cache
            started = time.perf_counter()
            pixels = cv2.imread(path, cv2.IMREAD_UNCHANGED)
            best[image] = min(best[image], time.perf_counter() - started)
            del pixels
    return best


# ------------------------------------------------------------------------------ memory


def peak_memory(root: Path, image: str, attitude_deg: float | None, position_m: float,
                lever_arm: np.ndarray | None = None) -> dict:
    """One image's marker extraction in a fresh process: its resident size before decoding (MB), its
    peak (MB) and the decoded image's size (MB)."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(1) as pool:
        return pool.apply(_measure_memory, (str(root), image, attitude_deg, position_m, lever_arm))


def _measure_memory(root: str, image: str, attitude_deg: float | None, position_m: float,
                    lever_arm: np.ndarray | None = None) -> dict:
    keep_freed_image_memory()  # as the job
    dataset = Dataset.load(root)
    rig = Rig.load(Path(root) / "truth" / "rig.json")
    before = _status_mb("VmRSS")
    process_image(dataset, image, rig, attitude_deg=attitude_deg, position_m=position_m, lever_arm=lever_arm)
    peak = _status_mb("VmHWM")
    return {"rss_before_mb": before, "peak_rss_mb": peak, "decoded_mb": dataset.read_image(image).nbytes / 2**20}


def _status_mb(field: str) -> float:
    """A field of /proc/self/status (kB) in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return float(line.split()[1]) / 1024
    raise DmaisError(f"markers bench: /proc/self/status has no {field}")


# ------------------------------------------------------------------------------ the table


def marker_phase_table(presets: Path, cache: Path, frames: int = 1, repeats: int = 2,
                       sizes: tuple[str, ...] = tuple(PRESETS)) -> pd.DataFrame:
    """Per image size, format, INS and path: the mean seconds of each phase per image, their total and
    its ratio to decoding, the windows searched, the images searched whole, the ids, whether every
    image's ids and positions and the windows' detections are the whole image's, and the peak memory."""
    rows = []
    for size in sizes:
        source = rendered_flight(presets / PRESETS[size], cache, frames)
        for fmt in FORMATS:
            root = encoded(source, fmt)
            surveyed = survey_ins(root)
            for ins, folder, bound, position, lever in (
                    ("simulator", root, PRIOR_ATTITUDE_DEG, PRIOR_POSITION_M, None),
                    ("survey", surveyed, SURVEY_BOUND_DEG, PRIOR_POSITION_M, None),
                    ("survey+lever", surveyed, SURVEY_BOUND_DEG, SURVEY_POSITION_M, simulated_lever_arm(root))):
                log.info("markers bench: %s %s, %s INS", size, fmt, ins)
                windowed, whole = path_rows(folder, bound, position, repeats, lever)
                first = pd.DataFrame(windowed)["image"].iloc[0]
                for path, table, memory_bound in (("windowed", windowed, bound), ("whole", whole, None)):
                    memory = peak_memory(folder, first, memory_bound, position, lever)
                    rows.append(_summary(size, fmt, ins, bound, position, path, pd.DataFrame(table), memory))
    return pd.DataFrame(rows)


def simulated_lever_arm(root: Path) -> np.ndarray:
    """(3,) m: the POS lever arm the simulator put into the dataset `root`'s frames.csv (its truth)."""
    return np.array(yaml.safe_load((root / "truth" / "simulation.yaml").read_text())["flight"]["lever_arm_m"], float)


def _summary(size: str, fmt: str, ins: str, bound: float, position: float, path: str, table: pd.DataFrame,
             memory: dict) -> dict:
    """One row of `marker_phase_table` from the per-image rows of one path."""
    means = {phase: float(table[phase].mean()) for phase in PHASES}
    total = sum(means.values())
    return {"size": size, "format": fmt, "ins": ins, "bound_deg": bound, "bound_m": position, "path": path,
            "images": len(table),
            **means, "total_s": total, "total_over_decode": total / means["decode_s"],
            "reference_decode_s": float(table["reference_decode_s"].mean()),
            "total_over_reference": total / float(table["reference_decode_s"].mean()),
            "windows": float(table["windows"].mean()), "whole_images": int(table["whole_image"].sum()),
            "identified": int(table["identified"].sum()), "same_ids": bool(table["same_ids"].all()),
            "same_detections": bool(table["same_detections"].all()),
            "peak_rss_mb": memory["peak_rss_mb"], "rss_before_mb": memory["rss_before_mb"],
            "decoded_mb": memory["decoded_mb"],
            "peak_over_decoded": (memory["peak_rss_mb"] - memory["rss_before_mb"]) / memory["decoded_mb"]}


def write_marker_phase_table(table: pd.DataFrame, csv: Path) -> Path:
    """Print the table and write it to `csv`."""
    print(table.to_string(index=False, float_format=lambda x: f"{x:.4g}"))
    return write_csv_atomic(csv, table.round(6))
