"""The generalized pose solver's global fallback (issue 31 item 1): where the certificate fails or
the solution puts most points behind, more starts reach the least-cost front-facing minimum."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.bench.pose_hard import KINDS, HardKind, hard_scene
from dmais_pipe.geometry import rotation_error
from dmais_pipe.pose import PoseError, fallback, pose_statistics, solver
from dmais_pipe.pose.certificate import tight_certified, tight_certified_numpy
from dmais_pipe.pose.solver import solve_generalized_pose

from pose_scenes import (centred_cost, dmais_scene, generalized_scene, multistart_minimum, narrow_camera_scene,
                         single_camera_scene)

NARROW = HardKind("narrow", 1, 4, (0.5, 0.5), 0.3, "one camera of 0.5 deg, 4 points")
TWO_CAMERAS = HardKind("two", 2, 2, (2.0, 2.0), 0.3, "two cameras of 2 deg, 2 points each")
TWO_NARROW = HardKind("two_narrow", 2, 4, (1.0, 1.0), 0.3, "two cameras of 1 deg, 4 points each")
#: Seeds of `hard_scene(np.random.default_rng(seed), kind)` where the template's roots alone miss
#: the minimum (found with this build; a kernel that no longer misses some of them still passes).
MISSED = [(NARROW, s) for s in (236, 667, 1536)] + [(TWO_CAMERAS, s) for s in (928, 1185, 1197, 1738)]
#: Seeds where the template's solution puts every point behind the cameras (the mirror pose, which
#: the dual certifies: eq. objfun cannot tell it from the pose in front).
BEHIND = [(TWO_NARROW, s) for s in (86, 263, 448)]
#: Seeds where the solver's dual fails and the tighter one of certificate.py proves the template's pose
#: (two of the rig's cameras with 2 points each; one camera alone is not tried, `solver._with_fallback`).
TIGHT = [(KINDS[5], s) for s in (6, 13, 21, 37)]


def _front(scene, R, t) -> float:
    depth = np.einsum("ij,ij->i", (scene.points - scene.points.mean(0)) @ R.T + t + R @ scene.points.mean(0)
                      - scene.origins, scene.directions)
    return float(np.mean(depth > 0))


def _reference(scene, seed):
    return multistart_minimum(scene.origins, scene.directions, scene.points, n_random=16, iterations=60, seed=seed,
                              starts=[scene.R])


def test_fallback_reaches_the_minimum_the_template_misses():
    """Scenes where the template's roots alone end far from the multi-start minimum (up to 120 deg
    and thousands of times its cost): with the fallback, the minimum, flagged as the fallback's."""
    missed_before = 0
    for kind, seed in MISSED:
        scene = hard_scene(np.random.default_rng(seed), kind)
        reference, R_reference, _ = _reference(scene, seed)
        plain = solve_generalized_pose(scene.origins, scene.directions, scene.points, fallback=False)
        before = centred_cost(scene.origins, scene.directions, scene.points, plain.R, plain.t)
        missed_before += before > reference * (1 + 1e-6)
        pose = solve_generalized_pose(scene.origins, scene.directions, scene.points)
        after = centred_cost(scene.origins, scene.directions, scene.points, pose.R, pose.t)
        assert after <= reference * (1 + 1e-6), (kind.name, seed, after / reference)
        assert rotation_error(pose.R, R_reference) < np.deg2rad(0.01)
        assert _front(scene, pose.R, pose.t) >= 0.5
        if before > reference * (1 + 1e-6):
            assert pose.fallback and pose.fallback_ms is not None
            assert pose.cost == pytest.approx(after, rel=1e-9)
            assert any(np.array_equal(c.R, pose.R) and c.cost == pose.cost for c in pose.candidates)
    assert missed_before >= len(MISSED) // 2


