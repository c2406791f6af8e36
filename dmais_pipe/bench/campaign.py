"""`dmais bench campaign`: the workflow at the scale of a flight campaign (10,000 frames, 50,055 images).

The targets (docs/design.md, "Marker batches"): such a flight plans in <= 30 s (`snakemake -n`, with and without the
SLURM profile), runs at most one cluster job per 50 images, costs <= 0.25 s of detection work per 12 MP
image (decode + detect + refine + identify + write) and <= 0.1 s of cluster overhead per image.

- `campaign_dataset`: a dataset whose flight repeats the frames of a simulated one (the demo's 30 frames
  of 5 cameras) up to `frames` frames, its calibration images as they are;
- `bench_campaign`, from the repository's root (where the Snakefile is), on that dataset as the
  workflow's dataset `campaign` (results/campaign/, which the bench owns and empties first):
  1. four dry runs, without and with the SLURM profile, each first with no plan file (cold) then with
     the one the first made (warm): wall seconds and the jobs Snakemake plans;
  2. one marker batch run by `dmais markers --batch` on one core, upstream results copied from the
     demo's: seconds per image of each phase, and what the process costs besides (its start, imports,
     loading the dataset);
  3. with `slurm`, a few flight batches run through the SLURM profile: per job its images, elapsed
     time, detection work, overhead and peak memory (sacct, the job's Snakemake benchmark file); with
     `slurm_lose`, the same batches again with one node lost midway: the run's wall time against the
     clean one's;
  4. marker extraction per phase at 12 MP and 140 MP, JPEG and 16-bit TIFF, windowed about the
     priors' predictions beside the whole image on the same images, and a job's peak memory
     (`bench.marker_costs`: rendered once into results/bench_marker_phases/), <csv>_marker_phases.csv;
  5. what a marker job and a pose job cost besides their work when they read the whole dataset and
     when they read their slice of it (slices.py), side by side (`_job_reads`).
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from datetime import datetime, timedelta
from pathlib import Path

import pandas as pd

from ..dataset import FRAMES, IMAGES, MANIFEST, OBSERVATIONS, Dataset
from ..errors import DmaisError
from ..files import copy_atomic, write_csv_atomic, write_yaml_atomic
from ..plan import MARKERS_PER_JOB
from .marker_costs import marker_phase_table, write_marker_phase_table

log = logging.getLogger(__name__)

#: The workflow's name of the campaign: results/campaign/, logs/campaign/, benchmarks/campaign/.
NAME = "campaign"
PROFILE = ("--workflow-profile", "workflow/profiles/slurm")
PHASES = ("decode_s", "detect_s", "refine_s", "identify_s", "write_s")
COLUMNS = ("metric", "value", "unit", "note")
#: Files a campaign dataset is made of besides its links to the source's image folders.
_OWN_FILES = (MANIFEST, "control_points.csv", "ground_points.csv", IMAGES, FRAMES, OBSERVATIONS)
_COPIED = (MANIFEST, "control_points.csv", "ground_points.csv")


# ------------------------------------------------------------------------------ the dataset


def campaign_dataset(source: str | Path, out: str | Path, frames: int = 10_000, frames_per_group: int = 500) -> Path:
    """Write the dataset folder `out` from the dataset `source` and return it: its flight has `frames`
    frames, frame k a copy of source frame k % n (n frames, in frames.csv order) with id `c<k:06d>` and
    group `line<k // frames_per_group:03d>`, and one image `<frame>_<camera>` per flight image of that
    source frame (its camera, path and priors). The other images, the points, the manifest and the given
    observations of non-flight images are the source's (those of flight images follow their copies);
    the folders the image paths start with are links to the source's; no truth/."""
    source, out = Path(source).absolute(), Path(out).absolute()
    if frames < 1 or frames_per_group < 1:
        raise DmaisError(f"campaign: frames ({frames}) and frames per group ({frames_per_group}) must be positive")
    _check_out(source, out)
    Dataset.load(source)  # a faulty source stops here with the loader's one-line error
    images, source_frames = _read(source / IMAGES), _read(source / FRAMES)
    if source_frames.empty:
        raise DmaisError(f"campaign: {source / FRAMES} has no flight frame to repeat")
    frame_copies, flight_frames = _frame_copies(source_frames, frames, frames_per_group)
    source_flight = images[images["stage"] == "flight"]
    flight = _repeat(source_flight, "placement", frame_copies)
    image_copies = pd.DataFrame({"new": flight["placement"] + "_" + flight["camera"], "source": flight["image"]})
    flight["image"] = image_copies["new"].to_numpy()
    written = [copy_atomic(source / name, out / name) for name in _COPIED if (source / name).exists()]
    written.append(write_csv_atomic(out / IMAGES, pd.concat([images[images["stage"] != "flight"], flight])))
    written.append(write_csv_atomic(out / FRAMES, flight_frames))
    if (source / OBSERVATIONS).exists():
        given = _read(source / OBSERVATIONS)
        kept = given[~given["image"].isin(source_flight["image"])]
        written.append(write_csv_atomic(out / OBSERVATIONS, pd.concat([kept, _repeat(given, "image", image_copies)])))
    written += [_link(source / name, out / name) for name in _linked_names(images)]
    _remove_stale(out, {path.name for path in written})
    return out


def _read(path: Path) -> pd.DataFrame:
    """A dataset CSV with every cell as its text ('' where empty), so that it is written back unchanged."""
    return pd.read_csv(path, dtype=str, keep_default_na=False, encoding="utf-8-sig")


