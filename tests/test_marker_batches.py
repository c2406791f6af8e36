"""Marker extraction in batches: how the images are split into jobs (plan.marker_batches) and how a
batch job resumes after a failure or a kill (stages.markers.run_batch and its progress file)."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from dmais_pipe import cli
from dmais_pipe.dataset import STAGES, Dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.plan import MARKERS_PER_JOB, marker_batches, workflow_plan
from dmais_pipe.sim.config import DEFAULTS
from dmais_pipe.stages import markers
from dmais_pipe.stages.markers import BATCH_COLUMNS
from dmais_pipe.workspace import Workspace

from conftest import observation_only
from test_dataset import _inputs, _write

#: Two cameras, four rendered intrinsics images each (~7 s to simulate); nothing else rendered.
RENDERED = {
    "name": "batches-rendered", "seed": 5,
    "rig": {"cameras": {name: DEFAULTS["rig"]["cameras"][name] for name in ("C0", "C1")}},
    "intrinsics": {"calib_images_per_camera": 3, "eval_images_per_camera": 1},
    "flight": {"frames_per_group": 1},
    "render": {"intrinsics": True, "extrinsics": False, "flight": False},
}
BATCH, PER_JOB = "intrinsics-C0-1", 4  # with 4 images a job, C0's intrinsics images are one batch
IMAGES = [f"intr_C0_{k:03d}" for k in range(4)]

#: Five cameras, every stage, no images rendered: files are attached by `plan_dataset`.
PLANNED = observation_only("batches-plan", seed=4, calib_images=10, eval_images=2, frames_per_group=3)


# ------------------------------------------------------------------------------ marker_batches


@pytest.fixture(scope="module")
def plan_dataset(simulated_dataset, tmp_path_factory):
    """A copy of PLANNED where, in images.csv order, image k has: k % 7 == 0 no file (its observations
    given), k % 7 == 1 a file and its observations given (so not extracted), else a file and no given
    observations (extracted); 7 and the 5 cameras of a flight frame mix the three within a camera.
    Returns the dataset and {(stage, camera): images to extract, in order}."""
    root = tmp_path_factory.mktemp("plan") / "dataset"
    shutil.copytree(simulated_dataset(PLANNED), root)
    (root / "images").mkdir()
    (root / "images" / "blank.png").write_bytes(b"not decoded by marker_batches")
    images = pd.read_csv(root / "images.csv", dtype=str, keep_default_na=False)
    observations = pd.read_csv(root / "observations.csv", dtype=str, keep_default_na=False)
    observed = set(observations["image"])
    extracted = [k % 7 > 1 or images["image"][k] not in observed for k in range(len(images))]
    images["path"] = ["" if k % 7 == 0 and images["image"][k] in observed else "images/blank.png"
                      for k in range(len(images))]
    dropped = set(images["image"][extracted])
    images.to_csv(root / "images.csv", index=False)
    observations[~observations["image"].isin(dropped)].to_csv(root / "observations.csv", index=False)
    expected = {}
    for image, stage, camera, extract in zip(images["image"], images["stage"], images["camera"], extracted):
        if extract:
            expected.setdefault((stage, camera), []).append(image)
    return Dataset.load(root), expected


def _check_batches(batches: dict, expected: dict[tuple[str, str], list[str]], per_job: int) -> None:
    """`batches` is `expected` (images to extract per stage and camera) split as documented."""
    names = set()
    for (stage, camera), images in expected.items():
        count = math.ceil(len(images) / per_job)
        ours = [f"{stage}-{camera}-{k:0{len(str(count))}d}" for k in range(1, count + 1)]
        names.update(ours)
        for name in ours:
            assert name in batches, (name, per_job)
            assert (batches[name]["stage"], batches[name]["camera"]) == (stage, camera), name
        runs = [batches[name]["images"] for name in ours]
        assert [image for run in runs for image in run] == images, (stage, camera, per_job)  # in order, each once
        sizes = [len(run) for run in runs]
        assert max(sizes) <= per_job and max(sizes) - min(sizes) <= 1 and min(sizes) >= 1, (stage, camera, sizes)
    assert set(batches) == names  # no other batch (none for a stage and camera without images to extract)


@pytest.mark.parametrize("per_job", [1, 2, 3, 4, 7, 12, 13, MARKERS_PER_JOB])
def test_batches_split_each_stage_and_camera_into_near_equal_runs(plan_dataset, per_job):
    dataset, expected = plan_dataset
    assert {stage for stage, _ in expected} == set(STAGES) and len({c for _, c in expected}) == 5  # all kinds
    assert len(expected) < len(STAGES) * 5  # and a stage with a camera that has nothing to extract
    assert max(len(images) for images in expected.values()) >= 10  # names of two digits with per_job=1
    batches = marker_batches(dataset, per_job)
    _check_batches(batches, expected, per_job)
    assert sorted(image for batch in batches.values() for image in batch["images"]) == sorted(
        dataset.images_to_extract())
    plan = workflow_plan(dataset, per_job)
    assert plan["batches"] == {stage: {name: {"camera": batch["camera"], "images": len(batch["images"])}
                                       for name, batch in batches.items() if batch["stage"] == stage}
                               for stage in STAGES}


def test_batch_names_are_as_documented(plan_dataset):
    dataset, expected = plan_dataset
    stage, camera = max(expected, key=lambda group: len(expected[group]))
    images = expected[stage, camera]
    assert 10 <= len(images) < 100
    one_each = marker_batches(dataset, 1)
    assert [one_each[f"{stage}-{camera}-{k:02d}"]["images"] for k in range(1, len(images) + 1)] == [[i] for i in images]
    assert f"{stage}-{camera}-1" not in one_each and f"{stage}-{camera}-{len(images) + 1:02d}" not in one_each
    halves = marker_batches(dataset, math.ceil(len(images) / 2))
    assert halves[f"{stage}-{camera}-1"]["images"] + halves[f"{stage}-{camera}-2"]["images"] == images
    everything = marker_batches(dataset, 10_000)
    assert everything == {f"{stage}-{camera}-1": {"stage": stage, "camera": camera, "images": images}
                          for (stage, camera), images in expected.items()}


class _Listed:
    """As much of a Dataset as marker_batches reads: images of three cameras in a given order."""

    def __init__(self, counts: dict[tuple[str, str], int]):
        rows = [(f"{stage}-{camera}-img{k}", camera, stage)
                for (stage, camera), n in counts.items() for k in range(n)]
        rows = rows[::2] + rows[1::2]  # interleave the cameras and stages of images.csv
        self.images = pd.DataFrame(rows, columns=["image", "camera", "stage"])
        self.cameras = {"A": None, "B": None, "C": None}

    def images_to_extract(self, stage=None):
        return [image for image, s in zip(self.images["image"], self.images["stage"]) if stage in (None, s)]


@pytest.mark.parametrize("per_job", [1, 2, 3, 5, 6, 10, 11])
def test_batches_of_every_size_near_the_limits(per_job):
    """Counts around multiples of per_job (exact, one more, one less) and none at all."""
    sizes = [0, 1, per_job - 1, per_job, per_job + 1, 2 * per_job, 2 * per_job + 1, 3 * per_job - 1, 23]
    for first in range(0, len(sizes), 3):
        counts = {(stage, camera): sizes[(first + i) % len(sizes)]
                  for i, (stage, camera) in enumerate((s, c) for s in STAGES for c in "ABC")}
        listed = _Listed(counts)
        expected = {}
        for image, stage, camera in zip(listed.images["image"], listed.images["stage"], listed.images["camera"]):
            expected.setdefault((stage, camera), []).append(image)
        _check_batches(marker_batches(listed, per_job), expected, per_job)


@pytest.mark.parametrize("per_job", [0, -1])
def test_fewer_than_one_image_per_job_is_refused(plan_dataset, per_job):
    with pytest.raises(ValueError, match=f"per_job must be at least 1, got {per_job}"):
        marker_batches(plan_dataset[0], per_job)
    with pytest.raises(ValueError, match="per_job must be at least 1"):
        workflow_plan(plan_dataset[0], per_job)


# ------------------------------------------------------------------------------ run_batch


@pytest.fixture(scope="module")
def rendered(simulated_dataset):
    return simulated_dataset(RENDERED)


@pytest.fixture(scope="module")
def uninterrupted(rendered, tmp_path_factory):
    """BATCH run once from start to end: its batch table and each image's markers file (bytes)."""
    workspace = Workspace.open(rendered, tmp_path_factory.mktemp("uninterrupted") / "results")
    assert marker_batches(workspace.dataset, PER_JOB)[BATCH]["images"] == IMAGES
    assert markers.run_batch(workspace, BATCH, PER_JOB) == [workspace.marker_batch_path(BATCH)]
    table = pd.read_csv(workspace.marker_batch_path(BATCH))
    assert list(table.columns) == list(BATCH_COLUMNS) and table["image"].tolist() == IMAGES
    assert set(table["camera"]) == {"C0"} and not table["resumed"].any()
    assert (table["identified"] >= 8).all() and (table["detected"] >= table["identified"]).all()
    return table, {image: workspace.markers_path(image).read_bytes() for image in IMAGES}


