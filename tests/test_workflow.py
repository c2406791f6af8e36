"""The Snakemake workflow on a tiny simulated dataset, run as a user would."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import site as site_module
import subprocess
import sys
import zipfile
from html.parser import HTMLParser
from pathlib import Path

import pandas as pd
import pytest
import yaml

from dmais_pipe.dataset import Dataset
from dmais_pipe.plan import marker_batches, workflow_plan
from dmais_pipe.stages.markers import BATCH_COLUMNS
from test_dataset import _inputs, _set_cells, _write

REPO = Path(__file__).resolve().parents[1]


class Headings(HTMLParser):
    def __init__(self):
        super().__init__()
        self.headings, self._in_heading = [], False

    def handle_starttag(self, tag, attrs):
        self._in_heading = tag == "h2"

    def handle_data(self, data):
        if self._in_heading:
            self.headings.append(data.strip())
            self._in_heading = False


def test_workflow_runs_every_stage_and_reports(tmp_path):
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump({
        "name": "tiny", "seed": 3,
        "intrinsics": {"calib_images_per_camera": 3, "eval_images_per_camera": 1},
        "flight": {"frames_per_group": 1},
        "render": {"intrinsics": False, "extrinsics": False, "flight": True},
    }))
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(
        {"dataset": "tiny", "simulate": "sim.yaml", "subsets": ["0", "012"], "markers_per_job": 3,
         "bench_pose": {"repeats": 2, "batch_frames": 5, "stage_frames": 0}}))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    command = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "config.yaml"), "--cores", "2"]
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]

    assert (tmp_path / "results/tiny/dataset/truth/rig.json").is_file()
    summary = pd.read_csv(tmp_path / "reports/tiny/dataset_summary.csv")
    assert set(summary["stage"]) == {"intrinsics", "extrinsics", "flight"}
    assert summary.loc[summary["stage"] == "intrinsics", "images"].tolist() == [4] * 5
    parser = Headings()
    parser.feed((tmp_path / "reports/tiny/dataset.html").read_text())
    assert parser.headings == ["Images and observations", "Points", "Truth rig", "Simulator noise budget",
                               "A rendered marker and its true centre"]

    results = tmp_path / "results/tiny"
    # the rendered flight images in marker jobs of at most markers_per_job (3) images per camera, each
    # identified with the rig the workflow calibrated; every image has its markers file
    flight_images = pd.read_csv(tmp_path / "results/tiny/dataset/images.csv").query("stage == 'flight'")["image"]
    assert len(flight_images) == 25
    batches = marker_batches(Dataset.load(results / "dataset"), 3)
    assert sorted(batches) == [f"flight-C{c}-{k}" for c in range(5) for k in (1, 2)]  # 5 images a camera: 3 + 2
    assert sorted(image for batch in batches.values() for image in batch["images"]) == sorted(flight_images)
    for name, batch in batches.items():
        assert (tmp_path / f"logs/tiny/markers/{name}.log").is_file(), name
        table = pd.read_csv(results / "markers" / "batches" / f"{name}.csv")
        assert list(table.columns) == list(BATCH_COLUMNS), name
        assert table["image"].tolist() == batch["images"] and set(table["camera"]) == {batch["camera"]}, name
        assert not table["resumed"].any(), name
    assert sorted(path.name for path in (results / "markers" / "batches").glob("*.csv")) == sorted(
        f"{name}.csv" for name in batches)
    for image in flight_images:
        assert (results / "markers" / f"{image}.csv").is_file(), image
    flight = pd.read_csv(results / "observations" / "flight.csv")
    assert set(flight["image"]) <= set(flight_images) and flight["image"].nunique() >= 20

    poses = pd.read_csv(results / "poses.csv", dtype={"frame": str})
    assert len(poses) == 5 and (results / "poses_0.csv").is_file() and (results / "poses_012.csv").is_file()
    evaluation = pd.read_csv(results / "evaluation.csv")
    assert evaluation["true_pos_err_m"].median() < 0.5 and evaluation["true_ang_err_arcmin"].median() < 5
    for table in ("intrinsics", "extrinsics_R", "extrinsics_t", "pose_methods", "conf", "lever_arm", "time_points"):
        assert (results / "tables" / f"{table}.csv").is_file(), table
        assert (tmp_path / "reports/tiny/tables" / f"{table}.csv").is_file(), table
    # the subsets, and the whole rig of poses.csv as tab:conf's #01234
    assert set(pd.read_csv(results / "tables" / "conf.csv", dtype={"subset": str})["subset"]) == {"0", "012", "01234"}

    parser = Headings()
    parser.feed((tmp_path / "reports/tiny/report.html").read_text())
    assert parser.headings == ["Dataset", "Marker quality per camera", "Detected markers on the images",
                               "Intrinsics per camera", "Rig layout", "Fields of view on the ground",
                               "Reprojection residuals per camera", "Per-frame pose errors",
                               "Attitude error: the paper's proxy and the truth", "Camera subsets",
                               "Pose accuracy beside other runs", "Error budget of the sigmas",
                               "The rig watched in flight",
                               "Runtime versus number of points", "Processing time per stage", "Comparison with the paper"]
    assert "Not available" not in (tmp_path / "reports/tiny/report.html").read_text()

    # `snakemake --report` carries the tables and the report's figures (report() in the rules)
    zipped = snakemake(tmp_path, "--configfile", str(tmp_path / "config.yaml"), "--report", "report.zip", timeout=300)
    assert zipped.returncode == 0, zipped.stderr[-3000:]
    with zipfile.ZipFile(tmp_path / "report.zip") as archive:
        names = {Path(name).name for name in archive.namelist()}
    assert {"fov_ground.svg", "markers_flight.jpg", "calibration_residuals.svg", "intrinsics.csv", "conf.csv",
            "pose_methods_vs_paper.csv", "evaluation.csv", "error_budget.csv", "mounting.csv", "report.html"} <= names


def snakemake(workdir: Path, *options: str, timeout: int = 120, python=sys.executable,
              env: dict | None = None) -> subprocess.CompletedProcess:
    """Snakemake of `python` on the Snakefile in workdir; env: by default this one with the venv's
    bin (`dmais`) first on PATH."""
    if env is None:
        env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    command = [str(python), "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
               *options]
    return subprocess.run(command, cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("config, message", [
    ({"dataset": "x", "dataset_dir": "d", "datset": "typo"}, "config: (top level): Additional properties are not "
     "allowed ('datset' was unexpected)"),
    ({"dataset": "x", "dataset_dir": "d", "subsets": ["0", "a"]}, "config: subsets.1: 'a' does not match"),
    ({"dataset": "x", "dataset_dir": "d", "pose": {"robustt": True}}, "config: pose: Additional properties are not "
     "allowed ('robustt' was unexpected)"),
    ({"dataset": "x", "dataset_dir": "d", "intrinsics": {"conf": "fast"}}, "config: intrinsics.conf: 'fast' is not one of"),
    ({"dataset": "x", "dataset_dir": "d", "simulate": "s.yaml"}, "config: give either dataset_dir"),
    ({"dataset": "x"}, "config: give either dataset_dir"),
    (None, "no configuration: run with --configfile"),
])
def test_config_faults_are_one_line(tmp_path, config, message):
    options = ["--cores", "1", "-n"]
    if config is not None:
        (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
        options += ["--configfile", str(tmp_path / "config.yaml")]
    result = snakemake(tmp_path, *options)
    assert result.returncode != 0
    assert (result.stdout + result.stderr).strip().splitlines() == [(result.stdout + result.stderr).strip()]
    assert message in result.stderr


def _fingerprint(root: Path) -> dict[str, tuple[str, int, int]]:
    """Every file below `root`: its content hash, mtime (ns) and mode."""
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns,
                                       p.stat().st_mode)
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_users_dataset_is_only_read(tmp_path):
    """The workflow on a dataset of the user's own (no `simulate:`), with files older than the
    repository (what once made Snakemake re-simulate over them): a dry run and a real run leave
    every input file byte-identical, with its timestamp, and add nothing to the folder."""
    simulator = tmp_path / "sim.yaml"
    simulator.write_text(yaml.safe_dump({
        "name": "mysite", "seed": 5,
        "intrinsics": {"calib_images_per_camera": 3, "eval_images_per_camera": 1},
        "flight": {"frames_per_group": 1},
        "render": {"intrinsics": False, "extrinsics": False, "flight": False},
    }))
    made = subprocess.run([sys.executable, "-m", "dmais_pipe.cli", "simulate", str(simulator),
                           "--out", str(tmp_path / "made")], capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    site = tmp_path / "survey" / "mysite"
    shutil.copytree(tmp_path / "made", site)
    for path in site.rglob("*"):
        os.utime(path, ns=(978307200 * 10**9, 978307200 * 10**9))  # 2001-01-01: older than any clone
    before = _fingerprint(site)
    work = tmp_path / "work"
    work.mkdir()
    (work / "mysite.yaml").write_text(yaml.safe_dump(
        {"dataset": "mysite", "dataset_dir": str(site), "subsets": ["0"], "bench_pose": {"repeats": 1,
                                                                                        "batch_frames": 2,
                                                                                        "stage_frames": 0},
         "intrinsics": {"methods": ["ours"]}, "pose": {"conf": "robust", "robust_threshold_px": 15}}))

    dry = snakemake(work, "--configfile", "mysite.yaml", "--cores", "2", "-n", "-p")
    assert dry.returncode == 0, dry.stderr[-3000:]
    assert "simulate" not in dry.stdout
    assert "--conf robust --set robust_threshold_px=15" in dry.stdout  # the config's stage settings
    assert "--set methods=ours" in dry.stdout
    run = snakemake(work, "--configfile", "mysite.yaml", "--cores", "2", timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]

    assert (work / "reports/mysite/report.html").is_file() and (work / "results/mysite/poses.csv").is_file()
    assert set(pd.read_csv(work / "results/mysite/tables/intrinsics.csv")["method"]) == {"ours"}
    assert _fingerprint(site) == before


def test_a_faulty_dataset_stops_the_dry_run_with_the_loaders_line(tmp_path):
    """The Snakefile learns the dataset from `dmais plan`: the same loader, so the same one line."""
    site = _write(tmp_path / "site", _inputs())
    plan = workflow_plan(Dataset.load(site))
    assert plan == {"cameras": ["C0", "C1"], "calibrated_cameras": ["C0", "C1"], "groups": ["1"], "geodetic": False,
                    "batches": {"intrinsics": {"intrinsics-C1-1": {"camera": "C1", "images": 1}},
                                "extrinsics": {"extrinsics-C1-1": {"camera": "C1", "images": 1}},
                                "flight": {"flight-C1-1": {"camera": "C1", "images": 1}}}}
    assert marker_batches(Dataset.load(site)) == {  # i0 has given observations and f0 no file: not extracted
        "intrinsics-C1-1": {"stage": "intrinsics", "camera": "C1", "images": ["i1"]},
        "extrinsics-C1-1": {"stage": "extrinsics", "camera": "C1", "images": ["e0"]},
        "flight-C1-1": {"stage": "flight", "camera": "C1", "images": ["f1"]}}
    (tmp_path / "site.yaml").write_text(yaml.safe_dump({"dataset": "site", "dataset_dir": str(site)}))
    dry = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n")
    assert dry.returncode == 0, dry.stderr[-2000:]
    assert "markers" in dry.stdout and "simulate" not in dry.stdout
    _set_cells(site, "images.csv", 2, camera="C9")
    dry = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n")
    assert dry.returncode != 0
    assert dry.stderr.strip().splitlines() == [
        f"dmais plan: error: {site / 'images.csv'}, line 4: unknown camera 'C9' (dataset.yaml has C0, C1)"]


def _site_without_venv_on_path(tmp_path: Path) -> dict:
    """A small dataset and its config site.yaml in tmp_path; the environment without the folder
    of this Python (the venv's bin, with `dmais`) on PATH."""
    site = _write(tmp_path / "site", _inputs())
    (tmp_path / "site.yaml").write_text(yaml.safe_dump({"dataset": "site", "dataset_dir": str(site)}))
    bin_dir = Path(sys.executable).parent
    path = os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep) if Path(p) != bin_dir)
    assert shutil.which("dmais", path=path) is None  # else the tests below prove nothing
    env = {**os.environ, "PATH": path}
    env.pop("VIRTUAL_ENV", None)
    return env


