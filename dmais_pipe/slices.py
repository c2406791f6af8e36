"""A job's slice of the dataset: only the images, frames and observations one workflow job needs.

Loading and validating the whole dataset costs every job the same seconds at campaign scale (50,055
images and 500,000 observations: ~5 s), more than a frame group's pose and a fifth of a marker
batch's detections. So the whole dataset is loaded once and cut into the parts the jobs need:

- marker batches (`write_marker_slices`; `dmais plan --out RESULTS`, which the workflow runs once
  per state of the dataset): per batch of plan.marker_batches, the dataset restricted to its images
  (`Dataset.restricted`: their frames, their given observations; every point) and the batch;
- flight groups (`write_group_slices`; `dmais plan --out RESULTS --slices pose`, the workflow's
  `pose_slices` rule once the observations are collected): per group of frames.csv, the dataset
  restricted to its frames and their flight images, and the observations of those images that
  Workspace.load_observations gives (validated whole).

Each is a pickle, RESULTS/slices/<kind>/<key>/<digest of its name>.pickle (<kind>: markers, pose),
listed in RESULTS/slices/<kind>.json. <key> digests what the cut was made from: the dataset's
tables' names, sizes and modification times as the load began (Dataset.stamps), for groups the
observation files' as they were before they were read, for batches the images per job, the
dataset folder, and the source of the code that loads and cuts. A job (`batch_workspace`,
`group_workspace`) reads its slice only under the key of those inputs as they are now: a slice is
never read once an input changed. Without a current slice the job loads the whole dataset, with
the loader's one-line errors; a slice was cut from inputs that passed them all, and it checks again
the one thing a load checks beyond the tables: the files of its images.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import pickle
import shutil
from dataclasses import replace
from pathlib import Path

from .dataset import Dataset, file_stamp, table_stamps
from .files import write_bytes_atomic, write_json_atomic
from .plan import marker_batches
from .workspace import Workspace, observation_files

log = logging.getLogger(__name__)

SLICES = "slices"
#: Bumped when what a slice holds changes.
SLICE_FORMAT = 1
#: The modules whose source decides a slice's content: the loader, the cut, the batches, the observations.
_SOURCES = ("dataset.py", "plan.py", "slices.py", "workspace.py")


# ------------------------------------------------------------------------------ a job's workspace


def batch_workspace(dataset_dir: str | Path, results: str | Path, batch: str, per_job: int) -> Workspace:
    """The workspace of marker batch `batch`'s job (plan.marker_batches with `per_job`): its slice of
    the dataset when one is current, else the whole dataset."""
    root = Path(dataset_dir).absolute()
    found = _read(results, "markers", _markers_key(root, table_stamps(root), per_job), batch, root)
    if found is None:
        return Workspace.open(dataset_dir, results)
    return Workspace(found["dataset"], results, batches={batch: found["batch"]})


def group_workspace(dataset_dir: str | Path, results: str | Path, group: str) -> Workspace:
    """The workspace of flight group `group`'s job: its slice of the dataset and of the observations
    when one is current, else the whole dataset."""
    root = Path(dataset_dir).absolute()
    key = _pose_key(root, table_stamps(root), _observation_stamps(results))
    found = _read(results, "pose", key, group, root)
    if found is None:
        return Workspace.open(dataset_dir, results)
    return Workspace(found["dataset"], results, observations=found["observations"])


# ------------------------------------------------------------------------------ cutting


def write_marker_slices(dataset: Dataset, results: str | Path, per_job: int) -> list[Path]:
    """Each marker batch's slice of the whole load `dataset` (module docstring) and RESULTS/slices/markers.json."""
    parts = {name: {"dataset": dataset.restricted(batch["images"], part=f"marker batch {name}"), "batch": batch}
             for name, batch in marker_batches(dataset, per_job).items()}
    return _write(results, "markers", _markers_key(dataset.root, dataset.stamps, per_job), parts)


