"""GeoJSON of the solved flight (RFC 7946: WGS 84 longitude, latitude, ellipsoidal height): each frame
as a point with its pose, sigmas and camera set, and each camera's ground footprint as a polygon.

The footprint of a camera in a frame is its image border (EDGE_SAMPLES pixels along each edge,
through the lens model) cast from the rig pose onto the local level plane through the mean of the
ground points that frame's pose used: the plane normal to the ellipsoid's at that mean point. A
border ray that does not reach the plane in front of the camera leaves that footprint out. The
geometry here is in the computation frame; `stages.export` converts it (geo.py) and writes.
"""

from __future__ import annotations

import numpy as np

from .rig import Rig

#: Pixels taken along each edge of the image for a footprint's outline (corners included).
EDGE_SAMPLES = 8


def border_pixels(width: int, height: int, samples: int = EDGE_SAMPLES) -> np.ndarray:
    """(4 (samples - 1), 2) pixels around the image's border, counter-clockwise as seen on the image
    (u right, v down), from the top-left corner, each corner once; pixel centres of the outermost
    pixels (OpenCV: 0 ... width - 1)."""
    u = np.linspace(0.0, width - 1.0, samples)
    v = np.linspace(0.0, height - 1.0, samples)
    left = np.column_stack([np.zeros(samples), v])[:-1]
    bottom = np.column_stack([u, np.full(samples, height - 1.0)])[:-1]
    right = np.column_stack([np.full(samples, width - 1.0), v[::-1]])[:-1]
    top = np.column_stack([u[::-1], np.zeros(samples)])[:-1]
    return np.vstack([left, bottom, right, top])


def footprint(rig: Rig, camera: str, R: np.ndarray, t: np.ndarray, point: np.ndarray,
              normal: np.ndarray) -> np.ndarray | None:
    """(k, 3) world points where `camera`'s border rays meet the plane through point (3,) with unit
    normal (3,), for the rig pose rig_from_world R (3, 3), t (3,); None where a ray misses it (parallel
    or behind the camera)."""
    spec = rig.cameras[camera]
    origins, directions = rig.rays(camera, border_pixels(spec.width, spec.height))
    world_origins = (origins - t) @ R  # R^T (v - t)
    world_directions = directions @ R
    along = world_directions @ normal
    if np.any(np.abs(along) < 1e-9):
        return None
    distance = ((point - world_origins) @ normal) / along
    if np.any(distance <= 0):
        return None
    return world_origins + distance[:, None] * world_directions


def feature(geometry_type: str, coordinates, properties: dict) -> dict:
    """A GeoJSON Feature; properties' NaN values become null (JSON has no NaN)."""
    clean = {key: (None if isinstance(value, float) and not np.isfinite(value) else value)
             for key, value in properties.items()}
    return {"type": "Feature", "geometry": {"type": geometry_type, "coordinates": coordinates}, "properties": clean}


def polygon_ring(lon_lat_h: np.ndarray) -> list:
    """A closed exterior ring of (k, 3) longitude, latitude, height, counter-clockwise in longitude
    and latitude (RFC 7946's right-hand rule)."""
    lon, lat = lon_lat_h[:, 0], lon_lat_h[:, 1]
    area = np.sum(lon * np.roll(lat, -1) - np.roll(lon, -1) * lat)
    ring = lon_lat_h if area > 0 else lon_lat_h[::-1]
    return [list(map(float, p)) for p in ring] + [list(map(float, ring[0]))]


def collection(features: list[dict], name: str) -> dict:
    """A FeatureCollection (WGS 84 coordinates, RFC 7946's default, so no crs member)."""
    return {"type": "FeatureCollection", "name": name, "features": features}
