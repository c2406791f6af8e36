"""bench.pose_stage's generated flights have the structure each kind names, and its dense reference solves
as pose.group_normal does."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.bench.pose_stage import dense_solve, generated_flight
from dmais_pipe.pose.group_normal import solve
from dmais_pipe.sim.config import DEFAULTS
from dmais_pipe.sim.scene import build_rig

from test_group_normal import random_normal, with_priors


@pytest.fixture(scope="module")
def rig():
    return build_rig(DEFAULTS["rig"])


def frames_per_point(observations: pd.DataFrame) -> pd.Series:
    frame = observations["image"].str.rsplit("_", n=1).str[0]
    return frame.groupby(observations["point_id"]).nunique()


@pytest.mark.parametrize("kind, least, most", [("hover", 6, 6), ("own", 1, 1), ("line", 1, 3)])
def test_each_kind_shares_its_points_as_named(rig, kind, least, most):
    frames, points, observations = generated_flight(np.random.default_rng(3), rig, kind, 2, 6)
    assert len(frames) == 12 and set(frames["group"]) == {"g0", "g1"}
    shared = frames_per_point(observations)
    assert shared.min() == least and shared.max() == most
    if kind == "line":
        assert (shared > 1).mean() > 0.3  # the tilted cameras see a marker from 2 or 3 frames 20 m apart
    assert set(observations["point_id"]) <= set(points["point_id"])
    per_image = observations.groupby("image").size()
    assert per_image.min() >= 3 and len(per_image) == 12 * len(rig.cameras)


@pytest.mark.parametrize("kind", ["shared", "own", "line"])
def test_the_dense_reference_solves_as_the_blocks(kind):
    structure, normal, _, _ = random_normal(kind, 12, None)
    normal = with_priors(normal)
    right = np.random.default_rng(2).normal(size=(structure.size, 2))
    x, rig_inverse = solve(normal, right)
    x_dense, rig_dense = dense_solve(normal, right)
    np.testing.assert_allclose(x, x_dense, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(rig_inverse, rig_dense, rtol=1e-9, atol=1e-14)
