"""`dmais export-colmap`: the calibrated rig and the solved flight frames as a COLMAP sparse model (colmap).

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

from ..calib.extrinsics import colmap_rig_config
from ..colmap import FORMATS, camera_prefixes, colmap_image_names, flight_reconstruction, write_model
from ..errors import DmaisError
from ..files import write_json_atomic
from ..workspace import Workspace, pose_observations_path
from . import setting

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
