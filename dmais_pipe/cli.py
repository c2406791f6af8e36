"""`dmais <stage> ...`: thin argument parsing over the stage functions.

User errors (DmaisError) and failures to read or write a file (OSError: permission, not a
directory, disk full, a file that vanished) are printed on one line to stderr and exit with status 2.

A command of the process's own command line (`main()`, a workflow job) imports its modules with the
garbage collector paused and ends without tearing its modules down (`_end`): a Python that loads
numpy, pandas and scipy spends ~0.2 CPU s collecting during those imports, which make no garbage, and
~0.2-0.5 s freeing them at exit.
"""

from __future__ import annotations

import argparse
import atexit
import functools
import gc
import importlib
import logging
import os
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from .errors import DmaisError, FileAccessError
from .plan import MARKERS_PER_JOB

log = logging.getLogger("dmais")


def _cmd_simulate(args) -> None:
    from .sim.simulate import simulate

    simulate(args.config, args.out, jobs=args.jobs)


def _cmd_validate(args) -> None:
    from .dataset import Dataset, keep_freed_image_memory

    dataset = Dataset.load(args.dataset)
    if not args.skip_images:
        keep_freed_image_memory()
        dataset.check_images()
    print(dataset.summary())


def _cmd_plan(args) -> None:
    import json

    from .dataset import Dataset
    from .files import write_json_atomic
    from .plan import workflow_plan

    if args.slices and args.out is None:
        raise DmaisError(f"plan: --slices {args.slices} needs --out RESULTS, the results folder they go to")
    if args.slices == "pose":  # once the observations are collected: no plan
        from .slices import write_group_slices
        from .workspace import Workspace

        write_group_slices(Workspace.open(args.dataset, args.out))
        return
    dataset = Dataset.load(args.dataset)
    plan = workflow_plan(dataset, args.per_job)
    if args.slices == "markers":  # before the plan file, whose presence tells the workflow all is written
        from .slices import write_marker_slices

        write_marker_slices(dataset, args.out, args.per_job)
    if args.json is None:
        print(json.dumps(plan, indent=1))
    else:
        write_json_atomic(args.json, plan)


def _cmd_summarize(args) -> None:
    from .report.dataset import summarize

    print(summarize(args.dataset, args.out))


def _workspace(args):
    from .workspace import Workspace

    return Workspace.open(args.dataset, args.out)


def _conf(args, module, *flags: tuple[str, object]):
    """The stage's named conf (--conf) with the options given as flags, then --set KEY=VALUE, applied."""
    from .stages import configure, settings_line

    overrides = [f"{key}={value}" for key, value in flags if value is not None] + list(args.set or [])
    conf = configure(module.CONFS, args.conf or next(iter(module.CONFS)), overrides, args.command)
    log.debug("%s settings: %s", args.command, settings_line(conf))
    return conf


def _print(paths) -> None:
    for path in paths:
        print(path)


def _cmd_intrinsics(args) -> None:
    from .stages import intrinsics

    conf = _conf(args, intrinsics, ("max_eps_calib_px", args.max_eps_px),
                 ("max_focal_deviation", args.max_focal_deviation))
    workspace = _workspace(args)
    if args.import_file:
        if not args.camera:
            raise DmaisError(f"intrinsics: --import {args.import_file} needs --camera NAME "
                             "(one per camera of the file)")
        _print(intrinsics.import_cameras(workspace, args.camera, args.import_file, conf))
        return
    if args.table:
        _print(intrinsics.write_table(workspace))
        return
    if args.camera:
        _print(intrinsics.run_cameras(workspace, args.camera, conf))
    else:
        _print(intrinsics.run(workspace, conf))


def _cmd_markers(args) -> None:
    from .dataset import keep_freed_image_memory
    from .stages import markers

    keep_freed_image_memory()  # this process reads its images one after another
    conf = _conf(args, markers)
    if args.batch:  # a workflow job: its slice of the dataset, where the plan cut one (slices.py)
        from .slices import batch_workspace

        _print(markers.run_batch(batch_workspace(args.dataset, args.out, args.batch, args.per_job), args.batch,
                                 args.per_job, conf))
        return
    workspace = _workspace(args)
    if args.collect:
        _print(markers.collect(workspace, args.collect))
    elif args.image:
        _print(markers.run_image(workspace, args.image, conf))
    else:
        _print(markers.run(workspace, conf))


