"""`report.html`: one self-contained page for a reader who did not run the pipeline.

Every figure is drawn with matplotlib and embedded (inline SVG, or a JPEG data URI for the image
montages), so the page needs no other file; the figures of the paper that the other results lack
(marker overlays, fields of view on the ground, calibration residuals) are also written beside the
page, figures/<name>.svg|jpg, for the workflow's report. Every section is an <h2> with a stable id
(SECTIONS). A section whose inputs are missing says what is missing instead of failing the report.
All text taken from files is HTML-escaped.
"""

from __future__ import annotations

import base64
import html
import io
import logging
from collections.abc import Callable
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from ..errors import DmaisError
from ..evaluate import ALL_GROUPS, TRUE_ERROR_COLUMNS
from ..files import write_bytes_atomic, write_text_atomic
from ..geometry import Rigid3
from ..rig import Rig
from ..workspace import Workspace, pose_observations_path
from .calibration import image_eps_figure, image_eps_table, residual_quiver_figure
from .dataset import rig_table, summary_table
from .footprint import angular_extent_deg, footprint_figure, ground_footprints
from .overlays import marker_montage
from .paper import BY_CONSTRUCTION, PAPER_TABLES, paper_notes

log = logging.getLogger(__name__)

SECTIONS = (
    ("dataset", "Dataset"),
    ("markers", "Marker quality per camera"),
    ("extraction", "Detected markers on the images"),
    ("intrinsics", "Intrinsics per camera"),
    ("rig", "Rig layout"),
    ("fov", "Fields of view on the ground"),
    ("residuals", "Reprojection residuals per camera"),
    ("frames", "Per-frame pose errors"),
    ("attitude", "Attitude error: the paper's proxy and the truth"),
    ("subsets", "Camera subsets"),
    ("runtime", "Runtime versus number of points"),
    ("stages", "Processing time per stage"),
    ("paper", "Comparison with the paper"),
)
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "d")
RATIO_LIMITS = (0.5, 2.0)
_MAX_TABLE_ROWS = 400
#: The figure files written beside the page (figures/<name>), removed first so none is left stale.
FIGURE_FILES = ("markers_calibration.jpg", "markers_flight.jpg", "fov_ground.svg", "calibration_residuals.svg",
                "calibration_image_eps.svg", "attitude_proxy_vs_truth.svg")
MONTAGE_DPI = 110


class MissingInput(Exception):
    """A section's input is absent; the message says which and how to make it."""


# ------------------------------------------------------------------------------ the page


def write_report(workspace: Workspace, out_html: str | Path, benchmarks_dir: str | Path | None = None,
                 paper_dir: str | Path | None = None) -> Path:
    """Write the HTML report of the workspace's results to `out_html` atomically; returns its path.

    It renders what the stages wrote (the evaluate stage's statistics, the report stage's
    comparisons with the paper). benchmarks_dir: folder of snakemake benchmark files (*.tsv,
    searched recursively), optional. paper_dir: the published tables (default: the package's).
    """
    context = _Context(workspace, benchmarks_dir, paper_dir, Path(out_html).parent / "figures")
    builders = {"dataset": _dataset_section, "markers": _markers_section, "extraction": _extraction_section,
                "intrinsics": _intrinsics_section, "rig": _rig_section, "fov": _fov_section,
                "residuals": _residuals_section, "frames": _frames_section, "attitude": _attitude_section,
                "subsets": _subsets_section, "runtime": _runtime_section, "stages": _stages_section,
                "paper": _paper_section}
    sections = [(key, title, _build(builders[key], context, key)) for key, title in SECTIONS]
    title = f"DMAIS report: {context.name}"
    return write_text_atomic(out_html, _page(title, context.intro(), sections))


class _Context:
    """Paths and lazily loaded inputs shared by the sections; loading raises MissingInput."""

    def __init__(self, workspace: Workspace, benchmarks_dir, paper_dir, figures_dir: Path):
        self.workspace, self.dataset, self.results = workspace, workspace.dataset, workspace.root
        self.benchmarks_dir = None if benchmarks_dir is None else Path(benchmarks_dir)
        self.paper_dir = paper_dir
        self.figures_dir = figures_dir
        for name in FIGURE_FILES:
            (figures_dir / name).unlink(missing_ok=True)

    def figure(self, name: str, fig, caption: str) -> str:
        """Write `fig` to figures/<name> (SVG, or JPEG for .jpg) and return it embedded with its caption."""
        if name.endswith(".jpg"):
            data = _jpeg(fig)
            write_bytes_atomic(self.figures_dir / name, data)
            content = f'<img alt="{_esc(name)}" src="data:image/jpeg;base64,{base64.b64encode(data).decode("ascii")}">'
        else:
            content = _svg(fig)
            write_text_atomic(self.figures_dir / name, content)
        return _figure(content, caption)

    @property
    def name(self) -> str:
        return self.dataset.name

    def intro(self) -> str:
        return (f"Dataset <code>{_esc(self.dataset.root)}</code>, results <code>{_esc(self.results)}</code>. "
                "Units: metres, pixels, arc-minutes (&prime;); eps_pos is the distance to the POS reference "
                "after the lever-arm calibration, eps_ang = eps_proj &times; angular resolution.")

    @cached_property
    def rig(self) -> Rig:
        if not self.workspace.has_rig():
            raise MissingInput(f"{self.workspace.rig_path} is missing (run `dmais extrinsics`).")
        return self.workspace.load_rig()

    @cached_property
    def truth_rig(self) -> Rig | None:
        """The simulator's rig, None for a real dataset (or one that cannot be loaded)."""
        try:
            path = self.dataset.truth_dir / "rig.json"
            return Rig.load(path) if path.is_file() else None
        except DmaisError:
            return None

    def table(self, name: str, hint: str) -> pd.DataFrame:
        """tables/<name>.csv (keys as text), or MissingInput with the hint."""
        table = self.workspace.load_table(name, PAPER_TABLES[name].keys if name in PAPER_TABLES else ())
        if table is None:
            raise MissingInput(f"{self.workspace.table_path(name)} is missing ({hint}).")
        return table


