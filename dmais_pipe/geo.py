"""Coordinate reference systems at the pipeline's edges, all conversions by pyproj (PROJ).

A dataset whose dataset.yaml names a `crs` (docs/dataset.md) gives its surveyed points in that CRS
and its POS positions in `pos_crs`; columns in pyproj's `always_xy` order (x = easting or longitude,
y = northing or latitude, z = height). A 2-D CRS is taken with ellipsoidal heights (`CRS.to_3d`).
Inside, every stage computes in one exact Cartesian frame, the **computation frame**: the
topocentric east-north-up frame (PROJ's `topocentric` conversion) of the WGS 84 ellipsoid whose
origin is `Geo.origin` (latitude, longitude, ellipsoidal height; dataset.yaml `origin`, by default
the point of the control points' mean in WGS 84 geocentric coordinates). The frame is ECEF turned
and moved, so distances and angles in it are true ones; a map projection's are not (its scale
factor, its grid convergence). Without `crs` the world frame is the dataset's own metric frame and
nothing here is used.

It is called at the edges only: dataset.py (reading, trajectory.py's positions), workspace.py and
stages/ (pose, evaluate, export: writing), the simulator's geodetic world and the benches; the
algorithms never see a CRS.

Names: `ecef` WGS 84 geocentric (EPSG:4978) metres (n, 3); `enu` the computation frame (n, 3);
`geodetic` (n, 3) latitude (deg), longitude (deg), ellipsoidal height (m), WGS 84 (EPSG:4979);
`ned_from_enu` (n, 3, 3) the rotation from the computation frame's axes to the local north-east-down
axes (true north, ellipsoid normal) at each point.
"""

from __future__ import annotations

import functools
import logging
import math
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import DmaisError
from .geometry import euler_zyx_from_rotation, euler_zyx_rates

if TYPE_CHECKING:  # imported where a CRS is used: not by every job of a dataset without one (0.1 s)
    import pyproj

log = logging.getLogger(__name__)

ECEF = "EPSG:4978"
GEODETIC = "EPSG:4979"
#: A point further than this (degrees of latitude or longitude) beyond its CRS's area of use is an
#: error (the CRS is very likely not the one the coordinates are in); nearer, outside, a warning.
FAR_OUTSIDE_DEG = 2.0
#: The step (deg) of the central differences through pyproj that give the north and east directions.
_STEP_DEG = 1e-4
_AXIS_M = 1e5
_ARCMIN_PER_RAD = 60.0 * 180.0 / math.pi


class GeoError(DmaisError):
    """A CRS that cannot be used, or coordinates that do not fit it; the caller names the file.
    row: the 0-based row of the coordinates at fault, where one is."""

    def __init__(self, message: str, row: int | None = None):
        self.row = row
        super().__init__(message)


# ------------------------------------------------------------------------------ CRS and transformers


@functools.lru_cache(maxsize=32)
def pyproj_crs(text: str) -> pyproj.CRS:
    """The CRS named by `text` (anything pyproj reads: EPSG:32633, WKT, a PROJ string) as it is;
    GeoError when pyproj does not know it."""
    import pyproj
    from pyproj.exceptions import CRSError

    try:
        return pyproj.CRS.from_user_input(text)
    except CRSError as error:
        raise GeoError(f"{text!r} is not a coordinate reference system pyproj knows ({_first_line(error)})") from None


@functools.lru_cache(maxsize=32)
def crs_3d(text: str) -> pyproj.CRS:
    """The CRS named by `text` (pyproj_crs) as a 3-D CRS: a 2-D one gains an ellipsoidal height
    axis. GeoError when pyproj does not know it or it has no datum to place points on the Earth."""
    crs = pyproj_crs(text)
    if crs.is_engineering or (crs.is_vertical and not crs.is_compound) or crs.is_bound and crs.source_crs.is_engineering:
        raise GeoError(f"{text!r} ({crs.name}) is not tied to the Earth; give a geographic, projected, "
                       "geocentric or compound CRS")
    return crs if len(crs.axis_info) >= 3 else crs.to_3d()