def _cmd_bench_markers(args) -> None:
    import pandas as pd

    from .bench.markers import bench_markers, summary

    if args.suite != "dataset":
        from .bench.marker_suites import run_suite

        run_suite(args.suite, args.csv, seed=args.seed, images=args.images)
        return
    frame = bench_markers(args.dataset, args.csv, rig_path=args.rig)
    stage = frame["image"].str.split("_").str[0]
    table = {name: summary(group) for name, group in frame.groupby(stage)}
    table["all"] = summary(frame)
    print(pd.DataFrame(table).to_string(float_format=lambda x: f"{x:.4g}"))
    print(f"per-image CSV: {args.csv}")


def _cmd_extrinsics(args) -> None:
    from .stages import extrinsics

    conf = _conf(args, extrinsics, ("use_priors", False if args.no_priors else None), ("backend", args.backend))
    _print(extrinsics.run(_workspace(args), conf))


def _cmd_pose(args) -> None:
    from .stages import pose

    cameras = [c for c in args.cameras.split(",") if c] if args.cameras else None
    groups = [g for g in args.groups.split(",") if g] if args.groups else None
    conf = _conf(args, pose, ("robust", args.robust or None), ("refine", args.refine or None))
    if groups is not None and len(groups) == 1 and not args.merge:  # a workflow job: its group's slice (slices.py)
        from .slices import group_workspace

        workspace = group_workspace(args.dataset, args.out, groups[0])
    else:
        workspace = _workspace(args)
    if args.merge:
        _print(pose.merge(workspace, args.merge, cameras=cameras, out=args.csv))
        return
    _print(pose.run(workspace, conf, cameras=cameras, groups=groups, out=args.csv))


def _cmd_evaluate(args) -> None:
    from .stages import evaluate

    conf = _conf(args, evaluate)
    _print(evaluate.run(_workspace(args), conf))


def _cmd_export_colmap(args) -> None:
    from .stages import export

    conf = _conf(args, export, ("formats", args.format))
    _print(export.run(_workspace(args), conf))


def _cmd_export_geojson(args) -> None:
    from .stages import export

    _print(export.run_geojson(_workspace(args)))


def _cmd_report(args) -> None:
    from .stages import report

    conf = _conf(args, report)
    _print(report.run(_workspace(args), args.html, conf, benchmarks=args.benchmarks))


def _cmd_bench_pose(args) -> None:
    from .bench.pose import bench_pose

    if not args.whole_stage_only:
        bench_pose(args.csv, repeats=args.repeats, batch_frames=args.batch_frames, stage_frames=args.stage_frames)
    if args.whole_stage or args.whole_stage_only:
        from .bench.pose_stage import bench_whole_stage

        bench_whole_stage(args.csv.with_name(args.csv.stem + "_whole_stage.csv"), args.work)


def _cmd_bench_pose_hard(args) -> None:
    from .bench.pose_hard import bench_pose_hard

    bench_pose_hard(args.csv, cases=args.cases, seed=args.seed, kinds=args.kinds.split(",") if args.kinds else None)


def _cmd_bench_campaign(args) -> None:
    from .bench.campaign import bench_campaign

    bench_campaign(args.source, args.out, args.csv, frames=args.frames, frames_per_group=args.frames_per_group,
                   slurm=args.slurm, slurm_batches=args.slurm_batches, stages=args.stages,
                   slurm_lose=args.slurm_lose, slurm_restore=args.slurm_restore)


def _cmd_bench_periodic(args) -> None:
    from .bench.periodic import bench_periodic, print_tables

    images, calibration = bench_periodic(args.photos, args.csv, seed=args.seed, work=args.work, model=args.model)
    print_tables(images, calibration, args.csv)


def _cmd_bench_stereo(args) -> None:
    from .bench.stereo import bench_stereo, print_table

    print_table(bench_stereo(args.photos, args.csv, model=args.model, work=args.work))
    print(f"wrote {args.csv}")


def _cmd_bench_sigma(args) -> None:
    from .bench.sigma import bench_sigma, print_table, simulation_grid

    simulations = simulation_grid(args.seeds, args.vibration, args.survey, pixel_px=args.pixel,
                                  mount_arcmin=args.mount, groups=args.groups, frames_per_group=args.frames_per_group,
                                  calib_images=args.calib_images, truth_rig=args.truth_rig,
                                  patterns=args.pattern, field_survey_m=args.field_survey,
                                  sigma_given=not args.survey_not_given) if args.simulate else []
    print_table(bench_sigma(args.csv, args.results or [], simulations, work=args.work), args.csv)