def _build(builder: Callable[[_Context], str], context: _Context, key: str) -> str:
    try:
        return builder(context)
    except MissingInput as missing:
        return _missing(str(missing))
    except DmaisError as error:
        log.warning("report section %s: %s", key, error)
        return _missing(f"This section could not be drawn: {error}")
    except (KeyError, ValueError, pd.errors.ParserError, pd.errors.EmptyDataError) as error:
        # A malformed table (missing column, unparsable value) must not cost the whole report.
        log.warning("report section %s: malformed input", key, exc_info=True)
        return _missing(f"This section could not be drawn from malformed input: {type(error).__name__}: {error}")


def _page(title: str, intro: str, sections: list[tuple[str, str, str]]) -> str:
    toc = "".join(f'<li><a href="#{key}">{_esc(name)}</a></li>' for key, name, _ in sections)
    body = "\n".join(f'<section><h2 id="{key}">{_esc(name)}</h2>\n{content}\n</section>'
                     for key, name, content in sections)
    style = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222;line-height:1.4}"
             "table{border-collapse:collapse;margin:0.5em 0}td,th{padding:2px 8px;border-bottom:1px solid #ddd;"
             "text-align:right}th{background:#f4f4f4}.missing{color:#a33;font-style:italic}"
             "figure{margin:1em 0}figcaption{font-size:90%;color:#555}svg{max-width:100%;height:auto}"
             "pre{background:#f7f7f7;padding:0.5em}.scroll{overflow-x:auto}td{white-space:nowrap}"
             ".note{font-size:92%;background:#f8f8ec;padding:0.4em 0.6em}")
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{_esc(title)}</title>"
            f"<style>{style}</style></head>\n<body><h1>{_esc(title)}</h1>\n<p>{intro}</p>\n"
            f"<nav><ul>{toc}</ul></nav>\n{body}\n</body></html>\n")


# ------------------------------------------------------------------------------ sections


def _dataset_section(ctx: _Context) -> str:
    dataset = ctx.dataset
    parts = [f"<pre>{_esc(dataset.summary())}</pre>", _table(summary_table(dataset))]
    if ctx.truth_rig is not None:
        parts.append("<p>Simulated dataset: ground truth under <code>truth/</code> is used for the true errors "
                     "below (never by the pipeline's estimation).</p>")
    return "\n".join(parts)


def _markers_section(ctx: _Context) -> str:
    images = ctx.table("marker_images", "no image's markers were extracted (observations given), or run "
                       "`dmais markers` and `dmais evaluate`")
    markers = {image: ctx.workspace.load_markers(image) for image in images["image"]}
    camera_of = dict(zip(images["image"], images["camera"]))
    caption = ("Sub-pixel standard deviation (per axis) of every refined corner, from the residual of its fit, "
               "per camera (log scale). Images are flagged when their median is well above their camera's "
               "median (`dmais evaluate`, settings flag_factor and flag_min_sigma_px).")
    parts = [_figure(_svg(marker_sigma_figure(markers, camera_of)), caption),
             _table(ctx.table("marker_cameras", "run `dmais evaluate`"))]
    flagged = images[images["flagged"]]
    if len(flagged):
        parts += ["<p>Flagged images (poor corners):</p>", _table(flagged.drop(columns="flagged"))]
    return "\n".join(parts)


def marker_sigma_figure(markers: dict[str, pd.DataFrame], camera_of: dict[str, str]):
    """Box plot of every corner's sigma_px per camera."""
    cameras = sorted({camera_of[image] for image in markers})
    values = [np.concatenate([t["sigma_px"].to_numpy(float) for i, t in markers.items() if camera_of[i] == c])
              for c in cameras]
    values = [v[np.isfinite(v) & (v > 0)] for v in values]
    fig = Figure(figsize=(1.2 * len(cameras) + 2.0, 3.2))
    ax = fig.subplots()
    ax.boxplot([v if len(v) else [np.nan] for v in values], showfliers=True)
    ax.set_xticks(range(1, len(cameras) + 1), cameras)
    ax.set_yscale("log")
    ax.set_ylabel("sigma (px)")
    return fig


