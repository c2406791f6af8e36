"""`dmais summarize DATASET --out REPORTS`: what a dataset holds, as CSV and a self-contained HTML page.

For simulated datasets (with `truth/`) the page also shows the truth rig, the noise budget and one
rendered marker beside its true centre. This module prepares the page's values (tables as text cells,
the marker as a PNG data URI); its markup and prose are the template templates/dataset_page.html.j2,
rendered autoescaped by report.page like the accuracy report.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ..dataset import Dataset
from ..files import write_bytes_atomic, write_csv_atomic, write_text_atomic
from ..geometry import euler_zyx_from_rotation
from ..rig import Rig
from .page import Image, Table, render, table_of


def summarize(dataset_dir: str | Path, out: str | Path) -> Path:
    """Write dataset_summary.csv, dataset.html (and marker_example.png when possible) to `out`."""
    dataset = Dataset.load(dataset_dir)
    out = Path(out)
    table = summary_table(dataset)
    write_csv_atomic(out / "dataset_summary.csv", table)
    example = marker_example(dataset)
    if example is not None:
        write_bytes_atomic(out / "marker_example.png", example[0])
    page = render("dataset_page.html.j2", **page_values(dataset, table, example))
    return write_text_atomic(out / "dataset.html", page)


def page_values(dataset: Dataset, summary: pd.DataFrame, example: tuple[bytes, str] | None) -> dict:
    """The context of dataset_page.html.j2; the truth rig, noise budget and marker are None when absent."""
    truth = dataset.truth_dir
    rig = Rig.load(truth / "rig.json") if (truth / "rig.json").is_file() else None
    simulation = truth / "simulation.yaml"
    config = yaml.safe_load(simulation.read_text()) if simulation.is_file() else None
    return {"dataset_name": dataset.name, "images": _cells(summary), "points": point_counts(dataset),
            "rig": None if rig is None else _cells(rig_table(rig)),
            "noise": None if config is None else _cells(noise_table(config)),
            "marker": None if example is None else marker_figure(*example)}


def point_counts(dataset: Dataset) -> dict[str, str]:
    """The Points section's numbers: control and ground points, flight frames, the marker size (m)."""
    return {"control": str(len(dataset.control_points)), "ground": str(len(dataset.ground_points)),
            "frames": str(len(dataset.frames)), "marker_size_m": f"{dataset.marker_size_m:g}"}


def marker_figure(png: bytes, caption: str) -> dict:
    """The rendered marker (marker_example's PNG) as an embedded image, with its caption."""
    return {"image": Image.data_uri(png, "image/png", alt="marker"), "caption": caption}


def summary_table(dataset: Dataset) -> pd.DataFrame:
    """Per stage and camera: images, images with files, observations given by the dataset."""
    images = dataset.images.assign(has_file=dataset.images["path"] != "")
    counts = dataset.observations.groupby("image").size()
    images = images.assign(observations=images["image"].map(counts).fillna(0).astype(int))
    table = images.groupby(["stage", "camera"], sort=True).agg(
        images=("image", "size"), image_files=("has_file", "sum"), observations=("observations", "sum"))
    return table.reset_index()


def rig_table(rig: Rig) -> pd.DataFrame:
    """Per camera of the rig: its intrinsics, rig_from_cam as ZYX Euler angles (deg), tilt (deg) and centre (m).
    With an opencv camera in the rig, also each camera's model and k2, p1, p2, k3 (d is k1)."""
    rows = []
    richer = any(camera.model != "radial1" for camera in rig.cameras.values())
    for name, camera in rig.cameras.items():
        rig_from_cam = rig.cam_from_rig[name].inverse()
        z, y, x = np.degrees(euler_zyx_from_rotation(rig_from_cam.R))
        tilt = np.degrees(np.arccos(np.clip(rig_from_cam.R[2, 2], -1.0, 1.0)))
        lens = {"model": camera.model, **dict(zip(("k2", "p1", "p2", "k3"), camera.distortion[1:]))} if richer else {}
        rows.append({"camera": name, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                     "d": camera.d, **lens, "euler_zyx_deg": f"({z:.3f}, {y:.3f}, {x:.3f})", "tilt_deg": round(tilt, 3),
                     "center_m": "({:.3f}, {:.3f}, {:.3f})".format(*rig_from_cam.t)})
    return pd.DataFrame(rows)