def _cmd_bench_mounting(args) -> None:
    from .bench.mounting import bench_mounting, print_table, simulations

    chosen = simulations(args.seeds, args.mount, args.vibration, args.survey, args.pixel, groups=args.groups,
                         frames_per_group=args.frames_per_group, calibrated=args.calibrated, patterns=args.pattern)
    print_table(bench_mounting(args.csv, chosen, pos=args.pos, work=args.work), args.csv)


def _cmd_bench_geodetic(args) -> None:
    from .bench.geodetic import bench_geodetic, print_table

    print_table(bench_geodetic(args.csv, args.preset, work=args.work), args.csv)


def _flight_patterns(text: str) -> list[str]:
    """An argparse type: comma-separated flight patterns of the simulator (sim.config.FLIGHT_PATTERNS)."""
    from .sim.config import FLIGHT_PATTERNS

    patterns = [part.strip() for part in text.split(",") if part.strip()]
    if not patterns or any(pattern not in FLIGHT_PATTERNS for pattern in patterns):
        raise argparse.ArgumentTypeError(f"{text!r}: expected flight patterns among {', '.join(FLIGHT_PATTERNS)}, "
                                         "comma-separated")
    return patterns


def _add_pattern_argument(parser: argparse.ArgumentParser) -> None:
    """--pattern, the simulated flights' patterns, of the benches that simulate (sigma, mounting)."""
    parser.add_argument("--pattern", type=_flight_patterns, default=["hover"],
                        help="the simulator's flight.pattern, comma-separated: hover (every frame over the same "
                             "markers), line (frames along a line, new markers each frame) (default: hover)")


