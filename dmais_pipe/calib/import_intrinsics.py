"""Intrinsics calibrated elsewhere: OpenCV's calibration files and COLMAP cameras files.

Both describe a pinhole camera (fx, fy, cx, cy) with OpenCV's distortion coefficients (k1, k2, p1,
p2, k3, k4, k5, k6, s1..s4, tau_x, tau_y; COLMAP's PINHOLE/RADIAL/OPENCV/FULL_OPENCV families are
the same model with some coefficients held at zero). `convert_camera` turns it into our Camera of
the dataset camera's model (camera.py): radial1 is that model with k1 = d and every other
coefficient zero, opencv with k1, k2, p1, p2, k3 and k4..tau_y zero. A file whose other
coefficients are zero converts exactly (the model's coefficients copied; residual ~1e-12 px,
rounding). A richer one is fitted: over a grid of pixels covering the image, the undistorted
normalized points x of the richer model are taken and the model's coefficients c minimize
sum |ours(x; c) - theirs(x)|^2, which is linear in c (the distortion is a sum of the coefficients
times functions of x, the columns of `project_unmasked`'s parameter Jacobian), e.g. radial1's

    ours(x; d) - (fx x + cx) = d fx x |x|^2,  the same in v with fy, cy.

The residual (max / RMS px over the grid) is the conversion's cost; above `max_residual_px` the
camera is refused, naming the largest coefficient that the model cannot represent.

A converted opencv model that folds inside the image (`Camera.folds_in_image`) has no observations
here to show that the fold lies beyond them (as a calibration's must, `calib.intrinsics.Plausibility`),
so the file is judged by the region where it is one-to-one (`Camera.one_to_one_region`): covering at
least MIN_ONE_TO_ONE_FRACTION of the image, it is accepted with a warning giving the region, which the
record keeps ("one_to_one"; pixels outside undistort to NaN). Real board calibrations fold, if at
all, in the corners no board reached (cv2.calibrateCamera on OpenCV's stereo sample: 0.1% of the
image beyond the fold; k1 -0.365, k2 0.145, k3 -0.029 on 1920 x 1080 at f = 1000 px: 15%); a
polynomial that turns back within the central half of its image is not a lens calibration.

Pixel conventions: OpenCV's files use ours (centre of the top-left pixel at (0, 0)); COLMAP's put
it at (0.5, 0.5), so its principal point is shifted by -0.5 px.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera, OneToOneRegion, project_unmasked
from ..errors import DmaisError
from .rig_ba import COLMAP_PIXEL_OFFSET

log = logging.getLogger(__name__)

#: OpenCV's distortion coefficients, in its order.
OPENCV_COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
DEFAULT_MAX_RESIDUAL_PX = 0.1
#: An imported opencv model must be one-to-one over at least this share of its image.
MIN_ONE_TO_ONE_FRACTION = 0.5
GRID_STEPS = 33  # grid points per image side for the fit
#: How a refusal names each of our models.
MODEL_DESCRIPTIONS = {"radial1": "one-coefficient model", "opencv": "opencv model (k1, k2, p1, p2, k3)"}

#: COLMAP models that are OpenCV's pinhole model with some coefficients: parameter names in
#: COLMAP's order; "f" is fx = fy.
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


@dataclass
class ForeignCamera:
    """A camera as another tool calibrated it: pinhole in our pixel convention plus OpenCV's
    distortion coefficients by name (absent ones are zero); width, height 0 where the file has no
    image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    model: str
    distortion: dict[str, float] = field(default_factory=dict)

    def coefficients(self) -> np.ndarray:
        """(14,) OpenCV's distortion vector."""
        return np.array([self.distortion.get(name, 0.0) for name in OPENCV_COEFFICIENTS])


@dataclass
class Conversion:
    camera: Camera
    residual_max_px: float
    residual_rms_px: float
    one_to_one: OneToOneRegion | None = None  # where the camera folds inside its image


# ------------------------------------------------------------------------------ reading


def split_pair(source: Path | str) -> tuple[Path, str | None]:
    """(file, pair) of an --import argument: FILE, or FILE:M<n> naming the pair M<n>, D<n> of a
    stereo calibration file (OpenCV's stereo_calib sample writes M1, D1, M2, D2)."""
    match = re.fullmatch(r"(.+):(M[0-9]+)", str(source))
    if match and not Path(source).is_file():
        return Path(match.group(1)), match.group(2)
    return Path(source), None


