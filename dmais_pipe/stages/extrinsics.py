"""`dmais extrinsics`: calibrate the rig, cam_from_rig of every camera (calib.extrinsics).

Writes rig.json (calibrated with the RTK camera-centre priors when the conf uses them and the
images carry them) and its COLMAP twin rig_config.json, extrinsics/rig_{known,unknown}.json for
both cases and, when both cases can run, the paper's comparison: tables/extrinsics_R.csv,
extrinsics_t.csv (with standard deviations and a note per row), tables/extrinsics_note.txt and
figures/extrinsics_layout.svg; and tables/survey_sigma.csv, the control points' survey sigma each
calibration took, given or estimated from its residuals (calib.survey_variance).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..calib.extrinsics import (DEFAULT_BACKEND, PRIOR_CENTER, ExtrinsicsResult, annotate_tables, calibrate_extrinsics,
                                calibration_covariance, colmap_rig_config, extrinsics_tables, field_survey_sigma,
                                image_prefixes, with_field_survey_rig, with_field_survey_sigma)
from ..calib.localize import DEFAULT_CENTER_SIGMA_M, DEFAULT_PIXEL_SIGMA_PX
from ..calib.rig_ba import BACKENDS
from ..camera import Camera
from ..dataset import largest_point_sigma
from ..errors import DmaisError
from ..report.layout import write_layout_svg
from ..workspace import Workspace
from . import setting

log = logging.getLogger(__name__)

LAYOUT_LABELS = ("with camera-centre priors (known)", "without priors (unknown)")
#: tables/survey_sigma.csv: per calibration (a camera's intrinsics, the rig), its control points whose
#: survey sigma the dataset gives and whose it estimated, the given sigmas' largest and the estimate (m).
SURVEY_SIGMA_COLUMNS = ("calibration", "points_given", "points_estimated", "sigma_given_max_m",
                        "sigma_estimated_m")


@dataclass(frozen=True)
class Conf:
    """How the rig is calibrated (calib.extrinsics)."""

    use_priors: bool = setting(True, "rig.json from the calibration with the images' RTK camera-centre priors "
                                     "(when they have them)")
    center_sigma_m: float = setting(DEFAULT_CENTER_SIGMA_M, "standard deviation of an RTK camera-centre prior (m)",
                                    above=0)
    pixel_sigma_px: float = setting(0.0, "standard deviation of a marker's pixel, per axis (px); 0: each camera's "
                                         f"eps_calib / sqrt(2), or {DEFAULT_PIXEL_SIGMA_PX} without one", minimum=0)
    backend: str = setting(DEFAULT_BACKEND, "the rig bundle adjuster, pycolmap or scipy (both reach the same "
                                            "optimum)")


#: "paper": with the RTK priors, as the paper's rig; "no_priors": the reprojections alone.
CONFS = {"paper": Conf(), "no_priors": Conf(use_priors=False)}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    """Calibrate with and without priors (when the images have them) and write the results."""
    if conf.backend not in BACKENDS:
        raise DmaisError(f"extrinsics: backend {conf.backend!r} is not one of {', '.join(BACKENDS)}")
    dataset = workspace.dataset
    images = dataset.images_of("extrinsics")
    if images.empty:
        raise DmaisError(f"{dataset.root}: no extrinsics images")
    has_priors = bool(images[list(PRIOR_CENTER)].notna().all(axis=1).any())
    if conf.use_priors and not has_priors:
        log.warning("extrinsics: no camera-centre priors in %s; calibrating without", dataset.root / "images.csv")
    *inputs, intrinsics_std, survey_effect, estimated, pixel_covariance = _inputs(workspace, conf.pixel_sigma_px)
    results = {case: _calibrate(workspace, conf, case, *inputs) for case in ([True, False] if has_priors else [False])}
    chosen = results[conf.use_priors and has_priors]
    unknown = _points_without_sigma(workspace)
    field = field_survey_sigma(estimated)
    field = chosen.ba.survey_sigma_m if field is None else field
    ba = chosen.ba
    if field is not None:
        log.info("extrinsics: the control points' survey sigma, not given for %d of them, estimated as %.2f mm",
                 len(unknown), 1e3 * field)
        intrinsics_std, survey_effect = with_field_survey_sigma(intrinsics_std, survey_effect,
                                                                {c: sigma for c, (sigma, _) in estimated.items()},
                                                                field, unknown)
        ba = with_field_survey_rig(ba, field)
    parameters, covariance = calibration_covariance(ba, intrinsics_std, survey_effect, pixel_covariance)
    written = [workspace.save_rig(chosen.rig, **chosen.extra(), calibration_covariance={
                   "parameters": parameters, "matrix": covariance.tolist()}),
               workspace.save_rig_config(colmap_rig_config(chosen.rig,
                                                           image_prefixes(dataset.images, chosen.rig.camera_names)))]
    written += [workspace.save_rig(result.rig, case="known" if case else "unknown", **result.extra())
                for case, result in results.items()]
    if len(results) == 2:
        written += _write_comparison(workspace, results[True], results[False])
    return written + [workspace.save_table("survey_sigma", _survey_table(workspace, chosen, estimated, unknown, field))]


def _points_without_sigma(workspace: Workspace) -> set[str]:
    """The control points whose survey sigma the dataset does not give."""
    ids = workspace.dataset.control_points.index.astype(str)
    return {point for point, sigma in zip(ids, largest_point_sigma(workspace.dataset.points, ids)) if np.isnan(sigma)}


def _survey_table(workspace: Workspace, chosen: ExtrinsicsResult, estimated: dict[str, tuple[float | None, int]],
                  unknown: set[str], field: float | None) -> pd.DataFrame:
    """tables/survey_sigma.csv (SURVEY_SIGMA_COLUMNS): a row per camera's intrinsics (the points of its
    survey_effect), the rig adjustment's (the points of its adjustment), and the field's, the sigma
    rig.json's calibration covariance carries (`calib.extrinsics.field_survey_sigma`)."""
    points = workspace.dataset.points
    rows = []
    for camera, (sigma, _) in estimated.items():
        seen = list((workspace.load_intrinsics(camera)[1].get("survey_effect") or {}))
        rows.append(_survey_row(camera, seen, points, unknown, sigma))
    rig_points = list(chosen.ba.survey_points)
    rows.append(_survey_row("rig", rig_points, points, unknown, chosen.ba.survey_sigma_m))
    rows.append(_survey_row("field", list(workspace.dataset.control_points.index.astype(str)), points, unknown, field))
    return pd.DataFrame(rows, columns=list(SURVEY_SIGMA_COLUMNS))


