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


def test_workflow_simulates_and_reports(tmp_path):
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump({
        "name": "tiny", "seed": 3,
        "intrinsics": {"calib_images_per_camera": 2, "eval_images_per_camera": 1},
        "flight": {"frames_per_group": 1},
        "render": {"intrinsics": False, "extrinsics": False, "flight": False},
    }))
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(
        {"dataset": "tiny", "dataset_dir": "data/tiny", "simulate": "sim.yaml"}))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    command = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "config.yaml"), "--cores", "1"]
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]

    assert (tmp_path / "data/tiny/truth/rig.json").is_file()
    summary = pd.read_csv(tmp_path / "reports/tiny/dataset_summary.csv")
    assert set(summary["stage"]) == {"intrinsics", "extrinsics", "flight"}
    assert summary.loc[summary["stage"] == "intrinsics", "images"].tolist() == [3] * 5
    parser = Headings()
    parser.feed((tmp_path / "reports/tiny/dataset.html").read_text())
    assert parser.headings == ["Images and observations", "Points", "Truth rig", "Simulator noise budget"]


def test_config_schema_rejects_unknown_keys(tmp_path):
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({"dataset": "x", "dataset_dir": "d", "datset": "typo"}))
    command = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "config.yaml"), "--cores", "1", "-n"]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert "datset" in result.stdout + result.stderr