@pytest.mark.parametrize("kind, seed", BEHIND)
def test_a_solution_behind_the_cameras_is_replaced(kind, seed):
    """The template's least-cost pose puts every point behind the cameras (eq. objfun cannot tell
    a pose from its mirror; the certificate may even hold): the fallback runs and returns the
    least-cost pose with the points in front."""
    scene = hard_scene(np.random.default_rng(seed), kind)
    plain = solve_generalized_pose(scene.origins, scene.directions, scene.points, fallback=False)
    assert _front(scene, plain.R, plain.t) < 0.5
    pose = solve_generalized_pose(scene.origins, scene.directions, scene.points)
    assert pose.fallback and _front(scene, pose.R, pose.t) == 1.0
    reference, _, _ = _reference(scene, seed)
    assert centred_cost(scene.origins, scene.directions, scene.points, pose.R, pose.t) <= reference * (1 + 1e-6)


def test_no_front_facing_pose_raises(monkeypatch):
    """When neither the template nor the fallback finds a pose with most points in front, the
    solver raises instead of returning a pose behind the cameras."""
    scene = hard_scene(np.random.default_rng(BEHIND[0][1]), BEHIND[0][0])
    monkeypatch.setattr(fallback, "search", lambda *args, **kwargs: None)
    with pytest.raises(PoseError, match="in front of their rays"):
        solve_generalized_pose(scene.origins, scene.directions, scene.points)


def test_fallback_runs_only_where_the_certificate_fails(monkeypatch):
    """Certified front-facing solutions never reach the fallback (the pose stage's frames); an
    uncertified one does, and its result says whether the fallback's pose was returned."""
    calls = []
    search = fallback.search
    monkeypatch.setattr(fallback, "search", lambda *args, **kwargs: calls.append(1) or search(*args, **kwargs))
    rng = np.random.default_rng(3)
    certified = 0
    for _ in range(10):
        origins, directions, points, _, _ = dmais_scene(rng, 8, noise_px=3.0)
        if solve_generalized_pose(origins, directions, points, fallback=False).certified:
            pose = solve_generalized_pose(origins, directions, points)
            assert pose.certified and not pose.fallback and pose.fallback_ms is None
            certified += 1
    assert certified >= 8 and not calls
    for seed in range(50):
        origins, directions, points, _, _ = narrow_camera_scene(np.random.default_rng(seed), 1.0, n=10)
        if not solve_generalized_pose(origins, directions, points, fallback=False).certified:
            break
    pose = solve_generalized_pose(origins, directions, points)
    assert calls == [1] and pose.fallback_ms is not None and pose.fallback_ms > 0


def test_homography_starts_contain_the_true_rotation():
    """For noise-free points on a plane, one rotation of the homography decomposition is the pose."""
    origins, directions, points, R, _ = single_camera_scene(np.random.default_rng(7), n=10, planar=True)
    stats = pose_statistics(origins, directions, points)
    problem = fallback._Problem(origins, directions / np.linalg.norm(directions, axis=1)[:, None],
                                points - stats.centroid, stats)
    assert problem.planar
    rotations = fallback.homography_rotations(problem)
    assert 2 <= len(rotations) <= 4
    assert min(rotation_error(Rh, R) for Rh in rotations) < 1e-5  # the others are degrees away


def test_flip_mirrors_the_plane_normal_about_the_line_of_sight():
    origins, directions, points, R, _ = narrow_camera_scene(np.random.default_rng(2), 1.0, n=10)
    stats = pose_statistics(origins, directions, points)
    problem = fallback._Problem(origins, directions / np.linalg.norm(directions, axis=1)[:, None],
                                points - stats.centroid, stats)
    flipped = fallback.flip(problem, R)
    n = R @ problem.normal
    s = problem.centred_translation(R)[0] - origins.mean(axis=0)
    s /= np.linalg.norm(s)
    np.testing.assert_allclose(flipped @ problem.normal, 2 * (n @ s) * s - n, atol=1e-12)