def marker_example(dataset: Dataset, zoom_half_size: int = 6) -> tuple[bytes, str] | None:
    """PNG of the smallest rendered marker, whole and zoomed to its centre, with the true centre marked."""
    truth_file = dataset.truth_dir / "observations.csv"
    rendered = dataset.images[dataset.images["path"] != ""]
    if not truth_file.is_file() or rendered.empty:
        return None
    truth = pd.read_csv(truth_file, dtype={"image": str, "point_id": str})
    truth = truth[truth["image"].isin(rendered["image"])]
    if truth.empty:
        return None
    row = truth.loc[truth["size_px"].idxmin()]
    image = dataset.read_image(row["image"])
    u, v = float(row["u"]), float(row["v"])
    whole = _crop(image, u, v, int(0.7 * row["size_px"]))
    zoom = _crop(image, u, v, zoom_half_size)
    return _plot_crops([whole, zoom]), (
        f"Image {row['image']}, point {row['point_id']}, marker ~{row['size_px']:.0f} px across; left the whole "
        f"marker, right its centre pixel by pixel. The red cross is the true projection of the control point, "
        f"({u:.2f}, {v:.2f}) px (the centre of a pixel is at integer coordinates).")


def _crop(image: np.ndarray, u: float, v: float, half: int) -> tuple[np.ndarray, float, float, int, int]:
    x0, y0 = max(int(round(u)) - half, 0), max(int(round(v)) - half, 0)
    return image[y0: int(round(v)) + half + 1, x0: int(round(u)) + half + 1], u, v, x0, y0


def _plot_crops(crops) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(crops), figsize=(4 * len(crops), 4), dpi=100)
    for ax, (crop, u, v, x0, y0) in zip(axes, crops):
        extent = (x0 - 0.5, x0 + crop.shape[1] - 0.5, y0 + crop.shape[0] - 0.5, y0 - 0.5)
        ax.imshow(crop, cmap="gray", vmin=0, vmax=255, interpolation="nearest", extent=extent)
        ax.plot([u], [v], marker="+", color="red", markersize=18, mew=1.5)
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def noise_table(config: dict) -> pd.DataFrame:
    """The simulator's noise sources (truth/simulation.yaml) and their standard deviations, as text."""
    fl = config["flight"]
    rows = [
        ("control points (survey)", f"{config['field']['survey_sigma_m'] * 1000:g} mm per axis"),
        ("calibration markers, not rendered", f"{config['calibration_pixel_sigma_px']:g} px per axis"),
        ("calibration priors", f"centre {config['calibration_priors']['center_sigma_m'] * 100:g} cm, "
                               f"attitude {config['calibration_priors']['attitude_sigma_deg']:g} deg"),
        ("ground markers (RTK)", "{:g}, {:g}, {:g} cm (x, y, z)".format(*np.multiply(fl["survey_sigma_m"], 100))),
        ("in-flight mount change", f"{fl['mount_sigma_arcmin']:g}' per axis per group, "
                                   f"{fl['vibration_sigma_arcmin']:g}' per frame"),
        ("flight markers, not rendered", f"{fl['pixel_sigma_px']:g} px per axis"),
        ("POS position", "{:g}, {:g}, {:g} cm; lever arm {} m".format(
            *np.multiply(fl["pos_sigma_m"], 100), fl["lever_arm_m"])),
        ("INS attitude prior", f"{fl['ins_attitude_sigma_deg']:g} deg per axis"),
    ]
    return pd.DataFrame(rows, columns=["source", "standard deviation"])


def _cells(frame: pd.DataFrame) -> Table:
    """The frame as the page's table: floats to 4 significant digits, as this page always showed them."""
    return table_of(frame, number=lambda x: f"{x:.4g}")
