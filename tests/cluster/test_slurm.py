"""The README's cluster section, run verbatim on a real single-node SLURM (`make test-cluster`).

`slurm_up.sh` brings the cluster up (as root, from Debian's packages); without root or packages the
module is skipped with its one-line reason. In two copies of the repository (sharing `.venv`), the
demo runs once with `make run` and once with the README's SLURM commands; the SLURM run is killed
while a marker batch is half done, its jobs cancelled, and resumed. Then the account and partition
override of the README and a failing job's message are checked, and every table of the two runs is
compared: equal, but for the columns that are wall-clock times (TIME_COLUMN) and the runtime
benchmark's tables (time_points*), which measure this machine rather than compute a result, and
to RTOL, a margin for sums whose order a library's threads decide (OpenCV's calibrateCamera, the
`opencv` rows of tab:intrinsics, moved by up to 1.5e-8 relative until it ran on one thread).
"""

from __future__ import annotations

import getpass
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[2]
#: Columns holding wall-clock times, the one thing two runs of the same config may not share.
TIME_COLUMN = re.compile(r"(^|_)(time|ms|s|seconds)(_|$)")
#: Relative tolerance of the numbers of two runs (the module docstring says why it is not zero).
RTOL = 1e-9
ACCOUNT, PARTITION = "dmais", "debug"  # made by slurm_up.sh besides the default partition
RUN_TIMEOUT_S = 900