def read_opencv_file(path: Path, pair: str | None = None) -> ForeignCamera:
    """A camera of an OpenCV calibration file (cv2.FileStorage YAML/XML/JSON): camera_matrix,
    distortion_coefficients, image_width, image_height, as OpenCV's calibration sample writes
    them; or, given `pair` M<n>, the matrices M<n>, D<n> of a stereo calibration (OpenCV's
    stereo_calib sample), whose files have no image size (width, height 0: the dataset's)."""
    import cv2

    if not Path(path).is_file():
        raise DmaisError(f"{path}: no such file")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        opened = storage.isOpened()
    except (cv2.error, SystemError) as error:  # OpenCV's parser errors surface as either
        raise DmaisError(f"{path}: not an OpenCV FileStorage file ({_first_line(error)})") from None
    if not opened:
        raise DmaisError(f"{path}: not an OpenCV FileStorage file")
    names = ("camera_matrix", "distortion_coefficients") if pair is None else (pair, "D" + pair[1:])
    if pair is None and storage.getNode("camera_matrix").empty():
        pairs = [key for key in storage.root().keys() if re.fullmatch(r"M[0-9]+", key)]
        if pairs:
            raise DmaisError(f"{path}: a stereo calibration ({', '.join(pairs)}); name the camera's pair, e.g. "
                             f"--import {path}:{pairs[0]}")
    K = _matrix(storage, names[0], path)
    coefficients = _matrix(storage, names[1], path).ravel()
    if K.shape != (3, 3) or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise DmaisError(f"{path}: {names[0]} {K.tolist()} is not a 3x3 intrinsic matrix")
    if K[0, 1] != 0:
        raise DmaisError(f"{path}: {names[0]} has skew {K[0, 1]:g}; our model has none")
    if len(coefficients) not in (4, 5, 8, 12, 14):
        raise DmaisError(f"{path}: {names[1]} has {len(coefficients)} values; OpenCV's have 4, 5, 8, 12 or 14")
    sized = pair is None or not storage.getNode("image_width").empty()
    size = [_integer(storage, key, path) if sized else 0 for key in ("image_width", "image_height")]
    model = "OpenCV" if pair is None else f"OpenCV stereo {pair}"
    return ForeignCamera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), *size, model=model,
                         distortion=dict(zip(OPENCV_COEFFICIENTS, map(float, coefficients))))


def read_colmap_cameras(path: Path) -> dict[int, ForeignCamera]:
    """The cameras of a COLMAP cameras.txt or cameras.bin, by camera id (read by pycolmap)."""
    import pycolmap

    path = Path(path)
    if not path.is_file():
        raise DmaisError(f"{path}: no such file")
    text = path.suffix == ".txt"
    if path.suffix not in (".txt", ".bin"):
        raise DmaisError(f"{path}: a COLMAP cameras file is cameras.txt or cameras.bin")
    reconstruction = pycolmap.Reconstruction()
    with tempfile.TemporaryDirectory() as scratch:  # pycolmap reads models: add an empty one around the file
        shutil.copyfile(path, Path(scratch) / f"cameras{path.suffix}")
        for name in ("images", "points3D"):
            (Path(scratch) / f"{name}{path.suffix}").write_bytes(b"" if text else struct.pack("<Q", 0))
        try:
            (reconstruction.read_text if text else reconstruction.read_binary)(scratch)
        except Exception as error:  # pycolmap raises ValueError/RuntimeError on malformed files
            raise DmaisError(f"{path}: not a COLMAP cameras file ({_first_line(error)})") from None
    if not reconstruction.cameras:
        raise DmaisError(f"{path}: holds no camera")
    return {int(camera_id): _from_colmap(camera, path) for camera_id, camera in reconstruction.cameras.items()}


def _from_colmap(camera, path: Path) -> ForeignCamera:
    model = camera.model.name
    if model not in COLMAP_MODELS:
        raise DmaisError(f"{path}: camera {camera.camera_id}: COLMAP model {model} is not a pinhole model with "
                         f"OpenCV distortion (supported: {', '.join(COLMAP_MODELS)})")
    values = dict(zip(COLMAP_MODELS[model], map(float, camera.params)))
    fx = values.get("fx", values.get("f"))
    fy = values.get("fy", values.get("f"))
    distortion = {k: v for k, v in values.items() if k in OPENCV_COEFFICIENTS}
    return ForeignCamera(fx, fy, values["cx"] - COLMAP_PIXEL_OFFSET, values["cy"] - COLMAP_PIXEL_OFFSET,
                         int(camera.width), int(camera.height), model=f"COLMAP {model}", distortion=distortion)