def test_snakemake_of_the_venv_runs_without_the_venv_on_path(tmp_path):
    """`.venv/bin/snakemake` with the venv not activated: its rules' `dmais` (the dry run's `dmais
    plan`, a job's shell command) is the one beside its Python, not a FileNotFoundError traceback."""
    env = _site_without_venv_on_path(tmp_path)
    dry = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n", env=env)
    assert dry.returncode == 0, dry.stdout[-2000:] + dry.stderr[-2000:]
    assert "markers" in dry.stdout
    run = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "reports/site/dataset_summary.csv",
                   timeout=300, env=env)
    assert run.returncode == 0, run.stderr[-2000:]
    assert pd.read_csv(tmp_path / "reports/site/dataset_summary.csv")["images"].sum() > 0


def test_snakemake_without_dmais_anywhere_says_so_in_one_line(tmp_path):
    """A Snakemake whose Python has no `dmais` beside it and none on PATH: one line, no jobs."""
    env = _site_without_venv_on_path(tmp_path)
    bare = tmp_path / "bare" / "python"  # the venv's interpreter, in a folder without its scripts
    bare.parent.mkdir()
    bare.symlink_to(os.path.realpath(sys.executable))
    env["PYTHONPATH"] = os.pathsep.join(site_module.getsitepackages())
    result = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n", python=bare, env=env)
    assert result.returncode != 0
    assert (result.stdout + result.stderr).strip() == (
        f"dmais is not installed: it is neither on PATH nor beside {bare} "
        "(make install, or run .venv/bin/snakemake after it)")