def _extraction_section(ctx: _Context) -> str:
    """fig:calib and fig:A: one calibration image and one flight frame per camera, detections drawn."""
    parts = []
    calibration = _calibration_showcase(ctx)
    if calibration:
        parts.append(ctx.figure("markers_calibration.jpg", _montage(ctx, calibration),
                                "Calibration images (per camera the intrinsics image with the most identified "
                                "markers), then crops at full resolution around single markers. Green: detected "
                                "and identified (point id); red: detected but not identified (markers/<image>.csv)."))
    frame, flight = _flight_showcase(ctx)
    if flight:
        parts.append(ctx.figure("markers_flight.jpg", _montage(ctx, flight),
                                f"Flight frame {frame}, one image per camera, with its detected markers "
                                "(green: identified, red: unidentified) and crops around single markers."))
    if not parts:
        raise MissingInput(f"No image with a file has a markers file under {ctx.results / 'markers'} "
                           "(run `dmais markers`).")
    return "\n".join(parts)


def _calibration_showcase(ctx: _Context) -> list[str]:
    """Per camera, its intrinsics image with a file and markers file that has the most identified markers."""
    chosen = []
    for camera in ctx.dataset.cameras:
        images = ctx.dataset.images_of("intrinsics", camera)
        counts = {image: int((ctx.workspace.load_markers(image)["point_id"] != "").sum())
                  for image, path in zip(images["image"], images["path"])
                  if path and ctx.workspace.markers_path(image).is_file()}
        if counts:
            chosen.append(max(counts, key=counts.get))
    return chosen


def _flight_showcase(ctx: _Context) -> tuple[str, list[str]]:
    """The first solved frame (poses.csv, else frames.csv) that has images with markers files, and those images."""
    poses = ctx.workspace.poses_path()
    frames = (pd.read_csv(poses, dtype={"frame": str})["frame"].tolist() if poses.is_file()
              else ctx.dataset.frames["frame"].tolist())
    flight = ctx.dataset.images_of("flight")
    for frame in frames:
        rows = flight[(flight["placement"] == frame) & (flight["path"] != "")]
        images = [i for i in rows["image"] if ctx.workspace.markers_path(i).is_file()]
        if images:
            return frame, images
    return "", []


def _montage(ctx: _Context, images: list[str]):
    camera_of = dict(zip(ctx.dataset.images["image"], ctx.dataset.images["camera"]))
    rows = [(f"{camera_of[image]} {image}", ctx.dataset.read_image(image), ctx.workspace.load_markers(image))
            for image in images]
    return marker_montage(rows)


def _intrinsics_section(ctx: _Context) -> str:
    workspace = ctx.workspace
    records = [workspace.load_intrinsics(c)[1] for c in ctx.dataset.cameras if workspace.intrinsics_path(c).is_file()]
    if not records:
        raise MissingInput(f"{workspace.root / 'intrinsics'} holds no <camera>.json (run `dmais intrinsics`).")
    parts = ["<p>Calibrated intrinsics (eq. 2-3 model) &plusmn; one standard deviation from the "
             "covariance of the final Levenberg-Marquardt; eps_calib / eps_eval are RMS reprojection "
             "distances on the calibration / held-out images.</p>", _table(intrinsics_table(records))]
    truth = ctx.truth_rig
    if truth is not None:
        parts += ["<p>Calibrated minus true values (simulator):</p>", _table(_intrinsics_vs_truth(records, truth))]
    parts += _calibration_residual_parts(ctx, records)
    baselines = workspace.load_table("intrinsics")
    if baselines is not None:
        parts += ["<p>All methods (tab:intrinsics layout): ours; opencv = cv2.calibrateCamera with the same "
                  "one-coefficient model; dlt_lm = our DLT + Levenberg-Marquardt baseline (in the paper's place "
                  "of Bouguet's toolbox, which is not run here); BabelCalib is not run.</p>", _table(baselines)]
    return "\n".join(parts)


def _calibration_residual_parts(ctx: _Context, records: list[dict]) -> list[str]:
    """The residual vectors over each sensor and the RMS per image, from what the intrinsics stage wrote."""
    parts = []
    residuals = {r["camera"]: table for r in records
                 if (table := ctx.workspace.load_calibration_residuals(r["camera"])) is not None}
    if residuals:
        sizes = {r["camera"]: (r["width"], r["height"]) for r in records}
        parts.append(ctx.figure("calibration_residuals.svg", residual_quiver_figure(residuals, sizes),
                                "Residual (observed minus projected) of every observation of our calibration, "
                                "drawn from the observed position over each sensor, magnified; blue: calibration "
                                "images after the final Levenberg-Marquardt, orange: held-out images after their "
                                "pose-only fit (intrinsics/<camera>.residuals.csv)."))
    else:
        parts.append(_missing("No intrinsics/<camera>.residuals.csv (written by `dmais intrinsics` since the "
                              "residual files were added): rerun the intrinsics stage for the residual vectors."))
    per_image = image_eps_table(records)
    if not per_image.empty:
        parts.append(ctx.figure("calibration_image_eps.svg", image_eps_figure(per_image),
                                "RMS reprojection distance per image: eps_calib of each calibration image, eps_eval "
                                "of each held-out image (intrinsics/<camera>.json)."))
    return parts