def test_attitude_prior_is_a_start_and_must_be_a_rotation():
    origins, directions, points, R, _ = narrow_camera_scene(np.random.default_rng(4), 1.0, n=10)
    stats = pose_statistics(origins, directions, points)
    problem = fallback._Problem(origins, directions, points - stats.centroid, stats)
    first, _ = fallback.starts(problem, np.empty((0, 3, 3)), np.empty(0), R)
    assert any(np.array_equal(start, R) for start in first)
    with pytest.raises(PoseError, match="attitude_prior"):
        solve_generalized_pose(origins, directions, points, attitude_prior=2 * R)


def _problem(origins, directions, points):
    stats = pose_statistics(origins, directions, points)
    unit = directions / np.linalg.norm(directions, axis=1)[:, None]
    return fallback._Problem(origins, unit, points - stats.centroid, stats), stats, unit


def test_mirror_puts_every_point_behind_at_the_same_cost():
    """For a central camera and planar points the half turn about the plane's normal is the pose's
    twin behind the camera: the same cost, every point on the other side."""
    origins, directions, points, R, _ = single_camera_scene(np.random.default_rng(5), n=10, noise_px=1.0, planar=True)
    problem, _, _ = _problem(origins, directions, points)
    cost, front = problem.costs(np.array([R, fallback.mirror(R, problem.normal)]))
    assert cost[1] == pytest.approx(cost[0], rel=1e-9)
    assert front.tolist() == [1.0, 0.0]


def test_sampled_starts_alone_reach_the_certified_minimum():
    """Without any candidate of the template, the sampled rotations find the global minimum of a
    generic scene (the solver's certified solution)."""
    from dmais_pipe.pose.solver import kernel

    origins, directions, points, _, _ = generalized_scene(np.random.default_rng(8), n=10, noise=1e-3, max_angle=np.pi)
    pose = solve_generalized_pose(origins, directions, points)
    assert pose.certified
    _, stats, unit = _problem(origins, directions, points)
    found = fallback.search(origins, unit, points, stats, np.empty((0, 3, 3)), np.empty(0),
                            certify=lambda R: kernel().certify(stats.H, stats.g, stats.c, R))
    assert found is not None and found.certified
    assert rotation_error(found.R, pose.R) < 1e-8
    np.testing.assert_allclose(found.t, pose.t, atol=1e-7)


def test_no_refinement_starts_beyond_the_budget(monkeypatch):
    """A spent budget refines no start: the search finds nothing (the solver then keeps its pose)."""
    from dmais_pipe.pose.solver import kernel

    refined = []
    monkeypatch.setattr(fallback, "refine_pose", lambda *args, **kwargs: refined.append(1))
    origins, directions, points, _, _ = narrow_camera_scene(np.random.default_rng(4), 1.0, n=10)
    _, stats, unit = _problem(origins, directions, points)
    pose = solve_generalized_pose(origins, directions, points, fallback=False)
    found = fallback.search(origins, unit, points, stats, pose.candidates.R, pose.candidates.in_front,
                            certify=lambda R: kernel().certify(stats.H, stats.g, stats.c, R), budget_s=0.0)
    assert found is None and not refined


@pytest.mark.parametrize("kind, seed", TIGHT)
def test_a_tightly_certified_pose_is_the_searched_one(kind, seed, monkeypatch):
    """Where the solver's dual fails but the dual with SO(3)'s redundant constraints proves the
    template's pose, the solve skips the search and returns, bit for bit, what the search returns
    (the template's pose: it finds none cheaper), which is the multi-start minimum."""
    scene = hard_scene(np.random.default_rng(seed), kind)
    plain = solve_generalized_pose(scene.origins, scene.directions, scene.points, fallback=False)
    stats = pose_statistics(scene.origins, scene.directions, scene.points)
    assert not plain.certified and tight_certified(stats.H, stats.g, stats.c, plain.R)
    pose = solve_generalized_pose(scene.origins, scene.directions, scene.points)
    assert pose.fallback_ms is None and not pose.certified
    monkeypatch.setattr(solver, "tight_certified", lambda *args: False)
    searched = solve_generalized_pose(scene.origins, scene.directions, scene.points)
    assert searched.fallback_ms is not None and not searched.fallback
    assert np.array_equal(pose.R, searched.R) and np.array_equal(pose.t, searched.t) and pose.cost == searched.cost
    reference, _, _ = _reference(scene, seed)
    assert centred_cost(scene.origins, scene.directions, scene.points, pose.R, pose.t) <= reference * (1 + 1e-6)