@functools.lru_cache(maxsize=32)
def _transformer(source: str, target: str) -> pyproj.Transformer:
    """The best transformation from CRS `source` to `target` (3-D, always_xy); GeoError naming the
    grid when the best one needs a grid PROJ does not have (a geoid model), rather than falling back
    to a worse one silently."""
    import pyproj
    from pyproj.transformer import TransformerGroup

    with warnings.catch_warnings():  # pyproj warns of a missing grid: said below, in one line
        warnings.simplefilter("ignore", UserWarning)
        group = TransformerGroup(crs_3d(source), crs_3d(target), always_xy=True)
    if not group.best_available and group.unavailable_operations:
        grids = [grid.short_name for grid in group.unavailable_operations[0].grids if not grid.available]
        raise GeoError(f"converting {source!r} to {target!r} needs the grid {', '.join(grids)}, which PROJ does "
                       f"not have (install it in {pyproj.datadir.get_data_dir()} or set PROJ_NETWORK=ON)")
    if not group.transformers:
        raise GeoError(f"pyproj has no transformation from {source!r} to {target!r}")
    return group.transformers[0]


@functools.lru_cache(maxsize=32)
def _topocentric(origin: tuple[float, float, float]) -> pyproj.Transformer:
    import pyproj

    lat, lon, h = origin
    return pyproj.Transformer.from_pipeline(
        f"+proj=topocentric +ellps=WGS84 +lat_0={lat!r} +lon_0={lon!r} +h_0={h!r}")


def _transform(transformer: pyproj.Transformer, xyz, direction: str = "FORWARD") -> np.ndarray:
    """(n, 3) of xyz (n, 3) through `transformer`; GeoError where PROJ gives no finite result."""
    from pyproj.exceptions import ProjError

    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    try:
        out = np.column_stack(transformer.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2], direction=direction,
                                                    errcheck=False))
    except ProjError as error:
        raise GeoError(f"cannot convert the coordinates ({_first_line(error)})") from None
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        row = int(np.argmax(bad))
        raise GeoError(f"({', '.join(f'{v:.10g}' for v in xyz[row])}) cannot be converted (PROJ gives no "
                       "finite result there)", row)
    return out


def _first_line(error: Exception) -> str:
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__


# ------------------------------------------------------------------------------ conversions


def ecef_from_crs(crs: str, xyz) -> np.ndarray:
    """(n, 3) WGS 84 geocentric coordinates of points xyz (n, 3) in `crs` (always_xy order)."""
    return _transform(_transformer(crs, ECEF), xyz)


def crs_from_ecef(crs: str, ecef) -> np.ndarray:
    """(n, 3) coordinates in `crs` (always_xy order) of WGS 84 geocentric points ecef (n, 3)."""
    return _transform(_transformer(ECEF, crs), ecef)


def geodetic_from_ecef(ecef) -> np.ndarray:
    """(n, 3) latitude (deg), longitude (deg), ellipsoidal height (m) on WGS 84 of ecef (n, 3)."""
    lon_lat_h = _transform(_transformer(ECEF, GEODETIC), ecef)
    return lon_lat_h[:, [1, 0, 2]]


def ecef_from_geodetic(geodetic) -> np.ndarray:
    """(n, 3) WGS 84 geocentric coordinates of geodetic (n, 3) latitude, longitude (deg), height (m)."""
    geodetic = np.asarray(geodetic, dtype=float).reshape(-1, 3)
    return _transform(_transformer(GEODETIC, ECEF), geodetic[:, [1, 0, 2]])


def enu_from_ecef(origin, ecef) -> np.ndarray:
    """(n, 3) east, north, up (m) in the topocentric frame at origin (latitude, longitude deg, height
    m; WGS 84) of geocentric points ecef (n, 3)."""
    return _transform(_topocentric(_origin_key(origin)), ecef)


def ecef_from_enu(origin, enu) -> np.ndarray:
    """(n, 3) geocentric points of topocentric enu (n, 3) at origin (the inverse of enu_from_ecef)."""
    return _transform(_topocentric(_origin_key(origin)), enu, direction="INVERSE")


def _origin_key(origin) -> tuple[float, float, float]:
    return tuple(float(v) for v in origin)


