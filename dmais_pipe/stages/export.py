"""`dmais export-colmap`: the calibrated rig and the solved flight frames as a COLMAP sparse model (colmap);
`dmais export-geojson` (`run_geojson`): the solved frames and the cameras' ground footprints as GeoJSON
(geojson.py), for a dataset with a crs.

Writes RESULTS/colmap/<format>/{cameras,images,points3D,rigs,frames}.{txt,bin} for each format of
the conf, and RESULTS/colmap/rig_config.json, the rig config whose image-name prefixes match the
model's image names. When the names are "<camera>/<dataset path>" (cameras sharing image folders,
`colmap.colmap_image_names`), RESULTS/colmap/images/<camera> are links to the dataset folder, so
that RESULTS/colmap/images serves as COLMAP's image folder; otherwise it is the dataset folder.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calib.extrinsics import colmap_rig_config
from ..colmap import FORMATS, camera_prefixes, colmap_image_names, flight_reconstruction, write_model
from ..errors import DmaisError
from ..evaluate import subset_cameras
from ..files import write_json_atomic
from ..geometry import rotation_from_quat
from ..geojson import collection, feature, footprint, polygon_ring
from ..workspace import CENTER, POSE_GEO_COLUMNS, QUAT, TRANSLATION, Workspace, pose_observations_path
from . import setting
from .pose import subset_label

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Conf:
    """What the export writes."""

    formats: tuple = setting(FORMATS, "the COLMAP model's file formats")


CONFS = {"default": Conf()}


def run(workspace: Workspace, conf: Conf = Conf()) -> list[Path]:
    """The model of poses.csv and its observations, in every format of `conf`, and its rig config."""
    bad = [f for f in conf.formats if f not in FORMATS]
    if bad or not conf.formats:
        raise DmaisError(f"export-colmap: formats must be among {', '.join(FORMATS)}, got {', '.join(conf.formats)}")
    dataset, rig = workspace.dataset, workspace.load_rig()
    poses = workspace.load_poses()
    observations = workspace.load_pose_observations()
    if observations is None:
        raise DmaisError(f"{pose_observations_path(workspace.poses_path())}: missing; run `dmais pose` again")
    prefixes = camera_prefixes(dataset.images, rig.camera_names)
    names = colmap_image_names(dataset.images, prefixes)
    reconstruction = flight_reconstruction(rig, poses, dataset.images, names, observations, dataset.points)
    log.info("export-colmap: %d frames, %d images, %d points, mean reprojection error %.3f px",
             reconstruction.num_frames(), reconstruction.num_images(), reconstruction.num_points3D(),
             reconstruction.compute_mean_reprojection_error())
    written = []
    for fmt in conf.formats:
        written += write_model(reconstruction, workspace.colmap_model_dir(fmt), fmt)
    written.append(write_json_atomic(workspace.colmap_dir / "rig_config.json", colmap_rig_config(rig, prefixes)))
    images = zip(dataset.images["image"], dataset.images["path"])
    if any(path and names.get(image, path) != path for image, path in images):
        _link_cameras(workspace, list(prefixes))
    return written


#: The poses columns a frame's point carries (with its camera set's label and x, y, z in crs).
POINT_PROPERTIES = ("frame", "group", "cameras", "n_points", "eps_proj_px", "certified", *POSE_GEO_COLUMNS)


def run_geojson(workspace: Workspace) -> list[Path]:
    """RESULTS/geojson/frames.geojson (a point per solved frame of poses.csv and of every camera
    subset's file, `camera_set` its label) and RESULTS/geojson/footprints.geojson (each camera's
    ground footprint in each frame of poses.csv)."""
    dataset, rig = workspace.dataset, workspace.load_rig()
    if dataset.geo is None:
        raise DmaisError(f"export-geojson: {dataset.root / 'dataset.yaml'} names no crs; GeoJSON needs the "
                         "dataset's coordinates on the Earth (docs/dataset.md, \"Real-world coordinates\")")
    sets = {subset_label(rig, rig.camera_names): workspace.poses_path(), **workspace.subset_labels()}
    points = []
    for label, path in sets.items():
        poses = workspace.load_poses(path, subset_cameras(label, rig) if path != workspace.poses_path() else None)
        points += _frame_points(workspace, poses, label)
    whole = workspace.load_poses()
    observations = workspace.load_pose_observations()
    if observations is None:
        raise DmaisError(f"{pose_observations_path(workspace.poses_path())}: missing; run `dmais pose` again")
    polygons = _footprints(workspace, rig, whole, observations)
    folder = workspace.root / "geojson"
    log.info("export-geojson: %d frame points, %d footprints -> %s", len(points), len(polygons), folder)
    return [write_json_atomic(folder / "frames.geojson", collection(points, "frames")),
            write_json_atomic(folder / "footprints.geojson", collection(polygons, "footprints"))]


def _frame_points(workspace: Workspace, poses, label: str) -> list[dict]:
    """A Point feature per row of `poses` (Workspace.load_poses) of the camera set `label`."""
    if "lat_deg" not in poses.columns:
        raise DmaisError(f"export-geojson: the poses of camera set {label} have no lat_deg; run `dmais pose` again")
    in_crs = workspace.dataset.geo.crs_from_enu(poses[list(CENTER)].to_numpy(float))
    features = []
    for k, row in enumerate(poses[list(POINT_PROPERTIES)].to_dict("records")):
        properties = {"camera_set": label, **row, **dict(zip(("x", "y", "z"), map(float, in_crs[k])))}
        properties["certified"] = str(properties["certified"]).lower() == "true"
        features.append(feature("Point", [row["lon_deg"], row["lat_deg"], row["h_m"]],
                                {key: (int(v) if key == "n_points" else v) for key, v in properties.items()}))
    return features


def _footprints(workspace: Workspace, rig, poses, observations) -> list[dict]:
    """A Polygon feature per frame of `poses` and camera (geojson.footprint), on the level plane
    through the mean of the ground points the frame's pose used."""
    geo, points = workspace.dataset.geo, workspace.dataset.points
    used = observations[observations["used"]]
    mean_point = points.loc[used["point_id"], ["x", "y", "z"]].groupby(used["frame"].to_numpy()).mean()
    features, missed = [], []
    for row in poses.itertuples(index=False):
        R = rotation_from_quat(np.array([getattr(row, c) for c in QUAT], dtype=float))
        t = np.array([getattr(row, c) for c in TRANSLATION], dtype=float)
        point = mean_point.loc[row.frame].to_numpy(float)
        normal = -geo.ned_from_enu(point[None])[0, 2]  # up: minus NED's down
        for camera in rig.camera_names:
            outline = footprint(rig, camera, R, t, point, normal)
            if outline is None:
                missed.append(f"{row.frame}/{camera}")
                continue
            geodetic = geo.geodetic_from_enu(outline)
            features.append(feature("Polygon", [polygon_ring(geodetic[:, [1, 0, 2]])],
                                    {"frame": row.frame, "group": row.group, "camera": camera}))
    if missed:
        log.warning("export-geojson: %d footprint(s) left out, a border ray missing the ground plane: %s",
                    len(missed), ", ".join(missed[:5]) + (", ..." if len(missed) > 5 else ""))
    return features


def _link_cameras(workspace: Workspace, cameras: list[str]) -> None:
    """RESULTS/colmap/images/<camera> -> the dataset folder, for names "<camera>/<dataset path>"."""
    folder = workspace.colmap_dir / "images"
    folder.mkdir(parents=True, exist_ok=True)
    target = workspace.dataset.root.resolve()
    for camera in cameras:
        partial = folder / f".{camera}.link"
        partial.unlink(missing_ok=True)
        os.symlink(target, partial, target_is_directory=True)
        os.replace(partial, folder / camera)
