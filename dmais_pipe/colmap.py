"""COLMAP round trip: the calibrated rig and the solved flight frames as a COLMAP sparse model.

The model (`flight_reconstruction`) holds
- cameras: one camera per rig camera, exactly its model (`calib.rig_ba.opencv_params`): OPENCV
  (fx, fy, cx, cy, k1, k2, p1, p2; radial1 is k1 = d, the rest 0) or, for an opencv camera with
  k3 != 0, FULL_OPENCV (k4 = k5 = k6 = 0), with the principal point in COLMAP's
  pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we at (0, 0);
- rig 1: the reference camera as its reference sensor, every other camera with sensor_from_rig =
  cam_from_rig;
- frames: one per solved flight frame (poses.csv), rig_from_world from its quaternion and translation;
- images: one per flight image of a solved frame, named as in rig_config.json (`colmap_image_names`);
  its points2D are the frame's observations (keypoints + 0.5 px), the ones the pose used linked to
  their 3D point;
- points3D: the control and ground points observed by a used observation, at their surveyed
  coordinates, point3D_id k + 1 for the k-th point id in sorted order.

`write_model` writes it as COLMAP text or binary files (atomically: into a temporary folder beside
the target, then each file renamed into place).
"""

from __future__ import annotations

import os
import posixpath
import tempfile
from pathlib import Path

import pandas as pd

from .calib.rig_ba import add_colmap_frame, add_colmap_rig, colmap_pixels
from .errors import DmaisError
from .rig import Rig
from .workspace import rig_from_world_of

FORMATS = ("text", "binary")
#: The files of a COLMAP sparse model (COLMAP >= 3.12: with rigs and frames), by format.
MODEL_FILES = {fmt: tuple(f"{name}.{'txt' if fmt == 'text' else 'bin'}"
                          for name in ("cameras", "images", "points3D", "rigs", "frames")) for fmt in FORMATS}
RIG_ID = 1  # the rig add_colmap_rig adds


def flight_reconstruction(rig: Rig, poses: pd.DataFrame, images: pd.DataFrame, names: dict[str, str],
                          observations: pd.DataFrame, points: pd.DataFrame):
    """The pycolmap.Reconstruction of the rig and the solved frames (see the module's docstring).

    poses: rows with frame, qw, qx, qy, qz, tx, ty, tz (rig_from_world); images: the dataset's
    images (image, camera, stage, placement); names: COLMAP name per image; observations: rows with
    frame, image, point_id, u, v, used (the poses' per-observation file); points: x, y, z indexed by
    point_id. Flight images of cameras outside the rig are left out.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    order = rig.cameras_reference_first
    camera_ids = add_colmap_rig(rec, rig.cameras, order, {c: rig.cam_from_rig[c].inverse() for c in order})
    used = observations[observations["used"]]
    missing = sorted(set(used["point_id"]) - set(points.index))
    if missing:
        raise DmaisError(f"COLMAP export: observed point(s) {', '.join(missing[:5])} are not control or ground points")
    tracks = {p: pycolmap.Track() for p in sorted(set(used["point_id"]))}
    flight = images[(images["stage"] == "flight") & images["camera"].isin(camera_ids)]
    by_frame = {frame: rows for frame, rows in flight.groupby("placement", sort=False)}
    by_image = {image: rows for image, rows in observations.groupby("image", sort=False)}
    image_id = 0
    for frame_id, row in enumerate(poses.itertuples(index=False), 1):
        frame_images = []
        for image in by_frame.get(row.frame, flight.iloc[:0]).itertuples(index=False):
            image_id += 1
            obs = by_image.get(image.image, observations.iloc[:0])
            uv = colmap_pixels(obs[["u", "v"]].to_numpy(dtype=float).reshape(-1, 2))
            frame_images.append(pycolmap.Image(name=names[image.image], camera_id=camera_ids[image.camera],
                                               image_id=image_id, keypoints=uv))
            for point2D_idx, (point_id, is_used) in enumerate(zip(obs["point_id"], obs["used"])):
                if is_used:
                    tracks[point_id].add_element(image_id, point2D_idx)
        add_colmap_frame(rec, frame_id, RIG_ID, rig_from_world_of(row), frame_images)
    for point_id, track in tracks.items():  # ids 1, 2, ... in sorted point-id order
        rec.add_point3D(points.loc[point_id, ["x", "y", "z"]].to_numpy(dtype=float), track)
    rec.update_point_3d_errors()
    return rec


def write_model(reconstruction, folder: str | Path, fmt: str) -> list[Path]:
    """Write the model into `folder` as COLMAP text or binary files; returns the files written."""
    if fmt not in FORMATS:
        raise DmaisError(f"COLMAP export: format {fmt!r} is not one of {', '.join(FORMATS)}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory(dir=folder, prefix=".colmap-") as scratch:
        (reconstruction.write_text if fmt == "text" else reconstruction.write_binary)(scratch)
        for name in MODEL_FILES[fmt]:
            os.replace(Path(scratch) / name, folder / name)
            written.append(folder / name)
    return written


def camera_prefixes(images: pd.DataFrame, cameras) -> dict[str, str]:
    """The image-name prefix per camera by which COLMAP tells a rig's cameras apart (rig_config.json).

    images: rows with camera and path ('' when the image has no file); cameras: the rig's camera
    names. When every camera's image files lie in a folder of its own (the layout of
    docs/dataset.md, "images/C0/0001.png"), that folder ("images/C0/"); otherwise (cameras sharing
    a folder, as the simulator's images/<stage>/<image>.png, or no files at all) "<camera>/".
    """
    cameras = list(cameras)
    folders = {}
    for name in cameras:
        paths = [p for p in images.loc[images["camera"] == name, "path"] if isinstance(p, str) and p]
        folders[name] = _common_folder(paths)
    values = list(folders.values())
    nested = any(a.startswith(b) for i, a in enumerate(values) for j, b in enumerate(values) if i != j)
    if "" in values or nested:
        return {name: f"{name}/" for name in cameras}
    return folders


def colmap_image_names(images: pd.DataFrame, prefixes: dict[str, str]) -> dict[str, str]:
    """COLMAP image name per image of a camera of `prefixes` (`camera_prefixes`), starting with its
    camera's prefix: the dataset's path when the prefixes are the cameras' folders, else "<camera>/"
    + the path (a COLMAP image folder then holds, per camera, a link named <camera> to the dataset
    folder); an image without a file gets its prefix + its image id.
    """
    names = {}
    for image, camera, path in zip(images["image"], images["camera"], images["path"]):
        if camera not in prefixes:
            continue
        has_file = isinstance(path, str) and bool(path)
        if has_file and path.startswith(prefixes[camera]):
            names[image] = path
        else:
            names[image] = prefixes[camera] + (path if has_file else image)
    if len(set(names.values())) < len(names):
        raise DmaisError("COLMAP export: two images would get the same COLMAP name; give each camera's image "
                         "files a folder of their own (docs/dataset.md, images.csv)")
    return names


def _common_folder(paths: list[str]) -> str:
    """The deepest folder holding every path, with a trailing "/" ('' for the dataset's top folder)."""
    folder = posixpath.commonpath([posixpath.dirname(p) for p in paths]) if paths else ""
    return folder + "/" if folder else ""