def write_group_slices(workspace: Workspace) -> list[Path]:
    """Each flight group's slice of the whole workspace's dataset and observations (module docstring)
    and RESULTS/slices/pose.json."""
    dataset = workspace.dataset
    stamps = _observation_stamps(workspace.root)  # before the files are read
    observations = workspace.load_observations()
    flight = dataset.images[dataset.images["stage"] == "flight"]
    group_of = flight["placement"].map(dict(zip(dataset.frames["frame"], dataset.frames["group"])))
    images_of = flight.groupby(group_of, sort=False)["image"]
    rows_of = observations.groupby(observations["image"].map(dict(zip(flight["image"], group_of))), sort=False).indices
    parts = {}
    for group, frames in dataset.frames.groupby("group", sort=False)["frame"]:
        images = images_of.get_group(group) if group in images_of.groups else []
        parts[group] = {"dataset": dataset.restricted(images, frames, part=f"flight group {group}"),
                        "observations": observations.iloc[rows_of.get(group, [])]}
    return _write(workspace.root, "pose", _pose_key(dataset.root, dataset.stamps, stamps), parts)


# ------------------------------------------------------------------------------ keys and files


def _markers_key(root: Path, stamps: str, per_job: int) -> str:
    return _key("markers", root, stamps, f"per_job={per_job}")


def _pose_key(root: Path, stamps: str, observation_stamps: str) -> str:
    return _key("pose", root, stamps, observation_stamps)


def _key(kind: str, root: Path, stamps: str, inputs: str) -> str:
    text = f"{SLICE_FORMAT}|{kind}|{root.resolve()}|{_code_digest()}|{stamps}|{inputs}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _observation_stamps(results: str | Path) -> str:
    """The observation files load_observations may read, by name, size and modification time."""
    return ";".join(f"{path.parent.name}/{path.name}:{file_stamp(path)}" for path in observation_files(Path(results)))


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """A digest of the source of the modules that load and cut (_SOURCES): other code, other slices."""
    package = Path(__file__).resolve().parent
    return hashlib.sha256(b"".join((package / name).read_bytes() for name in _SOURCES)).hexdigest()


def _slice_path(results: str | Path, kind: str, key: str, name: str) -> Path:
    """Names come from the user's tables (cameras, groups): the file is named by their digest."""
    return Path(results) / SLICES / kind / key / f"{hashlib.sha256(name.encode()).hexdigest()[:16]}.pickle"


def _write(results: str | Path, kind: str, key: str, parts: dict[str, dict]) -> list[Path]:
    """The slices `parts` (name -> the Dataset and what else the job reads) under `key`, their list
    RESULTS/slices/<kind>.json; then the slices of other keys are removed."""
    written = [write_bytes_atomic(_slice_path(results, kind, key, name),
                                  pickle.dumps({"format": SLICE_FORMAT, "name": name, **part},
                                               protocol=pickle.HIGHEST_PROTOCOL))
               for name, part in parts.items()]
    folder = Path(results) / SLICES / kind
    written.append(write_json_atomic(folder.with_suffix(".json"), {
        "key": key, "slices": {name: str(path.relative_to(folder)) for name, path in zip(parts, written)}}))
    for old in folder.glob("*"):  # none where nothing was cut
        if old.is_dir() and old.name != key:
            shutil.rmtree(old, ignore_errors=True)
    log.info("slices: %d %s slices in %s", len(parts), kind, folder / key)
    return written


def _read(results: str | Path, kind: str, key: str, name: str, root: Path) -> dict | None:
    """The slice `name` cut under `key`, its dataset at `root` (as the job names the folder) with its
    images' files checked; None where there is none (or it is unreadable)."""
    path = _slice_path(results, kind, key, name)
    try:
        with open(path, "rb") as handle:
            found = pickle.load(handle)
    except FileNotFoundError:
        log.info("slices: no current %s slice of %r in %s: the whole dataset is loaded", kind, name, path.parent)
        return None
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, TypeError, ValueError) as error:
        log.warning("slices: %s is unreadable (%s): the whole dataset is loaded", path, error)
        return None
    if not isinstance(found, dict) or found.get("format") != SLICE_FORMAT or found.get("name") != name:
        log.warning("slices: %s is not the slice of %r: the whole dataset is loaded", path, name)
        return None
    dataset = replace(found["dataset"], root=root)
    dataset.check_image_files()
    log.info("slices: %s of %s (%d images, %d frames)", dataset.part, root, len(dataset.images), len(dataset.frames))
    return {**found, "dataset": dataset}
