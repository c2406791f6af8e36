"""Simulator configuration: the physical defaults (the paper's DMAIS and noise budget) and presets.

A simulator YAML overrides any subset of `DEFAULTS` (nested keys); unknown keys are errors, so a
typo never silently falls back to a default. Presets live in `config/simulate/`.

Noise budget (see docs/simulator.md for the derivation):
- control points of the calibration field: RTK + total station, averaged, 1 mm per axis;
- calibration-image marker positions when not rendered: 0.1 px per axis (template matching);
- ground markers of the flight sites: RTK, 1.5 cm horizontal and 2.5 cm vertical per axis;
- in-flight camera mounting: each camera's cam_from_rig during a flight group deviates from the
  rooftop calibration by 0.15 arc-min per axis (thermal and mechanical change between calibration
  and flight) plus 0.3 arc-min per frame (vibration);
- flight marker positions when not rendered: 0.5 px per axis (vibration, turbulence at 350-500 m).
Together these give eps_proj ~ 4 px for a 5-camera frame, as tab:pose_methods.

Flight pattern (`flight.pattern`, `check_flight_pattern`): "hover" (the default) keeps each group's
frames around one pose, over the same markers; "line" flies them along a line, `line_spacing_m`
apart, with markers placed for every frame (sim.scene.flight_frames). A hover dataset's
truth/simulation.yaml leaves the two line settings out (`settings_to_write`), so that it is the
same file as before they existed.
"""

from __future__ import annotations

import copy
from pathlib import Path

import yaml

from ..camera import PARAMETER_NAMES
from ..errors import ConfigError, yaml_problem

# Truth rig. Intrinsics: tab:intrinsics ("Ours" rows) for f and d, C3's fy raised to 43700 px;
# principal points a few tens of pixels off the centre, as real lenses are. Extrinsics: the
# "known" columns of tab:extrinsics_R (rig_from_cam as intrinsic ZYX Euler angles, degrees) and
# tab:extrinsics_t (camera centres in the rig frame, metres); C0 is the rig frame.
_PAPER_RIG = {
    "reference_camera": "C0",
    "width": 4096,
    "height": 3000,
    "cameras": {
        "C0": {"fx": 45553.0, "fy": 45569.7, "cx": 2060.0, "cy": 1492.0, "d": 3.0715,
               "euler_zyx_deg": [0.0, 0.0, 0.0], "center_m": [0.0, 0.0, 0.0]},
        "C1": {"fx": 44922.5, "fy": 44963.4, "cx": 2028.0, "cy": 1515.0, "d": 2.0227,
               "euler_zyx_deg": [-179.811, -0.152, 46.233], "center_m": [-0.002, 0.102, -0.086]},
        "C2": {"fx": 44440.4, "fy": 44411.0, "cx": 2073.0, "cy": 1510.0, "d": 2.2361,
               "euler_zyx_deg": [-90.048, -1.170, 44.758], "center_m": [-0.113, -0.012, -0.100]},
        "C3": {"fx": 43737.5, "fy": 43700.0, "cx": 2038.0, "cy": 1478.0, "d": 2.2207,
               "euler_zyx_deg": [0.150, -0.047, 44.038], "center_m": [0.000, -0.143, -0.097]},
        "C4": {"fx": 44660.0, "fy": 44620.9, "cx": 2066.0, "cy": 1486.0, "d": 1.8864,
               "euler_zyx_deg": [90.140, 1.180, 45.615], "center_m": [0.122, -0.010, -0.100]},
    },
    "nominal_focal_px": 45000.0,
}