def ned_from_ecef(geodetic) -> np.ndarray:
    """(n, 3, 3) rotations from the geocentric axes to the north-east-down axes at geodetic (n, 3)
    points (latitude, longitude deg, height m): rows north, east, down. North and east are the
    directions in which the point moves when its latitude and longitude grow (central differences
    through pyproj, whose chords are parallel to the tangents to 1e-12); down completes them."""
    geodetic = np.asarray(geodetic, dtype=float).reshape(-1, 3)
    step = np.array([[_STEP_DEG, 0.0, 0.0], [0.0, _STEP_DEG, 0.0]])
    north, east = (ecef_from_geodetic(geodetic + s) - ecef_from_geodetic(geodetic - s) for s in step)
    north /= np.linalg.norm(north, axis=1, keepdims=True)
    east -= np.sum(east * north, axis=1, keepdims=True) * north  # orthogonal already to ~1e-12
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    return np.stack([north, east, np.cross(north, east)], axis=1)


def ecef_from_enu_rotation(origin) -> np.ndarray:
    """(3, 3) the rotation from the topocentric frame at origin to the geocentric axes (columns: east,
    north, up in ECEF), from pyproj's conversion of the frame's axes (100 km along each, so that
    PROJ's ~1e-9 m rounding at the Earth's radius is 1e-14 of them; the conversion is affine)."""
    ends = ecef_from_enu(origin, np.vstack([np.zeros(3), _AXIS_M * np.eye(3)]))
    u, _, vt = np.linalg.svd((ends[1:] - ends[0]).T / _AXIS_M)  # the nearest rotation
    return u @ vt


# ------------------------------------------------------------------------------ a dataset's frame


@dataclass(frozen=True)
class Geo:
    """A dataset's coordinate reference systems: `crs` of its points, `pos_crs` of its POS positions
    and camera-centre priors (as dataset.yaml gives them), and `origin` (latitude, longitude deg,
    ellipsoidal height m; WGS 84) of the computation frame. Picklable (strings and numbers): the
    transformers are made, and cached, on use."""

    crs: str
    pos_crs: str
    origin: tuple[float, float, float]

    def enu_from_crs(self, xyz, pos: bool = False) -> np.ndarray:
        """(n, 3) computation-frame coordinates of xyz (n, 3) in `crs` (pos: in `pos_crs`)."""
        return enu_from_ecef(self.origin, ecef_from_crs(self.pos_crs if pos else self.crs, xyz))

    def crs_from_enu(self, enu, pos: bool = False) -> np.ndarray:
        """(n, 3) coordinates in `crs` (pos: in `pos_crs`) of computation-frame points enu (n, 3)."""
        return crs_from_ecef(self.pos_crs if pos else self.crs, ecef_from_enu(self.origin, enu))

    def geodetic_from_enu(self, enu) -> np.ndarray:
        """(n, 3) latitude, longitude (deg), ellipsoidal height (m) on WGS 84 of enu (n, 3)."""
        return geodetic_from_ecef(ecef_from_enu(self.origin, enu))

    def enu_from_geodetic(self, geodetic) -> np.ndarray:
        """(n, 3) computation-frame coordinates of geodetic (n, 3) latitude, longitude, height."""
        return enu_from_ecef(self.origin, ecef_from_geodetic(geodetic))

    def ned_from_enu(self, enu) -> np.ndarray:
        """(n, 3, 3) the rotation from the computation frame's axes to north-east-down at each point
        enu (n, 3): ned_from_ecef there times the frame's ecef_from_enu."""
        return ned_from_ecef(self.geodetic_from_enu(enu)) @ ecef_from_enu_rotation(self.origin)


def default_origin(ecef) -> tuple[float, float, float]:
    """The computation frame's default origin: latitude, longitude, height of the mean of ecef (n, 3)
    (the control points), rounded to 1e-9 deg and 1 mm so that it reads back as written."""
    lat, lon, h = geodetic_from_ecef(np.mean(np.asarray(ecef, dtype=float).reshape(-1, 3), axis=0))[0]
    return round(float(lat), 9), round(float(lon), 9), round(float(h), 3)