def intrinsics_table(records: list[dict]) -> pd.DataFrame:
    """One row per camera JSON record: value &plusmn; std of fx, fy, cx, cy, d, the errors and counts."""
    rows = []
    for r in records:
        std = r.get("std") or {}
        row = {"camera": r.get("camera", "?")}
        for name in INTRINSIC_NAMES:
            row[name] = _pm(r.get(name), std.get(name), 4 if name == "d" else 1)
        row.update(eps_calib_px=r.get("eps_calib_px"), eps_eval_px=r.get("eps_eval_px"),
                   n_images=r.get("n_images"), n_observations=r.get("n_observations"))
        rows.append(row)
    return pd.DataFrame(rows)


def _pm(value, std, decimals: int) -> str:
    if value is None:
        return ""
    text = f"{value:.{decimals}f}"
    return text if std is None else f"{text} ± {std:.{max(decimals, 2)}g}"


def _intrinsics_vs_truth(records: list[dict], truth: Rig) -> pd.DataFrame:
    rows = []
    for r in records:
        camera = truth.cameras.get(r.get("camera"))
        if camera is not None:
            rows.append({"camera": r["camera"],
                         **{f"{n} - truth": r[n] - getattr(camera, n) for n in INTRINSIC_NAMES if n in r}})
    return pd.DataFrame(rows)


def _rig_section(ctx: _Context) -> str:
    parts = []
    layout = ctx.workspace.layout_figure_path
    if layout.is_file():
        parts.append(_figure(_svg_file(layout), "Camera centres and optical axes in the rig frame, calibrated with "
                             "and without the RTK camera-centre priors."))
    else:
        rigs = _rig_variants(ctx)
        if not rigs:
            raise MissingInput(f"{ctx.workspace.rig_path} is missing (run `dmais extrinsics`).")
        parts.append(_figure(_svg(rig_layout_figure(rigs)), "Camera centres (dots) and optical axes (lines) in the "
                             "rig frame (C0's; z drawn downwards, the way the cameras look); " + ", ".join(rigs) + "."))
    if ctx.workspace.has_rig():
        parts += ["<p>rig.json: rig_from_cam as ZYX Euler angles (deg) and camera centres (m).</p>",
                  _table(rig_table(ctx.rig))]
    for name, caption in (("extrinsics_R", "Relative rotations with known / unknown initial positions "
                           "(tab:extrinsics_R)"), ("extrinsics_t", "Relative translations (tab:extrinsics_t)")):
        table = ctx.workspace.load_table(name)
        if table is not None:
            parts += [f"<p>{_esc(caption)}:</p>", _table(table)]
    return "\n".join(parts)


def _rig_variants(ctx: _Context) -> dict[str, Rig]:
    """Rigs to draw: with and without priors when both exist, else rig.json; plus the truth."""
    rigs = {}
    for label, case in (("with priors", "known"), ("without priors", "unknown")):
        if ctx.workspace.case_rig_path(case).is_file():
            rigs[label] = Rig.load(ctx.workspace.case_rig_path(case))
    if not rigs and ctx.workspace.has_rig():
        rigs["rig.json"] = ctx.rig
    if rigs and ctx.truth_rig is not None:
        rigs["truth"] = ctx.truth_rig
    return rigs


def _fov_section(ctx: _Context) -> str:
    """fig:5cam: every camera's footprint on the ground for one solved frame, and the rig's angular extent."""
    rig = ctx.rig
    width, height = angular_extent_deg(rig)
    text = (f"<p>Total angular extent of the {len(rig.camera_names)} cameras (spread of all image-corner rays "
            f"seen along {_esc(rig.camera_names[0])}'s axis, from rig.json): {width:.1f}&deg; &times; "
            f"{height:.1f}&deg; (the paper: about 90&deg; &times; 90&deg;). Each camera alone covers "
            + ", ".join(f"{_esc(c)} {w:.2f}&deg; &times; {h:.2f}&deg;"
                        for c, (w, h) in ((c, _camera_fov_deg(rig, c)) for c in rig.camera_names)) + ".</p>")
    poses = ctx.workspace.poses_path()
    if not poses.is_file():
        return text + _missing(f"{poses} is missing (run `dmais pose`) for the footprints on the ground.")
    table = pd.read_csv(poses, dtype={"frame": str, "cameras": str})
    if table.empty:
        return text + _missing(f"{poses} has no frame.")
    full = table[table["cameras"].str.count(r"\+") == table["cameras"].str.count(r"\+").max()].iloc[0]
    rig_from_world = Rigid3.from_quat(full[["qw", "qx", "qy", "qz"]].to_numpy(float),
                                      full[["tx", "ty", "tz"]].to_numpy(float))
    ground = ctx.dataset.ground_points
    points = ground if len(ground) else ctx.dataset.control_points
    ground_z = float(points["z"].mean())
    footprints = ground_footprints(rig, rig_from_world, ground_z)
    centre = rig_from_world.center
    missing = [c for c, corners in footprints.items() if corners is None]
    fig = footprint_figure(footprints, centre[:2], points[["x", "y"]].to_numpy(float),
                           title=f"frame {full['frame']}, {centre[2] - ground_z:.0f} m above z = {ground_z:.1f} m")
    caption = (f"The image corners of every camera cut with the plane z = {ground_z:.1f} m (the mean height of the "
               f"{'ground' if len(ground) else 'control'} points) for frame {full['frame']}'s pose (poses.csv) "
               "and rig.json; grey dots: the markers." + (f" Not drawn (looking above the horizon): "
                                                         f"{', '.join(missing)}." if missing else ""))
    return text + ctx.figure("fov_ground.svg", fig, caption)


