"""The Snakemake workflow on a tiny simulated dataset, run as a user would."""

from __future__ import annotations

import os
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pandas as pd
import yaml

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
        {"dataset": "tiny", "dataset_dir": "data/tiny", "simulate": "sim.yaml", "subsets": ["0", "012"],
         "bench_pose": {"repeats": 2, "batch_frames": 5}}))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    command = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "config.yaml"), "--cores", "2"]
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]

    assert (tmp_path / "data/tiny/truth/rig.json").is_file()
    summary = pd.read_csv(tmp_path / "reports/tiny/dataset_summary.csv")
    assert set(summary["stage"]) == {"intrinsics", "extrinsics", "flight"}
    assert summary.loc[summary["stage"] == "intrinsics", "images"].tolist() == [4] * 5
    parser = Headings()
    parser.feed((tmp_path / "reports/tiny/dataset.html").read_text())
    assert parser.headings == ["Images and observations", "Points", "Truth rig", "Simulator noise budget",
                               "A rendered marker and its true centre"]

    results = tmp_path / "results/tiny"
    # one marker job per rendered flight image, identified with the rig the workflow calibrated
    flight_images = pd.read_csv(tmp_path / "data/tiny/images.csv").query("stage == 'flight'")["image"]
    assert len(flight_images) == 25
    for image in flight_images:
        assert (results / "markers" / f"{image}.csv").is_file() and (tmp_path / f"logs/tiny/markers/{image}.log").is_file()
    flight = pd.read_csv(results / "observations" / "flight.csv")
    assert set(flight["image"]) <= set(flight_images) and flight["image"].nunique() >= 20

    poses = pd.read_csv(results / "poses.csv", dtype={"frame": str})
    assert len(poses) == 5 and (results / "poses_0.csv").is_file() and (results / "poses_012.csv").is_file()
    evaluation = pd.read_csv(results / "evaluation.csv")
    assert evaluation["true_pos_err_m"].median() < 0.5 and evaluation["true_ang_err_arcmin"].median() < 5
    for table in ("intrinsics", "extrinsics_R", "extrinsics_t", "pose_methods", "conf", "time_points"):
        assert (results / "tables" / f"{table}.csv").is_file(), table
        assert (tmp_path / "reports/tiny/tables" / f"{table}.csv").is_file(), table
    assert set(pd.read_csv(results / "tables" / "conf.csv", dtype={"subset": str})["subset"]) == {"0", "012"}

    parser = Headings()
    parser.feed((tmp_path / "reports/tiny/report.html").read_text())
    assert parser.headings == ["Dataset", "Intrinsics per camera", "Rig layout", "Reprojection residuals per camera",
                               "Per-frame pose errors", "Camera subsets", "Runtime versus number of points",
                               "Processing time per stage", "Comparison with the paper"]
    assert "Not available" not in (tmp_path / "reports/tiny/report.html").read_text()


def test_config_schema_rejects_unknown_keys(tmp_path):
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"dataset": "x", "dataset_dir": "d", "datset": "typo"}))
    command = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "config.yaml"), "--cores", "1", "-n"]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert "datset" in result.stdout + result.stderr