def _matrix(storage, key: str, path: Path) -> np.ndarray:
    node = storage.getNode(key)
    matrix = None if node.empty() else node.mat()
    if matrix is None:
        raise DmaisError(f"{path}: missing matrix {key}")
    matrix = np.asarray(matrix, dtype=float)
    if not np.all(np.isfinite(matrix)):
        raise DmaisError(f"{path}: {key} holds a value that is not a finite number")
    return matrix


def _integer(storage, key: str, path: Path) -> int:
    node = storage.getNode(key)
    value = None if node.empty() else node.real()
    if value is None or value != int(value) or value <= 0:
        raise DmaisError(f"{path}: missing or invalid {key} (a positive integer)")
    return int(value)


def _first_line(error: Exception) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__


# ------------------------------------------------------------------------------ conversion


def convert_camera(foreign: ForeignCamera, name: str, model: str = "radial1",
                   max_residual_px: float = DEFAULT_MAX_RESIDUAL_PX) -> Conversion:
    """Our Camera of `model` closest to `foreign` (fx, fy, cx, cy kept; the model's distortion
    coefficients copied when the file has no others, else fitted: see the module docstring).

    Raises DmaisError naming the camera and its largest non-representable coefficient when the fit
    leaves more than `max_residual_px` anywhere on the grid, or when the converted opencv model folds
    back inside the central part of the image (`_checked_region`; one folding nearer the corners is
    accepted with a warning and its one-to-one region).
    """
    pinhole = Camera(foreign.fx, foreign.fy, foreign.cx, foreign.cy, 0.0, foreign.width, foreign.height, model)
    own = OPENCV_COEFFICIENTS[:len(pinhole.parameter_names) - 4]  # the file's names of the model's coefficients
    rays, theirs = _grid_projections(foreign)
    # ours at zero distortion, and its derivatives by the distortion coefficients: the model is linear in them
    linear, _, J = project_unmasked(rays, pinhole, jacobian=True)
    columns = [np.ascontiguousarray(J[:, :, k]) for k in range(4, J.shape[2])]  # (n, 2) each
    if not any(v for k, v in foreign.distortion.items() if k not in own):
        values = [foreign.distortion.get(k, 0.0) for k in own]  # the model's own coefficients: exact
    else:
        values = _least_squares(columns, theirs - linear)
    fitted = linear + sum(value * column for value, column in zip(values, columns))
    residual = np.linalg.norm(fitted - theirs, axis=1)
    camera = pinhole.with_parameters([foreign.fx, foreign.fy, foreign.cx, foreign.cy, *values])
    conversion = Conversion(camera, float(residual.max()), float(np.sqrt(np.mean(residual**2))))
    if conversion.residual_max_px > max_residual_px:
        raise _not_representable(foreign, name, conversion, own, max_residual_px)
    if camera.model != "radial1" and camera.folds_in_image:
        conversion.one_to_one = _checked_region(camera, name)
    return conversion


def _checked_region(camera: Camera, name: str) -> OneToOneRegion:
    """The one-to-one region of an imported camera that folds inside its image, with a warning; a
    DmaisError where it covers less than MIN_ONE_TO_ONE_FRACTION of the image."""
    region = camera.one_to_one_region()
    if not region.image_fraction >= MIN_ONE_TO_ONE_FRACTION:
        raise DmaisError(f"camera {name}: the imported {camera.model} model folds back inside the central part of "
                         f"the image ({region.describe()}; at least {MIN_ONE_TO_ONE_FRACTION:.0%} needed); not a lens "
                         "calibration")
    log.warning("camera %s: the imported %s model folds back inside the image: %s. Pixels outside it undistort to "
                "NaN", name, camera.model, region.describe())
    return region