def _camera_fov_deg(rig: Rig, camera: str) -> tuple[float, float]:
    cam = rig.cameras[camera]
    return (float(np.degrees(2 * np.arctan(cam.width / 2 / cam.fx))),
            float(np.degrees(2 * np.arctan(cam.height / 2 / cam.fy))))


def _residuals_section(ctx: _Context) -> str:
    workspace = ctx.workspace
    if not workspace.poses_path().is_file():
        raise MissingInput(f"{workspace.poses_path()} is missing (run `dmais pose`).")
    observations = workspace.load_pose_observations()
    if observations is None:
        raise MissingInput(f"{pose_observations_path(workspace.poses_path())} is missing (run `dmais pose`).")
    residuals = observations[observations["used"]].dropna(subset=["du", "dv"])
    if residuals.empty:
        raise MissingInput("No flight observation belongs to a frame of poses.csv.")
    cameras = [c for c in ctx.rig.camera_names if c in set(residuals["camera"])]
    caption = ("Top: observed minus projected marker positions over each sensor (colour = distance, px); "
               "bottom: histogram of the distances. Projections use rig.json and poses.csv; the observations "
               "each pose was solved from (RANSAC's inliers with --robust).")
    return "\n".join([_figure(_svg(residual_figure(residuals, ctx.rig, cameras)), caption),
                      _table(ctx.table("residuals", "run `dmais evaluate`"))])


def _frames_section(ctx: _Context) -> str:
    evaluation = ctx.workspace.load_evaluation()
    if evaluation is None:
        raise MissingInput(f"{ctx.workspace.evaluation_path()} is missing (run `dmais evaluate`).")
    parts = [_figure(_svg(frame_errors_figure(evaluation)),
                     "Errors of every frame in file order, coloured by flight group. eps_pos: distance to the POS "
                     "position after the one lever arm fitted over all frames (table below); eps_pos_group: after "
                     "removing each group's mean offset to the POS instead (a literal reading of the paper's "
                     "\"average offset\", which absorbs each group's bias)."
                     + (" True errors against the simulator's truth in the last panels." if
                        TRUE_ERROR_COLUMNS[0] in evaluation else ""))]
    parts.append(_pos_calibration_part(ctx))
    table = ctx.table("pose_methods", "run `dmais evaluate`")
    parts += ["<p>Per group mean and standard deviation (tab:pose_methods); eps_pos_* with the lever arm "
              "(compared with the paper), eps_pos_group_* with the per-group mean offsets:</p>", _table(table)]
    if len(evaluation) <= _MAX_TABLE_ROWS:
        parts += ["<details><summary>Every frame</summary>", _table(evaluation), "</details>"]
    return "\n".join(parts)


def _attitude_section(ctx: _Context) -> str:
    """eps_ang is the paper's proxy for the attitude error; beside it the true error where the simulator gives it."""
    evaluation = ctx.workspace.load_evaluation()
    if evaluation is None:
        raise MissingInput(f"{ctx.workspace.evaluation_path()} is missing (run `dmais evaluate`).")
    text = ("<p>eps_ang is not a measured attitude error: like the paper, it is eps_proj (the RMS reprojection "
            "distance, px) times the cameras' angular resolution (arc-minutes per pixel), a proxy that needs no "
            "attitude reference.")
    truth = TRUE_ERROR_COLUMNS[1]
    if truth not in evaluation:
        return text + " This dataset has no true attitude (no simulator truth), so only the proxy is shown.</p>"
    text += (" On this simulated dataset the true attitude error (the rotation angle between the estimated and "
             "the simulator's rig_from_world) is known and shown beside it.</p>")
    columns = {"eps_ang_arcmin": "eps_ang (proxy)", truth: "true attitude error"}
    if "crb_ang_arcmin" in evaluation:
        columns["crb_ang_arcmin"] = "Cramer-Rao bound"
    grouped = evaluation.groupby(evaluation["group"].astype(str), sort=False)[list(columns)].mean()
    table = grouped.rename(columns={c: f"{label} mean (′)" for c, label in columns.items()}).reset_index()
    caption = ("Per frame: the proxy eps_ang against the true attitude error (arc-minutes); the line is equality.")
    return "\n".join([text, ctx.figure("attitude_proxy_vs_truth.svg", attitude_figure(evaluation, truth), caption),
                      _table(table)])