def _comma_separated(kind):
    """An argparse type: 'a,b,c' -> [kind(a), kind(b), kind(c)]."""
    def parse(text: str) -> list:
        try:
            return [kind(part) for part in text.split(",") if part.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of {kind.__name__}s") from None
    return parse


def _parser() -> argparse.ArgumentParser:
    from .camera import MODELS

    parser = argparse.ArgumentParser(prog="dmais", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action=_VersionAction, nargs=0, help="print the installed version and exit")
    commands = parser.add_subparsers(dest="command", required=True)

    simulate = commands.add_parser("simulate", help="write a synthetic DMAIS dataset with ground truth")
    simulate.add_argument("config", type=Path, help="simulator YAML, e.g. config/simulate/demo.yaml")
    simulate.add_argument("--out", type=Path, required=True, help="dataset directory to create")
    simulate.add_argument("--jobs", type=int, default=1, help="processes rendering images in parallel (default: %(default)s)")
    simulate.set_defaults(run=_cmd_simulate)

    validate = commands.add_parser("validate", help="check a dataset directory and print a summary")
    validate.add_argument("dataset", type=Path)
    validate.add_argument("--skip-images", action="store_true", help="do not decode the image files")
    validate.set_defaults(run=_cmd_validate)

    plan = commands.add_parser("plan", help="what the workflow needs to know of a dataset, as JSON")
    plan.add_argument("dataset", type=Path)
    plan.add_argument("--per-job", type=_positive_int, default=MARKERS_PER_JOB,
                      help="images per marker batch (default: %(default)s)")
    plan.add_argument("--json", type=Path, help="write the plan to this file (atomically) instead of printing it")
    plan.add_argument("--out", type=Path, help="results folder of the --slices")
    plan.add_argument("--slices", choices=("markers", "pose"),
                      help="also cut what each marker batch's job reads (markers), or, without a plan, once "
                           "the observations are collected, each flight group's (pose) into RESULTS/slices/")
    plan.set_defaults(run=_cmd_plan)

    markers = commands.add_parser("markers", help="detect, refine and identify the markers of every image")
    markers.add_argument("dataset", type=Path)
    markers.add_argument("--out", type=Path, required=True, help="results folder")
    one = markers.add_mutually_exclusive_group()
    one.add_argument("--image", help="only this image -> RESULTS/markers/<image>.csv")
    one.add_argument("--batch", help="only this batch of images (a workflow job; `dmais plan` lists them) -> "
                                     "their markers files and RESULTS/markers/batches/<batch>.csv")
    one.add_argument("--collect", choices=("intrinsics", "extrinsics", "flight"),
                     help="only gather the stage's marker files -> RESULTS/observations/<stage>.csv")
    markers.add_argument("--per-job", type=_positive_int, default=MARKERS_PER_JOB,
                         help="images per batch, as the plan was made with (default: %(default)s)")
    markers.set_defaults(run=_cmd_markers)

    intrinsics = commands.add_parser("intrinsics", help="calibrate every camera's intrinsics from the field")
    intrinsics.add_argument("dataset", type=Path)
    intrinsics.add_argument("--out", type=Path, required=True, help="results folder")
    only = intrinsics.add_mutually_exclusive_group()
    only.add_argument("--camera", action="append", help="calibrate only this camera (repeatable); no table")
    only.add_argument("--table", action="store_true",
                      help="only write tables/intrinsics.csv from the cameras' intrinsics/<camera>.methods.csv")
    intrinsics.add_argument("--import", dest="import_file", type=Path, metavar="FILE",
                            help="take the --camera's intrinsics from an OpenCV calibration file (YAML/XML/JSON; "
                                 "FILE:M2 for the pair M2, D2 of a stereo calibration) or a COLMAP cameras.txt / "
                                 "cameras.bin instead of calibrating")
    # {conf.NAME}: the stage's default setting, filled in when the help is shown (`_stage_help`)
    intrinsics.add_argument("--max-eps-px", type=float,
                            help="refuse a calibration whose eps_calib exceeds this (px; default {conf.max_eps_calib_px})")
    intrinsics.add_argument("--max-focal-deviation", type=float,
                            help="refuse fx, fy further than this fraction from focal_px or from each other "
                                 "(default {conf.max_focal_deviation})")
    intrinsics.set_defaults(run=_cmd_intrinsics)

    extrinsics = commands.add_parser("extrinsics", help="calibrate the rig (cam_from_rig) from the placements")
    extrinsics.add_argument("dataset", type=Path)
    extrinsics.add_argument("--out", type=Path, required=True, help="results folder (with intrinsics/)")
    extrinsics.add_argument("--no-priors", action="store_true", help="write rig.json from the run without RTK priors")
    extrinsics.add_argument("--backend", choices=("pycolmap", "scipy"),
                            help="rig bundle adjuster (both reach the same optimum; default: pycolmap)")
    extrinsics.set_defaults(run=_cmd_extrinsics)

    pose = commands.add_parser("pose", help="estimate the rig pose of every flight frame")
    pose.add_argument("dataset", type=Path)
    pose.add_argument("--out", type=Path, required=True, help="results folder (with rig.json)")
    pose.add_argument("--cameras", help="comma-separated camera subset, e.g. C0,C1,C2 (default: all)")
    pose.add_argument("--groups", help="comma-separated frame groups to solve (default: all)")
    pose.add_argument("--robust", action="store_true", help="RANSAC against wrong correspondences first")
    pose.add_argument("--refine", action="store_true", help="polish on the reprojection error")
    pose.add_argument("--csv", type=Path, help="output CSV (default: RESULTS/poses.csv or poses_<label>.csv)")
    pose.add_argument("--merge", type=Path, nargs="+", metavar="PART",
                      help="only concatenate per-group pose files of --cameras into the output CSV")
    pose.set_defaults(run=_cmd_pose)

    evaluate = commands.add_parser("evaluate", help="pose errors against the POS reference (and truth), tables")
    evaluate.add_argument("dataset", type=Path)
    evaluate.add_argument("--out", type=Path, required=True, help="results folder (with poses.csv)")
    evaluate.set_defaults(run=_cmd_evaluate)

    export = commands.add_parser("export-colmap", help="the rig and the solved flight frames as a COLMAP model")
    export.add_argument("dataset", type=Path)
    export.add_argument("--out", type=Path, required=True, help="results folder (with rig.json and poses.csv)")
    export.add_argument("--format", choices=("text", "binary"), help="only this format (default: both)")
    export.set_defaults(run=_cmd_export_colmap)

    geojson = commands.add_parser("export-geojson", help="the solved frames (points) and the cameras' ground "
                                                         "footprints (polygons) as WGS 84 GeoJSON; needs a crs")
    geojson.add_argument("dataset", type=Path)
    geojson.add_argument("--out", type=Path, required=True, help="results folder (with rig.json and poses.csv)")
    geojson.set_defaults(run=_cmd_export_geojson)

    report = commands.add_parser("report", help="write the self-contained HTML report")
    report.add_argument("dataset", type=Path)
    report.add_argument("--out", type=Path, required=True, help="results folder")
    report.add_argument("--html", type=Path, required=True, help="report file, e.g. reports/demo/report.html")
    report.add_argument("--benchmarks", type=Path, help="folder of snakemake benchmark files (stage times)")
    report.set_defaults(run=_cmd_report)
    for stage, module in ((markers, "markers"), (intrinsics, "intrinsics"), (extrinsics, "extrinsics"), (pose, "pose"),
                          (evaluate, "evaluate"), (export, "export"), (report, "report")):
        _add_settings(stage, module)

    summarize = commands.add_parser("summarize", help="write a dataset summary (CSV + HTML) to a report folder")
    summarize.add_argument("dataset", type=Path)
    summarize.add_argument("--out", type=Path, required=True, help="report folder, e.g. reports/demo")
    summarize.set_defaults(run=_cmd_summarize)
    bench = commands.add_parser("bench", help="benchmarks: print a table and write CSV")
    benches = bench.add_subparsers(dest="bench", required=True)
    bench_markers = benches.add_parser("markers", help="marker extraction on a rendered dataset with truth")
    bench_markers.add_argument("dataset", type=Path, nargs="?", default=Path("results/demo/dataset"),
                               help="a rendered dataset with truth (default: the demo, as `make run` simulates it)")
    bench_markers.add_argument("--rig", type=Path, help="rig.json used to identify flight markers (e.g. truth/rig.json)")
    bench_markers.add_argument("--csv", type=Path, default=Path("reports/bench/markers.csv"),
                               help="output table (default: %(default)s)")
    bench_markers.add_argument("--suite", choices=["dataset", "regimes", "effects", "photos", "texture", "all"],
                               default="dataset",
                               help="dataset: the rendered dataset; regimes / effects / photos / texture: the refinement "
                                    "grid, the aerial-effects grid, the real chessboard photographs, false detections "
                                    "on textured ground (CSV beside --csv)")
    bench_markers.add_argument("--seed", type=int, default=0, help="seed of the synthetic suites (default: %(default)s)")
    bench_markers.add_argument("--images", type=int, help="images per cell (regimes: 4, texture: 2) or per effect (effects: 10)")
    bench_markers.set_defaults(run=_cmd_bench_markers)
    bench_pose = benches.add_parser(
        "pose", help="pose solver time vs points (tab:time_points), batch and pose-stage throughput")
    bench_pose.add_argument("--csv", type=Path, default=Path("reports/bench/pose_time_points.csv"),
                            help="output table (default: %(default)s)")
    bench_pose.add_argument("--repeats", type=int, default=200, help="solves per point count and method (default: %(default)s)")
    bench_pose.add_argument("--batch-frames", type=int, default=200, help="frames in the batch-throughput run (default: %(default)s)")
    bench_pose.add_argument("--stage-frames", type=int, default=10_000,
                            help="frames of the generated flight in the pose-stage throughput run (0: skip it; "
                                 "default: %(default)s)")
    bench_pose.add_argument("--whole-stage", action="store_true",
                            help="also time the whole dmais pose stage (error model and watched rig included) on "
                                 "generated flights of up to 10,000 frames per group, against a dense reference "
                                 "(bench/pose_stage.py; several minutes)")
    bench_pose.add_argument("--whole-stage-only", action="store_true", help="only the --whole-stage rows")
    bench_pose.add_argument("--work", type=Path, default=Path("results/bench/pose_stage"),
                            help="work folder of --whole-stage (default: %(default)s)")
    bench_pose.set_defaults(run=_cmd_bench_pose)
    pose_hard = benches.add_parser(
        "pose-hard", help="pose solver on hard narrow-field scenes against a multi-start reference, with and "
                          "without its global fallback")
    pose_hard.add_argument("--csv", type=Path, default=Path("reports/bench/pose_hard.csv"),
                           help="output table, the per-case rows beside it (default: %(default)s)")
    pose_hard.add_argument("--cases", type=_positive_int, default=400, help="scenes per kind (default: %(default)s)")
    pose_hard.add_argument("--seed", type=int, default=2031,
                           help="seed of the scenes (default: %(default)s; the fallback was tuned on others)")
    pose_hard.add_argument("--kinds", help="comma-separated kinds (default: all of bench.pose_hard.KINDS)")
    pose_hard.set_defaults(run=_cmd_bench_pose_hard)
    campaign = benches.add_parser("campaign", help="the workflow at flight-campaign scale: dry runs, one core, SLURM")
    campaign.add_argument("--source", type=Path, default=Path("results/demo/dataset"),
                          help="simulated dataset whose flight is repeated, with its run's results beside it "
                               "(default: the demo's, as `make run` makes it)")
    campaign.add_argument("--out", type=Path, default=Path("data/campaign"), help="campaign dataset to write "
                          "(default: %(default)s)")
    campaign.add_argument("--frames", type=_positive_int, default=10_000, help="flight frames (default: %(default)s)")
    campaign.add_argument("--frames-per-group", type=_positive_int, default=500,
                          help="frames per flight group (default: %(default)s)")
    campaign.add_argument("--slurm", action="store_true", help="also run flight batches through the SLURM profile")
    campaign.add_argument("--slurm-batches", type=_positive_int, default=4,
                          help="flight batches run on SLURM (default: %(default)s)")
    campaign.add_argument("--slurm-lose", metavar="COMMAND",
                          help="with --slurm, run the batches again and, once their jobs run on every node, lose "
                               "one: this shell command, {node} the node (the test cluster's: 'bash "
                               "tests/cluster/slurm_up.sh kill {node}'); its wall time against the clean run's")
    campaign.add_argument("--slurm-restore", metavar="COMMAND", default="true",
                          help="shell command that brings the lost node back after that run (the test cluster's: "
                               "'bash tests/cluster/slurm_up.sh')")
    campaign.add_argument("--stages", action="store_true",
                          help="also run every stage locally on the campaign with its flight observations given "
                               "(per-rule time and memory)")
    campaign.add_argument("--csv", type=Path, default=Path("reports/bench/campaign.csv"),
                          help="output table (default: %(default)s)")
    campaign.set_defaults(run=_cmd_bench_campaign)
    periodic = benches.add_parser("periodic", help="identification on a periodic target: real chessboard "
                                                   "photographs with loose priors, ids and intrinsics against OpenCV")
    periodic.add_argument("--photos", type=Path, help="folder of OpenCV's chessboard photographs (leftNN.jpg, "
                                                      "rightNN.jpg; default: tests/data/chessboard)")
    periodic.add_argument("--seed", type=int, default=0, help="seed of the priors' perturbation (default: %(default)s)")
    periodic.add_argument("--work", type=Path, help="folder for the dataset and results (default: a temporary one)")
    periodic.add_argument("--model", choices=MODELS, default="radial1",
                          help="the cameras' lens model, ours and OpenCV's (default: %(default)s)")
    periodic.add_argument("--csv", type=Path, default=Path("reports/bench/periodic.csv"),
                          help="per-image table; the intrinsics beside it, <stem>_intrinsics.csv (default: %(default)s)")
    periodic.set_defaults(run=_cmd_bench_periodic)
    stereo = benches.add_parser("stereo", help="a real stereo pair through intrinsics, extrinsics and pose against "
                                               "OpenCV's calibrateCamera, stereoCalibrate and solvePnP")
    stereo.add_argument("--photos", type=Path, help="folder of OpenCV's stereo chessboard photographs (leftNN.jpg, "
                                                    "rightNN.jpg; default: tests/data/chessboard)")
    stereo.add_argument("--model", choices=MODELS, default="opencv",
                        help="the cameras' lens model, ours and OpenCV's (default: %(default)s)")
    stereo.add_argument("--work", type=Path, help="folder for the dataset and results (default: a temporary one)")
    stereo.add_argument("--csv", type=Path, default=Path("reports/bench/stereo.csv"),
                        help="output table (default: %(default)s)")
    stereo.set_defaults(run=_cmd_bench_stereo)
    sigma = benches.add_parser("sigma", help="poses.csv's 1-sigma columns against the simulator's truth: "
                                             "RMS(error / sigma) and coverage per camera set and axis")
    sigma.add_argument("--results", type=Path, nargs="+", metavar="DIR",
                       help="results folders of workflow runs on simulated datasets (DIR/dataset), e.g. results/demo")
    sigma.add_argument("--simulate", action="store_true",
                       help="simulate observation-only flights (every vibration x survey x seed) and run the chain")
    sigma.add_argument("--seeds", type=_comma_separated(int), default=[1001, 1002, 1003],
                       help="simulation seeds, comma-separated (default: 1001,1002,1003)")
    sigma.add_argument("--vibration", type=_comma_separated(float), default=[0.0, 0.3, 1.0],
                       help="per-frame camera vibration, arc-min (default: 0,0.3,1)")
    sigma.add_argument("--survey", type=_comma_separated(float), default=[0.01, 0.02, 0.03],
                       help="ground-point survey sigma per axis, m (default: 0.01,0.02,0.03)")
    sigma.add_argument("--pixel", type=float, default=0.25, help="flight marker noise, px (default: %(default)s)")
    sigma.add_argument("--mount", type=float, default=0.15,
                       help="per-group mounting change of C1..C4, arc-min (default: %(default)s)")
    sigma.add_argument("--groups", type=_positive_int, default=6, help="flight groups (default: %(default)s)")
    sigma.add_argument("--frames-per-group", type=_positive_int, default=10, help="(default: %(default)s)")
    sigma.add_argument("--calib-images", type=_positive_int, default=6,
                       help="calibration images per camera (default: %(default)s, the demo's)")
    sigma.add_argument("--truth-rig", action="store_true", help="solve with the simulator's rig, no calibration")
    sigma.add_argument("--field-survey", type=float,
                       help="the calibration field's survey sigma per axis, m (default: the simulator's)")
    sigma.add_argument("--survey-not-given", action="store_true",
                       help="leave the points' survey sigmas (sigma_m) out of the datasets: the calibration and "
                            "the flight estimate them")
    _add_pattern_argument(sigma)
    sigma.add_argument("--work", type=Path, help="keep each simulation in WORK/<name> (default: a temporary folder)")
    sigma.add_argument("--csv", type=Path, default=Path("reports/bench/sigma.csv"),
                       help="output table, the per-frame rows beside it (default: %(default)s)")
    sigma.set_defaults(run=_cmd_bench_sigma)
    mounting = benches.add_parser("mounting", help="the in-flight mounting of each camera per flight group "
                                                   "(pose.mounting) against the simulator's truth")
    mounting.add_argument("--seeds", type=_comma_separated(int), default=[1001, 1002, 1003],
                          help="simulation seeds, comma-separated (default: 1001,1002,1003)")
    mounting.add_argument("--mount", type=_comma_separated(float), default=[0.0, 2.0],
                          help="per-group mounting change of C1..C4 per axis, arc-min, comma-separated "
                               "(default: 0,2)")
    mounting.add_argument("--vibration", type=float, default=0.3,
                          help="per-frame vibration, arc-min (default: %(default)s)")
    mounting.add_argument("--survey", type=float, default=0.025,
                          help="ground-point survey sigma per axis, m (default: %(default)s)")
    mounting.add_argument("--pixel", type=float, default=0.5, help="flight marker noise, px (default: %(default)s)")
    mounting.add_argument("--groups", type=_positive_int, default=4, help="flight groups (default: %(default)s)")
    mounting.add_argument("--frames-per-group", type=_positive_int, default=30, help="(default: %(default)s)")
    _add_pattern_argument(mounting)
    mounting.add_argument("--calibrated", action="store_true",
                          help="solve with the chain's calibrated rig (intrinsics, extrinsics), not the simulator's")
    mounting.add_argument("--pos", action="store_true",
                          help="also adjust with a prior on the rig centres from the POS (variant survey+pos)")
    mounting.add_argument("--work", type=Path, help="keep each simulation in WORK/<name> (default: a temporary folder)")
    mounting.add_argument("--csv", type=Path, default=Path("reports/bench/mounting.csv"),
                          help="output table, the per-camera and per-frame rows beside it (default: %(default)s)")
    mounting.set_defaults(run=_cmd_bench_mounting)
    geodetic = benches.add_parser("geodetic", help="the same observations solved in a CRS (survey in UTM, POS in "
                                                   "WGS 84) and in a local ENU frame, against the simulator's truth")
    geodetic.add_argument("--preset", type=Path, default=Path("config/simulate/geodetic.yaml"),
                          help="simulator preset with geodetic settings (default: %(default)s)")
    geodetic.add_argument("--work", type=Path, help="keep each run in WORK/<run> (default: a temporary folder)")
    geodetic.add_argument("--csv", type=Path, default=Path("reports/bench/geodetic.csv"),
                          help="output table (default: %(default)s)")
    geodetic.set_defaults(run=_cmd_bench_geodetic)
    return parser


def _add_settings(parser: argparse.ArgumentParser, stage: str) -> None:
    """--conf and --set, with every setting, its default and the named confs listed under --help
    (`_stage_help`: the stage is loaded only for its help, so other commands start without it, and
    an option's help may name a default setting as {conf.NAME})."""
    conf = parser.add_argument("--conf", metavar="NAME")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="change one setting of the conf (repeatable); the settings are listed below")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.format_help = functools.partial(_stage_help, parser, conf, stage)