DEFAULTS = {
    "name": "sim",
    "seed": 0,
    "rig": _PAPER_RIG,
    "marker_size_m": 2.0,
    "render": {
        "intrinsics": True,
        "extrinsics": True,
        "flight": True,
        "png_compression": 1,
        "settings": {},  # overrides of sim.render.RenderSettings
    },
    "field": {
        # The rig stands on a roof at `station` and looks north (+y) horizontally; the field has
        # three regions at the azimuths of the three horizontal cameras (C0 and two tilted ones).
        "station_m": [0.0, 0.0, 6.0],
        "region_azimuth_deg": [-45.0, 0.0, 45.0],
        "region_names": ["L", "C", "R"],
        "distance_m": [130.0, 280.0],
        "height_m": [2.0, 10.0],
        "region_half_width_deg": 2.6,
        "cell_deg": 1.05,  # azimuth spacing of the markers seen from the station
        "row_elevation_deg": [-0.9, 0.0, 0.9],  # rows 0.9 deg apart: a 2 m marker at 130 m spans 0.88
        "boards_per_region": 2,
        "board_min_distance_m": 200.0,
        "board_size_m": [3.0, 3.0],
        "board_cells": [4, 3],
        "facing_yaw_deg": 25.0,
        "survey_sigma_m": 0.001,
    },
    "intrinsics": {
        "calib_images_per_camera": 20,
        "eval_images_per_camera": 5,
        "aim_jitter_deg": [1.8, 1.3],
        "roll_jitter_deg": 4.0,
        "station_jitter_m": 0.3,
        "min_points": 8,
    },
    "extrinsics": {
        "placements": 5,
        "initial_roll_deg": 0.0,
        "adjust_jitter_deg": 0.1,
        "station_jitter_m": 0.05,
        "min_points": 6,
    },
    "calibration_priors": {
        "center_sigma_m": 0.02,
        "attitude_sigma_deg": 1.0,
    },
    "calibration_pixel_sigma_px": 0.1,
    "flight": {
        "altitude_m": 350.0,
        "altitude_jitter_m": 10.0,
        "sites": {
            "A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1, 2, 3]},
            "B": {"center_m": [-2200.0, 1800.0, 120.0], "groups": [4, 5]},
        },
        "group_offset_m": 40.0,
        "frames_per_group": 30,
        # How a group's frames move (FLIGHT_PATTERNS): "hover" around the group's pose, so every frame
        # sees the same markers; "line" along a straight line through it in the direction of its
        # heading, line_spacing_m apart (20 m: C0's footprint is ~23 m along the line, so each frame
        # sees mostly new markers), markers placed for every frame.
        "pattern": "hover",
        "line_spacing_m": 20.0,
        "markers_per_camera": 8,
        "marker_margin_frac": 0.15,
        "terrain_amplitude_m": 3.0,
        "hover_position_sigma_m": 1.0,
        "hover_attitude_sigma_deg": 0.2,
        "survey_sigma_m": [0.015, 0.015, 0.025],
        "mount_sigma_arcmin": 0.15,
        "vibration_sigma_arcmin": 0.3,
        "pixel_sigma_px": 0.5,
        "lever_arm_m": [0.15, -0.08, 0.32],
        "pos_sigma_m": [0.02, 0.02, 0.03],
        "ins_attitude_sigma_deg": 0.5,
        "ins_boresight_deg": [0.25, -0.15, 0.4],  # imu_from_rig as a rotation vector in the rig axes
        "border_margin_px": 20.0,
    },
    # Real-world coordinates (`check_geodetic`): with a crs, the world frame is the topocentric
    # east-north-up frame of WGS 84 at `origin` (latitude, longitude deg, ellipsoidal height m), and
    # the dataset gives its points in `crs` (e.g. a UTM zone, heights ellipsoidal), its POS positions
    # and camera-centre priors in `pos_crs` (WGS 84 longitude, latitude, height), dataset.yaml names
    # both and the origin; truth/ stays in the frame, with latitude, longitude, height and the NED
    # attitude beside. Without crs (the default) the world is a local metric frame, as before.
    # With `trajectory` (sbet or csv), frames.csv gives each frame's time instead of its POS position
    # and INS attitude, and the POS's trajectory is written beside it (sim/pos.py).
    "geodetic": {
        "crs": None,
        "pos_crs": "EPSG:4979",
        "origin": [35.0, 17.8, 100.0],
        "trajectory": None,
    },
}


#: A rig camera entry's keys besides its lens model's coefficients (all required but `model`).
CAMERA_KEYS = ("model", "fx", "fy", "cx", "cy", "euler_zyx_deg", "center_m")
#: Each lens model's coefficients in a rig camera entry (its parameters after fx, fy, cx, cy):
#: radial1's d is required, opencv's default to 0.
LENS_COEFFICIENTS = {model: names[4:] for model, names in PARAMETER_NAMES.items()}

#: flight.pattern's values (module docstring).
FLIGHT_PATTERNS = ("hover", "line")
#: The flight settings that only the line pattern uses, absent from a hover dataset's simulation.yaml.
LINE_SETTINGS = ("pattern", "line_spacing_m")