def attitude_figure(evaluation: pd.DataFrame, truth_column: str):
    """Scatter of eps_ang (x) against the true attitude error (y) per frame, coloured by group."""
    fig = Figure(figsize=(4.6, 4.2))
    ax = fig.subplots()
    for group, rows in evaluation.groupby(evaluation["group"].astype(str), sort=False):
        ax.scatter(rows["eps_ang_arcmin"], rows[truth_column], s=12, label=f"group {group}")
    top = float(np.nanmax(evaluation[["eps_ang_arcmin", truth_column]].to_numpy(float))) * 1.05
    ax.plot([0, top], [0, top], color="0.5", lw=0.8)
    ax.set(xlim=(0, top), ylim=(0, top))
    ax.set_xlabel("eps_ang = eps_proj × resolution (′)")
    ax.set_ylabel("true attitude error (′)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def _pos_calibration_part(ctx: _Context) -> str:
    """tables/lever_arm.csv with what its rows mean (or a line saying it is missing)."""
    table = ctx.workspace.load_table("lever_arm")
    if table is None:
        return _missing(f"{ctx.workspace.table_path('lever_arm')} is missing (run `dmais evaluate`).")
    world = table["parameter"].str.startswith("world_offset").any()
    text = ("The frames share one attitude, so no lever arm could be told from a world offset: eps_pos removes "
            "one world-frame offset POS - estimate (m)." if world else
            "POS lever arm: the POS reference point in the rig frame (POS = rig centre + R_world_from_rig l), "
            "fitted once over every frame of poses.csv and applied to every camera subset; 1-sigma with an error "
            "shared by a group's frames.")
    if table["parameter"].str.startswith("boresight").any():
        text += (" INS boresight: imu_from_rig as a rotation vector in the rig axes (INS attitude = B "
                 "rig_from_world), from frames.csv's INS attitudes.")
    if "truth" in table:
        text += " truth: the simulator's values."
    return "\n".join([f"<p>{_esc(text)}</p>", _table(table)])


def _subsets_section(ctx: _Context) -> str:
    conf = ctx.table("conf", "run `dmais pose --cameras ...` per subset, then `dmais evaluate`")
    caption = ("Mean errors per camera subset (label = camera indexes, e.g. 012 = C0, C1, C2; the full rig of "
               "poses.csv is the label of all its cameras) and flight group; log scale. eps_pos with the full rig's "
               "lever arm, eps_pos_group with the full rig's per-group mean offsets.")
    return "\n".join([_figure(_svg(subset_figure(conf)), caption), _table(conf_wide(conf))])


def conf_wide(conf: pd.DataFrame) -> pd.DataFrame:
    """tab:conf's layout: rows (group, metric), one column per subset label."""
    metrics = [c for c in ("eps_pos_mean_m", "eps_pos_group_mean_m", "eps_ang_mean_arcmin", "eps_proj_mean_px")
               if c in conf]
    long = conf.melt(id_vars=["group", "subset"], value_vars=metrics, var_name="metric")
    labels = list(dict.fromkeys(conf["subset"]))
    wide = long.pivot_table(index=["group", "metric"], columns="subset", values="value", sort=False)
    return wide.reindex(columns=labels).reset_index().rename_axis(columns=None)


def _runtime_section(ctx: _Context) -> str:
    table = ctx.table("time_points", "run the runtime benchmark")
    return "\n".join([_figure(_svg(runtime_figure(table)), "Mean solve time against the number of 2D-3D "
                              "correspondences (tab:time_points)."), _table(table)])


def _stages_section(ctx: _Context) -> str:
    if ctx.benchmarks_dir is None:
        raise MissingInput("Not available: no benchmark folder was given (snakemake `benchmark:` files).")
    table = benchmark_table(ctx.benchmarks_dir)
    if table.empty:
        raise MissingInput(f"Not available: {ctx.benchmarks_dir} holds no benchmark *.tsv file.")
    return "\n".join([_figure(_svg(stage_figure(table)), "Total wall time per stage (sum over its jobs)."),
                      _table(table)])


def benchmark_table(folder: str | Path) -> pd.DataFrame:
    """Per stage: jobs, total / mean / max wall time (s), max RSS (MB) from snakemake benchmark files.

    The stage is a file's first folder below `folder`, or its name without .tsv when it lies directly
    in `folder`. Columns: stage, jobs, total_s, mean_s, max_s, max_rss_mb.
    """
    folder = Path(folder)
    rows = []
    for path in sorted(folder.rglob("*.tsv")):
        relative = path.relative_to(folder)
        stage = relative.parts[0] if len(relative.parts) > 1 else path.stem
        frame = pd.read_csv(path, sep="\t")
        if "s" not in frame or frame.empty:
            continue
        rss = frame["max_rss"] if "max_rss" in frame else pd.Series([np.nan])
        rows.append({"stage": stage, "s": float(frame["s"].mean()), "rss": pd.to_numeric(rss, errors="coerce").max()})
    if not rows:
        return pd.DataFrame(columns=["stage", "jobs", "total_s", "mean_s", "max_s", "max_rss_mb"])
    runs = pd.DataFrame(rows)
    table = runs.groupby("stage", sort=False).agg(jobs=("s", "size"), total_s=("s", "sum"), mean_s=("s", "mean"),
                                                  max_s=("s", "max"), max_rss_mb=("rss", "max"))
    return table.reset_index()


def _paper_section(ctx: _Context) -> str:
    comparisons = {name: table for name in PAPER_TABLES
                   if (table := ctx.workspace.load_table(f"{name}_vs_paper")) is not None}
    if not comparisons:
        raise MissingInput(f"No table of {ctx.results / 'tables'} has a published counterpart yet.")
    low, high = RATIO_LIMITS
    parts = [f"<p>Our tables beside the paper's published numbers (ratio = ours / paper). Rows flagged "
             f"differ by more than a factor {high:g}. In tab:intrinsics the paper's Bouguet row holds our own "
             "DLT + LM baseline (dlt_lm; Bouguet's toolbox is not run), its OpenCV row our cv2.calibrateCamera run, "
             "and its BabelCalib row is the paper's alone (column ours_is). A corrected misprint of the paper is "
             "named in the note column. Angles near &plusmn;180&deg; or 0 make ratios meaningless, see the "
             "difference column.</p>"]
    notes = paper_notes(ctx.paper_dir)
    for name, table in comparisons.items():
        flagged = table.assign(flag=np.where((table["ratio"] < low) | (table["ratio"] > high), "!", ""))
        parts += [f"<h3>{_esc(name)}</h3>"]
        parts += [f'<p class="note">{_esc(notes[name])}</p>'] if name in notes else []
        if ctx.truth_rig is not None and name in BY_CONSTRUCTION:
            parts.append(f'<p class="note">By construction: {_esc(BY_CONSTRUCTION[name])}</p>')
        run_note = ctx.workspace.load_extrinsics_note()  # the extrinsics stage explains its run
        if name == "extrinsics_t" and run_note:
            parts.append(f'<p class="note">This run: {_esc(run_note)}</p>')
        parts.append(_table(flagged))
    return "\n".join(parts)


# ------------------------------------------------------------------------------ figures


def rig_layout_figure(rigs: dict[str, Rig]):
    """3D view per rig: camera centres and optical axes (rig frame, metres)."""
    fig = Figure(figsize=(4.2 * len(rigs), 4.2))
    for k, (label, rig) in enumerate(rigs.items(), 1):
        ax = fig.add_subplot(1, len(rigs), k, projection="3d")
        centres = np.array([rig.camera_center(c) for c in rig.camera_names])
        extent = max(float(np.ptp(centres, axis=0).max()), 0.1)
        for name, centre in zip(rig.camera_names, centres):
            axis = rig.cam_from_rig[name].R[2] * 0.6 * extent  # optical axis (camera z) in the rig frame
            ax.plot(*zip(centre, centre + axis), color="tab:blue")
            ax.scatter(*centre, color="tab:red", s=12)
            ax.text(*centre, f" {name}", fontsize=8)
        middle, half = (centres.max(axis=0) + centres.min(axis=0)) / 2, 0.8 * extent
        ax.set(xlim=(middle[0] - half, middle[0] + half), ylim=(middle[1] - half, middle[1] + half),
               zlim=(middle[2] + half, middle[2] - half))  # z inverted: the cameras look down
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
    fig.tight_layout()
    return fig


def residual_figure(residuals: pd.DataFrame, rig: Rig, cameras: list[str]):
    """Per camera: residual distance over the sensor (top) and its histogram (bottom)."""
    fig = Figure(figsize=(3.0 * len(cameras) + 0.5, 5.6))
    axes = fig.subplots(2, len(cameras), squeeze=False)
    distance = np.hypot(residuals["du"], residuals["dv"])
    top = float(np.nanpercentile(distance, 99)) or 1.0
    for k, camera in enumerate(cameras):
        mine = residuals["camera"] == camera
        cam = rig.cameras[camera]
        ax = axes[0, k]
        points = ax.scatter(residuals.loc[mine, "u"], residuals.loc[mine, "v"], c=distance[mine], s=6,
                            cmap="viridis", vmin=0, vmax=top, rasterized=True)
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_title(camera, fontsize=10)
        ax.set_xlabel("u (px)", fontsize=8)
        axes[1, k].hist(distance[mine], bins=30, range=(0, top), color="tab:blue")
        axes[1, k].set_xlabel("distance (px)", fontsize=8)
    fig.colorbar(points, ax=axes[0, :].tolist(), shrink=0.8, label="px")
    return fig


def frame_errors_figure(evaluation: pd.DataFrame):
    """eps_pos, eps_ang, eps_proj (and the true errors) per frame, coloured by group."""
    panels = [(c, label) for c, label in (("eps_pos_m", "eps_pos, lever arm (m)"),
                                          ("eps_pos_group_m", "eps_pos, group offsets (m)"),
                                          ("eps_ang_arcmin", "eps_ang (′)"), ("eps_proj_px", "eps_proj (px)"))
              if c in evaluation]
    panels += [(c, label) for c, label in zip(TRUE_ERROR_COLUMNS, ("true position error (m)",
                                                                   "true attitude error (′)")) if c in evaluation]
    fig = Figure(figsize=(9, 1.9 * len(panels) + 0.4))
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    evaluation = evaluation.reset_index(drop=True)  # the index is the frame's position in the file
    for ax, (column, label) in zip(axes, panels):
        for group, rows in evaluation.groupby(evaluation["group"].astype(str), sort=False):
            ax.plot(rows.index, rows[column], marker="o", ms=3, lw=0.8, label=f"group {group}")
        ax.set_ylabel(label, fontsize=8)
    axes[0].legend(fontsize=7, ncol=6)
    axes[-1].set_xlabel("frame (file order)")
    fig.tight_layout()
    return fig


def subset_figure(conf: pd.DataFrame):
    """Grouped bars per subset label (x) and group (bars), one panel per metric, log scale."""
    metrics = [(c, label) for c, label in (("eps_pos_mean_m", "eps_pos, lever arm (m)"),
                                           ("eps_pos_group_mean_m", "eps_pos, group offsets (m)"),
                                           ("eps_ang_mean_arcmin", "eps_ang (′)"),
                                           ("eps_proj_mean_px", "eps_proj (px)")) if c in conf]
    labels = list(dict.fromkeys(conf["subset"]))
    groups = [g for g in dict.fromkeys(conf["group"]) if g != ALL_GROUPS] or [ALL_GROUPS]
    width = 0.8 / len(groups)
    fig = Figure(figsize=(3.4 * len(metrics), 3.4))
    axes = fig.subplots(1, len(metrics), squeeze=False)[0]
    x = np.arange(len(labels))
    for ax, (column, name) in zip(axes, metrics):
        for k, group in enumerate(groups):
            rows = conf[conf["group"] == group].set_index("subset").reindex(labels)
            ax.bar(x + (k - (len(groups) - 1) / 2) * width, rows[column].to_numpy(dtype=float), width,
                   label=f"group {group}")
        ax.set_xticks(x, [f"#{label}" for label in labels])
        ax.set_yscale("log")
        ax.set_title(name, fontsize=10)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return fig


def runtime_figure(table: pd.DataFrame):
    """Time (ms) against n_points for every *_ms column."""
    fig = Figure(figsize=(6, 3.6))
    ax = fig.subplots()
    n = pd.to_numeric(table["n_points"], errors="coerce")
    for column in [c for c in table.columns if c.endswith("_ms")]:
        ax.plot(n, table[column], marker="o", label=column.removesuffix("_ms"))
    ax.set_xlabel("points")
    ax.set_ylabel("time (ms)")
    ax.legend()
    fig.tight_layout()
    return fig


def stage_figure(table: pd.DataFrame):
    """Horizontal bars: total wall time per stage (s)."""
    fig = Figure(figsize=(6, 0.4 * len(table) + 1.2))
    ax = fig.subplots()
    ax.barh(table["stage"].astype(str), table["total_s"], color="tab:green")
    ax.invert_yaxis()
    ax.set_xlabel("wall time (s)")
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------ HTML helpers


def _svg(fig) -> str:
    """The figure as an inline <svg> element (text kept as text)."""
    import matplotlib

    buffer = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "dmais"}):
        fig.savefig(buffer, format="svg", bbox_inches="tight")
    text = buffer.getvalue()
    return text[text.index("<svg"):]


