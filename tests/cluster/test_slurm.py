"""The README's cluster section, run verbatim on a real SLURM of several nodes (`make test-cluster`).

`slurm_up.sh` brings the cluster up (as root, from Debian's packages): a controller and three nodes, each
in its own network namespace, sharing this file system; without root or packages the module is skipped
with its one-line reason. In two copies of the repository (sharing `.venv`), the demo runs once with
`make run` and once with the README's SLURM commands; the SLURM run is killed while a marker batch is
half done and jobs run on several nodes, its jobs cancelled, and resumed. Then the account and partition
override of the README and a failing job's message are checked, and every table of the two runs is
compared: equal, but for the columns that are wall-clock times (TIME_COLUMN) and the runtime
benchmark's tables (time_points*), which measure this machine rather than compute a result, and
to RTOL, a margin for sums whose order a library's threads decide (OpenCV's calibrateCamera, the
`opencv` rows of tab:intrinsics, moved by up to 1.5e-8 relative until it ran on one thread).

Then a campaign-sized slice (CAMPAIGN_FRAMES frames of 5 images made from the demo's dataset as
`dmais bench campaign` makes them, CAMPAIGN_PER_JOB images a marker job) runs locally and on SLURM,
where one node dies (`slurm_up.sh kill`: its slurmd and every process of its jobs) once jobs run on
every node: the SLURM run finishes unattended, its tables equal the local run's, no finished image is
extracted again, and once the node is back the README's command has nothing to do.
"""

from __future__ import annotations

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
SLURM_UP = REPO / "tests/cluster/slurm_up.sh"
#: The node-loss run's slice: 400 frames of 5 cameras (2,000 flight images), 40 flight marker jobs.
CAMPAIGN, CAMPAIGN_FRAMES, CAMPAIGN_PER_JOB = "campaign_nodes", 400, 50
CAMPAIGN_TIMEOUT_S = 2400


def readme_cluster_commands() -> list[str]:
    """The sh blocks of the README's "Running on a cluster" section, as they are written."""
    text = (REPO / "README.md").read_text()
    section = text.split("## Running on a cluster", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```sh\n(.*?)```", section, re.S)


def copy_repository(target: Path) -> Path:
    """The repository's files (tracked and not ignored) in `target`, with the pose solver's compiled
    modules of the repository's build and a link to its .venv."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.decode().split("\0")
    built = subprocess.run(["git", "ls-files", "-z", "--others", "--ignored", "--exclude-standard", "dmais_pipe"],
                           cwd=REPO, capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed + [name for name in built if name.endswith((".so", ".txt"))]):
        source = REPO / name
        if source.is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target / name)
    (target / ".venv").symlink_to(REPO / ".venv")
    return target


def start(script: str, cwd: Path, log: Path) -> subprocess.Popen:
    """`script` in bash (stopping at the first failing command) in its own process group. The copy's
    package comes first on the path (PYTHONPATH, which its SLURM jobs inherit): .venv's editable install
    would otherwise import the repository's, which may change while the test runs."""
    return subprocess.Popen(["bash", "-ec", script], cwd=cwd, stdout=open(log, "w"), stderr=subprocess.STDOUT,
                            start_new_session=True,
                            env={**os.environ, "PATH": _path_without_venv(), "PYTHONPATH": str(cwd)})


def finish(process: subprocess.Popen, log: Path, timeout: float = RUN_TIMEOUT_S) -> str:
    process.wait(timeout=timeout)
    output = log.read_text()
    assert process.returncode == 0, output[-4000:]
    return output


def _path_without_venv() -> str:
    """PATH as a user's fresh shell has it: the README's `source .venv/bin/activate` adds the venv."""
    venv = str(REPO / ".venv" / "bin")
    return os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep) if p != venv)


def cancel_jobs(folder: Path, seconds: float = 120) -> None:
    """`scancel` the SLURM jobs that run in `folder` (a copy's runs) and wait until they are gone."""
    deadline = time.monotonic() + seconds
    while True:
        listed = subprocess.run(["squeue", "-h", "-o", "%i|%Z"], capture_output=True, text=True).stdout
        ids = [job for job, where in (line.split("|", 1) for line in listed.splitlines() if "|" in line)
               if Path(where).is_relative_to(folder)]
        if not ids:
            return
        subprocess.run(["scancel", *ids])
        assert time.monotonic() < deadline, f"SLURM jobs {ids} left after scancel"
        time.sleep(0.5)


