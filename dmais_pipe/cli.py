"""`dmais <stage> ...`: thin argument parsing over the stage functions.

User errors (DmaisError) and failures to read or write a file (OSError: permission, not a
directory, disk full, a file that vanished) are printed on one line to stderr and exit with status 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .errors import DmaisError, FileAccessError
from .files import read_only

log = logging.getLogger("dmais")


def _cmd_simulate(args) -> None:
    from .sim.simulate import simulate

    simulate(args.config, args.out, jobs=args.jobs)


def _cmd_validate(args) -> None:
    from .dataset import Dataset

    dataset = Dataset.load(args.dataset)
    if not args.skip_images:
        dataset.check_images()
    print(dataset.summary())


def _cmd_plan(args) -> None:
    import json

    from .dataset import Dataset
    from .plan import workflow_plan

    print(json.dumps(workflow_plan(Dataset.load(args.dataset)), indent=1))


def _cmd_summarize(args) -> None:
    from .report.dataset import summarize

    print(summarize(args.dataset, args.out))


def _cmd_intrinsics(args) -> None:
    from .calib.intrinsics import Plausibility, run_intrinsics, write_intrinsics_table

    if args.table:
        print(write_intrinsics_table(args.dataset, args.out))
        return
    limits = Plausibility(max_eps_calib_px=args.max_eps_px, max_focal_deviation=args.max_focal_deviation)
    for path in run_intrinsics(args.dataset, args.out, cameras=args.camera, limits=limits):
        print(path)


def _cmd_markers(args) -> None:
    from .markers.stage import collect_observations, run_markers, run_markers_image

    if args.image:
        print(run_markers_image(args.dataset, args.out, args.image))
    elif args.collect:
        print(collect_observations(args.dataset, args.out, args.collect))
    else:
        print(run_markers(args.dataset, args.out, jobs=args.jobs))


def _cmd_bench_markers(args) -> None:
    import pandas as pd

    from .markers.bench import bench_markers, summary

    if args.suite != "dataset":
        from .markers.bench_suites import run_suite

        run_suite(args.suite, args.csv, seed=args.seed, images=args.images)
        return
    frame = bench_markers(args.dataset, args.csv, rig_path=args.rig)
    stage = frame["image"].str.split("_").str[0]
    table = {name: summary(group) for name, group in frame.groupby(stage)}
    table["all"] = summary(frame)
    print(pd.DataFrame(table).to_string(float_format=lambda x: f"{x:.4g}"))
    print(f"per-image CSV: {args.csv}")


def _cmd_extrinsics(args) -> None:
    from .calib.extrinsics import run_extrinsics

    for path in run_extrinsics(args.dataset, args.out, use_priors=not args.no_priors, backend=args.backend):
        print(path)


def _cmd_pose(args) -> None:
    from .pose.stage import merge_poses, run_pose

    cameras = [c for c in args.cameras.split(",") if c] if args.cameras else None
    groups = [g for g in args.groups.split(",") if g] if args.groups else None
    if args.merge:
        print(merge_poses(args.dataset, args.out, args.merge, cameras=cameras, out=args.csv))
        return
    print(run_pose(args.dataset, args.out, cameras=cameras, robust=args.robust, refine=args.refine,
                   groups=groups, out=args.csv))


def _cmd_evaluate(args) -> None:
    from .evaluate import run_evaluate

    for path in run_evaluate(args.dataset, args.out):
        print(path)


def _cmd_report(args) -> None:
    from .files import copy_atomic
    from .report.html import write_report
    from .report.paper import write_paper_comparisons

    write_paper_comparisons(args.out, args.out / "tables")
    print(write_report(args.dataset, args.out, args.html, benchmarks_dir=args.benchmarks))
    for table in sorted((args.out / "tables").glob("*.csv")):  # the CSV tables beside the HTML
        print(copy_atomic(table, args.html.parent / "tables" / table.name))


def _cmd_bench_pose(args) -> None:
    from .pose.bench import bench_pose

    bench_pose(args.csv, repeats=args.repeats, batch_frames=args.batch_frames)


def _parser() -> argparse.ArgumentParser:
    from .calib.intrinsics import Plausibility

    parser = argparse.ArgumentParser(prog="dmais", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    commands = parser.add_subparsers(dest="command", required=True)

    simulate = commands.add_parser("simulate", help="write a synthetic DMAIS dataset with ground truth")
    simulate.add_argument("config", type=Path, help="simulator YAML, e.g. config/simulate/demo.yaml")
    simulate.add_argument("--out", type=Path, required=True, help="dataset directory to create")
    simulate.add_argument("--jobs", type=int, default=1, help="processes rendering images in parallel")
    simulate.set_defaults(run=_cmd_simulate)

    validate = commands.add_parser("validate", help="check a dataset directory and print a summary")
    validate.add_argument("dataset", type=Path)
    validate.add_argument("--skip-images", action="store_true", help="do not decode the image files")
    validate.set_defaults(run=_cmd_validate)

    plan = commands.add_parser("plan", help="what the workflow needs to know of a dataset, as JSON")
    plan.add_argument("dataset", type=Path)
    plan.set_defaults(run=_cmd_plan)

    markers = commands.add_parser("markers", help="detect, refine and identify the markers of every image")
    markers.add_argument("dataset", type=Path)
    markers.add_argument("--out", type=Path, required=True, help="results folder")
    markers.add_argument("--jobs", type=int, default=1, help="images processed in parallel")
    one = markers.add_mutually_exclusive_group()
    one.add_argument("--image", help="only this image -> RESULTS/markers/<image>.csv (one workflow job)")
    one.add_argument("--collect", choices=("intrinsics", "extrinsics", "flight"),
                     help="only gather the stage's marker files -> RESULTS/observations/<stage>.csv")
    markers.set_defaults(run=_cmd_markers)

    intrinsics = commands.add_parser("intrinsics", help="calibrate every camera's intrinsics from the field")
    intrinsics.add_argument("dataset", type=Path)
    intrinsics.add_argument("--out", type=Path, required=True, help="results folder")
    only = intrinsics.add_mutually_exclusive_group()
    only.add_argument("--camera", action="append", help="calibrate only this camera (repeatable); no table")
    only.add_argument("--table", action="store_true",
                      help="only write tables/intrinsics.csv from the cameras' intrinsics/<camera>.methods.csv")
    defaults = Plausibility()
    intrinsics.add_argument("--max-eps-px", type=float, default=defaults.max_eps_calib_px,
                            help="refuse a calibration whose eps_calib exceeds this (px; default %(default)s)")
    intrinsics.add_argument("--max-focal-deviation", type=float, default=defaults.max_focal_deviation,
                            help="refuse fx, fy further than this fraction from focal_px or from each other "
                                 "(default %(default)s)")
    intrinsics.set_defaults(run=_cmd_intrinsics)

    extrinsics = commands.add_parser("extrinsics", help="calibrate the rig (cam_from_rig) from the placements")
    extrinsics.add_argument("dataset", type=Path)
    extrinsics.add_argument("--out", type=Path, required=True, help="results folder (with intrinsics/)")
    extrinsics.add_argument("--no-priors", action="store_true", help="write rig.json from the run without RTK priors")
    extrinsics.add_argument("--backend", choices=("pycolmap", "scipy"), default="pycolmap",
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

    report = commands.add_parser("report", help="write the self-contained HTML report")
    report.add_argument("dataset", type=Path)
    report.add_argument("--out", type=Path, required=True, help="results folder")
    report.add_argument("--html", type=Path, required=True, help="report file, e.g. reports/demo/report.html")
    report.add_argument("--benchmarks", type=Path, help="folder of snakemake benchmark files (stage times)")
    report.set_defaults(run=_cmd_report)

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
    bench_markers.add_argument("--csv", type=Path, default=Path("reports/bench/markers.csv"))
    bench_markers.add_argument("--suite", choices=["dataset", "regimes", "effects", "photos", "all"], default="dataset",
                               help="dataset: the rendered dataset; regimes / effects / photos: the refinement grid, "
                                    "the aerial-effects grid, the real chessboard photographs (CSV beside --csv)")
    bench_markers.add_argument("--seed", type=int, default=0, help="seed of the synthetic suites")
    bench_markers.add_argument("--images", type=int, help="images per cell (regimes: 4) or per effect (effects: 10)")
    bench_markers.set_defaults(run=_cmd_bench_markers)
    bench_pose = benches.add_parser("pose", help="pose solver time vs points (tab:time_points) and batch throughput")
    bench_pose.add_argument("--csv", type=Path, default=Path("reports/bench/pose_time_points.csv"))
    bench_pose.add_argument("--repeats", type=int, default=200, help="solves per point count and method")
    bench_pose.add_argument("--batch-frames", type=int, default=200, help="frames in the batch-throughput run")
    bench_pose.set_defaults(run=_cmd_bench_pose)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
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


if __name__ == "__main__":
    sys.exit(main())