def _jpeg(fig) -> bytes:
    """The figure as JPEG bytes (image montages: photographs compress far better than in SVG or PNG)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="jpeg", dpi=MONTAGE_DPI, pil_kwargs={"quality": 85})
    return buffer.getvalue()


def _svg_file(path: Path) -> str:
    """An SVG file as an <img> with a data URI (scripts in it cannot run, its ids cannot clash)."""
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<img alt="{_esc(path.name)}" src="data:image/svg+xml;base64,{data}">'


def _figure(content: str, caption: str) -> str:
    return f"<figure>{content}<figcaption>{_esc(caption)}</figcaption></figure>"


def _table(frame: pd.DataFrame) -> str:
    """The frame as an HTML table; wide ones scroll sideways instead of wrapping their cells."""
    html = frame.to_html(index=False, border=0, escape=True, na_rep="", float_format=_number)
    return f'<div class="scroll">{html}</div>'



def _number(x: float) -> str:
    """4 significant digits, but large values (focal lengths, coordinates) to 0.1 without exponent."""
    return f"{x:.1f}" if 1e4 <= abs(x) < 1e9 else f"{x:.4g}"


def _missing(message: str) -> str:
    return f'<p class="missing">{_esc(message)}</p>'


def _esc(value) -> str:
    return html.escape(str(value), quote=True)