def readme_cluster_commands() -> list[str]:
    """The sh blocks of the README's "Running on a cluster" section, as they are written."""
    text = (REPO / "README.md").read_text()
    section = text.split("## Running on a cluster", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```sh\n(.*?)```", section, re.S)


def copy_repository(target: Path) -> Path:
    """The repository's files (tracked and not ignored) in `target`, with a link to its .venv."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target / name)
    (target / ".venv").symlink_to(REPO / ".venv")
    return target


def start(script: str, cwd: Path, log: Path) -> subprocess.Popen:
    """`script` in bash (stopping at the first failing command) in its own process group."""
    return subprocess.Popen(["bash", "-ec", script], cwd=cwd, stdout=open(log, "w"), stderr=subprocess.STDOUT,
                            start_new_session=True, env={**os.environ, "PATH": _path_without_venv()})


def finish(process: subprocess.Popen, log: Path) -> str:
    process.wait(timeout=RUN_TIMEOUT_S)
    output = log.read_text()
    assert process.returncode == 0, output[-4000:]
    return output


def _path_without_venv() -> str:
    """PATH as a user's fresh shell has it: the README's `source .venv/bin/activate` adds the venv."""
    venv = str(REPO / ".venv" / "bin")
    return os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep) if p != venv)


def wait_for_idle_queue(seconds: float = 120) -> None:
    deadline = time.monotonic() + seconds
    while subprocess.run(["squeue", "-h"], capture_output=True, text=True).stdout.strip():
        assert time.monotonic() < deadline, "SLURM jobs left after scancel"
        time.sleep(0.5)


def progress_lines(results: Path) -> list[str]:
    """Every image each marker batch recorded as finished, over all runs."""
    return [line.split(",")[0] for path in sorted((results / "markers" / "batches").glob("*.progress"))
            for line in path.read_text().splitlines()[1:]]


@pytest.fixture(scope="module")
def slurm():
    done = subprocess.run(["bash", str(REPO / "tests/cluster/slurm_up.sh")], capture_output=True, text=True,
                          timeout=900)
    if done.returncode == 77:
        pytest.skip(done.stderr.strip().splitlines()[-1])
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.fixture(scope="module")
def runs(slurm, tmp_path_factory):
    """The demo run locally and on SLURM (killed once midway and resumed), the override and the broken
    dataset's runs: their folders and what the tests check of them."""
    started_processes = []
    try:
        yield _runs(tmp_path_factory, started_processes)
    finally:  # a failed step leaves nothing running
        for process in started_processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
        subprocess.run(["scancel", "--user", getpass.getuser()])


def _runs(tmp_path_factory, started_processes: list) -> dict:
    local = copy_repository(tmp_path_factory.mktemp("local"))
    cluster = copy_repository(tmp_path_factory.mktemp("slurm"))
    logs = tmp_path_factory.mktemp("logs")
    started = time.strftime("%Y-%m-%dT%H:%M:%S")

    def run(script: str, cwd: Path, name: str) -> subprocess.Popen:
        started_processes.append(start(script, cwd, logs / f"{name}.log"))
        return started_processes[-1]

    run_locally = run("make run", local, "local")
    first, override = readme_cluster_commands()[:2]
    interrupted = run(first, cluster, "slurm_killed")
    half_done = wait_for_a_half_done_batch(interrupted, cluster / "results/demo/markers/batches")
    os.killpg(interrupted.pid, signal.SIGKILL)  # the controlling snakemake dies without cleaning up
    interrupted.wait()
    finished_before = {p.name: p.stat().st_mtime_ns for p in (cluster / "results/demo/markers/batches").glob("*.csv")}
    subprocess.run(["scancel", "--user", getpass.getuser()], check=True)  # as the README says
    wait_for_idle_queue()

    resumed = run(f"source .venv/bin/activate\nsnakemake --configfile config/config.yaml --unlock\n{first}",
                  cluster, "slurm_resumed")
    resumed_output = finish(resumed, logs / "slurm_resumed.log")
    broken = start_broken_batch(cluster, local, run)
    with_names = override.replace("slurm_account=NAME", f"slurm_account={ACCOUNT}").replace(
        "slurm_partition=NAME", f"slurm_partition={PARTITION}").strip()
    overridden = run(f"source .venv/bin/activate\n{with_names} --forcerun dataset_report", cluster, "slurm_override")
    finish(overridden, logs / "slurm_override.log")
    broken.wait(timeout=RUN_TIMEOUT_S)
    failed = {"failed_returncode": broken.returncode, "failed_output": (logs / "slurm_broken.log").read_text(),
              "bad_image": broken.image, "progress_after_failure": progress_lines(cluster / "results/mysite")}
    (cluster / "mysite" / broken.image_path).write_bytes(broken.original)
    finish(run(f"source .venv/bin/activate\n{broken.command}", cluster, "slurm_repaired"), logs / "slurm_repaired.log")
    finish(run_locally, logs / "local.log")
    return {"local": local, "slurm": cluster, "started": started, "half_done": half_done,
            "finished_before": finished_before, "resumed_output": resumed_output, **failed}


def wait_for_a_half_done_batch(process: subprocess.Popen, batches: Path) -> str:
    """The first marker batch seen with a finished image (its progress file) and no table yet."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while True:
        half_done = [p.stem for p in batches.glob("*.progress") if not p.with_suffix(".csv").exists()]
        if half_done:
            return half_done[0]
        assert process.poll() is None, "the SLURM run ended before a marker batch was half done"
        assert time.monotonic() < deadline, "no marker batch started on SLURM"
        time.sleep(0.05)


def start_broken_batch(cluster: Path, local: Path, run) -> subprocess.Popen:
    """A user's dataset (the demo's, copied once simulated) with one unreadable intrinsics image, its
    batch run on SLURM as a target of the README's command: the process, with what repairs it."""
    while not (local / "results/demo/dataset/images.csv").is_file():  # the local run simulates it
        time.sleep(0.5)
    time.sleep(2)  # let the simulator's last renames land
    user = cluster / "mysite"
    shutil.copytree(local / "results/demo/dataset", user, ignore=shutil.ignore_patterns("truth"))
    images = pd.read_csv(user / "images.csv")
    row = images[images["stage"] == "intrinsics"].iloc[3]
    original = (user / row["path"]).read_bytes()
    (user / row["path"]).write_bytes(original[: len(original) // 3])  # a PNG cut short
    (cluster / "mysite.yaml").write_text(f"dataset: mysite\ndataset_dir: {user}\n")
    first = readme_cluster_commands()[0].strip().splitlines()[-1]
    target = f"results/mysite/markers/batches/intrinsics-{row['camera']}-1.csv"  # before --configfile's values
    command = first.replace("snakemake ", f"snakemake {target} ", 1).replace("config/config.yaml", "mysite.yaml")
    process = run(f"source .venv/bin/activate\n{command}", cluster, "slurm_broken")
    process.image, process.image_path, process.original, process.command = row["image"], row["path"], original, command
    return process


def test_a_failed_job_names_its_image_and_keeps_the_batchs_finished_images(runs):
    assert runs["failed_returncode"] != 0
    lines = [line for line in runs["failed_output"].splitlines() if "dmais markers: error:" in line]
    assert lines and runs["bad_image"] in lines[0] and "intrinsics-" in lines[0], runs["failed_output"][-3000:]
    assert runs["bad_image"] not in runs["progress_after_failure"] and len(runs["progress_after_failure"]) >= 1
    batch = next((runs["slurm"] / "results/mysite/markers/batches").glob("*.csv"))
    table = pd.read_csv(batch)
    assert table.loc[table["image"] == runs["bad_image"], "resumed"].tolist() == [False]
    assert table.loc[table["image"] != runs["bad_image"], "resumed"].all()  # not redone after the repair


def test_the_resumed_run_redid_no_finished_work(runs):
    results = runs["slurm"] / "results/demo"
    batches = results / "markers" / "batches"
    for name, mtime in runs["finished_before"].items():  # complete batches were not run again
        assert (batches / name).stat().st_mtime_ns == mtime, name
    extracted = progress_lines(results)
    assert len(extracted) == len(set(extracted)), "an image was extracted twice"
    half_done = pd.read_csv(batches / f"{runs['half_done']}.csv")
    assert half_done["resumed"].any(), f"batch {runs['half_done']} redid its finished images"
    assert "slurm" in runs["resumed_output"].lower()


def test_jobs_ran_on_slurm_with_the_overridden_account_and_partition(runs):
    fields = "JobID,Comment,Account,Partition,State"
    jobs = subprocess.run(["sacct", "-X", "-n", "-P", "-S", runs["started"], "-o", fields], capture_output=True,
                          text=True, check=True).stdout.splitlines()
    rows = [line.split("|") for line in jobs]
    report_jobs = [row for row in rows if row[1].startswith("rule_dataset_report")]
    assert report_jobs and report_jobs[-1][2:] == [ACCOUNT, PARTITION, "COMPLETED"], rows
    markers_jobs = [row for row in rows if row[1].startswith("rule_markers")]
    assert len(markers_jobs) >= len(list((runs["slurm"] / "results/demo/markers/batches").glob("*.csv")))


def test_slurm_tables_equal_the_local_runs(runs):
    local, cluster = runs["local"], runs["slurm"]
    tables = sorted({p.relative_to(local) for folder in ("reports/demo/tables", "results/demo")
                     for p in (local / folder).rglob("*.csv")
                     if not p.name.startswith("time_points") and "markers/batches" not in str(p)})
    assert len(tables) > 200  # the report's tables, every image's markers, poses, observations, ...
    for name in tables:
        ours, theirs = pd.read_csv(local / name), pd.read_csv(cluster / name)
        keep = [c for c in ours.columns if not TIME_COLUMN.search(str(c))]
        if "quantity" in ours:  # a vs_paper table: its time rows
            ours, theirs = (t[~t["quantity"].astype(str).str.contains("time|ms")] for t in (ours, theirs))
        pd.testing.assert_frame_equal(ours[keep].reset_index(drop=True), theirs[keep].reset_index(drop=True),
                                      check_exact=False, rtol=RTOL, atol=0, obj=str(name))