def check_flight_pattern(config: dict) -> str:
    """flight.pattern of resolved settings, after checking it and line_spacing_m; ConfigError otherwise."""
    flight = config["flight"]
    pattern = flight["pattern"]
    if pattern not in FLIGHT_PATTERNS:
        raise ConfigError(f"simulator setting 'flight.pattern' is {pattern!r}; expected one of "
                          f"{', '.join(FLIGHT_PATTERNS)}")
    spacing = flight["line_spacing_m"]
    if isinstance(spacing, bool) or not isinstance(spacing, (int, float)) or not spacing > 0:
        raise ConfigError(f"simulator setting 'flight.line_spacing_m' must be a number above 0, got {spacing!r}")
    return pattern


def check_camera_entry(name: str, entry) -> str:
    """The lens model of the rig camera entry `name` (default radial1), after checking its keys
    against it; ConfigError naming the camera and the unknown model, the key of the other model (or
    unknown) or the missing key."""
    where = f"simulator setting 'rig.cameras.{name}'"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a mapping, got {entry!r}")
    model = entry.get("model", "radial1")
    if model not in LENS_COEFFICIENTS:
        raise ConfigError(f"simulator setting 'rig.cameras.{name}.model' is {model!r}; expected one of "
                          f"{', '.join(LENS_COEFFICIENTS)}")
    coefficients = LENS_COEFFICIENTS[model]
    unknown = sorted(set(entry) - set(CAMERA_KEYS) - set(coefficients))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(str, unknown))} for model {model} "
                          f"(its coefficients: {', '.join(coefficients)})")
    missing = [key for key in CAMERA_KEYS[1:] + (("d",) if model == "radial1" else ()) if key not in entry]
    if missing:
        raise ConfigError(f"{where}: missing {', '.join(missing)}")
    return model


def settings_to_write(config: dict) -> dict:
    """The resolved settings as truth/simulation.yaml holds them: a hover flight's without LINE_SETTINGS,
    a local frame's without `geodetic` (so that both are the files written before those settings)."""
    if config["geodetic"]["crs"] is None:
        config = {key: value for key, value in config.items() if key != "geodetic"}
    if config["flight"]["pattern"] != "hover":
        return config
    flight = {key: value for key, value in config["flight"].items() if key not in LINE_SETTINGS}
    return {**config, "flight": flight}


def check_geodetic(config: dict) -> None:
    """The `geodetic` settings: crs and pos_crs strings (or crs None), origin three numbers within
    the latitude and longitude ranges; ConfigError otherwise (the CRSs themselves are checked by
    pyproj when the dataset is written)."""
    geodetic = config["geodetic"]
    for key in ("crs", "pos_crs"):
        value = geodetic[key]
        if not (value is None and key == "crs") and not (isinstance(value, str) and value.strip()):
            raise ConfigError(f"simulator setting 'geodetic.{key}' must be a CRS name such as EPSG:32633, got {value!r}")
    if geodetic["trajectory"] not in (None, "sbet", "csv"):
        raise ConfigError(f"simulator setting 'geodetic.trajectory' must be sbet, csv or null, got "
                          f"{geodetic['trajectory']!r}")
    origin = geodetic["origin"]
    if (not isinstance(origin, list) or len(origin) != 3
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in origin)
            or abs(origin[0]) > 90 or abs(origin[1]) > 180):
        raise ConfigError(f"simulator setting 'geodetic.origin' must be [latitude deg, longitude deg, height m], "
                          f"got {origin!r}")


def merge(defaults: dict, overrides: dict, where: str = "") -> dict:
    """Deep copy of `defaults` with `overrides` applied; unknown keys raise ConfigError."""
    merged = copy.deepcopy(defaults)
    for key, value in overrides.items():
        path = f"{where}.{key}" if where else str(key)
        if key not in defaults:
            raise ConfigError(f"unknown simulator setting {path!r}")
        free_form = key in ("settings", "sites", "cameras")
        if isinstance(defaults[key], dict) and isinstance(value, dict) and not free_form:
            merged[key] = merge(defaults[key], value, path)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def load_config(path: str | Path) -> dict:
    """Simulator settings from a YAML file: DEFAULTS with the file's values applied."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except yaml.YAMLError as error:
        problem, line = yaml_problem(error)
        raise ConfigError(f"{path}{'' if line is None else f', line {line}'}: invalid YAML: {problem}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of settings")
    try:
        config = merge(DEFAULTS, data)
        check_flight_pattern(config)
        check_geodetic(config)
        for name, entry in config["rig"]["cameras"].items():
            check_camera_entry(name, entry)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None
    return config
