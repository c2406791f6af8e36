"""`dmais bench campaign`'s dataset (campaign_dataset: a flight of many frames repeating a small one's)
and the parts of the bench that need no workflow run."""

from __future__ import annotations

import math
import shutil
import subprocess

import pandas as pd
import pytest

from dmais_pipe import cli
from dmais_pipe.bench import campaign as campaign_bench
from dmais_pipe.bench.campaign import _slurm_rows, campaign_dataset, given_flight_source, job_stats
from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.plan import marker_batches

from conftest import observation_only

#: Five cameras, 10 flight frames in 5 groups, no image rendered: files are attached by `source`.
SOURCE = observation_only("campaign-source", seed=6, calib_images=3, eval_images=1, frames_per_group=2)
FRAMES, PER_GROUP, PER_JOB = 23, 5, 4


def _read(path):
    return pd.read_csv(path, dtype=str, keep_default_na=False)


@pytest.fixture(scope="module")
def source(simulated_dataset, tmp_path_factory):
    """A copy of SOURCE where every third flight image has no file and its observations given, and
    every other image a file (one blank PNG for all, never decoded here) and no given observations."""
    root = tmp_path_factory.mktemp("campaign") / "source"
    shutil.copytree(simulated_dataset(SOURCE), root)
    shutil.rmtree(root / "truth")
    (root / "images").mkdir()
    (root / "images" / "blank.png").write_bytes(b"not decoded")
    images, observations = _read(root / "images.csv"), _read(root / "observations.csv")
    given = set(images.query("stage == 'flight'")["image"][::3]) & set(observations["image"])
    images["path"] = ["" if image in given else "images/blank.png" for image in images["image"]]
    images.to_csv(root / "images.csv", index=False)
    observations[observations["image"].isin(given)].to_csv(root / "observations.csv", index=False)
    return root


@pytest.fixture(scope="module")
def campaign(source, tmp_path_factory):
    out = tmp_path_factory.mktemp("campaign") / "out"
    assert campaign_dataset(source, out, frames=FRAMES, frames_per_group=PER_GROUP) == out
    return out


def test_the_flight_repeats_the_source_frames_in_groups(source, campaign):
    frames, source_frames = _read(campaign / "frames.csv"), _read(source / "frames.csv")
    assert frames["frame"].tolist() == [f"c{k:06d}" for k in range(FRAMES)]
    sizes = frames.groupby("group", sort=False).size()
    assert sizes.index.tolist() == [f"line{g:03d}" for g in range(math.ceil(FRAMES / PER_GROUP))]
    assert sizes.tolist() == [5, 5, 5, 5, 3]
    repeated = source_frames.iloc[[k % len(source_frames) for k in range(FRAMES)]].reset_index(drop=True)
    others = [c for c in frames.columns if c not in ("frame", "group")]
    pd.testing.assert_frame_equal(frames[others], repeated[others])


def test_each_frame_has_the_images_of_its_source_frame(source, campaign):
    images, source_images = _read(campaign / "images.csv"), _read(source / "images.csv")
    calibration = source_images[source_images["stage"] != "flight"]
    pd.testing.assert_frame_equal(images.iloc[:len(calibration)], calibration)
    flight, source_flight = images.iloc[len(calibration):], source_images.query("stage == 'flight'")
    source_frames = _read(source / "frames.csv")["frame"]
    expected = pd.concat([source_flight[source_flight["placement"] == source_frames[k % len(source_frames)]]
                          .assign(placement=f"c{k:06d}") for k in range(FRAMES)])
    assert len(flight) == len(expected) > FRAMES
    assert flight["image"].is_unique and not set(flight["image"]) & set(calibration["image"])
    assert (flight["image"] == flight["placement"] + "_" + flight["camera"]).all()
    same = [c for c in images.columns if c != "image"]
    pd.testing.assert_frame_equal(flight[same].reset_index(drop=True), expected[same].reset_index(drop=True))


def test_given_observations_follow_the_copies_of_their_images(source, campaign):
    given, source_given = _read(campaign / "observations.csv"), _read(source / "observations.csv")
    images = _read(campaign / "images.csv")
    without_file = set(images.loc[images["path"] == "", "image"])
    assert without_file and set(given["image"]) == without_file
    first = given[given["image"].str.startswith("c000000_")]
    placement = _read(source / "images.csv").set_index("image")["placement"]
    of_first = source_given[source_given["image"].map(placement) == _read(source / "frames.csv")["frame"][0]]
    assert sorted(zip(first["point_id"], first["u"])) == sorted(zip(of_first["point_id"], of_first["u"]))


def test_the_campaign_loads_and_splits_into_batches_per_camera(source, campaign):
    dataset = Dataset.load(campaign)
    assert (campaign / "images").is_symlink() and (campaign / "images").resolve() == (source / "images").resolve()
    assert not (campaign / "truth").exists()
    assert len(dataset.frames) == FRAMES
    batches = marker_batches(dataset, PER_JOB)
    for camera in dataset.cameras:
        todo = [image for image in dataset.images_to_extract("flight") if image.endswith(f"_{camera}")]
        ours = [batch for batch in batches.values() if batch["stage"] == "flight" and batch["camera"] == camera]
        assert len(ours) == math.ceil(len(todo) / PER_JOB) > 1
        assert [image for batch in ours for image in batch["images"]] == todo