def _copy(dataset: Path, tmp_path: Path) -> Workspace:
    """A workspace on a copy of `dataset` (its files' times kept), whose files a test may change."""
    return Workspace.open(shutil.copytree(dataset, tmp_path / "dataset"), tmp_path / "results")


def _progress(workspace: Workspace) -> Path:
    return workspace.marker_batch_path(BATCH).with_suffix(".progress")


def _corrupt(workspace: Workspace, image: str) -> bytes:
    """Cut `image`'s file in half (a partly copied file); returns its bytes to restore it with."""
    path = workspace.dataset.image_path(image)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return data


def _restore(workspace: Workspace, image: str, data: bytes) -> None:
    workspace.dataset.image_path(image).write_bytes(data)


def _fail_on(workspace: Workspace, image: str, conf=markers.Conf()) -> bytes:
    """Run BATCH with `image` corrupt: it fails naming it; returns the image's bytes."""
    data = _corrupt(workspace, image)
    with pytest.raises(DmaisError) as failure:
        markers.run_batch(workspace, BATCH, PER_JOB, conf)
    message = str(failure.value)
    assert f"1 of {len(IMAGES)} images of batch {BATCH} failed, first {image}:" in message
    assert "cannot be decoded" in message and "\n" not in message
    return data


def _written(workspace: Workspace) -> dict[str, tuple[int, int]]:
    """Each markers file's inode and time: a file written anew (atomically, through a rename) changes both."""
    stats = {image: workspace.markers_path(image).stat() for image in IMAGES if workspace.markers_path(image).is_file()}
    return {image: (stat.st_ino, stat.st_mtime_ns) for image, stat in stats.items()}