def running_jobs(states: str = "R") -> list[tuple[str, str]]:
    """(node, rule and wildcards: the plugin's job comment) of every SLURM job in `states` (squeue's -t;
    "all": every job the controller has not yet seen end)."""
    listed = subprocess.run(["squeue", "-h", "-t", states, "-o", "%N|%k"], capture_output=True, text=True).stdout
    return [tuple(line.split("|", 1)) for line in listed.splitlines() if "|" in line]


def batch_of(comment: str) -> str | None:
    """The marker batch of a job comment (rule_markers_wildcards_<batch>), else None."""
    return comment.split("_wildcards_", 1)[1] if comment.startswith("rule_markers_wildcards_") else None


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
    nodes = subprocess.run(["sinfo", "-h", "-N", "-o", "%N"], capture_output=True, text=True).stdout.split()
    assert len(set(nodes)) >= 2, f"slurm_up.sh brought up {nodes}, not several nodes"
    return sorted(set(nodes))


@pytest.fixture(scope="module")
def runs(slurm, tmp_path_factory):
    """The demo run locally and on SLURM (killed once midway and resumed), the override and the broken
    dataset's runs: their folders and what the tests check of them."""
    started_processes, copies = [], []
    try:
        yield _runs(tmp_path_factory, started_processes, copies)
    finally:  # a failed step leaves nothing running
        for process in started_processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
        for copy in copies:
            cancel_jobs(copy)


def _runs(tmp_path_factory, started_processes: list, copies: list) -> dict:
    local = copy_repository(tmp_path_factory.mktemp("local"))
    cluster = copy_repository(tmp_path_factory.mktemp("slurm"))
    copies.append(cluster)
    logs = tmp_path_factory.mktemp("logs")
    started = time.strftime("%Y-%m-%dT%H:%M:%S")

    def run(script: str, cwd: Path, name: str) -> subprocess.Popen:
        started_processes.append(start(script, cwd, logs / f"{name}.log"))
        return started_processes[-1]

    run_locally = run("make run", local, "local")
    first, override = readme_cluster_commands()[:2]
    interrupted = run(first, cluster, "slurm_killed")
    half_done, nodes_at_kill = wait_for_a_half_done_batch(interrupted, cluster / "results/demo/markers/batches")
    os.killpg(interrupted.pid, signal.SIGKILL)  # the controlling snakemake dies without cleaning up
    interrupted.wait()
    finished_before = {p.name: p.stat().st_mtime_ns for p in (cluster / "results/demo/markers/batches").glob("*.csv")}
    cancel_jobs(cluster)  # as the README says (scancel), of this run's jobs only

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
            "nodes_at_kill": nodes_at_kill, "finished_before": finished_before, "resumed_output": resumed_output,
            **failed}


