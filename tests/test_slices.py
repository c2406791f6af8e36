"""A job's slice of the dataset (slices.py): what a marker batch's or a flight group's job reads is
the whole load filtered to its images, frames and observations; a changed input is never read from
a slice; and a job gives the same results from its slice as from the whole dataset."""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from dmais_pipe import cli
from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import DatasetError
from dmais_pipe.plan import marker_batches
from dmais_pipe.slices import batch_workspace, group_workspace, write_group_slices, write_marker_slices
from dmais_pipe.stages import markers, pose
from dmais_pipe.workspace import Workspace

from conftest import observation_only
from test_marker_batches import IMAGES, RENDERED

#: The pose stage's small flight (tests/test_pose_stage.py), so that the session simulates it once.
SIM = observation_only("pose-small", seed=5, calib_images=6, eval_images=2, frames_per_group=2)
SLICE_PER_JOB = 3


@pytest.fixture
def root(simulated_dataset, tmp_path) -> Path:
    """A copy of SIM where every image k of images.csv with k % 3 != 0 has a file and no given
    observations (so the stages' batches have images to extract), the others as simulated."""
    root = shutil.copytree(simulated_dataset(SIM), tmp_path / "dataset")
    (root / "images").mkdir()
    (root / "images" / "blank.png").write_bytes(b"never decoded here")
    images = pd.read_csv(root / "images.csv", dtype=str, keep_default_na=False)
    extracted = [k % 3 != 0 for k in range(len(images))]
    images.loc[extracted, "path"] = "images/blank.png"
    images.to_csv(root / "images.csv", index=False)
    given = pd.read_csv(root / "observations.csv", dtype=str, keep_default_na=False)
    given[~given["image"].isin(images["image"][extracted])].to_csv(root / "observations.csv", index=False)
    return root


def _same_dataset(part: Dataset, whole: Dataset, images, frames) -> None:
    """`part` is `whole` with only the rows of `images` and `frames`."""
    chosen = whole.images[whole.images["image"].isin(images)]
    pd.testing.assert_frame_equal(part.images, chosen)
    pd.testing.assert_frame_equal(part.frames, whole.frames[whole.frames["frame"].isin(frames)])
    pd.testing.assert_frame_equal(part.observations, whole.observations[whole.observations["image"].isin(images)])
    pd.testing.assert_frame_equal(part.control_points, whole.control_points)
    pd.testing.assert_frame_equal(part.ground_points, whole.ground_points)
    assert part.image_lines == {image: whole.image_lines[image] for image in chosen["image"]}
    same = ("root", "name", "reference_camera", "cameras", "marker_size_m", "description", "stamps")
    assert all(getattr(part, name) == getattr(whole, name) for name in same)
    assert part.part and not whole.part


def test_a_batch_slice_is_the_whole_load_filtered(root, tmp_path):
    whole, results = Dataset.load(root), tmp_path / "results"
    batches = marker_batches(whole, SLICE_PER_JOB)
    assert {batch["stage"] for batch in batches.values()} == {"intrinsics", "extrinsics", "flight"}
    write_marker_slices(whole, results, SLICE_PER_JOB)
    for name, batch in batches.items():
        workspace = batch_workspace(root, results, name, SLICE_PER_JOB)
        placements = whole.images.loc[whole.images["image"].isin(batch["images"])
                                      & (whole.images["stage"] == "flight"), "placement"]
        _same_dataset(workspace.dataset, whole, batch["images"], placements)
        assert workspace.marker_batches(SLICE_PER_JOB) == {name: batch}
        with pytest.raises(ValueError, match="holds only marker batch"):
            workspace.load_observations()
    # another batch size is another plan: its jobs load the whole dataset
    assert not batch_workspace(root, results, name, SLICE_PER_JOB + 1).dataset.part


def test_a_group_slice_is_the_whole_load_filtered(root, tmp_path):
    whole = Workspace.open(root, tmp_path / "results")
    given = whole.load_observations()
    whole.root.mkdir()
    given.iloc[::2].to_csv(tmp_path / "results" / "observations.csv", index=False)  # read instead of the dataset's
    observations = whole.load_observations()
    assert len(observations) < len(given)
    write_group_slices(whole)
    flight = whole.dataset.images_of("flight")
    groups = whole.dataset.frames.groupby("group")["frame"]
    assert len(groups) > 1
    for group, frames in groups:
        workspace = group_workspace(root, whole.root, group)
        images = flight.loc[flight["placement"].isin(frames), "image"]
        _same_dataset(workspace.dataset, whole.dataset, images, frames)
        pd.testing.assert_frame_equal(workspace.load_observations(), observations[observations["image"].isin(images)])


def test_a_dataset_without_batches_has_no_slices(simulated_dataset, tmp_path):
    whole = Dataset.load(simulated_dataset(SIM))  # every image's observations given: nothing to extract
    assert not marker_batches(whole, SLICE_PER_JOB)
    (listed,) = write_marker_slices(whole, tmp_path / "results", SLICE_PER_JOB)
    assert listed == tmp_path / "results" / "slices" / "markers.json"
    assert json.loads(listed.read_text())["slices"] == {}


def _touch_later(path: Path) -> None:
    """`path` with the same content and size but another modification time."""
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))