def _rerun(workspace: Workspace, uninterrupted, conf=markers.Conf(), compare: bool = True) -> list[str]:
    """Run BATCH again; check it completes as an uninterrupted run did (with compare: the same counts
    and markers files); returns the images it redid: resumed False in its table and their markers files
    written anew, the others' files untouched."""
    before = _written(workspace)
    assert markers.run_batch(workspace, BATCH, PER_JOB, conf) == [workspace.marker_batch_path(BATCH)]
    table = pd.read_csv(workspace.marker_batch_path(BATCH))
    reference, files = uninterrupted
    assert list(table.columns) == list(BATCH_COLUMNS) and table["image"].tolist() == IMAGES
    assert set(table["camera"]) == {"C0"} and table["resumed"].dtype == bool
    assert (table[["decode_s", "detect_s", "identify_s", "write_s"]] >= 0).all().all()
    if compare:
        pd.testing.assert_frame_equal(table[["image", "camera", "detected", "identified"]],
                                      reference[["image", "camera", "detected", "identified"]])
        for image in IMAGES:
            assert workspace.markers_path(image).read_bytes() == files[image], image
    redone = table.loc[~table["resumed"], "image"].tolist()
    after = _written(workspace)
    assert sorted(image for image in IMAGES if after[image] != before.get(image)) == sorted(redone)
    return redone


def _progress_rows(workspace: Workspace) -> pd.DataFrame:
    return pd.read_csv(_progress(workspace), dtype={"image": str, "key": str})