def outside_area_of_use(crs: str, ecef) -> tuple[np.ndarray, str]:
    """How far (deg of latitude or longitude, 0 inside) each geocentric point ecef (n, 3) lies
    outside the area of use of `crs`, and that area's description ('' and zeros when the CRS
    states none)."""
    area = crs_3d(crs).area_of_use
    ecef = np.asarray(ecef, dtype=float).reshape(-1, 3)
    if area is None:
        return np.zeros(len(ecef)), ""
    lat, lon = geodetic_from_ecef(ecef)[:, :2].T
    west, south, east, north = area.bounds
    width = (east - west) % 360.0 or 360.0
    beyond_east = (lon - west) % 360.0 - width  # > 0 east of the area (the area may cross 180 deg)
    beyond_lon = np.where(beyond_east > 0, np.minimum(beyond_east, 360.0 - width - beyond_east), 0.0)
    beyond_lat = np.maximum(south - lat, 0.0) + np.maximum(lat - north, 0.0)
    where = f"{area.name} ({west:g} to {east:g} deg E, {south:g} to {north:g} deg N)"
    return np.maximum(beyond_lon, beyond_lat), where


# ------------------------------------------------------------------------------ attitude in NED


def ned_attitude(ned_from_world, world_from_rig) -> np.ndarray:
    """(F, 3) heading, pitch, roll (deg) of ned_from_rig = ned_from_world (F, 3, 3) @ world_from_rig
    (F, 3, 3): its intrinsic ZYX Euler angles (heading about down in [0, 360), pitch in [-90, 90],
    roll in (-180, 180])."""
    angles = np.degrees(euler_zyx_from_rotation(np.asarray(ned_from_world) @ np.asarray(world_from_rig)))
    angles = np.atleast_2d(angles)
    angles[:, 0] %= 360.0
    return angles


def ned_sigmas(ned_from_world, world_attitude_deg, ned_attitude_deg, sigma_position, sigma_attitude,
               covariance) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma of the rig centre along north, east, down (F, 3) m and of the NED heading, pitch, roll
    (F, 3) arc-min.

    covariance (F, 6, 6): the linearised covariance of (omega, centre) (pose.uncertainty: omega the
    rig-axes rotation, centre in the world axes); sigma_position (F, 3) m and sigma_attitude (F, 3)
    arc-min the sigmas written along the world axes and of the world angles world_attitude_deg (F, 3),
    which for frames past the linearisation are the re-solves' (nonlinear.py). The covariances of
    the world centre and angles are scaled to those sigmas (their correlations kept; a factor 1
    elsewhere), then turned: the centre's by ned_from_world (F, 3, 3), the angles' through the
    body-frame rotation they share, d ned = E_ned^-1 E_world d world (geometry.euler_zyx_rates)."""
    covariance = np.asarray(covariance, dtype=float)
    E_world = euler_zyx_rates(np.radians(world_attitude_deg))
    E_ned_inverse = np.linalg.inv(euler_zyx_rates(np.radians(ned_attitude_deg)))
    world_angles = np.linalg.solve(E_world, np.linalg.solve(E_world, covariance[:, :3, :3]).swapaxes(1, 2))
    position = _scaled(covariance[:, 3:, 3:], np.asarray(sigma_position, dtype=float))
    angles = _scaled(world_angles, np.radians(np.asarray(sigma_attitude, dtype=float) / 60.0))
    turn = E_ned_inverse @ E_world
    ned_position = ned_from_world @ position @ np.swapaxes(ned_from_world, 1, 2)
    ned_angles = turn @ angles @ np.swapaxes(turn, 1, 2)
    return (np.sqrt(np.clip(np.diagonal(ned_position, axis1=1, axis2=2), 0.0, None)),
            np.sqrt(np.clip(np.diagonal(ned_angles, axis1=1, axis2=2), 0.0, None)) * _ARCMIN_PER_RAD)


def _scaled(covariance: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """covariance (F, 3, 3) with its diagonal scaled to sigma (F, 3) squared, correlations kept."""
    own = np.sqrt(np.clip(np.diagonal(covariance, axis1=1, axis2=2), 0.0, None))
    factor = np.where(own > 0, sigma / np.where(own > 0, own, 1.0), 1.0)
    return covariance * factor[:, :, None] * factor[:, None, :]
