"""Shared fixtures: simulated datasets with ground truth, made once per distinct settings."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from dmais_pipe.sim.simulate import simulate

#: tests/cluster runs the demo on a SLURM it brings up (as root): only `make test-cluster` collects it.
collect_ignore = [] if os.environ.get("DMAIS_CLUSTER_TEST") else ["cluster"]


def observation_only(name: str, seed: int, calib_images: int, eval_images: int, frames_per_group: int) -> dict:
    """Simulator settings of a small dataset whose markers are given as observations (no images)."""
    return {
        "name": name,
        "seed": seed,
        "intrinsics": {"calib_images_per_camera": calib_images, "eval_images_per_camera": eval_images},
        "flight": {"frames_per_group": frames_per_group},
        "render": {"intrinsics": False, "extrinsics": False, "flight": False},
    }


@pytest.fixture(scope="session")
def simulated_dataset(tmp_path_factory):
    """simulated_dataset(settings) -> the dataset folder simulated from `settings` (a simulator
    config mapping), written once per session for equal settings. Tests must not modify it."""
    made: dict[str, Path] = {}

    def make(settings: dict) -> Path:
        key = yaml.safe_dump(settings, sort_keys=True)
        if key not in made:
            root = tmp_path_factory.mktemp(str(settings.get("name", "sim")))
            (root / "sim.yaml").write_text(key)
            made[key] = simulate(root / "sim.yaml", root / "dataset")
        return made[key]

    return make