def test_a_failed_image_does_not_stop_the_batch_and_only_it_is_redone(rendered, uninterrupted, tmp_path):
    workspace = _copy(rendered, tmp_path)
    data = _fail_on(workspace, IMAGES[1])  # the images before and after it are done
    assert not workspace.marker_batch_path(BATCH).exists() and not workspace.markers_path(IMAGES[1]).exists()
    rows = _progress_rows(workspace)
    assert rows["image"].tolist() == [IMAGES[0], *IMAGES[2:]]
    assert list(rows.columns) == ["image", "key", "markers", *BATCH_COLUMNS[2:-1]]
    for image in rows["image"]:
        assert workspace.markers_path(image).read_bytes() == uninterrupted[1][image], image
    _restore(workspace, IMAGES[1], data)
    assert _rerun(workspace, uninterrupted) == [IMAGES[1]]
    table = pd.read_csv(workspace.marker_batch_path(BATCH))
    # the resumed images' counts and times are those the failed run recorded
    resumed = table[table["resumed"]].reset_index(drop=True)
    pd.testing.assert_frame_equal(resumed[list(rows.columns[3:])], rows[list(rows.columns[3:])],
                                  check_exact=False, rtol=1e-5, atol=1e-6)
    # a completed batch run again (its job's end unnoticed by a Snakemake killed meanwhile) redoes nothing
    assert _rerun(workspace, uninterrupted) == []


def test_a_killed_batch_redoes_the_images_it_had_not_finished(rendered, uninterrupted, tmp_path, monkeypatch):
    """A job killed on its third image (a node lost) kept the first two; a markers file that is gone
    since is redone although the progress file lists it."""
    workspace = _copy(rendered, tmp_path)
    process_image = markers.process_image

    def killed_on_the_third(dataset, image, *args, **kwargs):
        if image == IMAGES[2]:
            raise KeyboardInterrupt  # SIGINT; nothing of the batch's own handling runs
        return process_image(dataset, image, *args, **kwargs)

    monkeypatch.setattr(markers, "process_image", killed_on_the_third)
    with pytest.raises(KeyboardInterrupt):
        markers.run_batch(workspace, BATCH, PER_JOB)
    monkeypatch.undo()
    assert _progress_rows(workspace)["image"].tolist() == IMAGES[:2]
    assert _rerun(workspace, uninterrupted) == IMAGES[2:]

    data = _fail_on(workspace, IMAGES[3])  # a progress file again, listing the first three
    _restore(workspace, IMAGES[3], data)
    workspace.markers_path(IMAGES[0]).unlink()
    assert _rerun(workspace, uninterrupted) == [IMAGES[0], IMAGES[3]]


@pytest.mark.parametrize("change", ["image file touched", "image file replaced by itself", "settings",
                                    "images.csv touched"])