def _grid_projections(foreign: ForeignCamera) -> tuple[np.ndarray, np.ndarray]:
    """Rays (n, 3) (x, y, 1) of a GRID_STEPS x GRID_STEPS grid of pixels covering the image, undistorted
    by `foreign`'s model, and their pixels (n, 2) by that model (OpenCV's projection)."""
    import cv2

    K = np.array([[foreign.fx, 0.0, foreign.cx], [0.0, foreign.fy, foreign.cy], [0.0, 0.0, 1.0]])
    coefficients = foreign.coefficients()
    u, v = np.meshgrid(np.linspace(-0.5, foreign.width - 0.5, GRID_STEPS),
                       np.linspace(-0.5, foreign.height - 0.5, GRID_STEPS))
    grid = np.column_stack([u.ravel(), v.ravel()])
    # OpenCV's iterative inverse, approximate: the fit compares both models at these points, so they need
    # only cover the image
    xy = cv2.undistortPoints(grid.reshape(-1, 1, 2), K, coefficients).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays, cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, coefficients)[0].reshape(-1, 2)


def _not_representable(foreign: ForeignCamera, name: str, conversion: Conversion, own: tuple[str, ...],
                       max_residual_px: float) -> DmaisError:
    """The refusal of a conversion that leaves too much, naming the file's largest coefficient that the
    model lacks (`own`: the file's names of the model's coefficients)."""
    extra = {k: v for k, v in foreign.distortion.items() if k not in own and v != 0}
    worst = max(extra, key=lambda k: abs(extra[k])) if extra else own[0]
    extra.setdefault(worst, foreign.distortion.get(worst, 0.0))
    camera = conversion.camera
    best = ", ".join(f"{k} = {v:.6g}" for k, v in zip(camera.parameter_names[4:], camera.parameters[4:]))
    return DmaisError(f"camera {name}: {worst} = {extra[worst]:.6g} is not representable by the "
                      f"{MODEL_DESCRIPTIONS[camera.model]}: the best {best} leaves {conversion.residual_max_px:.3g} "
                      f"px max, {conversion.residual_rms_px:.3g} px RMS over the image (limit {max_residual_px:g} px)")


def one_coefficient_camera(foreign: ForeignCamera, name: str,
                           max_residual_px: float = DEFAULT_MAX_RESIDUAL_PX) -> Conversion:
    """`convert_camera` into the radial1 model (the paper's one coefficient d)."""
    return convert_camera(foreign, name, "radial1", max_residual_px)


def _least_squares(columns: list[np.ndarray], target: np.ndarray) -> list[float]:
    """The coefficients c (m,) minimizing |sum_j c_j columns[j] - target|^2; columns (n, 2) each,
    target (n, 2)."""
    if len(columns) == 1:  # the closed form (radial1's d, bit for bit as it always was)
        return [float(np.sum(columns[0] * target) / np.sum(columns[0] ** 2))]
    A = np.column_stack([column.ravel() for column in columns])
    scale = np.linalg.norm(A, axis=0)  # r^2, r^4, r^6 differ by orders of magnitude on a narrow field
    scale[scale == 0] = 1.0
    solution = np.linalg.lstsq(A / scale, target.ravel(), rcond=None)[0] / scale
    return [float(value) for value in solution]


def imported_record(name: str, conversion: Conversion, foreign: ForeignCamera, source: Path) -> dict:
    """The intrinsics/<camera>.json record of an imported camera (the calibration's own fields empty)."""
    return {"camera": name, **conversion.camera.to_dict(), "std": {}, "eps_calib_px": None, "eps_eval_px": None,
            "n_images": 0, "n_observations": 0, "method": f"imported from {source}",
            "imported": {"file": str(source), "model": foreign.model, "fx": foreign.fx, "fy": foreign.fy,
                         "cx": foreign.cx, "cy": foreign.cy, "distortion": foreign.distortion,
                         "residual_max_px": conversion.residual_max_px,
                         "residual_rms_px": conversion.residual_rms_px},
            **({} if conversion.one_to_one is None else {"one_to_one": conversion.one_to_one.to_dict()})}


# ------------------------------------------------------------------------------ writing


def write_opencv_file(camera: Camera, path: Path) -> Path:
    """`camera` as an OpenCV calibration file (camera_matrix, distortion_coefficients (k1, k2, p1, p2,
    k3; radial1: k1 = d, the rest 0), image_width, image_height), in the format of its suffix
    (.yaml, .xml, .json)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".opencv-") as scratch:
        partial = Path(scratch) / path.name  # written whole, then renamed into place
        storage = cv2.FileStorage(str(partial), cv2.FILE_STORAGE_WRITE)
        storage.write("image_width", camera.width)
        storage.write("image_height", camera.height)
        storage.write("camera_matrix", camera.K)
        storage.write("distortion_coefficients", np.array([camera.distortion], dtype=float).T)
        storage.release()
        os.replace(partial, path)
    return path