def _survey_row(calibration: str, seen: list[str], points: pd.DataFrame, unknown: set[str],
                sigma: float | None) -> dict:
    given = [point for point in seen if point not in unknown]
    sigmas = largest_point_sigma(points, given) if given else np.zeros(0)
    return {"calibration": calibration, "points_given": len(given), "points_estimated": len(seen) - len(given),
            "sigma_given_max_m": float(sigmas.max()) if len(sigmas) else np.nan,
            "sigma_estimated_m": np.nan if sigma is None else sigma}


def _inputs(workspace: Workspace, pixel_sigma_px: float
            ) -> tuple[pd.DataFrame, dict[str, Camera], dict[str, float], dict[str, dict], dict[str, dict],
                       dict[str, tuple[float | None, int]], dict[str, np.ndarray]]:
    """The extrinsics images' observations, the calibrated cameras, each camera's pixel sigma
    (pixel_sigma_px when positive, else from the camera's calibration), and its intrinsics' standard
    deviations, control-point survey effects, the survey sigma it estimated with its observations'
    count and its pixel covariance (its record's `std`, `survey_effect`, `survey_sigma_estimated_m`,
    `n_observations` and `pixel_covariance`, empty or None where it has none: for rig.json's
    `calibration_covariance`)."""
    dataset = workspace.dataset
    images = dataset.images_of("extrinsics")
    observations = workspace.load_observations()
    observations = observations[observations["image"].isin(set(images["image"]))]
    names = [c for c in dataset.cameras if c in set(images["camera"]) or c == dataset.reference_camera]
    cameras, pixel_sigma, std, survey_effect, estimated, pixel_covariance = {}, {}, {}, {}, {}, {}
    for name in names:
        cameras[name], record = workspace.load_intrinsics(name)
        std[name] = record.get("std") or {}
        survey_effect[name] = record.get("survey_effect") or {}
        estimated[name] = (record.get("survey_sigma_estimated_m"), int(record.get("n_observations") or 0))
        if record.get("pixel_covariance") is not None:
            pixel_covariance[name] = np.asarray(record["pixel_covariance"], dtype=float)
        # per-axis pixel sigma from the intrinsic calibration's RMS point distance (eps / sqrt 2)
        eps = record.get("eps_calib_px")
        if pixel_sigma_px > 0:
            pixel_sigma[name] = pixel_sigma_px
        elif eps and np.isfinite(eps) and eps > 0:
            pixel_sigma[name] = float(eps) / np.sqrt(2.0)
        else:
            pixel_sigma[name] = DEFAULT_PIXEL_SIGMA_PX
    return observations, cameras, pixel_sigma, std, survey_effect, estimated, pixel_covariance


def _calibrate(workspace: Workspace, conf: Conf, use_priors: bool, observations: pd.DataFrame,
               cameras: dict[str, Camera], pixel_sigma: dict[str, float]) -> ExtrinsicsResult:
    dataset = workspace.dataset
    log.info("extrinsics: calibrating %s camera-centre priors", "with" if use_priors else "without")
    return calibrate_extrinsics(cameras, dataset.reference_camera, dataset.images_of("extrinsics"), observations,
                                dataset.points, use_priors=use_priors, center_sigma=conf.center_sigma_m,
                                pixel_sigma=pixel_sigma, backend=conf.backend)


def _write_comparison(workspace: Workspace, known: ExtrinsicsResult, unknown: ExtrinsicsResult) -> list[Path]:
    """tab:extrinsics_R, tab:extrinsics_t (with standard deviations and notes), their note and the layout figure."""
    table_R, table_t, note = annotate_tables(*extrinsics_tables(known.rig, unknown.rig), known, unknown)
    log.info("extrinsics: %s", note)
    return [workspace.save_table("extrinsics_R", table_R, float_format="%.6f"),
            workspace.save_table("extrinsics_t", table_t, float_format="%.6f"),
            workspace.save_extrinsics_note(note),
            write_layout_svg(workspace.layout_figure_path, [known.rig, unknown.rig], list(LAYOUT_LABELS),
                             title="Camera layout in the rig frame (fig:extrinsics)")]