def wait_for_a_half_done_batch(process: subprocess.Popen, batches: Path) -> tuple[str, set[str]]:
    """The first marker batch seen with a finished image (its progress file) and no table yet while jobs
    run on several nodes, and those nodes."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while True:
        half_done = [p.stem for p in batches.glob("*.progress") if not p.with_suffix(".csv").exists()]
        nodes = {node for node, _ in running_jobs()}
        if half_done and len(nodes) >= 2:
            return half_done[0], nodes
        assert process.poll() is None, "the SLURM run ended before a marker batch was half done on several nodes"
        assert time.monotonic() < deadline, "no marker batch half done while jobs ran on several nodes"
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
    assert len(runs["nodes_at_kill"]) >= 2, runs["nodes_at_kill"]  # killed while jobs ran on several nodes


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
    assert_tables_equal(runs["local"], runs["slurm"], "demo", least=200)


def assert_tables_equal(local: Path, cluster: Path, name: str, least: int) -> None:
    """Every table of the run `name` in `cluster` equals `local`'s (the module docstring says how);
    more than `least` of them: the report's tables, every image's markers, poses, observations, ..."""
    tables = sorted({p.relative_to(local) for folder in (f"reports/{name}/tables", f"results/{name}")
                     for p in (local / folder).rglob("*.csv")
                     if not p.name.startswith("time_points") and "markers/batches" not in str(p)})
    assert len(tables) > least
    for table in tables:
        ours, theirs = pd.read_csv(local / table), pd.read_csv(cluster / table)
        keep = [c for c in ours.columns if not TIME_COLUMN.search(str(c))]
        if "quantity" in ours:  # a vs_paper table: its time rows
            ours, theirs = (t[~t["quantity"].astype(str).str.contains("time|ms")] for t in (ours, theirs))
        pd.testing.assert_frame_equal(ours[keep].reset_index(drop=True), theirs[keep].reset_index(drop=True),
                                      check_exact=False, rtol=RTOL, atol=0, obj=str(table))


# ------------------------------------------------------------------------------ a node dies mid-campaign


@pytest.fixture(scope="module")
def node_lost(slurm, runs, tmp_path_factory):
    """The campaign slice run locally and on SLURM, where a node is killed midway (`_node_lost`)."""
    started_processes = []
    try:
        yield _node_lost(slurm, runs, tmp_path_factory, started_processes)
    finally:
        for process in started_processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
        cancel_jobs(runs["slurm"])
        subprocess.run(["bash", str(SLURM_UP)], capture_output=True, timeout=300)  # the killed node back


def _node_lost(nodes: list[str], runs: dict, tmp_path_factory, started_processes: list) -> dict:
    local, cluster = runs["local"], runs["slurm"]
    logs = tmp_path_factory.mktemp("campaign_logs")
    dataset = tmp_path_factory.mktemp("campaign") / "data"
    make = (f"from dmais_pipe.bench.campaign import campaign_dataset\ncampaign_dataset('results/demo/dataset', "
            f"'{dataset}', frames={CAMPAIGN_FRAMES}, frames_per_group={CAMPAIGN_FRAMES // 2})")
    finish(start(f".venv/bin/python -c \"{make}\"", local, logs / "campaign_dataset.log"),
           logs / "campaign_dataset.log")
    settings = (f"dataset: {CAMPAIGN}\ndataset_dir: {dataset}\nmarkers_per_job: {CAMPAIGN_PER_JOB}\n"
                "bench_pose: {repeats: 5, batch_frames: 10, stage_frames: 0}\n")  # as the bench's --stages run
    for copy in (local, cluster):
        (copy / f"{CAMPAIGN}.yaml").write_text(settings)
    # every rule but export_colmap, as the bench's whole-workflow run: the campaign's image copies share their
    # files, hence their COLMAP names
    targets = f"reports/{CAMPAIGN}/report.html reports/{CAMPAIGN}/dataset.html"
    command = readme_cluster_commands()[0].strip().splitlines()[-1].replace(
        "snakemake ", f"snakemake {targets} ", 1).replace("config/config.yaml", f"{CAMPAIGN}.yaml")
    started = time.strftime("%Y-%m-%dT%H:%M:%S")

    def run(script: str, cwd: Path, name: str) -> subprocess.Popen:
        started_processes.append(start(f"source .venv/bin/activate\n{script}", cwd, logs / f"{name}.log"))
        return started_processes[-1]

    clean = run(f"snakemake {targets} --cores 2 --configfile {CAMPAIGN}.yaml", local, "campaign_local")
    lost = run(command, cluster, "campaign_node_lost")
    results = cluster / "results" / CAMPAIGN
    killed = wait_for_jobs_on_every_node(lost, results / "markers" / "batches", nodes)
    subprocess.run(["bash", str(SLURM_UP), "kill", killed["node"]], check=True, capture_output=True)
    lost_output = finish(lost, logs / "campaign_node_lost.log", CAMPAIGN_TIMEOUT_S)
    finish(clean, logs / "campaign_local.log", CAMPAIGN_TIMEOUT_S)
    subprocess.run(["bash", str(SLURM_UP)], check=True, capture_output=True, timeout=300)
    again = finish(run(command, cluster, "campaign_again"), logs / "campaign_again.log")
    incomplete = [p.name for p in (cluster / ".snakemake" / "incomplete").glob("*")]
    return {**killed, "local": local, "slurm": cluster, "results": results, "started": started,
            "output": lost_output, "again": again, "incomplete": incomplete}


def wait_for_jobs_on_every_node(process: subprocess.Popen, batches: Path, nodes: list[str]) -> dict:
    """Once jobs run on every node, a flight batch is finished and another half done on a node: that node,
    that batch, and the tables (name: mtime) of the batches finished by then whose jobs are gone."""
    deadline = time.monotonic() + CAMPAIGN_TIMEOUT_S
    while True:
        jobs = running_jobs()
        # a job whose table is written but still completing (CG) on the node to be killed ends NODE_FAIL
        # and is run again: finished means ended for the controller
        running = {batch_of(comment) for _, comment in running_jobs("all")}
        half_done = [(node, batch) for node, batch in ((n, batch_of(c)) for n, c in jobs)
                     if batch and batch.startswith("flight-") and not (batches / f"{batch}.csv").exists()
                     and len(_lines(batches / f"{batch}.progress")) > 1]
        finished = {p.name: p.stat().st_mtime_ns for p in batches.glob("flight-*.csv") if p.stem not in running}
        if {node for node, _ in jobs} == set(nodes) and finished and half_done:
            return {"node": half_done[0][0], "batch": half_done[0][1], "finished_before": finished,
                    "jobs_at_kill": jobs}
        assert process.poll() is None, "the SLURM run ended before jobs ran on every node"
        assert time.monotonic() < deadline, "flight marker jobs never ran on every node at once"
        time.sleep(0.2)


def _lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        return []


def test_a_lost_node_changes_no_table(node_lost):
    assert len(node_lost["jobs_at_kill"]) >= 3, node_lost["jobs_at_kill"]
    assert_tables_equal(node_lost["local"], node_lost["slurm"], CAMPAIGN, least=5 * CAMPAIGN_FRAMES)


def test_a_lost_node_redoes_no_finished_image_and_leaves_no_partial_file(node_lost):
    results, batches = node_lost["results"], node_lost["results"] / "markers" / "batches"
    for name, mtime in node_lost["finished_before"].items():  # finished batches were not run again
        assert (batches / name).stat().st_mtime_ns == mtime, name
    extracted = progress_lines(results)
    assert len(extracted) == len(set(extracted)), "an image was extracted twice"
    assert len(extracted) >= 5 * CAMPAIGN_FRAMES
    lost_batch = pd.read_csv(batches / f"{node_lost['batch']}.csv")
    assert lost_batch["resumed"].any(), f"{node_lost['batch']} redid the images it had finished on the lost node"
    partial = [str(p) for p in results.rglob("*") if p.is_file() and (p.name.startswith(".") or p.suffix == ".tmp")]
    assert partial == [] and node_lost["incomplete"] == []


def test_the_lost_nodes_jobs_failed_visibly(node_lost):
    node, batch = node_lost["node"], node_lost["batch"]
    listed = subprocess.run(["sacct", "-X", "-n", "-P", "-S", node_lost["started"], "-o",
                             "JobID,Comment,State,NodeList"], capture_output=True, text=True, check=True).stdout
    rows = [line.split("|") for line in listed.splitlines() if line.count("|") == 3]
    failed = [row for row in rows if row[2] == "NODE_FAIL"]
    assert failed and all(row[3] == node for row in failed), rows
    ids = [row[0] for row in failed if batch_of(row[1]) == batch]
    assert ids, f"sacct shows no NODE_FAIL job of {batch}: {failed}"
    output = node_lost["output"]
    block = output.split(f"SLURM-job '{ids[0]}' failed", 1)[1].split("Trying to restart job", 1)[0]
    assert "NODE_FAIL" in block and f"Host: {node}" in block, block[-3000:]  # the job's log, shown
    completed = [row for row in rows if batch_of(row[1]) == batch and row[2] == "COMPLETED"]
    assert completed and completed[-1][3] != node  # retried elsewhere


def test_with_the_node_back_the_readme_command_has_nothing_to_do(node_lost):
    assert "Nothing to be done" in node_lost["again"], node_lost["again"][-2000:]