def test_a_rerun_redoes_what_its_inputs_changed(rendered, uninterrupted, tmp_path, change):
    workspace = _copy(rendered, tmp_path)
    data = _fail_on(workspace, IMAGES[3])
    _restore(workspace, IMAGES[3], data)
    conf, redone, compare = markers.Conf(), [IMAGES[0], IMAGES[3]], True
    if change == "image file touched":
        stat = workspace.dataset.image_path(IMAGES[0]).stat()
        os.utime(workspace.dataset.image_path(IMAGES[0]), ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    elif change == "image file replaced by itself":  # same size, a new time: as a new copy of the image
        _restore(workspace, IMAGES[0], workspace.dataset.image_path(IMAGES[0]).read_bytes())
    elif change == "settings":
        conf, redone, compare = markers.Conf(identify_gate_px=markers.Conf().identify_gate_px * 1.5), IMAGES, False
    else:
        stat = (workspace.dataset.root / "images.csv").stat()
        os.utime(workspace.dataset.root / "images.csv", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
        redone = IMAGES
    assert _rerun(workspace, uninterrupted, conf, compare) == redone


def test_a_rerun_with_the_same_inputs_resumes_after_a_failure_with_other_settings(rendered, uninterrupted, tmp_path):
    """The progress of a run with other settings is not resumed, and is not lost for a run with them."""
    workspace = _copy(rendered, tmp_path)
    other = markers.Conf(identify_gate_px=markers.Conf().identify_gate_px * 1.5)
    data = _fail_on(workspace, IMAGES[3], other)
    _restore(workspace, IMAGES[3], data)
    assert _rerun(workspace, uninterrupted) == IMAGES


def test_markers_rewritten_with_other_settings_since_are_redone(rendered, uninterrupted, tmp_path):
    """Runs with the default settings, then others, then the default again: the last run must not resume
    the default run's records, whose markers files the run with other settings has overwritten."""
    workspace = _copy(rendered, tmp_path)
    other = markers.Conf(identify_gate_px=markers.Conf().identify_gate_px * 1.5)
    _restore(workspace, IMAGES[3], _fail_on(workspace, IMAGES[3]))
    _restore(workspace, IMAGES[3], _fail_on(workspace, IMAGES[3], other))
    assert _rerun(workspace, uninterrupted) == IMAGES


@pytest.mark.parametrize("cut", ["inside the key", "after the key", "after the image", "after the last comma",
                                 "inside the header"])
def test_a_line_cut_short_by_a_kill_is_ignored(rendered, uninterrupted, tmp_path, cut):
    """A kill while a record is written leaves its line cut short, without a newline: that image is
    redone, the complete lines before it are resumed."""
    workspace = _copy(rendered, tmp_path)
    data = _fail_on(workspace, IMAGES[3])
    _restore(workspace, IMAGES[3], data)
    progress = _progress(workspace)
    lines = progress.read_text().splitlines(keepends=True)
    assert [line.split(",")[0] for line in lines] == ["image", *IMAGES[:3]] and lines[-1].endswith("\n")
    last = lines[-1].split(",")
    if cut == "inside the header":
        progress.write_text(lines[0][:7])
        redone = IMAGES
    else:
        kept = {"inside the key": last[0] + "," + last[1][:5], "after the key": ",".join(last[:2]) + ",",
                "after the image": last[0], "after the last comma": ",".join(last[:-1]) + ","}[cut]
        progress.write_text("".join(lines[:-1]) + kept)
        redone = IMAGES[2:]
    assert _rerun(workspace, uninterrupted) == redone


def test_the_record_written_after_a_line_cut_short_is_kept(rendered, tmp_path):
    """A kill cut the third image's line; the next run redoes that image and fails on the fourth: its
    progress file must list the third image as finished, so that the run after that resumes it."""
    workspace = _copy(rendered, tmp_path)
    data = _fail_on(workspace, IMAGES[3])
    progress = _progress(workspace)
    text = progress.read_text()
    progress.write_text(text[: text.rindex(IMAGES[2]) + len(IMAGES[2]) + 5])
    _fail_on(workspace, IMAGES[3])  # the third image redone and recorded again
    _restore(workspace, IMAGES[3], data)
    markers.run_batch(workspace, BATCH, PER_JOB)
    table = pd.read_csv(workspace.marker_batch_path(BATCH))
    assert table["resumed"].tolist() == [True, True, True, False]


def test_a_markers_file_rewritten_by_another_command_is_redone(rendered, uninterrupted, tmp_path):
    workspace = Workspace.open(rendered, tmp_path / "results")
    markers.run_batch(workspace, BATCH, PER_JOB)
    markers.run_image(workspace, IMAGES[0], markers.Conf(identify_min_inliers=100))  # identifies nothing
    if workspace.markers_path(IMAGES[0]).read_bytes() == uninterrupted[1][IMAGES[0]]:
        pytest.fail("the other settings should change the markers file")
    markers.run_batch(workspace, BATCH, PER_JOB)
    table = pd.read_csv(workspace.marker_batch_path(BATCH))
    assert workspace.markers_path(IMAGES[0]).read_bytes() == uninterrupted[1][IMAGES[0]]
    assert table["identified"].tolist() == uninterrupted[0]["identified"].tolist()


# ------------------------------------------------------------------------------ image names


def _named(tmp_path: Path, name: str) -> tuple[Workspace, str]:
    """The small hand-made dataset of test_dataset with a second intrinsics image of C1, i2, and i1
    renamed `name` (grey 64 x 48 images: nothing detected): a workspace and the batch of the two."""
    inputs = _inputs()
    images = inputs["images"]
    images.loc[images["image"] == "i1", "image"] = name
    inputs["images"] = pd.concat([images, pd.DataFrame([{"image": "i2", "camera": "C1", "stage": "intrinsics",
                                                         "split": "eval", "path": "images/i2.png"}])])
    workspace = Workspace.open(_write(tmp_path / "site", inputs), tmp_path / "results")
    (batch,) = [b for b, spec in marker_batches(workspace.dataset).items() if spec["images"] == [name, "i2"]]
    return workspace, batch


def test_a_cut_inside_a_character_of_an_image_name_is_ignored(tmp_path):
    workspace, batch = _named(tmp_path, "bild-ä")
    progress = workspace.marker_batch_path(batch).with_suffix(".progress")
    progress.parent.mkdir(parents=True)
    progress.write_bytes(b"image,key,markers,detected,identified,decode_s,detect_s,identify_s,write_s\n"
                         + "bild-ä".encode()[:-1])
    markers.run_batch(workspace, batch)


def test_an_image_name_with_a_comma_is_resumed(tmp_path):
    workspace, batch = _named(tmp_path, "i1,left")
    i2 = workspace.dataset.image_path("i2")
    data = i2.read_bytes()
    i2.write_bytes(b"")
    with pytest.raises(DmaisError, match=f"1 of 2 images of batch {batch} failed, first i2: "):
        markers.run_batch(workspace, batch)
    i2.write_bytes(data)
    markers.run_batch(workspace, batch)
    table = pd.read_csv(workspace.marker_batch_path(batch))
    assert table["image"].tolist() == ["i1,left", "i2"]
    assert table["resumed"].tolist() == [True, False]


# ------------------------------------------------------------------------------ the CLI


def test_the_cli_runs_a_batch_and_names_an_unknown_one_on_one_line(rendered, uninterrupted, tmp_path, capsys):
    results = tmp_path / "results"
    assert cli.main(["markers", str(rendered), "--out", str(results), "--batch", "nosuch"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1
    assert captured.err.startswith("dmais markers: error: markers: no batch 'nosuch' among the 2 marker batches of ")
    assert f"with {MARKERS_PER_JOB} images per job" in captured.err
    # a batch of another batch size is unknown: the job must be given the plan's --per-job
    assert cli.main(["markers", str(rendered), "--out", str(results), "--batch", "intrinsics-C0-2",
                     "--per-job", "4"]) == 2
    assert "no batch 'intrinsics-C0-2' among the 2 marker batches" in capsys.readouterr().err
    assert not results.exists()
    assert cli.main(["markers", str(rendered), "--out", str(results), "--batch", BATCH, "--per-job", "4"]) == 0
    assert capsys.readouterr().out == f"{results / 'markers' / 'batches' / BATCH}.csv\n"
    for image in IMAGES:
        assert (results / "markers" / f"{image}.csv").read_bytes() == uninterrupted[1][image], image
    with pytest.raises(SystemExit) as refused:
        cli.main(["markers", str(rendered), "--out", str(results), "--batch", BATCH, "--per-job", "0"])
    assert refused.value.code == 2 and "--per-job: 0 is not positive" in capsys.readouterr().err


def test_the_cli_names_the_failed_image_and_the_batch_on_one_line(rendered, tmp_path, capsys):
    workspace = _copy(rendered, tmp_path)
    _corrupt(workspace, IMAGES[2])
    assert cli.main(["markers", str(workspace.dataset.root), "--out", str(workspace.root), "--batch", BATCH,
                     "--per-job", "4"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"dmais markers: error: markers: 1 of 4 images of batch {BATCH} "
                                                   f"failed, first {IMAGES[2]}: ")


def test_the_plan_file_lists_the_batches_of_its_batch_size(rendered, tmp_path, capsys):
    assert cli.main(["plan", str(rendered), "--per-job", "3", "--json", str(tmp_path / "plan.json")]) == 0
    assert capsys.readouterr().out == ""
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert plan == workflow_plan(Dataset.load(rendered), 3)
    assert plan["batches"] == {"intrinsics": {f"intrinsics-C{c}-{k}": {"camera": f"C{c}", "images": 2}
                                              for c in (0, 1) for k in (1, 2)}, "extrinsics": {}, "flight": {}}