def test_the_tight_certificate_refuses_what_is_not_the_global_minimum():
    """The template's poses that miss the minimum (MISSED) and a certified pose turned by 0.01 deg are
    not proven; the certified poses of the rig's scenes are."""
    for kind, seed in MISSED:
        scene = hard_scene(np.random.default_rng(seed), kind)
        plain = solve_generalized_pose(scene.origins, scene.directions, scene.points, fallback=False)
        reference, _, _ = _reference(scene, seed)
        if centred_cost(scene.origins, scene.directions, scene.points, plain.R, plain.t) > reference * (1 + 1e-6):
            stats = pose_statistics(scene.origins, scene.directions, scene.points)
            assert not tight_certified(stats.H, stats.g, stats.c, plain.R), (kind.name, seed)
    rng = np.random.default_rng(5)
    for _ in range(5):
        origins, directions, points, _, _ = dmais_scene(rng, 8, noise_px=0.5)
        pose = solve_generalized_pose(origins, directions, points, fallback=False)
        stats = pose_statistics(origins, directions, points)
        assert pose.certified and tight_certified(stats.H, stats.g, stats.c, pose.R)
        turned = Rotation.from_rotvec([0.0, 0.0, np.deg2rad(0.01)]).as_matrix() @ pose.R
        assert not tight_certified(stats.H, stats.g, stats.c, turned)


def test_the_compiled_tight_certificate_answers_as_numpys():
    """The compiled certificate (_certificate.pyx) against its numpy steps: the same answer on the hard
    scenes the solver's dual fails (TIGHT: proven; MISSED: some refused), on the rig's certified poses and
    on them turned by 0.01 deg to 20 deg (refused), and on statistics that are not finite (refused)."""
    cases = []
    for kind, seed in TIGHT + MISSED:
        scene = hard_scene(np.random.default_rng(seed), kind)
        plain = solve_generalized_pose(scene.origins, scene.directions, scene.points, fallback=False)
        stats = pose_statistics(scene.origins, scene.directions, scene.points)
        cases.append((stats.H, stats.g, stats.c, plain.R))
    rng = np.random.default_rng(11)
    for angle in (0.0, 0.01, 1.0, 20.0):
        for _ in range(4):
            origins, directions, points, _, _ = dmais_scene(rng, 8, noise_px=0.5)
            pose = solve_generalized_pose(origins, directions, points, fallback=False)
            stats = pose_statistics(origins, directions, points)
            turn = Rotation.from_rotvec(rng.normal(size=3) * np.deg2rad(angle) / np.sqrt(3)).as_matrix()
            cases.append((stats.H, stats.g, stats.c, turn @ pose.R))
    answers = [tight_certified(*case) for case in cases]
    assert answers == [tight_certified_numpy(*case) for case in cases]
    assert sum(answers[:len(TIGHT)]) == len(TIGHT) and not all(answers[len(TIGHT):len(TIGHT) + len(MISSED)])
    assert all(answers[-16:-12]) and not any(answers[-12:])
    H, g, c, R = cases[-1]
    unknown = np.full_like(H, np.nan)
    assert not tight_certified(unknown, g, c, R) and not tight_certified_numpy(unknown, g, c, R)