def test_a_changed_input_is_never_read_from_a_slice(root, tmp_path):
    whole, results = Dataset.load(root), tmp_path / "results"
    name = next(iter(marker_batches(whole, SLICE_PER_JOB)))
    group = whole.frames["group"].iloc[0]
    write_marker_slices(whole, results, SLICE_PER_JOB)
    write_group_slices(Workspace(whole, results))
    assert batch_workspace(root, results, name, SLICE_PER_JOB).dataset.part
    assert group_workspace(root, results, group).dataset.part
    _touch_later(root / "frames.csv")
    assert not batch_workspace(root, results, name, SLICE_PER_JOB).dataset.part
    assert not group_workspace(root, results, group).dataset.part

    write_marker_slices(Dataset.load(root), results, SLICE_PER_JOB)
    write_group_slices(Workspace.open(root, results))
    assert group_workspace(root, results, group).dataset.part
    Workspace(whole, tmp_path).load_observations().to_csv(results / "observations.csv", index=False)
    assert not group_workspace(root, results, group).dataset.part  # a results file appeared

    # a table broken after the slices were cut: the job stops with the whole load's error
    lines = (root / "images.csv").read_text().splitlines()
    (root / "images.csv").write_text("\n".join([*lines, lines[-1]]) + "\n")
    assert_the_job_stops_as_the_load(root, results, name, "duplicate image id")


def assert_the_job_stops_as_the_load(root, results, name: str, message: str) -> None:
    """The marker batch `name`'s job stops with the whole load's error, which says `message`."""
    with pytest.raises(DatasetError) as from_load:
        Dataset.load(root)
    with pytest.raises(DatasetError) as from_job:
        batch_workspace(root, results, name, SLICE_PER_JOB)
    assert message in str(from_job.value) and str(from_job.value) == str(from_load.value)


def test_a_slice_checks_the_files_of_its_images(root, tmp_path):
    whole, results = Dataset.load(root), tmp_path / "results"
    batches = marker_batches(whole, SLICE_PER_JOB)
    write_marker_slices(whole, results, SLICE_PER_JOB)
    first = whole.images.loc[whole.images["path"] != "", "image"].iloc[0]  # the load names it first
    name = next(name for name, batch in batches.items() if first in batch["images"])
    (root / "images" / "blank.png").unlink()  # no table changes: the slices stay current
    assert_the_job_stops_as_the_load(root, results, name, "does not exist")


def test_the_plan_never_writes_into_the_dataset(root, capsys):
    assert cli.main(["plan", str(root), "--out", str(root / "results"), "--slices", "markers"]) == 2
    assert "only reads" in capsys.readouterr().err and not (root / "results").exists()
    assert cli.main(["plan", str(root), "--slices", "pose"]) == 2
    assert "needs --out" in capsys.readouterr().err


def test_a_pose_job_solves_the_same_from_its_slice(simulated_dataset, tmp_path, caplog):
    dataset = simulated_dataset(SIM)
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(dataset / "truth" / "rig.json", results / "rig.json")
    group = sorted(Dataset.load(dataset).frames["group"].unique())[1]
    whole = pose.run(Workspace.open(dataset, results), groups=[group], out=tmp_path / "whole" / "part.csv")
    assert cli.main(["plan", str(dataset), "--out", str(results), "--slices", "pose"]) == 0
    caplog.clear()
    caplog.set_level(logging.INFO, logger="dmais_pipe.slices")
    assert cli.main(["pose", str(dataset), "--out", str(results), "--groups", group, "--csv",
                     str(tmp_path / "sliced" / "part.csv")]) == 0
    assert f"flight group {group} of" in caplog.text
    for path in whole:
        expected, got = pd.read_csv(path), pd.read_csv(tmp_path / "sliced" / path.name)
        assert len(got)
        pd.testing.assert_frame_equal(got.drop(columns="time_ms", errors="ignore"),
                                      expected.drop(columns="time_ms", errors="ignore"))


def test_a_marker_job_finds_the_same_from_its_slice(simulated_dataset, tmp_path, caplog):
    dataset, batch = simulated_dataset(RENDERED), "intrinsics-C0-2"  # one image a job: IMAGES[1]
    whole = Workspace.open(dataset, tmp_path / "whole")
    markers.run_batch(whole, batch, 1)
    sliced = tmp_path / "sliced"
    assert cli.main(["plan", str(dataset), "--per-job", "1", "--out", str(sliced), "--json", str(sliced / "plan.json"),
                     "--slices", "markers"]) == 0
    caplog.clear()
    caplog.set_level(logging.INFO, logger="dmais_pipe.slices")
    assert cli.main(["markers", str(dataset), "--out", str(sliced), "--batch", batch, "--per-job", "1"]) == 0
    assert f"marker batch {batch} of" in caplog.text
    assert (sliced / "markers" / f"{IMAGES[1]}.csv").read_bytes() == whole.markers_path(IMAGES[1]).read_bytes()
    counts = ["image", "camera", "detected", "identified", "resumed"]
    pd.testing.assert_frame_equal(pd.read_csv(sliced / "markers" / "batches" / f"{batch}.csv")[counts],
                                  pd.read_csv(whole.marker_batch_path(batch))[counts])