def test_the_plan_is_made_once_per_state_of_the_dataset(tmp_path):
    """The dry run writes results/<dataset>/plan/<key>.json and later runs (a cluster job's own
    Snakemake) read it instead of loading the dataset; an edited table makes a new plan."""
    site = _write(tmp_path / "site", _inputs())
    (tmp_path / "site.yaml").write_text(yaml.safe_dump({"dataset": "site", "dataset_dir": str(site),
                                                        "markers_per_job": 7}))
    assert snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n").returncode == 0
    (made,) = (tmp_path / "results/site/plan").glob("*.json")
    plan = json.loads(made.read_text())
    assert plan == workflow_plan(Dataset.load(site), 7)
    slices = json.loads((tmp_path / "results/site/slices/markers.json").read_text())["slices"]  # each job's part
    assert set(slices) == {batch for stage in plan["batches"].values() for batch in stage}
    plan["batches"]["flight"] = {"flight-C1-9": {"camera": "C1", "images": 1}}  # read from the file, not remade
    made.write_text(json.dumps(plan))
    dry = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n")
    assert "markers/batches/flight-C1-9.csv" in dry.stdout and "flight-C1-1.csv" not in dry.stdout
    _set_cells(site, "images.csv", 2, prior_x=1.5)  # another state of the dataset
    dry = snakemake(tmp_path, "--configfile", "site.yaml", "--cores", "1", "-n")
    assert "flight-C1-1.csv" in dry.stdout and "flight-C1-9.csv" not in dry.stdout
    assert [p.name for p in (tmp_path / "results/site/plan").glob("*.json")] != [made.name]
    assert len(list((tmp_path / "results/site/plan").glob("*.json"))) == 1  # the older plan is gone
