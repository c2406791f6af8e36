"""Dataset directory: loading, round trip, and one precise error per kind of malformed input."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from dmais_pipe.cli import main
from dmais_pipe.dataset import CameraSpec, Dataset, largest_point_sigma, point_sigma, write_dataset
from dmais_pipe.errors import DatasetError
from dmais_pipe.workspace import Workspace

W, H = 64, 48
QUAT = (0.5, 0.5, -0.5, 0.5)


def _inputs() -> dict:
    manifest = {
        "name": "tiny",
        "description": "test dataset",
        "reference_camera": "C0",
        "cameras": {"C0": {"width": W, "height": H, "focal_px": 500.0}, "C1": {"width": W, "height": H}},
        "marker_size_m": 1.5,
    }
    control = pd.DataFrame({"point_id": ["007", "A1", "A2", "A3"], "x": [0.1, 1e-9, 2.0, -3.25],
                            "y": [1 / 3, 0.0, 5.5, 1e6 + 1e-6], "z": [0.0, 1.0, 2.0, 3.0]})
    ground = pd.DataFrame({"point_id": ["G1", "G2"], "x": [10.0, 11.0], "y": [20.0, 21.0], "z": [0.5, 0.25]})
    images = pd.DataFrame([
        {"image": "i0", "camera": "C0", "stage": "intrinsics", "split": "calib", "path": "images/i0.png",
         "prior_x": 1.0, "prior_y": 2.0, "prior_z": 3.0, "prior_qw": QUAT[0], "prior_qx": QUAT[1],
         "prior_qy": QUAT[2], "prior_qz": QUAT[3]},
        {"image": "i1", "camera": "C1", "stage": "intrinsics", "split": "eval", "path": "images/i1.png"},
        {"image": "e0", "camera": "C1", "stage": "extrinsics", "placement": "p0", "path": "images/e0.png",
         "prior_x": 4.0, "prior_y": 5.0, "prior_z": 6.0},
        {"image": "f0", "camera": "C0", "stage": "flight", "placement": "g1_f000", "path": ""},
        {"image": "f1", "camera": "C1", "stage": "flight", "placement": "g1_f000", "path": "images/f1.png"},
    ])
    frames = pd.DataFrame({"frame": ["g1_f000"], "group": ["1"], "pos_x": [100.0], "pos_y": [200.0],
                           "pos_z": [1000.0], "prior_qw": [1.0], "prior_qx": [0.0], "prior_qy": [0.0],
                           "prior_qz": [0.0]})
    observations = pd.DataFrame({"image": ["f0", "f0", "i0"], "point_id": ["G1", "G2", "007"],
                                 "u": [10.5, 20.25, 0.0], "v": [30.125, 40.0, 47.0]})
    return {"manifest": manifest, "control_points": control, "images": images, "ground_points": ground,
            "frames": frames, "observations": observations}


def _write(root: Path, inputs: dict) -> Path:
    write_dataset(root, inputs["manifest"], inputs["control_points"], inputs["images"],
                  ground_points=inputs["ground_points"], frames=inputs["frames"],
                  observations=inputs["observations"])
    for path in inputs["images"]["path"]:
        if path:
            (root / path).parent.mkdir(parents=True, exist_ok=True)
            (root / path).write_bytes(cv2.imencode(".png", np.full((H, W), 128, np.uint8))[1].tobytes())
    return root


@pytest.fixture
def root(tmp_path) -> Path:
    return _write(tmp_path / "ds", _inputs())


# ------------------------------------------------------------------------------ valid datasets


def test_loads_with_clean_types(root):
    ds = Dataset.load(root)
    ds.check_images()
    assert ds.name == "tiny" and ds.reference_camera == "C0" and ds.marker_size_m == 1.5
    assert ds.cameras == {"C0": CameraSpec(W, H, 500.0), "C1": CameraSpec(W, H, None)}
    assert list(ds.control_points.index) == ["007", "A1", "A2", "A3"]
    assert ds.control_points.loc["A3", "y"] == 1e6 + 1e-6 and ds.control_points.loc["007", "y"] == 1 / 3
    assert list(ds.points.index) == ["007", "A1", "A2", "A3", "G1", "G2"]
    assert list(ds.images.columns[:7]) == ["image", "camera", "stage", "split", "placement", "path", "prior_x"]
    assert ds.images["prior_qw"].dtype == float and np.isnan(ds.images.loc[1, "prior_x"])
    assert ds.images.loc[1, "placement"] == "" and ds.frames.loc[0, "group"] == "1"
    assert list(ds.images_of("flight", camera="C1")["image"]) == ["f1"]
    assert list(ds.images_of("intrinsics", split="eval")["image"]) == ["i1"]
    assert ds.image_path("f0") is None and ds.image_path("i0") == root.absolute() / "images/i0.png"
    assert ds.read_image("i0").shape == (H, W)
    assert ds.truth_dir == root.absolute() / "truth"
    summary = ds.summary()
    assert "tiny" in summary and "4 control, 2 ground" in summary and "observations: 3" in summary


def test_round_trip_is_exact(root, tmp_path):
    inputs = _inputs()
    first = Dataset.load(root)
    pd.testing.assert_frame_equal(first.control_points.reset_index(), inputs["control_points"], check_dtype=False)
    pd.testing.assert_frame_equal(first.observations, inputs["observations"], check_dtype=False)
    copy = tmp_path / "copy"
    write_dataset(copy, inputs["manifest"], first.control_points, first.images, ground_points=first.ground_points,
                  frames=first.frames, observations=first.observations)
    (copy / "images").symlink_to(root / "images")
    second = Dataset.load(copy)
    for name in ("control_points", "ground_points", "images", "frames", "observations"):
        pd.testing.assert_frame_equal(getattr(first, name), getattr(second, name), check_exact=True)
    assert yaml.safe_load((copy / "dataset.yaml").read_text()) == inputs["manifest"]


def test_camera_model_round_trips_and_defaults_to_radial1(tmp_path):
    """`model: opencv` is read, written back only where it is not the default, and re-reads the same."""
    inputs = _inputs()
    inputs["manifest"]["cameras"]["C1"]["model"] = "opencv"
    root = _write(tmp_path / "ds", inputs)
    ds = Dataset.load(root)
    assert ds.cameras == {"C0": CameraSpec(W, H, 500.0, "radial1"), "C1": CameraSpec(W, H, None, "opencv")}
    written = yaml.safe_load((root / "dataset.yaml").read_text())
    assert written["cameras"] == {"C0": {"width": W, "height": H, "focal_px": 500.0},
                                  "C1": {"width": W, "height": H, "model": "opencv"}}
    copy = tmp_path / "copy"
    write_dataset(copy, written, ds.control_points, ds.images, ground_points=ds.ground_points, frames=ds.frames,
                  observations=ds.observations)
    assert (copy / "dataset.yaml").read_bytes() == (root / "dataset.yaml").read_bytes()
    (copy / "images").symlink_to(root / "images")
    assert Dataset.load(copy).cameras == ds.cameras
    assert f"C1 {W}x{H} model opencv" in ds.summary() and "C0 " in ds.summary()


def test_optional_files_absent_and_extra_columns(tmp_path):
    inputs = _inputs()
    inputs["images"] = inputs["images"][inputs["images"]["stage"] != "flight"]
    inputs["control_points"]["surveyor"] = "bob"
    root = tmp_path / "ds"
    write_dataset(root, inputs["manifest"], inputs["control_points"], inputs["images"])
    assert "prior_q" in (root / "images.csv").read_text()
    for path in inputs["images"]["path"]:
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / path), np.zeros((H, W), np.uint8))
    ds = Dataset.load(root)
    assert ds.ground_points.empty and list(ds.ground_points.columns) == ["x", "y", "z"]
    assert ds.frames.empty and ds.observations.empty
    assert list(ds.control_points["surveyor"]) == ["bob"] * 4


def test_priors_omitted_when_absent(tmp_path):
    inputs = _inputs()
    images = inputs["images"].drop(columns=["prior_qw", "prior_qx", "prior_qy", "prior_qz"])
    images[["prior_x", "prior_y", "prior_z"]] = np.nan
    write_dataset(tmp_path, inputs["manifest"], inputs["control_points"], images)
    header = (tmp_path / "images.csv").read_text().splitlines()[0]
    assert header == "image,camera,stage,split,placement,path"


def test_read_image_converts_colour_and_keeps_16_bit(root):
    cv2.imwrite(str(root / "images/i0.png"), np.full((H, W, 3), (10, 20, 30), np.uint8))
    cv2.imwrite(str(root / "images/i1.png"), np.full((H, W), 40000, np.uint16))
    ds = Dataset.load(root)
    gray = ds.read_image("i0")
    assert gray.shape == (H, W) and gray.dtype == np.uint8
    assert ds.read_image("i1").dtype == np.uint16
    assert ds.check_images() == 4


def test_read_image_gives_the_files_pixels_in_every_format(root):
    """PNG, TIFF (uncompressed and LZW) and JPEG, 8- and 16-bit, grey, BGR and BGRA: the pixels as
    written (lossless) or as cv2.imdecode of the file's bytes converted to grey (JPEG, colour)."""
    rng = np.random.default_rng(7)
    grey8 = rng.integers(0, 256, (H, W), dtype=np.uint8)
    grey16 = rng.integers(0, 65536, (H, W), dtype=np.uint16)
    colour = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    files = [("a.png", grey8, []), ("b.png", grey16, []), ("c.tif", grey16, [cv2.IMWRITE_TIFF_COMPRESSION, 1]),
             ("d.tif", grey8, [cv2.IMWRITE_TIFF_COMPRESSION, 5]), ("e.jpg", grey8, [cv2.IMWRITE_JPEG_QUALITY, 90]),
             ("f.jpg", colour, []), ("g.png", np.dstack([colour, grey8]), []), ("h.tif", colour, [])]
    for name, pixels, flags in files:
        assert cv2.imwrite(str(root / "images" / name), pixels, flags)
    rows = pd.read_csv(root / "images.csv", dtype=str, keep_default_na=False)
    extra = pd.DataFrame([{**rows.iloc[1].to_dict(), "image": f"x{k}", "path": f"images/{name}"}
                          for k, (name, _, _) in enumerate(files)])
    pd.concat([rows, extra]).to_csv(root / "images.csv", index=False)
    ds = Dataset.load(root)
    for k, (name, pixels, _) in enumerate(files):
        decoded = cv2.imdecode(np.frombuffer((root / "images" / name).read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED)
        if decoded.ndim == 3:
            decoded = cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY if decoded.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        expected = pixels if name.endswith((".png", ".tif")) and pixels.ndim == 2 else decoded
        got = ds.read_image(f"x{k}")
        assert got.dtype == expected.dtype and np.array_equal(got, expected), name


def test_a_dataset_under_a_folder_whose_name_is_not_utf8_reads_its_images(tmp_path):
    """A path OpenCV cannot take as text (bytes that are not UTF-8, as the command line can give):
    the file's bytes are decoded instead of OpenCV being handed the name (its binding would crash)."""
    root = _write(tmp_path / os.fsdecode(b"fl\xfcge"), _inputs())
    ds = Dataset.load(root)
    assert np.array_equal(ds.read_image("i0"), np.full((H, W), 128, np.uint8))
    assert ds.check_images() == 4


def test_the_memory_of_a_freed_image_serves_the_next_without_fresh_pages():
    """After keep_freed_image_memory, a second block of a 12 MP 16-bit image's size (24 MB) reuses the
    first's pages: no page faults, where the default allocator maps it anew and faults its pages in again."""
    code = ("import resource, sys\n"
            "import numpy as np\n"
            "from dmais_pipe.dataset import keep_freed_image_memory\n"
            "assert sys.argv[1] == 'default' or keep_freed_image_memory()\n"
            "first = np.ones(24 * 2**20, np.uint8)\n"
            "del first\n"
            "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
            "second = np.ones(24 * 2**20, np.uint8)\n"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n")
    default, kept = (int(subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True,
                                        check=True).stdout) for mode in ("default", "keep"))
    assert default >= 12 and kept <= default // 10, (default, kept)  # 12 huge pages or 6,144 small at least


def test_an_images_row_found_by_its_id_is_the_masks(root):
    """image_path and read_image find the row through the grouped positions; it is the boolean mask's,
    in the whole load and in a slice of it, and an unknown image is refused."""
    ds = Dataset.load(root)
    for part in (ds, ds.restricted(["f1", "e0"], part="a slice")):
        for image in part.images["image"]:
            row = part.images[part.images["image"] == image].iloc[0]
            assert part._row(image).equals(row)
            assert part.image_path(image) == (part.root / row["path"] if row["path"] else None)
    with pytest.raises(DatasetError, match="unknown image 'i0'"):
        ds.restricted(["f1"]).image_path("i0")


def test_quaternions_are_normalized(root):
    _set_cells(root, "images.csv", 0, prior_qw="2", prior_qx="0", prior_qy="0", prior_qz="0")
    assert Dataset.load(root).images.loc[0, ["prior_qw", "prior_qx"]].tolist() == [1.0, 0.0]


def test_load_observations_from_dataset_and_results(root, tmp_path):
    ds = Dataset.load(root)
    given = Workspace(ds, tmp_path / "nothing-yet").load_observations()
    assert list(given.columns) == ["image", "camera", "point_id", "u", "v"]
    assert list(given["camera"]) == ["C0", "C0", "C0"]
    results = tmp_path / "results"
    results.mkdir()
    assert Workspace(ds, results).load_observations().equals(given)
    (results / "observations.csv").write_text("image,camera,point_id,u,v\ni1,C1,A1,1.5,2.5\n")
    found = Workspace(ds, results).load_observations()
    assert found.loc[0, "point_id"] == "A1" and found.loc[0, "u"] == 1.5
    (results / "observations.csv").write_text("image,camera,point_id,u,v\ni1,C0,A1,1.5,2.5\n")
    with pytest.raises(DatasetError, match=r"results/observations\.csv, line 2: camera 'C0'"):
        Workspace(ds, results).load_observations()


# ------------------------------------------------------------------------------ malformed datasets


def _rows(root: Path, name: str) -> list[list[str]]:
    with (root / name).open(newline="") as file:
        return list(csv.reader(file))


def _save_rows(root: Path, name: str, rows: list[list[str]]) -> None:
    with (root / name).open("w", newline="") as file:
        csv.writer(file, lineterminator="\n").writerows(rows)


def _set_cells(root: Path, name: str, row: int, **values) -> None:
    """Set cells of data row `row` (0-based; file line row + 2)."""
    rows = _rows(root, name)
    for column, value in values.items():
        rows[row + 1][rows[0].index(column)] = value
    _save_rows(root, name, rows)


def _drop_column(root: Path, name: str, column: str) -> None:
    rows = _rows(root, name)
    k = rows[0].index(column)
    _save_rows(root, name, [row[:k] + row[k + 1:] for row in rows])


def _append_copy(root: Path, name: str, row: int) -> None:
    rows = _rows(root, name)
    _save_rows(root, name, rows + [rows[row + 1]])


def _edit_manifest(root: Path, **changes) -> None:
    data = yaml.safe_load((root / "dataset.yaml").read_text())
    data.update(changes)
    (root / "dataset.yaml").write_text(yaml.safe_dump(data))


# (edit, file named, line or None, substrings the message must contain)
LOAD_ERRORS = {
    "missing images.csv": (lambda r: (r / "images.csv").unlink(), "images.csv", None, ["missing"]),
    "missing manifest": (lambda r: (r / "dataset.yaml").unlink(), "dataset.yaml", None, ["missing"]),
    "missing frames.csv": (lambda r: (r / "frames.csv").unlink(), "frames.csv", None, ["flight images", "line 5"]),
    "missing column": (lambda r: _drop_column(r, "control_points.csv", "z"), "control_points.csv", 1,
                       ["missing column(s) z"]),
    "NaN coordinate": (lambda r: _set_cells(r, "control_points.csv", 1, x="nan"), "control_points.csv", 3,
                       ["column x", "'nan'"]),
    "empty coordinate": (lambda r: _set_cells(r, "ground_points.csv", 0, z=""), "ground_points.csv", 2,
                         ["column z is empty"]),
    "text in number": (lambda r: _set_cells(r, "observations.csv", 2, u="abc"), "observations.csv", 4,
                       ["column u", "'abc'"]),
    "inf in frame": (lambda r: _set_cells(r, "frames.csv", 0, pos_z="inf"), "frames.csv", 2, ["pos_z", "'inf'"]),
    "duplicate point id": (lambda r: _set_cells(r, "control_points.csv", 2, point_id="007"), "control_points.csv",
                           4, ["duplicate point id '007'", "line 2"]),
    "duplicate across files": (lambda r: _set_cells(r, "ground_points.csv", 1, point_id="A1"), "ground_points.csv",
                               3, ["'A1'", "control_points.csv, line 3"]),
    "duplicate image": (lambda r: _set_cells(r, "images.csv", 1, image="i0"), "images.csv", 3,
                        ["duplicate image id 'i0'", "line 2"]),
    "unknown camera": (lambda r: _set_cells(r, "images.csv", 2, camera="C9"), "images.csv", 4,
                       ["unknown camera 'C9'"]),
    "bad stage": (lambda r: _set_cells(r, "images.csv", 1, stage="flying"), "images.csv", 3, ["stage 'flying'"]),
    "missing split": (lambda r: _set_cells(r, "images.csv", 1, split=""), "images.csv", 3, ["split is empty"]),
    "split outside intrinsics": (lambda r: _set_cells(r, "images.csv", 2, split="calib"), "images.csv", 4,
                                 ["split 'calib'"]),
    "missing placement": (lambda r: _set_cells(r, "images.csv", 2, placement=""), "images.csv", 4,
                          ["placement is empty"]),
    "placement not a frame": (lambda r: _set_cells(r, "images.csv", 4, placement="nope"), "images.csv", 6,
                              ["'f1'", "'nope'", "frames.csv"]),
    "image file missing": (lambda r: (r / "images/e0.png").unlink(), "images.csv", 4,
                           ["'e0'", "'images/e0.png' does not exist"]),
    "no path, no observations": (lambda r: _set_cells(r, "images.csv", 1, path=""), "images.csv", 3,
                                 ["'i1'", "neither a path nor rows in observations.csv"]),
    "partial prior": (lambda r: _set_cells(r, "images.csv", 2, prior_y="", prior_z=""), "images.csv", 4,
                      ["prior_x, prior_y, prior_z", "only prior_x"]),
    "zero quaternion": (lambda r: _set_cells(r, "frames.csv", 0, prior_qw="0"), "frames.csv", 2,
                        ["quaternion norm"]),
    "observation unknown point": (lambda r: _set_cells(r, "observations.csv", 1, point_id="ZZ"),
                                  "observations.csv", 3, ["unknown point id 'ZZ'"]),
    "observation unknown image": (lambda r: _set_cells(r, "observations.csv", 0, image="x9"),
                                  "observations.csv", 2, ["unknown image 'x9'"]),
    "duplicate observation": (lambda r: _append_copy(r, "observations.csv", 1), "observations.csv", 5,
                              ["duplicate observation", "('f0', 'G2')", "line 3"]),
    "wrong field count": (lambda r: (r / "ground_points.csv").open("a").write("G9,1,2\n"), "ground_points.csv", 4,
                          ["3 fields"]),
    "unknown manifest key": (lambda r: _edit_manifest(r, marker_size=2), "dataset.yaml", None,
                             ["unknown key 'marker_size'"]),
    "reference not a camera": (lambda r: _edit_manifest(r, reference_camera="C7"), "dataset.yaml", None,
                               ["reference_camera 'C7'"]),
    "bad width": (lambda r: _edit_manifest(r, cameras={"C0": {"width": 0, "height": H}, "C1": {"width": W,
                                                                                               "height": H}}),
                  "dataset.yaml", None, ["cameras.C0.width", "positive integer"]),
    "unknown camera model": (lambda r: _edit_manifest(r, cameras={"C0": {"width": W, "height": H},
                                                                  "C1": {"width": W, "height": H, "model": "fisheye"}}),
                             "dataset.yaml", None, ["cameras.C1.model must be one of radial1, opencv, got 'fisheye'"]),
    "invalid yaml": (lambda r: (r / "dataset.yaml").write_text("name: [unclosed\n"), "dataset.yaml", 2,
                     ["invalid YAML"]),
    "no control points": (lambda r: (r / "control_points.csv").write_text("point_id,x,y,z\n"),
                          "control_points.csv", None, ["no points"]),
    "collinear field": (lambda r: (r / "control_points.csv").write_text(
        "point_id,x,y,z\n007,0,0,0\nA1,1,2,3\nA2,2,4.0001,6\nA3,-3,-6,-9\n"), "control_points.csv", None,
        ["4 control points are collinear", "plane or a volume"]),
    "coincident field": (lambda r: (r / "control_points.csv").write_text(
        "point_id,x,y,z\n007,5,5,5\nA1,5,5,5\nA2,5,5,5\n"), "control_points.csv", None, ["coincide"]),
    "observation far outside its image": (lambda r: _set_cells(r, "observations.csv", 0, u="1e6"),
                                          "observations.csv", 2, ["(1e+06, 30.125) lies outside image 'f0'",
                                                                  "(64x48 px)"]),
    "observation just outside its image": (lambda r: _set_cells(r, "observations.csv", 2, v=str(H - 0.5 + 2.01)),
                                           "observations.csv", 4, ["lies outside image 'i0'"]),
}


@pytest.mark.parametrize("case", list(LOAD_ERRORS))
def test_malformed_dataset_names_file_and_line(root, case):
    edit, name, line, parts = LOAD_ERRORS[case]
    edit(root)
    with pytest.raises(DatasetError) as info:
        Dataset.load(root)
    message = str(info.value)
    where = name if line is None else f"{name}, line {line}:"
    assert where in message and Path(info.value.path).name == name and info.value.line == line, message
    for part in parts:
        assert part in message, message


IMAGE_ERRORS = {
    "cannot be decoded": (lambda r: (r / "images/i1.png").write_bytes(b"garbage, not a PNG"), 3,
                          ["'i1'", "'images/i1.png' cannot be decoded"]),
    "wrong size": (lambda r: cv2.imwrite(str(r / "images/e0.png"), np.zeros((32, 40), np.uint8)), 4,
                   ["'e0'", "is 40x32, camera C1 expects 64x48"]),
}


@pytest.mark.parametrize("case", list(IMAGE_ERRORS))
def test_bad_image_file_found_by_check_images(root, case):
    edit, line, parts = IMAGE_ERRORS[case]
    edit(root)
    ds = Dataset.load(root)
    with pytest.raises(DatasetError) as info:
        ds.check_images()
    message = str(info.value)
    assert f"images.csv, line {line}:" in message, message
    for part in parts:
        assert part in message, message


def test_planar_field_and_observations_on_the_image_border_load(root):
    (root / "control_points.csv").write_text("point_id,x,y,z\n007,0,0,0\nA1,1,0,0\nA2,0,1,0\nA3,1,1,0\n"
                                             "G9,0.5,0.5,0\n")
    (root / "ground_points.csv").write_text("point_id,x,y,z\nG1,1,2,3\nG2,2,3,4\n")
    _set_cells(root, "observations.csv", 0, u=str(-0.5 - 2.0), v=str(H - 0.5 + 2.0))
    ds = Dataset.load(root)
    assert len(ds.control_points) == 5 and ds.observations.loc[0, "u"] == -2.5


def test_results_observations_outside_an_image_are_refused(root, tmp_path):
    ds = Dataset.load(root)
    (tmp_path / "observations.csv").write_text(f"image,camera,point_id,u,v\ni1,C1,A1,{W + 10},2.5\n")
    with pytest.raises(DatasetError, match=r"observations\.csv, line 2: observation \(74, 2\.5\) lies outside "
                                           r"image 'i1' \(64x48 px\)"):
        Workspace(ds, tmp_path).load_observations()


def test_point_ids_stay_strings(root):
    assert _rows(root, "control_points.csv")[1][0] == "007"
    ds = Dataset.load(root)
    assert pd.api.types.is_string_dtype(ds.control_points.index) and ds.control_points.index[0] == "007"
    assert pd.api.types.is_string_dtype(ds.observations["point_id"]) and ds.observations.loc[2, "point_id"] == "007"


# ------------------------------------------------------------------------------ CLI


def test_validate_cli(root, capsys):
    assert main(["validate", str(root)]) == 0
    assert "dataset tiny" in capsys.readouterr().out
    _set_cells(root, "images.csv", 2, camera="C9")
    assert main(["validate", str(root)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "unknown camera 'C9'" in err and "images.csv, line 4" in err
    _set_cells(root, "images.csv", 2, camera="C1")
    _edit_manifest(root, cameras={"C0": {"width": W, "height": H}, "C1": {"width": W, "height": H, "model": "OpenCV"}})
    assert main(["validate", str(root)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "cameras.C1.model must be one of radial1, opencv" in err, err


def test_truncated_png_is_one_line_without_the_decoders_own(root, capfd):
    """libpng writes its complaint straight to file descriptor 2: it is folded into our one line."""
    cv2.imwrite(str(root / "images/i1.png"), (np.random.default_rng(0).random((H, W)) * 255).astype(np.uint8))
    data = (root / "images/i1.png").read_bytes()
    (root / "images/i1.png").write_bytes(data[: len(data) // 2])
    assert main(["validate", str(root)]) == 2
    err = capfd.readouterr().err.strip()
    assert err.splitlines() == [err] and "line 3: image 'i1': file 'images/i1.png' cannot be decoded (" in err
    assert "incomplete" in err and "WARN" not in err


def test_simulator_config_with_a_yaml_error_is_one_line(tmp_path, capsys):
    (tmp_path / "sim.yaml").write_text("name: x\nseed: [1\n")
    assert main(["simulate", str(tmp_path / "sim.yaml"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "sim.yaml, line 3: invalid YAML: expected ',' or ']'" in err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ survey sigma of the points


def test_points_survey_sigma_is_read_and_written_and_optional(tmp_path):
    inputs = _inputs()
    inputs["control_points"]["sigma_m"] = [0.001, np.nan, 0.002, 0.0]
    root = _write(tmp_path / "ds", inputs)
    assert _rows(root, "control_points.csv")[0] == ["point_id", "x", "y", "z", "sigma_m"]
    assert _rows(root, "control_points.csv")[2][4] == ""  # the point without one
    ds = Dataset.load(root)
    np.testing.assert_array_equal(ds.control_points["sigma_m"].to_numpy(), [0.001, np.nan, 0.002, 0.0])
    assert "sigma_m" not in ds.ground_points.columns  # a file without the column has none
    assert np.isnan(ds.points.loc["G1", "sigma_m"])


def test_points_vertical_survey_sigma_is_read_written_and_looked_up_per_axis(tmp_path):
    inputs = _inputs()
    inputs["ground_points"]["sigma_m"] = [0.015, np.nan]
    inputs["ground_points"]["sigma_z_m"] = [0.025, 0.03]
    root = _write(tmp_path / "ds", inputs)
    assert _rows(root, "ground_points.csv")[0] == ["point_id", "x", "y", "z", "sigma_m", "sigma_z_m"]
    ds = Dataset.load(root)
    ids = ["G1", "G2", "A1", "nowhere"]
    np.testing.assert_array_equal(point_sigma(ds.points, ids), [
        [0.015, 0.015, 0.025], [np.nan, np.nan, 0.03], [np.nan] * 3, [np.nan] * 3])
    np.testing.assert_array_equal(largest_point_sigma(ds.points, ids), [0.025, 0.03, np.nan, np.nan])  # NaN: none given


@pytest.mark.parametrize("column", ["sigma_m", "sigma_z_m"])
@pytest.mark.parametrize("cell, message", [("-0.01", "-0.01 is negative"),
                                           ("abc", "'abc' is not a finite number"),
                                           ("inf", "'inf' is not a finite number")])
def test_points_survey_sigma_that_is_not_a_sigma_is_refused_naming_the_line(tmp_path, column, cell, message):
    inputs = _inputs()
    inputs["ground_points"][column] = [0.02, 0.03]
    root = _write(tmp_path / "ds", inputs)
    _set_cells(root, "ground_points.csv", 1, **{column: cell})
    message = f"column {column}: {message}"
    with pytest.raises(DatasetError, match=rf"ground_points\.csv, line 3: {message}"):
        Dataset.load(root)