def _frame_copies(source_frames: pd.DataFrame, frames: int, frames_per_group: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(copies: new, source frame ids (frames, 2); the new frames.csv table (frames rows))."""
    table = source_frames.iloc[[k % len(source_frames) for k in range(frames)]].reset_index(drop=True)
    copies = pd.DataFrame({"new": [f"c{k:06d}" for k in range(frames)], "source": table["frame"]})
    table["frame"] = copies["new"]
    table["group"] = [f"line{k // frames_per_group:03d}" for k in range(frames)]
    return copies, table


def _repeat(table: pd.DataFrame, column: str, copies: pd.DataFrame) -> pd.DataFrame:
    """The rows of `table` whose `column` is a source id of `copies` (new, source), once per copy in
    copies' order (rows of one source in table's order), `column` set to the copy's new id."""
    keys = copies.rename(columns={"new": "\0new", "source": "\0source"})
    joined = keys.merge(table, left_on="\0source", right_on=column, how="inner", sort=False)
    joined[column] = joined["\0new"]
    return joined[list(table.columns)].reset_index(drop=True)


def _linked_names(images: pd.DataFrame) -> list[str]:
    """The top-level names (folders, or files) of the dataset folder that image paths start with."""
    return sorted({Path(path).parts[0] for path in images["path"] if path})


def _link(target: Path, link: Path) -> Path:
    """`link` made (or replaced) as a symbolic link to `target`."""
    temporary = link.with_name(f".{link.name}.link")
    temporary.unlink(missing_ok=True)
    temporary.symlink_to(target.resolve(), target_is_directory=target.is_dir())
    os.replace(temporary, link)
    return link


def _check_out(source: Path, out: Path) -> None:
    """`out` is the source's folder, or an existing folder that is not a campaign dataset: refuse it."""
    if out.resolve() == source.resolve():
        raise DmaisError(f"campaign: the campaign dataset {out} would overwrite its source; give another --out")
    if out.exists() and not out.is_dir():
        raise DmaisError(f"campaign: {out} is a file, not a folder for the campaign dataset")
    for entry in out.iterdir() if out.is_dir() else ():
        if not (entry.name in _OWN_FILES or entry.is_symlink() or entry.name.startswith(".")):
            raise DmaisError(f"campaign: {out} holds {entry.name}, so it is not a campaign dataset "
                             "`dmais bench campaign` wrote; give another --out")


def _remove_stale(out: Path, written: set[str]) -> None:
    """Files and links of an earlier campaign dataset in `out` that this one does not have."""
    for entry in out.iterdir():
        if entry.name not in written and not entry.name.startswith(".") and (entry.is_symlink() or entry.is_file()):
            entry.unlink()


def given_flight_source(source: str | Path, demo: str | Path, out: str | Path) -> Path:
    """Write the dataset folder `out`: `source`'s files as links, but observations.csv, which adds to
    the source's own the flight observations its run identified (`demo`/observations/flight.csv), so
    that a campaign made from it runs every stage of the workflow but flight marker extraction."""
    source, out = Path(source).absolute(), Path(out).absolute()
    _check_out(source, out)
    flight = pd.read_csv(Path(demo) / "observations" / "flight.csv", dtype={"image": str, "point_id": str})
    given = _read(source / OBSERVATIONS) if (source / OBSERVATIONS).exists() else flight.iloc[:0, :0]
    observations = pd.concat([given, flight[["image", "point_id", "u", "v"]]], ignore_index=True)
    written = [write_csv_atomic(out / OBSERVATIONS, observations)]
    names = [*_COPIED, IMAGES, FRAMES, *_linked_names(_read(source / IMAGES))]
    written += [_link(source / name, out / name) for name in names if (source / name).exists()]
    _remove_stale(out, {path.name for path in written})
    return out


# ------------------------------------------------------------------------------ the bench