def _stage_help(parser: argparse.ArgumentParser, conf: argparse.Action, stage: str) -> str:
    """The --help text of a stage's command, with its named confs and settings (`settings_help`)."""
    from importlib import import_module

    from .stages import settings_help

    module = import_module(f"dmais_pipe.stages.{stage}")
    confs = module.CONFS
    conf.help = f"named settings of the stage: {', '.join(confs)} (default: {next(iter(confs))})"
    for action in parser._actions:  # argparse keeps no other list of a parser's options
        if action.help and "{conf." in action.help:
            action.help = action.help.format(conf=module.Conf())
    parser.epilog = settings_help(confs) + "\n\nSee docs/design.md, 'Stage settings'."
    return argparse.ArgumentParser.format_help(parser)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    return value


class _VersionAction(argparse.Action):
    """--version: the installed version looked up only when asked (importlib.metadata costs a job ~0.1 s)."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog} {_version()}")
        parser.exit()


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("dmais_pipe")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


#: The modules of a command besides cli, imported with the collector paused (`_imported`); a command
#: missing here imports its own as it runs, only slower.
_MODULES = {"plan": ("dataset", "plan", "slices"), "markers": ("stages.markers", "slices"),
            "intrinsics": ("stages.intrinsics",), "extrinsics": ("stages.extrinsics",),
            "pose": ("stages.pose", "slices"), "evaluate": ("stages.evaluate",), "export-colmap": ("stages.export",),
            "report": ("stages.report",), "validate": ("dataset",)}


def main(argv: list[str] | None = None) -> int:
    """Run `dmais ARGV...` (default: the process's command line, which then ends with the command:
    `_end`) and return its exit status: 0, or 2 after a one-line error."""
    own = argv is None
    with _collector_paused(freeze=own):
        try:
            args = _parser().parse_args(argv)  # a stage's --help loads the stage (and the pose solver's cores)
        except DmaisError as error:
            print(f"dmais: error: {error}", file=sys.stderr)
            return _end(2) if own else 2
        try:
            _imported(args.command)
        except DmaisError as error:  # a stage's compiled cores built for another CPU (build_cpu.py)
            print(f"dmais {args.command}: error: {error}", file=sys.stderr)
            return _end(2) if own else 2
    status = _run(args)
    return _end(status) if own else status


def _run(args) -> int:
    """The status of the parsed command `args` run: 0, or 2 after printing its error on one line."""
    from .files import read_only

    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    dataset = getattr(args, "dataset", None)  # a command's dataset is only read, whatever it writes
    try:
        with read_only(dataset):
            args.run(args)
    except OSError as error:  # reading or writing a file the user named, or the disk, failed
        error = FileAccessError.of(error)
        print(f"dmais {args.command}: error: {error}", file=sys.stderr)
        return 2
    except DmaisError as error:
        print(f"dmais {args.command}: error: {error}", file=sys.stderr)
        return 2
    return 0


@contextmanager
def _collector_paused(freeze: bool):
    """No garbage collection within the block (imports allocate much and free little); with `freeze`,
    what the block made is then left out of every later collection (gc.freeze)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.freeze()
        if was_enabled:
            gc.enable()


def _imported(command: str) -> None:
    """Import the modules `command` runs with (_MODULES)."""
    for name in _MODULES.get(command, ()):
        importlib.import_module(f"{__package__}.{name}")


def _end(status: int) -> int:
    """End the process with `status` as sys.exit would (atexit handlers, logging flushed, the
    streams flushed), but without freeing its modules one by one. Where a thread other than the
    main one still runs, return `status` for the normal exit, which waits for it."""
    if threading.active_count() > 1:
        return status
    atexit._run_exitfuncs()  # logging.shutdown, concurrent.futures, multiprocessing, weakref.finalize
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: what the normal exit would print is lost
            status = status or 120
    os._exit(status)


if __name__ == "__main__":
    sys.exit(main())
