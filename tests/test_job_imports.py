"""A workflow job imports only what it uses (issue 40, per-job overhead): each job below runs as the
workflow runs it, in a Python of its own, which then lists the heavy modules it had loaded. Those
the job does not use must not be among them: pyproj (a dataset without a CRS), the calibration
package and scipy.optimize (a flight marker batch), scipy.spatial (a flight marker batch: its
neighbour look-ups are markers.neighbours', its rotations geometry's own), OpenCV (the plan, which
reads no image)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dmais_pipe.dataset import Dataset
from dmais_pipe.plan import marker_batches

from test_marker_windows import FLIGHT
from test_slices import SIM

#: Loaded by no job: the report's and the workflow's libraries.
UNUSED = ("matplotlib", "jinja2", "snakemake", "dmais_pipe.report", "dmais_pipe.bench")
#: Run `dmais ARGS...` (argv[2:]) in this Python; with argv[1] "crs" then convert a point through
#: pyproj (the probe's control). Last line: the job's status and which of the watched modules it loaded.
PROBE = """
import json, sys
from dmais_pipe import cli
status = cli.main(sys.argv[2:])
if sys.argv[1] == "crs":
    from dmais_pipe import geo
    geo.ecef_from_crs("EPSG:4979", [[10.0, 50.0, 100.0]])
watched = ("cv2", "pandas", "pyproj", "scipy.optimize", "scipy.spatial", "scipy.special",
           "dmais_pipe.calib") + """ + repr(UNUSED) + """
print(json.dumps({"status": status, "loaded": [m for m in watched if m in sys.modules]}))
"""


def _job(*args: str, then: str = "") -> dict:
    """The status of `dmais args...` run in a new Python, the watched modules it loaded, its log."""
    done = subprocess.run([sys.executable, "-c", PROBE, then, *args], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return {**json.loads(done.stdout.splitlines()[-1]), "log": done.stderr}


@pytest.fixture(scope="module")
def flight(simulated_dataset, tmp_path_factory) -> tuple[Path, Path]:
    """A rendered flight frame (test_marker_windows.FLIGHT) and a results folder with its rig and
    the marker batches' slices (one image a job), as the workflow has them before the marker jobs."""
    dataset = simulated_dataset(FLIGHT)
    results = tmp_path_factory.mktemp("job_imports") / "results"
    results.mkdir()
    shutil.copy(dataset / "truth" / "rig.json", results / "rig.json")
    plan = _job("plan", str(dataset), "--per-job", "1", "--out", str(results), "--json",
                str(results / "plan.json"), "--slices", "markers")
    assert plan["status"] == 0
    assert {"cv2", "pyproj"}.isdisjoint(plan["loaded"]) and "pandas" in plan["loaded"]
    return dataset, results


def test_a_flight_marker_job_loads_neither_pyproj_nor_the_calibration(flight):
    dataset, results = flight
    batch = next(name for name in marker_batches(Dataset.load(dataset), 1) if name.startswith("flight-C0-"))
    job = _job("markers", str(dataset), "--out", str(results), "--batch", batch, "--per-job", "1")
    assert job["status"] == 0 and f"marker batch {batch} of" in job["log"]  # its slice read
    assert (results / "markers" / "batches" / f"{batch}.csv").is_file()
    assert {"cv2", "pandas", "scipy.special"} <= set(job["loaded"])  # what it uses (the fit's erf), so that
    # the probe is seen to see
    assert {"pyproj", "scipy.optimize", "scipy.spatial", "dmais_pipe.calib", *UNUSED}.isdisjoint(job["loaded"])


def test_the_probe_sees_pyproj_where_a_crs_is_used(flight):
    dataset, results = flight
    job = _job("validate", str(dataset), "--skip-images", then="crs")
    assert job["status"] == 0 and "pyproj" in job["loaded"]


def test_a_pose_job_and_its_slices_load_no_pyproj(simulated_dataset, tmp_path):
    dataset = simulated_dataset(SIM)
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(dataset / "truth" / "rig.json", results / "rig.json")
    group = Dataset.load(dataset).frames["group"].iloc[0]
    cut = _job("plan", str(dataset), "--out", str(results), "--slices", "pose")
    assert cut["status"] == 0 and {"cv2", "pyproj"}.isdisjoint(cut["loaded"])
    job = _job("pose", str(dataset), "--out", str(results), "--groups", group, "--csv", str(tmp_path / "part.csv"))
    assert job["status"] == 0 and f"flight group {group} of" in job["log"]
    assert (tmp_path / "part.csv").is_file() and "pandas" in job["loaded"]
    assert {"pyproj", *UNUSED}.isdisjoint(job["loaded"]) and {"pyproj", *UNUSED}.isdisjoint(cut["loaded"])