def bench_campaign(source: Path, out: Path, csv: Path, frames: int = 10_000, frames_per_group: int = 500,
                   slurm: bool = False, slurm_batches: int = 4, stages: bool = False, slurm_lose: str | None = None,
                   slurm_restore: str = "true") -> pd.DataFrame:
    """Run the bench (module docstring), print its table and write it to `csv` (metric, value, unit,
    note); with `slurm`, the per-job table too, beside it (<csv>_slurm_jobs.csv), and with `slurm_lose`
    the same batches again with a node lost (`_with_a_node_lost`); with `stages`, the
    per-rule table of a whole run (`_all_stages`, <csv>_stages.csv). Returns the table."""
    root = _repository()
    source, out, csv = Path(source).absolute(), Path(out).absolute(), Path(csv).absolute()
    demo = _demo_results(source)
    log.info("campaign: writing %d frames into %s", frames, out)
    dataset = campaign_dataset(source, out, frames, frames_per_group)
    results = root / "results" / NAME
    shutil.rmtree(results, ignore_errors=True)
    config = write_yaml_atomic(results / f"{NAME}.yaml", {"dataset": NAME, "dataset_dir": str(dataset)})
    rows, plan = _dry_runs(root, config, results)
    rows += _one_core(root, dataset, demo, results, plan)
    rows += _job_reads(root, source, demo, out, dataset, results, plan, frames, frames_per_group)
    jobs = None
    if slurm and shutil.which("sbatch") is None:
        print("slurm: skipped: sbatch is not on PATH")
    elif slurm and not has_slurm_plugin():
        print(f"slurm: skipped: {NO_PLUGIN}")
    elif slurm:
        jobs = _on_slurm(root, config, results, plan, slurm_batches)
        rows += _slurm_rows(jobs)
        if slurm_lose:
            rows += _with_a_node_lost(root, config, results, plan, slurm_batches, slurm_lose, slurm_restore,
                                      jobs.attrs["wall_s"])
    if stages:
        _all_stages(root, source, demo, out.with_name(f"{out.name}_stages"), csv, frames, frames_per_group)
    table = pd.DataFrame(rows, columns=COLUMNS, dtype=object)  # counts stay integers
    print(table.to_string(index=False, formatters={"value": _shown}))
    write_csv_atomic(csv, table)
    phases = marker_phase_table(root / "config" / "simulate", root / "results" / "bench_marker_phases")
    write_marker_phase_table(phases, csv.with_name(f"{csv.stem}_marker_phases.csv"))
    if jobs is not None:
        print(jobs.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
        write_csv_atomic(csv.with_name(f"{csv.stem}_slurm_jobs.csv"), jobs.round(4))
    return table


def _all_stages(root: Path, source: Path, demo: Path, out: Path, csv: Path, frames: int, frames_per_group: int):
    """The workflow but its COLMAP export, locally on every core, on the campaign of `frames` frames whose
    flight observations are given (`given_flight_source`; its marker extraction is what the rest measures):
    per rule its jobs, total and largest wall time and peak memory, from the rules' benchmark files."""
    from ..report.html import benchmark_table

    given = given_flight_source(source, demo, out.with_name(f"{out.name}_source"))
    dataset = campaign_dataset(given, out, frames, frames_per_group)
    name = f"{NAME}_stages"
    for folder in ("results", "benchmarks", "logs"):
        shutil.rmtree(root / folder / name, ignore_errors=True)
    bench_pose = {"repeats": 5, "batch_frames": 10, "stage_frames": 0}  # the runtime benchmark is not the subject
    config = write_yaml_atomic(root / "results" / name / f"{name}.yaml",
                               {"dataset": name, "dataset_dir": str(dataset), "bench_pose": bench_pose})
    # every rule but export_colmap: the campaign's image copies share their files, hence their COLMAP names
    targets = [f"reports/{name}/report.html", f"reports/{name}/dataset.html"]
    seconds, _ = _run([_tool("snakemake"), *targets, "--cores", str(os.cpu_count()), "--configfile", str(config)],
                      root, timeout=6 * 3600)
    table = benchmark_table(root / "benchmarks" / name)
    print(f"every stage on {frames} frames with given flight observations: {seconds:.0f} s "
          f"on {os.cpu_count()} cores")
    print(table.to_string(index=False, float_format=lambda x: f"{x:.2f}"))
    write_csv_atomic(csv.with_name(f"{csv.stem}_stages.csv"), table.round(3))


def _row(metric: str, value, unit: str, note: str = "") -> dict:
    return {"metric": metric, "value": round(value, 4) if isinstance(value, float) else value, "unit": unit,
            "note": note}


def _shown(value) -> str:
    return str(value) if isinstance(value, int) or abs(value) >= 1000 else f"{value:.4g}"


def _repository() -> Path:
    """The source tree this package runs from, whose Snakefile the bench runs."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "Snakefile").is_file():
        raise DmaisError(f"campaign: no Snakefile in {root}: the bench runs the workflow of a source checkout "
                         "(pip install -e .)")
    return root


def _demo_results(source: Path) -> Path:
    """The results folder of the source dataset's run (results/demo for results/demo/dataset)."""
    if not (source / MANIFEST).is_file() or not (source.parent / "rig.json").is_file():
        raise DmaisError(f"campaign: no dataset with calibrated results at {source} (and {source.parent}): "
                         "run `make run` first")
    return source.parent


def _tool(name: str) -> str:
    """`name` installed beside the running Python (the venv's snakemake, dmais)."""
    path = Path(sys.executable).parent / name
    if not path.is_file():
        raise DmaisError(f"campaign: {name} is not installed beside {sys.executable} (make install)")
    return str(path)


def _run(command: list[str], root: Path, timeout: float) -> tuple[float, subprocess.CompletedProcess]:
    """(wall seconds, the finished process) of `command` run in `root`; a failure raises one line."""
    started = time.perf_counter()
    try:
        done = subprocess.run(command, cwd=root, env=_tools_env(), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise DmaisError(f"campaign: `{' '.join(command)}` took longer than {timeout:.0f} s") from None
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        lines = [line for line in (done.stderr + "\n" + done.stdout).splitlines() if line.strip()] or ["no output"]
        last = next((line for line in reversed(lines) if "Error" in line), lines[-1]).strip()
        raise DmaisError(f"campaign: `{' '.join(command)}` failed (status {done.returncode}): {last}")
    return seconds, done


def _tools_env() -> dict[str, str]:
    """The environment of the bench's commands: this Python's folder (the venv's snakemake, dmais) first on PATH."""
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}


def job_stats(text: str) -> dict[str, int]:
    """Rule -> jobs (and 'total') of the "Job stats:" table of Snakemake's output `text` ({} without one)."""
    lines = text.splitlines()
    start = next((k for k, line in enumerate(lines) if line.strip() == "Job stats:"), None)
    stats = {}
    for line in lines[start + 3:] if start is not None else ():  # after the header and its dashes
        cells = line.split()
        if len(cells) != 2 or not cells[1].isdigit():
            break
        stats[cells[0]] = int(cells[1])
    return stats


# ------------------------------------------------------------------------------ dry runs


NO_PLUGIN = "Snakemake's SLURM executor plugin is not installed (make install-slurm)"


def has_slurm_plugin() -> bool:
    """Whether Snakemake's SLURM executor plugin, which the SLURM profile names, is installed."""
    return importlib.util.find_spec("snakemake_executor_plugin_slurm") is not None


def _dry_runs(root: Path, config: Path, results: Path) -> tuple[list[dict], dict]:
    """Rows of the four dry runs (the two without the SLURM profile where its plugin is not installed) and
    of the jobs they plan; the plan file the runs made (`dmais plan`)."""
    rows, stats = [], {}
    profiles = (False, True) if has_slurm_plugin() else (False,)
    if len(profiles) == 1:
        print(f"dry runs with the SLURM profile: skipped: {NO_PLUGIN}")
    for profile in profiles:
        shutil.rmtree(results / "plan", ignore_errors=True)
        for run in ("cold", "warm"):
            command = [_tool("snakemake"), "-n", "--configfile", str(config), *(PROFILE if profile else ())]
            log.info("campaign: dry run %s%s", run, " with the SLURM profile" if profile else "")
            seconds, done = _run(command, root, timeout=1800)
            stats = job_stats(done.stdout + "\n" + done.stderr)
            rows.append(_row(f"dry_run{'_profile' if profile else ''}_{run}_s", seconds, "s",
                             ("makes the plan file (dmais plan)" if run == "cold" else "reads the plan file")
                             + "; target: <= 30 s"))
    plan = json.loads(next((results / "plan").glob("*.json")).read_text())
    images = sum(batch["images"] for stage in plan["batches"].values() for batch in stage.values())
    markers = stats.get("markers", 0)
    rows += [_row("jobs_total", stats.get("total", 0), "jobs", "every rule of the workflow, nothing done yet"),
             _row("marker_jobs", markers, "jobs", f"markers_per_job {MARKERS_PER_JOB}"),
             _row("images", images, "images", "images to extract (images.csv rows with a file)"),
             _row("images_per_marker_job", images / max(markers, 1), "images", "target: >= 50"),
             _row("images_per_job", images / max(stats.get("total", 0), 1), "images",
                  "over every job of the run; target: >= 50 (<= 1 cluster job per 50 images)")]
    return rows, plan


# ------------------------------------------------------------------------------ one core


def _one_core(root: Path, dataset: Path, demo: Path, results: Path, plan: dict) -> list[dict]:
    """Rows of the first flight batch run by `dmais markers --batch` pinned to CPU 0 (taskset)."""
    _copy_upstream(demo, results, plan)
    batch = next(iter(plan["batches"]["flight"]))
    _forget(results, [batch])
    command = ["taskset", "-c", "0", _tool("dmais"), "markers", str(dataset), "--out", str(results),
               "--batch", batch, "--per-job", str(MARKERS_PER_JOB)]
    log.info("campaign: marker batch %s on one core", batch)
    wall, _ = _run(command, root, timeout=3600)
    phases = pd.read_csv(results / "markers" / "batches" / f"{batch}.csv")[list(PHASES)]
    resumed = _medians([_timed(command, root) for _ in range(3)])  # its every image done: the job without work
    images, work = len(phases), float(phases.to_numpy().sum())
    note = f"{batch}: {images} images, mean per image"
    return [*(_row(f"one_core_{phase}", float(phases[phase].mean()), "s", note) for phase in PHASES),
            _row("one_core_per_image_s", work / images, "s", "decode+detect+refine+identify+write; target: <= 0.25 s"),
            _row("one_core_batch_wall_s", wall, "s", f"`dmais markers --batch {batch}` as a process"),
            _row("one_core_overhead_per_image_s", (wall - work) / images, "s",
                 "(wall - phases) / images: interpreter start, imports, loading the dataset, planning its "
                 "batches, per-image bookkeeping"),
            _row("one_core_resumed_batch_cpu_s", resumed[1], "s", f"the same `dmais markers --batch {batch}` again, "
                 "every image resumed: the job's overhead, CPU (median of 3); target: <= 1 s")]


def _copy_upstream(demo: Path, results: Path, plan: dict) -> None:
    """The demo's results the flight batches need, into `results` in the order the workflow makes
    them (so that none is older than its inputs and Snakemake plans no job upstream): per calibration
    stage its marker batches and markers files, its observations, then the intrinsics or the rig."""
    for stage in ("intrinsics", "extrinsics"):
        names = [f"markers/batches/{batch}.csv" for batch in plan["batches"][stage]]
        names += [f"markers/{image}.csv" for name in list(names)
                  for image in pd.read_csv(_needed(demo / name), dtype=str)["image"]]
        names.append(f"observations/{stage}.csv")
        if stage == "intrinsics":
            names += [f"intrinsics/{camera}{ext}" for camera in plan["calibrated_cameras"]
                      for ext in (".json", ".methods.csv", ".residuals.csv")]
        else:
            names += ["rig.json", "rig_config.json", "tables/extrinsics_R.csv", "tables/extrinsics_t.csv"]
        for name in names:
            copy_atomic(_needed(demo / name), results / name)


def _needed(path: Path) -> Path:
    if not path.is_file():
        raise DmaisError(f"campaign: {path} is missing: run `make run` first")
    return path


def _forget(results: Path, batches: list[str]) -> None:
    """Remove the batches' tables and progress files, so that they are done again from the start."""
    for batch in batches:
        for suffix in (".csv", ".progress"):
            (results / "markers" / "batches" / f"{batch}{suffix}").unlink(missing_ok=True)


# ------------------------------------------------------------------------------ SLURM


def _slurm_batches(plan: dict, count: int) -> list[str]:
    """The `count` flight batches the SLURM runs take: the first of each camera in turn."""
    flight = plan["batches"]["flight"]
    return sorted(flight, key=lambda name: (name.rsplit("-", 1)[1], list(flight).index(name)))[:count]


def _slurm_command(root: Path, config: Path, results: Path, batches: list[str]) -> list[str]:
    """The SLURM profile's snakemake command of `batches`, forgotten first (`_forget`) and checked by a dry
    run to be their marker jobs alone."""
    _forget(results, batches)
    targets = [f"results/{NAME}/markers/batches/{batch}.csv" for batch in batches]
    command = [_tool("snakemake"), *targets, *PROFILE, "--configfile", str(config)]  # --configfile takes 1+ values
    _, dry = _run([*command, "-n"], root, timeout=1800)
    planned = job_stats(dry.stdout + "\n" + dry.stderr)
    if planned != {"markers": len(batches), "total": len(batches)}:
        raise DmaisError(f"campaign: the SLURM run would run {planned} instead of {len(batches)} marker jobs "
                         f"(results in {results} older than their inputs?)")
    return command


def _on_slurm(root: Path, config: Path, results: Path, plan: dict, count: int) -> pd.DataFrame:
    """Per job (one per batch) of `count` flight batches (`_slurm_batches`) run through
    the SLURM profile: batch, images, elapsed_s, shell_s (the job's `dmais markers`), work_s (its
    phases), overhead_per_image_s ((elapsed - work) / images), max_rss_mb."""
    flight = plan["batches"]["flight"]
    batches = _slurm_batches(plan, count)
    command = _slurm_command(root, config, results, batches)
    start = (datetime.now() - timedelta(seconds=5)).strftime("%Y-%m-%dT%H:%M:%S")
    log.info("campaign: %d marker jobs on SLURM: %s", len(batches), ", ".join(batches))
    wall, done = _run(command, root, timeout=3 * 3600)
    found = re.search(r"SLURM run ID: (\S+)", done.stdout + done.stderr)
    if found is None:
        raise DmaisError("campaign: the SLURM run printed no run ID to find its jobs with in sacct")
    jobs = _sacct(found.group(1), start)
    table = pd.DataFrame([_job(results, root, batch, flight[batch]["images"], jobs) for batch in batches])
    table.attrs["wall_s"] = wall
    return table


def _with_a_node_lost(root: Path, config: Path, results: Path, plan: dict, count: int, lose: str, restore: str,
                      clean_wall_s: float) -> list[dict]:
    """The main table's rows of the `_on_slurm` batches run again on SLURM, where one node is lost midway: once
    the run's jobs are on every node of the cluster and a flight batch is half done (its progress file
    has an image, its table is not written), the shell command `lose` is run with {node} that batch's
    node (e.g. the test cluster's `bash tests/cluster/slurm_up.sh kill {node}`: a power loss); the run
    must then finish unattended (the profile's retries), and `restore` brings the node back after it.
    Rows: its wall time, the ratio to the clean run's `clean_wall_s` against the target (N / (N - 1)) x 1.3
    for N nodes, and the jobs sacct shows ended NODE_FAIL."""
    batches = _slurm_batches(plan, count)
    command = _slurm_command(root, config, results, batches)
    nodes = _cluster_nodes()
    start = (datetime.now() - timedelta(seconds=5)).strftime("%Y-%m-%dT%H:%M:%S")
    output = results / "slurm_node_lost.log"
    log.info("campaign: %d marker jobs on SLURM, one of %d nodes to be lost", len(batches), len(nodes))
    started = time.perf_counter()
    with open(output, "w") as sink:
        process = subprocess.Popen(command, cwd=root, stdout=sink, stderr=subprocess.STDOUT,
                                   env=_tools_env())
        try:
            node = _lose_a_node(process, root, results / "markers" / "batches", nodes, lose)
            process.wait(timeout=3 * 3600)
        finally:
            if process.poll() is None:
                process.kill()
    wall = time.perf_counter() - started
    _shell(restore, "restore")
    text = output.read_text()
    if process.returncode != 0:
        raise DmaisError(f"campaign: the SLURM run with node {node} lost failed (status {process.returncode}); "
                         f"its output: {output}")
    found = re.search(r"SLURM run ID: (\S+)", text)
    failed = _node_failures(found.group(1), start) if found else []
    bound = len(nodes) / (len(nodes) - 1) * 1.3
    return [_row("slurm_node_lost_wall_s", wall, "s", f"{node} of {len(nodes)} nodes lost once jobs ran on every "
                 f"node; NODE_FAIL jobs retried: {len(failed)} ({', '.join(failed)})"),
            _row("slurm_node_lost_ratio", wall / clean_wall_s, "x",
                 f"of the clean run's {clean_wall_s:.1f} s; target: <= N / (N - 1) x 1.3 = {bound:.2f}")]


def _cluster_nodes() -> list[str]:
    """The SLURM nodes that are up (sinfo), at least two."""
    listed = subprocess.run(["sinfo", "-h", "-N", "-o", "%N|%t"], capture_output=True, text=True).stdout
    nodes = sorted({node for node, state in (line.split("|") for line in listed.splitlines() if "|" in line)
                    if not state.startswith(("down", "drain", "fail"))})
    if len(nodes) < 2:
        raise DmaisError(f"campaign: losing a node needs a SLURM of two or more nodes up; sinfo shows {nodes}")
    return nodes


def _lose_a_node(process: subprocess.Popen, root: Path, batches: Path, nodes: list[str], lose: str) -> str:
    """Wait until the SLURM jobs of the run in `root` run on every node of `nodes` and one of them is a
    flight batch half done (its progress file in `batches` has an image, its table is not written), run
    `lose` for that job's node and return the node."""
    while True:
        listed = subprocess.run(["squeue", "-h", "-t", "R", "-o", "%N|%k|%Z"], capture_output=True, text=True).stdout
        jobs = [line.split("|") for line in listed.splitlines() if line.count("|") == 2]
        jobs = [(node, comment.split("_wildcards_", 1)[-1]) for node, comment, where in jobs
                if Path(where) == root and comment.startswith("rule_markers_wildcards_flight-")]
        half_done = [node for node, batch in jobs if not (batches / f"{batch}.csv").exists()
                     and (batches / f"{batch}.progress").is_file()
                     and len((batches / f"{batch}.progress").read_text().splitlines()) > 1]
        if {node for node, _ in jobs} >= set(nodes) and half_done:
            _shell(lose.replace("{node}", half_done[0]), "lose")
            return half_done[0]
        if process.poll() is not None:
            raise DmaisError("campaign: the SLURM run ended before its jobs ran on every node at once "
                             "(give it more batches: --slurm-batches)")
        time.sleep(0.2)


def _shell(command: str, what: str) -> None:
    """Run the user's shell `command` (--slurm-{what}); a failure raises one line."""
    done = subprocess.run(command, shell=True, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        last = (done.stderr.strip() or done.stdout.strip() or "no output").splitlines()[-1]
        raise DmaisError(f"campaign: --slurm-{what} `{command}` failed (status {done.returncode}): {last}")


def _node_failures(run_id: str, start: str) -> list[str]:
    """The jobs of the SLURM run `run_id` that ended NODE_FAIL, as job@node."""
    listed = subprocess.run(["sacct", "-n", "-P", "-X", "-S", start, "--name", run_id, "-o", "JobID,State,NodeList"],
                            capture_output=True, text=True, check=True).stdout
    return [f"{job}@{node}" for job, state, node in (line.split("|") for line in listed.splitlines()
                                                    if line.count("|") == 2) if state == "NODE_FAIL"]


def _job(results: Path, root: Path, batch: str, images: int, jobs: pd.DataFrame) -> dict:
    """One batch's row of the per-job table (`_on_slurm`)."""
    mine = jobs[jobs["batch"] == batch]
    if mine.empty:
        raise DmaisError(f"campaign: sacct shows no completed SLURM job of batch {batch}")
    job = mine.iloc[-1]
    work = float(pd.read_csv(results / "markers" / "batches" / f"{batch}.csv")[list(PHASES)].to_numpy().sum())
    benchmark = pd.read_csv(root / "benchmarks" / NAME / "markers" / f"{batch}.tsv", sep="\t").iloc[0]
    # sacct samples memory every 30 s (JobAcctGatherFrequency) and misses short peaks: the larger counts
    rss = max(float(job["max_rss_mb"]) if pd.notna(job["max_rss_mb"]) else 0.0, float(benchmark["max_rss"]))
    return {"batch": batch, "job": job["job"], "node": job["node"], "images": images, "elapsed_s": job["elapsed_s"],
            "shell_s": float(benchmark["s"]), "work_s": work,
            "overhead_per_image_s": (job["elapsed_s"] - work) / images, "max_rss_mb": rss}


def _sacct(run_id: str, start: str) -> pd.DataFrame:
    """The completed marker jobs of the SLURM run `run_id` (its job name): job, batch, node, elapsed_s and
    max_rss_mb (the largest of its steps')."""
    fields = ["sacct", "-n", "-P", "-S", start]
    jobs = subprocess.run([*fields, "-X", "--name", run_id, "-o", "JobID,Comment,NodeList,Elapsed,State"],
                          capture_output=True, text=True, check=True).stdout
    rows = [line.split("|") for line in jobs.splitlines() if line.count("|") == 4]
    rows = [(job, comment.split("_wildcards_", 1)[-1], node, _seconds(elapsed)) for job, comment, node, elapsed, state
            in rows if comment.startswith("rule_markers") and state == "COMPLETED"]
    table = pd.DataFrame(rows, columns=["job", "batch", "node", "elapsed_s"])
    if table.empty:
        return table.assign(max_rss_mb=[])
    steps = subprocess.run([*fields, "-j", ",".join(table["job"]), "-o", "JobID,MaxRSS"],
                           capture_output=True, text=True, check=True).stdout
    rss = {}
    for job, size in (line.split("|") for line in steps.splitlines() if line.count("|") == 1):
        key = job.split(".")[0]
        rss[key] = max(rss.get(key, 0.0), _megabytes(size))
    return table.assign(max_rss_mb=table["job"].map(rss).fillna(float("nan")))


def _seconds(elapsed: str) -> float:
    """sacct's [D-]HH:MM:SS (or MM:SS) in seconds."""
    days, _, clock = elapsed.rpartition("-")
    seconds = 0.0
    for part in clock.split(":"):
        seconds = 60 * seconds + float(part)
    return seconds + 86400 * int(days or 0)


def _megabytes(size: str) -> float:
    """sacct's MaxRSS (e.g. 281234K, 1.2G; '' when not measured) in MB (2^20 bytes)."""
    if not size:
        return 0.0
    scale = {"K": 2 ** -10, "M": 1.0, "G": 2 ** 10, "T": 2 ** 20}
    return float(size[:-1]) * scale[size[-1]] if size[-1] in scale else float(size) / 2 ** 20


def _slurm_rows(jobs: pd.DataFrame) -> list[dict]:
    """The main table's rows of the per-job table (`_on_slurm`)."""
    images = int(jobs["images"].sum())
    per_image = lambda column: float(column.sum()) / images  # noqa: E731
    note = "sum over the jobs / their images"
    per_node = jobs["node"].value_counts().sort_index()
    return [_row("slurm_jobs", len(jobs), "jobs", f"{images} images, 1 CPU each"),
            _row("slurm_nodes", len(per_node), "nodes",
                 "jobs per node: " + ", ".join(f"{node} {count}" for node, count in per_node.items())),
            _row("slurm_run_wall_s", float(jobs.attrs["wall_s"]), "s",
                 "the controlling snakemake: submission, queue, status checks (the profile's interval)"),
            _row("slurm_elapsed_per_job_s", float(jobs["elapsed_s"].mean()), "s", "sacct Elapsed, mean"),
            _row("slurm_per_image_s", per_image(jobs["work_s"]), "s", f"detection work; {note}; target: <= 0.25 s"),
            _row("slurm_overhead_per_image_s", per_image(jobs["elapsed_s"] - jobs["work_s"]), "s",
                 f"(elapsed - work); {note}; target: <= 0.1 s"),
            _row("slurm_job_snakemake_per_image_s", per_image(jobs["elapsed_s"] - jobs["shell_s"]), "s",
                 "(elapsed - the job's shell command): the job's own snakemake"),
            _row("slurm_job_dmais_start_per_image_s", per_image(jobs["shell_s"] - jobs["work_s"]), "s",
                 "(shell command - work): the dmais process besides its phases"),
            _row("slurm_max_rss_mb", float(jobs["max_rss_mb"].max()), "MB",
                 "largest over the jobs (sacct's steps, the rule's benchmark file)")]


# ------------------------------------------------------------------------------ what a job reads


#: `_job_reads`' jobs: a Python importing what `dmais <stage>` imports as `dmais` does (cli.main: the
#: collector paused), and that also reads what the job of one marker batch or flight group reads
#: (slices.batch_workspace, group_workspace: its slice where one is current, else the whole dataset),
#: does nothing else and ends as `dmais` ends (cli._end).
_JOB_START = ("from dmais_pipe import cli\nwith cli._collector_paused(freeze=True):\n"
              "    cli._imported({stage!r})\n")
_JOB_END = "cli._end(0)\n"
_JOB_READS = {  # logging as `dmais` logs, so that the log says whether the slice was read
    "markers": "import logging, sys\nlogging.basicConfig(level=logging.INFO)\n"
               "from dmais_pipe.slices import batch_workspace\n"
               "dataset, results, batch, per_job = sys.argv[1:]\n"
               "workspace = batch_workspace(dataset, results, batch, int(per_job))\n"
               "workspace.marker_batches(int(per_job))[batch], workspace.load_rig()\n",
    "pose": "import logging, sys\nlogging.basicConfig(level=logging.INFO)\n"
            "from dmais_pipe.slices import group_workspace\n"
            "workspace = group_workspace(*sys.argv[1:])\n"
            "workspace.load_observations(), workspace.load_rig()\n",
}


def _job_reads(root: Path, source: Path, demo: Path, out: Path, dataset: Path, results: Path, plan: dict,
               frames: int, frames_per_group: int, repeats: int = 3) -> list[dict]:
    """Rows of what a job costs besides its work when it reads the whole dataset and when it reads
    its slice (slices.py), side by side: every measurement `repeats` times, the two ways in turn,
    their medians. The whole dataset is read where the slices are moved aside.

    - the plan (`dmais plan`) with and without cutting the marker batches' slices;
    - a marker job: a Python importing the markers stage, and reading what the first flight batch's
      job reads (its batch, its images and frames, the rig);
    - a pose job, on the campaign whose flight observations are given (`given_flight_source`),
      collected into observations/flight.csv and cut (`dmais plan --slices pose`) as the workflow
      does: a Python importing the pose stage, and reading what the first group's job reads (its
      frames, images and observations, the rig); and that group's `dmais pose` with the first
      camera, whose files must be equal both ways."""
    rows = _plan_rows(root, dataset, results, str(MARKERS_PER_JOB), repeats)
    batch = next(iter(plan["batches"]["flight"]))
    reads = [str(dataset), str(results), batch, str(MARKERS_PER_JOB)]
    rows += _reads_rows(root, results, "markers", reads, f"batch {batch}'s job reads (its images, the rig)", repeats)
    return rows + _pose_job_rows(root, source, demo, out, results, plan, frames, frames_per_group, repeats)


def _reads_rows(root: Path, results: Path, stage: str, arguments: list[str], what: str, repeats: int) -> list[dict]:
    """Rows of a Python importing `stage`, and of one reading besides what a job reads (`_JOB_READS`
    with `arguments`) both ways: wall and CPU (user + system) seconds."""
    started = _JOB_START.format(stage=stage)
    start = _medians([_timed([sys.executable, "-c", started + _JOB_END], root) for _ in range(repeats)])
    reads = [sys.executable, "-c", started + _JOB_READS[stage] + _JOB_END, *arguments]
    ways = _both_ways(root, results, reads, repeats)
    rows = []
    for kind, k in (("", 0), ("_cpu", 1)):
        rows += [_row(f"{stage}_job_start{kind}_s", start[k], "s", f"a Python importing the {stage} stage"),
                 _row(f"{stage}_job_reads_whole{kind}_s", ways["whole"][k], "s",
                      f"that, reading what {what}: the whole dataset"),
                 _row(f"{stage}_job_reads_slice{kind}_s", ways["slice"][k], "s",
                      f"that, reading what {what}: its slice" + ("; target: <= 1 s" if not kind else ""))]
    return rows


def _plan_rows(root: Path, dataset: Path, results: Path, per_job: str, repeats: int) -> list[dict]:
    """Rows of `dmais plan` of the campaign without and with the marker batches' slices (medians)."""
    plan = [_tool("dmais"), "plan", str(dataset), "--per-job", per_job, "--json", str(results / "plan" / "bench.json")]
    seconds = {"": [], "slices": []}
    for _ in range(repeats):
        seconds[""].append(_run(plan, root, timeout=1800)[0])
        seconds["slices"].append(_run([*plan, "--out", str(results), "--slices", "markers"], root, timeout=1800)[0])
    (results / "plan" / "bench.json").unlink()
    batches = len(json.loads((results / "slices" / "markers.json").read_text())["slices"])
    return [_row("plan_s", _median(seconds[""]), "s", "`dmais plan`: the whole dataset loaded, its batches"),
            _row("plan_slices_s", _median(seconds["slices"]), "s",
                 f"`dmais plan --slices markers`: and the {batches} marker batches' slices cut (once per run)")]


def _pose_job_rows(root: Path, source: Path, demo: Path, out: Path, results: Path, plan: dict, frames: int,
                   frames_per_group: int, repeats: int) -> list[dict]:
    """The pose job's rows of `_job_reads`, on a campaign with given flight observations."""
    given = given_flight_source(source, demo, out.with_name(f"{out.name}_jobs_source"))
    dataset = campaign_dataset(given, out.with_name(f"{out.name}_jobs"), frames, frames_per_group)
    results = results / "pose_jobs"
    for name in ("rig.json", "observations/intrinsics.csv", "observations/extrinsics.csv"):
        copy_atomic(_needed(demo / name), results / name)
    dmais, group = _tool("dmais"), plan["groups"][0]
    _run([dmais, "markers", str(dataset), "--out", str(results), "--collect", "flight"], root, timeout=1800)
    cut, _ = _run([dmais, "plan", str(dataset), "--out", str(results), "--slices", "pose"], root, timeout=1800)
    with open(results / "observations" / "flight.csv") as handle:
        observations = sum(1 for _ in handle) - 1
    what = f"group {group}'s job reads (its images, its share of {observations} flight observations, the rig)"
    rows = _reads_rows(root, results, "pose", [str(dataset), str(results), group], what, repeats)
    cameras = ",".join(plan["cameras"][1:])  # the subset of the tilted cameras, whose solves are quick
    jobs = {way: [dmais, "pose", str(dataset), "--out", str(results), "--cameras", cameras, "--groups", group,
                  "--csv", str(results / way / f"{group}.csv")] for way in ("whole", "slice")}
    ways = _both_ways(root, results, jobs["whole"], 1, jobs["slice"])
    _check_equal_parts(results / "whole", results / "slice")
    return [_row("pose_slices_s", cut, "s", "`dmais plan --slices pose` (rule pose_slices): every group's slice "
                 "cut, once per run"), *rows,
            _row("pose_job_whole_s", ways["whole"][0], "s", f"`dmais pose --cameras {cameras} --groups {group}`, "
                 "the whole dataset read"),
            _row("pose_job_slice_s", ways["slice"][0], "s", "the same job reading its slice; its files equal but "
                 "time_ms")]


def _both_ways(root: Path, results: Path, command: list[str], repeats: int,
               sliced: list[str] | None = None) -> dict[str, tuple[float, float]]:
    """Median (wall, CPU) seconds (`_timed`) of `command` reading the whole dataset (RESULTS/slices moved
    aside) and of `sliced` (default: the same command) reading its slice, run in turn `repeats` times
    each: {"whole": ..., "slice": ...}."""
    seconds = {"whole": [], "slice": []}
    for _ in range(repeats):
        with _slices_aside(results):
            seconds["whole"].append(_timed(command, root, sliced=False))
        seconds["slice"].append(_timed(sliced or command, root, sliced=True))
    return {way: _medians(values) for way, values in seconds.items()}


def _timed(command: list[str], root: Path, sliced: bool | None = None) -> tuple[float, float]:
    """(wall, CPU: user + system) seconds of `command` (`_run`); with `sliced`, its log must say that
    it read its slice (True) or the whole dataset (False), slices.py's lines."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall, done = _run(command, root, timeout=3600)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if sliced is not None and (re.search(r"slices: (marker batch|flight group) ", done.stderr) is None) == sliced:
        raise DmaisError(f"campaign: `{' '.join(command)}` read " + ("the whole dataset, not its slice (cut for "
                         "other inputs?)" if sliced else "a slice where none was"))
    return wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


@contextmanager
def _slices_aside(results: Path):
    """RESULTS/slices renamed for the block, so that its jobs find no slice and read the whole dataset."""
    aside = results / ".slices-aside"
    os.replace(results / "slices", aside)
    try:
        yield
    finally:
        os.replace(aside, results / "slices")


def _check_equal_parts(whole: Path, sliced: Path) -> None:
    """The pose part files written reading the whole dataset and reading the slice are equal but for time_ms."""
    for path in sorted(whole.glob("*.csv")):
        a, b = (pd.read_csv(p, dtype=str, keep_default_na=False) for p in (path, sliced / path.name))
        if not a.drop(columns="time_ms", errors="ignore").equals(b.drop(columns="time_ms", errors="ignore")):
            raise DmaisError(f"campaign: {path.name} differs between the pose job reading the whole dataset and "
                             "reading its slice")


def _median(values: list[float]) -> float:
    return float(pd.Series(values).median())


def _medians(values: list[tuple[float, float]]) -> tuple[float, float]:
    """The median of each element of `values`' tuples."""
    return tuple(_median(list(column)) for column in zip(*values))
