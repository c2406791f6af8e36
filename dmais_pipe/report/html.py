"""`report.html`: one self-contained page for a reader who did not run the pipeline.

This module prepares what the page shows, section by section: numbers formatted to their digits,
tables as rows of text cells, figures drawn with matplotlib and embedded (inline SVG, or a JPEG data URI
for the image montages), so the page needs no other file. The page's markup and prose are jinja2
templates (report/templates/: report.html.j2, one sections/<id>.html.j2 per section), rendered by
report.page with autoescaping, so all text taken from files is HTML-escaped. The figures of the paper
that the other results lack (marker overlays, fields of view on the ground, calibration residuals) are
also written beside the page, figures/<name>.svg|jpg, for the workflow's report. Every section is an
<h2> with a stable id (SECTIONS). A section whose inputs are missing says what is missing instead of
failing the report.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd
from markupsafe import Markup
from matplotlib.figure import Figure

from ..camera import PARAMETER_NAMES
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
from .page import Image, render, table_of
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
    ("accuracy", "Pose accuracy beside other runs"),
    ("budget", "Error budget of the sigmas"),
    ("mounting", "The rig watched in flight"),
    ("runtime", "Runtime versus number of points"),
    ("stages", "Processing time per stage"),
    ("paper", "Comparison with the paper"),
)
#: The intrinsics table's parameter columns: every model's (camera.PARAMETER_NAMES), radial1's first.
INTRINSIC_NAMES = tuple(dict.fromkeys(name for names in PARAMETER_NAMES.values() for name in names))
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
                 paper_dir: str | Path | None = None, compare_with: Sequence[str] = ()) -> Path:
    """Write the HTML report of the workspace's results to `out_html` atomically; returns its path.

    It renders what the stages wrote (the evaluate stage's statistics, the report stage's
    comparisons with the paper). benchmarks_dir: folder of snakemake benchmark files (*.tsv,
    searched recursively), optional. paper_dir: the published tables (default: the package's).
    compare_with: other runs whose pose accuracy is shown beside this one's (`comparison_runs`).
    """
    context = _Context(workspace, benchmarks_dir, paper_dir, Path(out_html).parent / "figures", compare_with)
    builders = {"dataset": _dataset_section, "markers": _markers_section, "extraction": _extraction_section,
                "intrinsics": _intrinsics_section, "rig": _rig_section, "fov": _fov_section,
                "residuals": _residuals_section, "frames": _frames_section, "attitude": _attitude_section,
                "subsets": _subsets_section, "accuracy": _accuracy_section, "budget": _budget_section,
                "mounting": _mounting_section,
                "runtime": _runtime_section,
                "stages": _stages_section,
                "paper": _paper_section}
    sections = [_section(key, title, builders[key], context) for key, title in SECTIONS]
    page = render("report.html.j2", dataset_name=context.name, dataset_root=str(context.dataset.root),
                  results=str(context.results), sections=sections)
    return write_text_atomic(out_html, page)


@dataclass(frozen=True)
class Section:
    """One <h2> of the page: its id, its title, and its body (sections/<id>.html.j2) or why it has none."""

    key: str
    title: str
    body: Markup | None = None
    missing: str | None = None


class _Context:
    """Paths and lazily loaded inputs shared by the sections; loading raises MissingInput."""

    def __init__(self, workspace: Workspace, benchmarks_dir, paper_dir, figures_dir: Path,
                 compare_with: Sequence[str] = ()):
        self.workspace, self.dataset, self.results = workspace, workspace.dataset, workspace.root
        self.benchmarks_dir = None if benchmarks_dir is None else Path(benchmarks_dir)
        self.paper_dir = paper_dir
        self.compare_with = tuple(compare_with)
        self.figures_dir = figures_dir
        for name in FIGURE_FILES:
            (figures_dir / name).unlink(missing_ok=True)

    def figure(self, name: str, fig) -> Image:
        """Write `fig` to figures/<name> (SVG, or JPEG for .jpg) and return it to embed."""
        if name.endswith(".jpg"):
            data = _jpeg(fig)
            write_bytes_atomic(self.figures_dir / name, data)
            return Image.data_uri(data, "image/jpeg", alt=name)
        svg = _svg(fig)
        write_text_atomic(self.figures_dir / name, svg)
        return Image.inline(svg)

    @property
    def name(self) -> str:
        return self.dataset.name

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


def _section(key: str, title: str, builder: Callable[[_Context], dict], context: _Context) -> Section:
    """The section drawn from the values its builder prepares, or the note saying why it could not be."""
    try:
        values = builder(context)
    except MissingInput as missing:
        return Section(key, title, missing=str(missing))
    except DmaisError as error:
        log.warning("report section %s: %s", key, error)
        return Section(key, title, missing=f"This section could not be drawn: {error}")
    except (KeyError, ValueError, pd.errors.ParserError, pd.errors.EmptyDataError) as error:
        # A malformed table (missing column, unparsable value) must not cost the whole report.
        log.warning("report section %s: malformed input", key, exc_info=True)
        return Section(key, title, missing="This section could not be drawn from malformed input: "
                                           f"{type(error).__name__}: {error}")
    # Rendered outside the try: a template naming a value its section lacks is a bug, not a missing input.
    return Section(key, title, body=render(f"sections/{key}.html.j2", **values))


# ------------------------------------------------------------------------------ sections
# Each returns the values of its template, sections/<id>.html.j2, which holds the section's prose.


def _dataset_section(ctx: _Context) -> dict:
    return {"summary": ctx.dataset.summary(), "images": table_of(summary_table(ctx.dataset)),
            "simulated": ctx.truth_rig is not None}


def _markers_section(ctx: _Context) -> dict:
    images = ctx.table("marker_images", "no image's markers were extracted (observations given), or run "
                       "`dmais markers` and `dmais evaluate`")
    markers = {image: ctx.workspace.load_markers(image) for image in images["image"]}
    camera_of = dict(zip(images["image"], images["camera"]))
    flagged = images[images["flagged"]]
    return {"sigma_figure": Image.inline(_svg(marker_sigma_figure(markers, camera_of))),
            "cameras": table_of(ctx.table("marker_cameras", "run `dmais evaluate`")),
            "flagged": table_of(flagged.drop(columns="flagged")) if len(flagged) else None}


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


def _extraction_section(ctx: _Context) -> dict:
    """fig:calib and fig:A: one calibration image and one flight frame per camera, detections drawn."""
    calibration = _calibration_showcase(ctx)
    frame, flight = _flight_showcase(ctx)
    if not calibration and not flight:
        raise MissingInput(f"No image with a file has a markers file under {ctx.results / 'markers'} "
                           "(run `dmais markers`).")
    montages = {name: ctx.figure(f"markers_{name}.jpg", _montage(ctx, images))
                for name, images in (("calibration", calibration), ("flight", flight)) if images}
    return {"calibration": montages.get("calibration"), "flight": montages.get("flight"), "flight_frame": frame}


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


def _intrinsics_section(ctx: _Context) -> dict:
    workspace = ctx.workspace
    records = [workspace.load_intrinsics(c)[1] for c in ctx.dataset.cameras if workspace.intrinsics_path(c).is_file()]
    if not records:
        raise MissingInput(f"{workspace.root / 'intrinsics'} holds no <camera>.json (run `dmais intrinsics`).")
    truth = ctx.truth_rig
    methods = workspace.load_table("intrinsics")
    return {"cameras": table_of(intrinsics_table(records)), "models": _models_text(records),
            "versus_truth": None if truth is None else table_of(_intrinsics_vs_truth(records, truth)),
            **_calibration_residual_figures(ctx, records),
            "methods": None if methods is None else table_of(methods)}


def _models_text(records: list[dict]) -> str:
    """The lens models of the records, as the intrinsics section names them."""
    names = {"radial1": "eq. 2-3 model", "opencv": "OpenCV's model: k1, k2, p1, p2, k3"}
    return "; ".join(names[m] for m in sorted({_model(r) for r in records}, key=list(names).index))


def _calibration_residual_figures(ctx: _Context, records: list[dict]) -> dict:
    """The residual vectors over each sensor and the RMS per image (each None when its input is missing)."""
    residuals = {r["camera"]: table for r in records
                 if (table := ctx.workspace.load_calibration_residuals(r["camera"])) is not None}
    vectors = None
    if residuals:
        sizes = {r["camera"]: (r["width"], r["height"]) for r in records}
        vectors = ctx.figure("calibration_residuals.svg", residual_quiver_figure(residuals, sizes))
    per_image = image_eps_table(records)
    return {"residual_vectors": vectors,
            "image_eps": None if per_image.empty else ctx.figure("calibration_image_eps.svg",
                                                                  image_eps_figure(per_image))}


def intrinsics_table(records: list[dict]) -> pd.DataFrame:
    """One row per camera JSON record: value &plusmn; std of its model's parameters, the errors and
    counts; the columns of every model present (a "model" column once a camera is not radial1)."""
    rows = []
    for r in records:
        std = r.get("std") or {}
        row = {"camera": r.get("camera", "?"), "model": _model(r)}
        for k, name in enumerate(PARAMETER_NAMES[_model(r)]):
            row[name] = _pm(r.get(name), std.get(name), 1 if k < 4 else 4 if name == "d" else 5)
        row.update(eps_calib_px=r.get("eps_calib_px"), eps_eval_px=r.get("eps_eval_px"),
                   n_images=r.get("n_images"), n_observations=r.get("n_observations"),
                   one_to_one=_one_to_one_text(r.get("one_to_one")))
        rows.append(row)
    models = {_model(r) for r in records}
    names = [n for n in INTRINSIC_NAMES if any(n in PARAMETER_NAMES[m] for m in models)]
    columns = ["camera", *(["model"] if models - {"radial1"} else []), *names,
               "eps_calib_px", "eps_eval_px", "n_images", "n_observations",
               *(["one_to_one"] if any(r.get("one_to_one") for r in records) else [])]
    return pd.DataFrame(rows, columns=columns)


def _one_to_one_text(region: dict | None) -> str:
    """The one-to-one region of a model that folds inside its image (an intrinsics record's
    "one_to_one"), as the table shows it: its radius from the principal point and share of the image,
    and how far the observations' rays reach towards the fold; "" for the whole image."""
    if not region:
        return ""
    reach = region.get("observed_reach")
    observed = "" if reach is None else f", observations to {reach:.0%} of the fold's radius"
    return f"{region['radius_px']:.0f} px, {region['image_fraction']:.1%} of the image{observed}"


def _model(record: dict) -> str:
    """The lens model of an intrinsics record (Camera.to_dict: none named is radial1)."""
    return record.get("model", "radial1")


def _pm(value, std, decimals: int) -> str:
    if value is None:
        return ""
    text = f"{value:.{decimals}f}"
    return text if std is None else f"{text} ± {std:.{max(decimals, 2)}g}"


def _intrinsics_vs_truth(records: list[dict], truth: Rig) -> pd.DataFrame:
    """Per calibrated camera with a true one: each parameter the two models share minus its truth."""
    rows = []
    for r in records:
        camera = truth.cameras.get(r.get("camera"))
        if camera is not None:
            true = dict(zip(camera.parameter_names, camera.parameters))
            shared = [n for n in PARAMETER_NAMES[_model(r)] if n in r and n in true]
            rows.append({"camera": r["camera"], **{f"{n} - truth": r[n] - true[n] for n in shared}})
    return pd.DataFrame(rows)


def _rig_section(ctx: _Context) -> dict:
    layout = ctx.workspace.layout_figure_path
    if layout.is_file():
        image, drawn = Image.data_uri(layout.read_bytes(), "image/svg+xml", alt=layout.name), None
    else:
        rigs = _rig_variants(ctx)
        if not rigs:
            raise MissingInput(f"{ctx.workspace.rig_path} is missing (run `dmais extrinsics`).")
        image, drawn = Image.inline(_svg(rig_layout_figure(rigs))), list(rigs)
    extrinsics = {name: ctx.workspace.load_table(name) for name in ("extrinsics_R", "extrinsics_t", "survey_sigma")}
    return {"layout": image, "drawn_rigs": drawn,
            "rig": table_of(rig_table(ctx.rig)) if ctx.workspace.has_rig() else None,
            **{name: None if table is None else table_of(table) for name, table in extrinsics.items()}}


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


def _fov_section(ctx: _Context) -> dict:
    """fig:5cam: every camera's footprint on the ground for one solved frame, and the rig's angular extent."""
    rig = ctx.rig
    width, height = angular_extent_deg(rig)
    return {"extent": {"cameras": len(rig.camera_names), "axis_camera": rig.camera_names[0],
                       "width": f"{width:.1f}", "height": f"{height:.1f}"},
            "cameras": [{"name": c, "width": f"{w:.2f}", "height": f"{h:.2f}"}
                        for c, (w, h) in ((c, _camera_fov_deg(rig, c)) for c in rig.camera_names)],
            **_footprints(ctx, rig)}


def _footprints(ctx: _Context, rig: Rig) -> dict:
    """The figure of the footprints for the first full-rig frame of poses.csv, or why there is none."""
    poses = ctx.workspace.poses_path()
    if not poses.is_file():
        return {"footprints_missing": f"{poses} is missing (run `dmais pose`) for the footprints on the ground."}
    table = pd.read_csv(poses, dtype={"frame": str, "cameras": str})
    if table.empty:
        return {"footprints_missing": f"{poses} has no frame."}
    full = table[table["cameras"].str.count(r"\+") == table["cameras"].str.count(r"\+").max()].iloc[0]
    rig_from_world = Rigid3.from_quat(full[["qw", "qx", "qy", "qz"]].to_numpy(float),
                                      full[["tx", "ty", "tz"]].to_numpy(float))
    ground = ctx.dataset.ground_points
    points = ground if len(ground) else ctx.dataset.control_points
    ground_z = float(points["z"].mean())
    footprints = ground_footprints(rig, rig_from_world, ground_z)
    centre = rig_from_world.center
    fig = footprint_figure(footprints, centre[:2], points[["x", "y"]].to_numpy(float),
                           title=f"frame {full['frame']}, {centre[2] - ground_z:.0f} m above z = {ground_z:.1f} m")
    return {"footprints_missing": None, "footprints": ctx.figure("fov_ground.svg", fig), "frame": full["frame"],
            "ground_z": f"{ground_z:.1f}", "points_kind": "ground" if len(ground) else "control",
            "not_drawn": [c for c, corners in footprints.items() if corners is None]}


def _camera_fov_deg(rig: Rig, camera: str) -> tuple[float, float]:
    cam = rig.cameras[camera]
    return (float(np.degrees(2 * np.arctan(cam.width / 2 / cam.fx))),
            float(np.degrees(2 * np.arctan(cam.height / 2 / cam.fy))))


def _residuals_section(ctx: _Context) -> dict:
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
    return {"residual_figure": Image.inline(_svg(residual_figure(residuals, ctx.rig, cameras))),
            "per_camera": table_of(ctx.table("residuals", "run `dmais evaluate`"))}


def _frames_section(ctx: _Context) -> dict:
    evaluation = ctx.workspace.load_evaluation()
    if evaluation is None:
        raise MissingInput(f"{ctx.workspace.evaluation_path()} is missing (run `dmais evaluate`).")
    return {"errors_figure": Image.inline(_svg(frame_errors_figure(evaluation))),
            "true_errors": TRUE_ERROR_COLUMNS[0] in evaluation,
            "lever_arm": _lever_arm(ctx),
            "pose_methods": table_of(ctx.table("pose_methods", "run `dmais evaluate`")),
            "every_frame": table_of(evaluation) if len(evaluation) <= _MAX_TABLE_ROWS else None}


def _attitude_section(ctx: _Context) -> dict:
    """eps_ang is the paper's proxy for the attitude error; beside it the true error where the simulator gives it."""
    evaluation = ctx.workspace.load_evaluation()
    if evaluation is None:
        raise MissingInput(f"{ctx.workspace.evaluation_path()} is missing (run `dmais evaluate`).")
    truth = TRUE_ERROR_COLUMNS[1]
    if truth not in evaluation:
        return {"scatter": None}
    columns = {"eps_ang_arcmin": "eps_ang (proxy)", truth: "true attitude error"}
    if "crb_ang_arcmin" in evaluation:
        columns["crb_ang_arcmin"] = "Cramer-Rao bound"
    grouped = evaluation.groupby(evaluation["group"].astype(str), sort=False)[list(columns)].mean()
    table = grouped.rename(columns={c: f"{label} mean (′)" for c, label in columns.items()}).reset_index()
    return {"scatter": ctx.figure("attitude_proxy_vs_truth.svg", attitude_figure(evaluation, truth)),
            "per_group": table_of(table)}


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


def _lever_arm(ctx: _Context) -> dict:
    """tables/lever_arm.csv and which kinds of rows it has (or why it is missing)."""
    table = ctx.workspace.load_table("lever_arm")
    if table is None:
        return {"missing": f"{ctx.workspace.table_path('lever_arm')} is missing (run `dmais evaluate`)."}
    return {"missing": None, "table": table_of(table),
            "world_offset": table["parameter"].str.startswith("world_offset").any(),
            "boresight": table["parameter"].str.startswith("boresight").any(), "truth": "truth" in table}


def _subsets_section(ctx: _Context) -> dict:
    conf = ctx.table("conf", "run `dmais pose --cameras ...` per subset, then `dmais evaluate`")
    return {"subset_figure": Image.inline(_svg(subset_figure(conf))), "conf": table_of(conf_wide(conf))}


#: The accuracy comparison's metrics (conf.csv columns of the all-groups rows), the true errors where simulated.
ACCURACY_METRICS = ("eps_pos_mean_m", "eps_ang_mean_arcmin", "eps_proj_mean_px", "true_pos_err_mean_m",
                    "true_ang_err_mean_arcmin")
#: How to make a run's tables that are not there yet (the embedded demo's config is config/config.yaml).
_RUN_HINT = ("run the workflow with that run's config first (the DMAIS demo: `snakemake --cores 2 --configfile "
             "config/config.yaml`), then this report again")


def comparison_runs(results: Path, names: Sequence[str]) -> dict[str, Path]:
    """label -> results folder of each run to compare with: a name is a sibling of `results` (the
    workflow's results/<dataset>), a path (with a separator) is taken as given. The label is the
    folder's name, or its path where that name is taken; `results` itself and repeats are left out."""
    runs, seen = {}, {results.resolve()}
    for name in names:
        folder = Path(name) if ("/" in name or "\\" in name) else results.parent / name
        if folder.resolve() in seen:
            continue
        seen.add(folder.resolve())
        runs[str(folder) if folder.name in runs or folder.name == results.name else folder.name] = folder
    return runs


def accuracy_table(confs: Mapping[str, pd.DataFrame]) -> pd.DataFrame:
    """Pose accuracy per camera subset of several runs side by side.

    confs: run label -> its tables/conf.csv (subset labels as text), the first this run. Each run's
    all-groups rows (group ALL_GROUPS); one row per subset label (the first run's order, then the
    others'), for each of ACCURACY_METRICS that some run has one column per run, "<metric> [<run>]";
    blank where a run lacks the subset or the metric.
    """
    rows = {label: _all_groups(conf) for label, conf in confs.items()}
    subsets = list(dict.fromkeys(s for table in rows.values() for s in table.index))
    table = pd.DataFrame({"subset": subsets})
    for metric in ACCURACY_METRICS:
        for label, run in rows.items():
            if metric in run:
                values = pd.to_numeric(run[metric], errors="coerce").reindex(subsets).to_numpy(float)
                table[f"{metric} [{label}]"] = values
    return table


def _all_groups(conf: pd.DataFrame) -> pd.DataFrame:
    """A conf table's all-groups rows, indexed by subset label (text)."""
    rows = conf[conf["group"].astype(str) == ALL_GROUPS]
    return rows.set_index(rows["subset"].astype(str))


def run_description(label: str, rig: Rig | None) -> dict:
    """One line of the compared runs' table: cameras, image size, mean focal length, lens model and
    field of view of the run's rig.json (blank without one)."""
    if rig is None:
        return {"run": label, "cameras": "", "image_px": "", "focal_px": "", "model": "", "fov_deg": ""}
    cams = [rig.cameras[c] for c in rig.camera_names]
    sizes = sorted({f"{c.width}x{c.height}" for c in cams})
    fov = np.degrees(2 * np.arctan([[c.width / 2 / c.fx, c.height / 2 / c.fy] for c in cams])).mean(axis=0)
    return {"run": label, "cameras": len(cams), "image_px": ", ".join(sizes),
            "focal_px": f"{np.mean([c.fx for c in cams]):.0f}", "model": ", ".join(sorted({c.model for c in cams})),
            "fov_deg": f"{fov[0]:.1f} x {fov[1]:.1f}"}


def _accuracy_section(ctx: _Context) -> dict:
    """This run's pose accuracy per camera subset beside that of the runs named by compare_with."""
    confs = {ctx.results.name: ctx.table("conf", "run `dmais pose --cameras ...` per subset, then `dmais evaluate`")}
    rigs = {ctx.results.name: ctx.rig if ctx.workspace.has_rig() else None}
    absent = []
    for label, folder in comparison_runs(ctx.results, ctx.compare_with).items():
        path = folder / "tables" / "conf.csv"
        if not path.is_file():
            absent.append(f"{path} is missing: {_RUN_HINT}.")
            continue
        confs[label] = pd.read_csv(path, dtype={"group": str, "subset": str})
        rigs[label] = _rig_or_none(folder / "rig.json")
    return {"runs": table_of(pd.DataFrame([run_description(label, rig) for label, rig in rigs.items()])),
            "accuracy": table_of(accuracy_table(confs)), "absent": absent, "compared": len(confs) > 1}


def _rig_or_none(path: Path) -> Rig | None:
    """Another run's rig.json, None when it is absent or unreadable (its description stays blank)."""
    try:
        return Rig.load(path) if path.is_file() else None
    except DmaisError as error:
        log.warning("report: %s", error)
        return None


def _budget_section(ctx: _Context) -> dict:
    budget = ctx.workspace.load_table("error_budget", ("subset", "component", "unit", "source", "error_measure"))
    if budget is None:
        raise MissingInput(f"{ctx.workspace.table_path('error_budget')} is missing (run `dmais pose`, which writes "
                           "each poses file's budget, then `dmais evaluate`).")
    components = budget[budget["component"] != "total"]
    totals = budget[budget["component"] == "total"].dropna(axis=1, how="all")
    measure = totals["error_measure"].iloc[0] if "error_measure" in totals and len(totals) else None
    return {"shares": Image.inline(_svg(budget_figure(components))),
            "components": table_of(components.drop(columns=[c for c in components if c.startswith("rms_")
                                                             or c == "error_measure"])),
            "totals": table_of(totals.drop(columns=["sigma", "unit", "source", "position_share_pct",
                                                    "attitude_share_pct"], errors="ignore")),
            "truth": measure == "truth"}


def budget_figure(components: pd.DataFrame):
    """Stacked bars per camera set: each component's share of the predicted position and attitude variance."""
    fig = Figure(figsize=(7.2, 3.0))
    axes = fig.subplots(1, 2, sharey=True)
    labels = list(dict.fromkeys(components["subset"].astype(str)))
    names = list(dict.fromkeys(components["component"]))
    for ax, column, title in zip(axes, ("position_share_pct", "attitude_share_pct"), ("position", "attitude")):
        bottom = np.zeros(len(labels))
        for name in names:
            rows = components[components["component"] == name]
            share = rows.set_index(rows["subset"].astype(str))[column].reindex(labels).fillna(0.0).to_numpy(float)
            ax.bar(labels, share, bottom=bottom, label=name)
            bottom += share
        ax.set_title(f"share of the {title} variance")
        ax.set_xlabel("camera set")
    axes[0].set_ylabel("%")
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    return fig


def _mounting_section(ctx: _Context) -> dict:
    mounting = ctx.workspace.load_table("mounting", ("group", "camera"))
    if mounting is None:
        raise MissingInput(f"{ctx.workspace.table_path('mounting')} is missing (run `dmais pose` with every camera, "
                           "then `dmais evaluate`).")
    if not len(mounting):
        raise MissingInput(f"{ctx.workspace.table_path('mounting')} has no group: none could be adjusted (see the "
                           "pose log).")
    return {"deltas": Image.inline(_svg(mounting_figure(mounting))), "rows": table_of(mounting),
            "flagged": int(mounting["significant"].astype(str).eq("True").sum())}


def mounting_figure(mounting: pd.DataFrame):
    """Per non-reference camera, each group's in-flight rotation change (rx, ry, rz) with its 1-sigma bars."""
    cameras = [c for c in dict.fromkeys(mounting["camera"])
               if mounting.loc[mounting["camera"] == c, ["sigma_rx_arcmin", "sigma_ry_arcmin"]].to_numpy(float).any()]
    fig = Figure(figsize=(2.4 * max(len(cameras), 1), 2.8))
    axes = np.atleast_1d(fig.subplots(1, max(len(cameras), 1), sharey=True))
    for ax, camera in zip(axes, cameras):
        rows = mounting[mounting["camera"] == camera]
        x = np.arange(len(rows))
        for k, axis in enumerate(("rx", "ry", "rz")):
            ax.errorbar(x + (k - 1) * 0.2, rows[f"d_{axis}_arcmin"], yerr=rows[f"sigma_{axis}_arcmin"], fmt="o",
                        ms=3, capsize=2, label=axis)
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_xticks(x, rows["group"].astype(str))
        ax.set_title(camera)
        ax.set_xlabel("group")
    axes[0].set_ylabel("change (′)")
    axes[-1].legend(fontsize=7)
    fig.tight_layout()
    return fig


def conf_wide(conf: pd.DataFrame) -> pd.DataFrame:
    """tab:conf's layout: rows (group, metric), one column per subset label."""
    metrics = [c for c in ("eps_pos_mean_m", "eps_pos_group_mean_m", "eps_ang_mean_arcmin", "eps_proj_mean_px")
               if c in conf]
    long = conf.melt(id_vars=["group", "subset"], value_vars=metrics, var_name="metric")
    labels = list(dict.fromkeys(conf["subset"]))
    wide = long.pivot_table(index=["group", "metric"], columns="subset", values="value", sort=False)
    return wide.reindex(columns=labels).reset_index().rename_axis(columns=None)


def _runtime_section(ctx: _Context) -> dict:
    table = ctx.table("time_points", "run the runtime benchmark")
    return {"runtime_figure": Image.inline(_svg(runtime_figure(table))), "time_points": table_of(table)}


def _stages_section(ctx: _Context) -> dict:
    if ctx.benchmarks_dir is None:
        raise MissingInput("Not available: no benchmark folder was given (snakemake `benchmark:` files).")
    table = benchmark_table(ctx.benchmarks_dir)
    if table.empty:
        raise MissingInput(f"Not available: {ctx.benchmarks_dir} holds no benchmark *.tsv file.")
    return {"stage_figure": Image.inline(_svg(stage_figure(table))), "stages": table_of(table)}


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


def _paper_section(ctx: _Context) -> dict:
    comparisons = {name: table for name in PAPER_TABLES
                   if (table := ctx.workspace.load_table(f"{name}_vs_paper")) is not None}
    if not comparisons:
        raise MissingInput(f"No table of {ctx.results / 'tables'} has a published counterpart yet.")
    low, high = RATIO_LIMITS
    notes = paper_notes(ctx.paper_dir)
    simulated = ctx.truth_rig is not None
    run_note = ctx.workspace.load_extrinsics_note() or None  # the extrinsics stage explains its run
    return {"flag_factor": f"{high:g}",
            "comparisons": [{"name": name, "note": notes.get(name),
                             "by_construction": BY_CONSTRUCTION.get(name) if simulated else None,
                             "run_note": run_note if name == "extrinsics_t" else None,
                             "table": table_of(table.assign(flag=np.where((table["ratio"] < low)
                                                                         | (table["ratio"] > high), "!", "")))}
                            for name, table in comparisons.items()]}


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


# ------------------------------------------------------------------------------ figures to embed


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