def test_a_second_campaign_replaces_the_first(source, tmp_path):
    out = tmp_path / "out"
    campaign_dataset(source, out, frames=40, frames_per_group=100)
    campaign_dataset(source, out, frames=3, frames_per_group=100)
    assert len(Dataset.load(out).frames) == 3


@pytest.mark.parametrize("where", ["source", "foreign"])
def test_a_folder_that_is_not_a_campaign_is_refused(source, tmp_path, where):
    out = source if where == "source" else tmp_path / "mine"
    if where == "foreign":
        (out / "truth").mkdir(parents=True)
    with pytest.raises(DmaisError, match="give another --out"):
        campaign_dataset(source, out, frames=3)


def test_the_bench_without_the_demo_says_to_run_it_on_one_line(tmp_path, capsys):
    assert cli.main(["bench", "campaign", "--source", str(tmp_path / "none"), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert "make run" in error and error.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_job_stats_reads_snakemake_table():
    text = ("Building DAG of jobs...\nJob stats:\njob                count\n---------------  -------\n"
            "markers              4\nobservations         1\ntotal                5\n\nReasons:\n")
    assert job_stats(text) == {"markers": 4, "observations": 1, "total": 5}
    assert job_stats("Nothing to be done (all requested files are present and up to date).") == {}


def test_the_slurm_rows_count_the_jobs_of_each_node():
    jobs = pd.DataFrame({"node": ["n2", "n1", "n2", "n3"], "images": [100, 100, 100, 50],
                         "elapsed_s": [40.0, 30.0, 36.0, 20.0], "shell_s": [35.0, 26.0, 32.0, 17.0],
                         "work_s": [30.0, 24.0, 30.0, 15.0], "max_rss_mb": [300.0, 310.0, 290.0, 200.0]})
    jobs.attrs["wall_s"] = 80.0
    rows = {row["metric"]: row for row in _slurm_rows(jobs)}
    assert rows["slurm_nodes"]["value"] == 3 and rows["slurm_nodes"]["note"] == "jobs per node: n1 1, n2 2, n3 1"
    assert rows["slurm_overhead_per_image_s"]["value"] == pytest.approx(27.0 / 350, abs=1e-4)  # (elapsed - work) / images


def test_a_source_with_the_flight_observations_given_extracts_no_flight_image(source, tmp_path):
    """given_flight_source: the flight observations a run identified join the source's given ones,
    so that a campaign made from it extracts markers of no flight image (`--stages`)."""
    demo = tmp_path / "demo"
    (demo / "observations").mkdir(parents=True)
    images = _read(source / "images.csv")
    flight = images.query("stage == 'flight' and path != ''")["image"]
    point = _read(source / "ground_points.csv")["point_id"].iloc[0]
    identified = pd.DataFrame({"image": flight, "camera": "C0", "point_id": point, "u": 1.5, "v": 2.5})
    identified.to_csv(demo / "observations" / "flight.csv", index=False)
    given = given_flight_source(source, demo, tmp_path / "given")
    observations = _read(given / "observations.csv")
    assert len(observations) == len(_read(source / "observations.csv")) + len(flight)
    assert set(flight) <= set(observations["image"]) and list(observations.columns) == ["image", "point_id", "u", "v"]
    assert (given / "images.csv").is_symlink() and (given / "images").is_symlink()
    dataset = Dataset.load(given)
    assert dataset.images_to_extract("flight") == []
    assert dataset.images_to_extract("intrinsics") == Dataset.load(source).images_to_extract("intrinsics")


@pytest.mark.parametrize("plugin", [True, False])
def test_the_dry_runs_use_the_slurm_profile_only_where_its_plugin_is_installed(tmp_path, monkeypatch, capsys, plugin):
    commands = []

    def run(command, root, timeout):
        commands.append(command)
        (tmp_path / "plan").mkdir(exist_ok=True)
        (tmp_path / "plan" / "p.json").write_text('{"batches": {"markers": {"b": {"images": 60}}}}')
        done = subprocess.CompletedProcess(command, 0, "Job stats:\njob count\nmarkers 1\ntotal 1\n", "")
        return 1.0, done

    monkeypatch.setattr(campaign_bench, "_run", run)
    monkeypatch.setattr(campaign_bench, "has_slurm_plugin", lambda: plugin)
    rows, plan = campaign_bench._dry_runs(tmp_path, tmp_path / "c.yaml", tmp_path)
    profiled = [c for c in commands if "--workflow-profile" in c]
    assert len(commands) == (4 if plugin else 2) and len(profiled) == (2 if plugin else 0)
    assert any(r["metric"] == "dry_run_profile_cold_s" for r in rows) == plugin
    assert ("make install-slurm" in capsys.readouterr().out) != plugin
    assert plan["batches"]["markers"]["b"]["images"] == 60
