import functools
import hashlib
import importlib.util
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path


def find_dmais():
    """Every rule runs `dmais`. Where it is not on PATH but installed beside the Python running
    Snakemake (`.venv/bin/snakemake` with the venv not activated), that folder joins PATH, also for
    the jobs; where it is nowhere, one line says so instead of each job's "command not found"."""
    if shutil.which("dmais"):
        return
    beside = Path(sys.executable).parent
    if not (beside / "dmais").is_file():
        sys.exit(f"dmais is not installed: it is neither on PATH nor beside {sys.executable} "
                 "(make install, or run .venv/bin/snakemake after it)")
    os.environ["PATH"] = f"{beside}{os.pathsep}{os.environ.get('PATH', '')}"


find_dmais()

DATASET = config["dataset"]
RESULTS = f"results/{DATASET}"
#: A simulated dataset lives in a folder the workflow owns; a user's dataset is only ever read.
DATASET_DIR = f"{RESULTS}/dataset" if config.get("simulate") else config["dataset_dir"]
REPORTS = f"reports/{DATASET}"
LOGS = f"logs/{DATASET}"
BENCHMARKS = f"benchmarks/{DATASET}"
#: Camera subsets of tab:conf, as camera indexes in the manifest's order ("01" = first two cameras).
SUBSETS = config.get("subsets", ["0", "01", "012", "1234"])
#: Images per marker job (the config's markers_per_job; the schema's default is plan.MARKERS_PER_JOB).
MARKERS_PER_JOB = config["markers_per_job"]
BENCH_POSE = {"repeats": 50, "batch_frames": 100, "stage_frames": 10_000, **config.get("bench_pose", {})}


def dataset_manifest():
    """The dataset's manifest: written by `simulate` or given by the user (an input, never an output)."""
    return f"{DATASET_DIR}/dataset.yaml"


def dataset_ready():
    """The manifest path once the dataset exists: with `simulate`, waits for that checkpoint so that
    the images, cameras and frame groups below are read from the simulated files."""
    if config.get("simulate") and workflow.is_main_process:  # a job's own Snakemake runs after simulate
        return checkpoints.simulate.get().output.manifest
    return dataset_manifest()


#: Bumped when `dmais plan`'s JSON or what it writes changes, so that a plan file of an older layout
#: is not read (3: the plan also cuts the marker batches' slices, RESULTS/slices/; 4: `geodetic`).
PLAN_FORMAT = 4


def _plan_file(dataset_dir):
    """RESULTS/plan/<key>.json, the key a digest of the dataset's tables (name, size, mtime), the
    batch size and the package's source: the plan is made once per run of the workflow and read by
    every job's own Snakemake (on a cluster, each job parses the workflow again), and made anew when
    the dataset or the package changes (the slices it cuts are only read by the code that cut them)."""
    root = Path(dataset_dir)
    digest = hashlib.sha256(f"{PLAN_FORMAT}|{root.resolve()}|{MARKERS_PER_JOB}|{_package_digest()}".encode())
    for path in sorted(root.glob("*.csv")) + [root / "dataset.yaml"]:
        stat = path.stat() if path.is_file() else None  # none: `dmais plan` names what is missing
        digest.update(f"{path.name}:{stat and (stat.st_size, stat.st_mtime_ns)};".encode())
    return Path(RESULTS) / "plan" / f"{digest.hexdigest()[:16]}.json"


@functools.lru_cache(maxsize=1)
def _package_digest():
    """A digest of the source of the dmais_pipe that this Python finds ('' where it finds none: the
    rules' dmais is installed elsewhere), without importing it."""
    spec = importlib.util.find_spec("dmais_pipe")
    if spec is None or spec.origin is None:
        return ""
    digest = hashlib.sha256()
    for path in sorted(Path(spec.origin).parent.rglob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()


@functools.lru_cache(maxsize=None)
def _plan(dataset_dir):
    """`dmais plan DATASET`: the dataset as the stages see it (validated by the same loader; a
    faulty dataset stops here with its one-line error), from its plan file when one is there. Making
    it also cuts each marker batch's slice of the dataset, which its job reads (slices.py)."""
    path = _plan_file(dataset_dir)
    if not path.is_file():
        command = ["dmais", "plan", dataset_dir, "--per-job", str(MARKERS_PER_JOB), "--json", str(path),
                   "--out", RESULTS, "--slices", "markers"]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(done.stderr.strip() or f"dmais plan {dataset_dir} failed")
        if workflow.is_main_process:  # plans of earlier states of the dataset
            for old in path.parent.glob("*.json"):
                if old != path:
                    old.unlink(missing_ok=True)
    return json.loads(path.read_text())


def plan():
    return _plan(str(Path(dataset_ready()).parent))


def cameras():
    """Camera names in the manifest's (= the rig's) order."""
    return plan()["cameras"]


def marker_batches(stage):
    """Names of the marker batches of `stage` (plan.marker_batches: per camera, at most
    MARKERS_PER_JOB images of a file and no given observations each)."""
    return list(plan()["batches"][stage])


def calibrated_cameras():
    """Cameras with intrinsics images, in manifest order."""
    return plan()["calibrated_cameras"]


def geojson_outputs():
    """The GeoJSON export's files where the dataset has a crs (plan's `geodetic`), else none."""
    if not plan().get("geodetic"):
        return []
    return [f"{RESULTS}/geojson/frames.geojson", f"{RESULTS}/geojson/footprints.geojson"]


def groups():
    """Flight frame groups, in the order of frames.csv."""
    return plan()["groups"]


def subset_cameras(label):
    """Camera names of a subset label ("012" -> C0,C1,C2 for a rig C0..C4); "all" -> every camera."""
    names = cameras()
    return names if label == "all" else [names[int(k)] for k in label]


def subset_labels():
    """The configured subsets that are proper subsets of this rig (the whole rig is poses.csv)."""
    n = len(cameras())
    return [s for s in SUBSETS if all(int(k) < n for k in s) and len(set(s)) < n]


def stage_settings(stage):
    """The workflow config's section of `stage` as `dmais <stage>` options: `--conf NAME` and one
    `--set KEY=VALUE` per setting (the defaults are the code's; docs/design.md, "Stage settings")."""
    section = dict(GIVEN_SETTINGS[stage])
    options = ["--conf", section.pop("conf")] if "conf" in section else []
    for key, value in section.items():
        if isinstance(value, bool):
            value = str(value).lower()
        elif isinstance(value, list):
            value = ",".join(str(v) for v in value)
        options += ["--set", f"{key}={value}"]
    return " ".join(shlex.quote(str(option)) for option in options)


def marker_inputs(wildcards):
    """A batch's prerequisites: extrinsics images are identified with the calibrated intrinsics of
    their camera, flight images with the calibrated rig."""
    stage = next(stage for stage, batches in plan()["batches"].items() if wildcards.batch in batches)
    inputs = {"manifest": dataset_ready()}
    if stage == "extrinsics":
        inputs["intrinsics"] = f"{RESULTS}/intrinsics/{plan()['batches'][stage][wildcards.batch]['camera']}.json"
    elif stage == "flight":
        inputs["rig"] = f"{RESULTS}/rig.json"
    return inputs


def pose_parts(label):
    """An input function: the per-group pose files of subset `label` (None: the wildcard's)."""

    def parts(wildcards):
        return expand(f"{RESULTS}/poses/{label or wildcards.subset}/{{group}}.csv", group=groups())

    return parts


DMAIS_ENV = "../envs/dmais.yaml"
