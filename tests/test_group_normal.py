"""pose.group_normal: the blocks equal J^T J of the whole Jacobian, and both orders of elimination (and the
block-diagonal and banded factorisations of the frames) solve as a dense solve of the whole matrix."""

from __future__ import annotations

import numpy as np
import pytest

from dmais_pipe.errors import DmaisError
from dmais_pipe.pose import _group, group_normal
from dmais_pipe.pose.group_normal import FRAMES_FIRST, POINTS_FIRST, GroupNormal, assemble, group_structure, solve

L, R = 9, 5  # a frame's pose (6) and one camera's jitter (3); the rig's unknowns


def observations(rng, kind: str, n_frames: int):
    """(frame, point, n_points) of a group: `shared` every frame sees the same 6 points, `own` each frame
    its own 5, `own_twice` its own 3 each seen twice (by two cameras), `line` each frame 3 new points and
    the 3 of each of the two frames before, `shuffled_line` a line whose frames are numbered at random
    (their own order ties them over the whole group; the band's order is the line's)."""
    if kind == "shared":
        frame, point = np.divmod(np.arange(n_frames * 6), 6)
        return frame, point, 6
    if kind == "own":
        frame = np.repeat(np.arange(n_frames), 5)
        return frame, np.arange(5 * n_frames), 5 * n_frames
    if kind == "own_twice":
        frame = np.repeat(np.arange(n_frames), 6)
        return frame, 3 * frame + np.tile([0, 1, 2, 2, 0, 1], n_frames), 3 * n_frames
    frame = np.repeat(np.arange(n_frames), 9)
    back = np.tile(np.repeat([0, 1, 2], 3), n_frames)
    point = 3 * np.maximum(frame - back, 0) + np.tile(np.arange(3), 3 * n_frames)
    keep = frame - back >= 0
    if kind == "shuffled_line":
        return rng.permutation(n_frames)[frame[keep]], point[keep], 3 * n_frames
    return frame[keep], point[keep], 3 * n_frames


def random_normal(kind: str, n_frames: int, method: str | None, seed: int = 0):
    """A GroupNormal of random Jacobians with priors on every unknown, and the whole Jacobian (2N + n, n)."""
    rng = np.random.default_rng(seed)
    frame, point, n_points = observations(rng, kind, n_frames)
    n = len(frame)
    camera = rng.integers(0, 2, n)  # which of two jitter/rig column sets an observation uses
    local_cols = np.concatenate([np.broadcast_to(np.arange(6), (n, 6)), 6 + np.zeros((n, 3), int) + np.arange(3)],
                                axis=1)
    rig_cols = np.where(camera[:, None] == 0, [0, 1, 2], [2, 3, 4])
    structure = group_structure(frame, point, local_cols, rig_cols, n_frames, L, R, n_points, method)
    local_J, rig_J, point_J = (rng.normal(size=(n, 2, k)) for k in (9, 3, 3))
    e = rng.normal(size=(n, 2))
    normal = assemble(structure, local_J, rig_J, point_J, e)
    size = structure.size
    J = np.zeros((2 * n, size))
    rows = np.arange(2 * n).reshape(n, 2)
    first, points = n_frames * L, n_frames * L + R + 3 * point[:, None] + np.arange(3)
    np.add.at(J, (rows[:, :, None], (frame[:, None] * L + local_cols)[:, None, :]), local_J)
    np.add.at(J, (rows[:, :, None], (first + rig_cols)[:, None, :]), rig_J)
    np.add.at(J, (rows[:, :, None], points[:, None, :]), point_J)
    return structure, normal, J, e


def with_priors(normal, weight: float = 2.0):
    """`normal` with `weight` added to every diagonal (a prior on every unknown)."""
    A, Hpp, Hrr = normal.A.copy(), normal.Hpp.copy(), normal.Hrr.copy()
    A[:, np.arange(L), np.arange(L)] += weight
    Hpp[:, np.arange(3), np.arange(3)] += weight
    Hrr[np.diag_indices(R)] += weight
    return GroupNormal(normal.structure, A, normal.Wr, Hrr, Hpp, normal.Hpr, normal.Wp, normal.b_local,
                       normal.b_rig, normal.b_point)


@pytest.mark.parametrize("kind", ["shared", "own", "own_twice", "line"])
def test_the_blocks_are_those_of_the_whole_jacobian(kind):
    _, normal, J, e = random_normal(kind, 7, None)
    np.testing.assert_allclose(normal.dense(), J.T @ J, rtol=0, atol=1e-10)
    np.testing.assert_allclose(normal.gradient, J.T @ e.ravel(), rtol=0, atol=1e-10)


@pytest.mark.parametrize("solve_block", [16, 128])
@pytest.mark.parametrize("method", [FRAMES_FIRST, POINTS_FIRST])
@pytest.mark.parametrize("kind, n_frames", [("shared", 9), ("own", 9), ("own_twice", 9), ("line", 9),
                                           ("line", 120), ("shuffled_line", 120)])
def test_each_elimination_solves_as_the_dense_matrix(kind, n_frames, method, solve_block, monkeypatch):
    monkeypatch.setattr(group_normal, "POINT_CHUNK", 7)  # several chunks of points
    monkeypatch.setattr(group_normal, "SOLVE_BLOCK", solve_block)  # blocks within and wider than a line's band
    monkeypatch.setattr(group_normal, "CHUNK_NUMBERS", 2000)  # several chunks of frames
    structure, normal, _, _ = random_normal(kind, n_frames, method)
    normal = with_priors(normal)
    right = np.random.default_rng(1).normal(size=(structure.size, 3))
    x, rig_inverse = solve(normal, right)
    dense = normal.dense()
    np.testing.assert_allclose(x, np.linalg.solve(dense, right), rtol=1e-9, atol=1e-12)
    first = structure.n_frames * L
    np.testing.assert_allclose(rig_inverse, np.linalg.inv(dense)[first:first + R, first:first + R], rtol=1e-9,
                               atol=1e-14)


@pytest.mark.parametrize("kind", ["shared", "line"])
def test_damped_equations_raise_every_diagonal_and_are_put_back_after(kind):
    _, normal, _, _ = random_normal(kind, 9, None)
    normal = with_priors(normal)
    before = normal.dense()
    with normal.damped(0.3) as damped:
        dense = damped.dense()
        np.testing.assert_array_equal(np.diag(dense), np.diag(before) * 1.3)
        np.testing.assert_array_equal(dense - np.diag(np.diag(dense)), before - np.diag(np.diag(before)))
    np.testing.assert_array_equal(normal.dense(), before)
    with pytest.raises(ZeroDivisionError), normal.damped(2.0):
        raise ZeroDivisionError  # put back on an error too
    np.testing.assert_array_equal(normal.dense(), before)


def scaled(normal, scale: np.ndarray) -> GroupNormal:
    """The normal equations D N D and gradient D b with D = diag(scale) (F L + R + 3P,)."""
    s = normal.structure
    F, L_, R_ = s.n_frames, s.local_size, s.rig_size
    local, rig, point = scale[:F * L_].reshape(F, L_), scale[F * L_:F * L_ + R_], scale[F * L_ + R_:].reshape(-1, 3)
    Wp = normal.Wp * local[s.frame[:, None], s.local_cols][:, :, None] * point[s.point][:, None, :]
    return GroupNormal(s, normal.A * local[:, :, None] * local[:, None, :], normal.Wr * local[:, :, None] * rig,
                       normal.Hrr * np.outer(rig, rig), normal.Hpp * point[:, :, None] * point[:, None, :],
                       normal.Hpr * point[:, :, None] * rig, Wp, normal.b_local * local, normal.b_rig * rig,
                       normal.b_point * point)


@pytest.mark.parametrize("method", [FRAMES_FIRST, POINTS_FIRST])
@pytest.mark.parametrize("kind", ["shared", "own", "line"])
def test_a_scaling_of_the_unknowns_by_powers_of_two_scales_the_solution_exactly(kind, method):
    """solve is not given equations scaled to a unit diagonal (a group's radians, metres and 45,000 px focal
    lengths give condition numbers of 1e13): every step gives the scaled unknowns' solution bit for bit."""
    structure, normal, _, _ = random_normal(kind, 30, method)
    normal = with_priors(normal)
    rng = np.random.default_rng(4)
    scale = np.exp2(rng.integers(-20, 21, structure.size).astype(float))
    right = rng.normal(size=(structure.size, 2))
    x, rig_inverse = solve(normal, right)
    x_scaled, rig_inverse_scaled = solve(scaled(normal, scale), right * scale[:, None])
    np.testing.assert_array_equal(x_scaled * scale[:, None], x)
    first = structure.n_frames * L
    rig = scale[first:first + R]
    np.testing.assert_array_equal(rig_inverse_scaled * np.outer(rig, rig), rig_inverse)


def test_the_cheaper_order_is_chosen():
    assert random_normal("shared", 50, None)[0].method == FRAMES_FIRST
    assert random_normal("own", 50, None)[0].method == POINTS_FIRST
    line = random_normal("line", 200, None)[0]
    assert line.method == POINTS_FIRST and line.frames_tied and line.band == 2
    assert random_normal("shuffled_line", 200, None)[0].band == 2
    assert not random_normal("own", 50, None)[0].frames_tied
    assert random_normal("own_twice", 50, None)[0].method == POINTS_FIRST


@pytest.mark.parametrize("method", [FRAMES_FIRST, POINTS_FIRST])
def test_an_undetermined_frame_is_refused(method):
    structure, normal, _, _ = random_normal("own", 4, method)
    normal = with_priors(normal)
    normal.A[2], normal.Wr[2] = 0.0, 0.0  # frame 2 seen by nothing
    normal.Wp[structure.frame == 2] = 0.0
    with pytest.raises(DmaisError, match="not determined"):
        solve(normal, np.ones((structure.size, 1)))


@pytest.mark.parametrize("segment_bytes", [20_000, 60_000])
@pytest.mark.parametrize("kind", ["line", "shuffled_line"])
def test_a_band_made_a_segment_at_a_time_solves_as_the_kept_one(kind, segment_bytes, monkeypatch):
    monkeypatch.setattr(group_normal, "POINT_CHUNK", 7)
    structure, normal, _, _ = random_normal(kind, 120, POINTS_FIRST)
    normal = with_priors(normal)
    right = np.random.default_rng(1).normal(size=(structure.size, 3))
    kept = solve(normal, right)
    monkeypatch.setattr(group_normal, "KEPT_FACTOR_BYTES", 0)
    monkeypatch.setattr(group_normal, "SEGMENT_BYTES", segment_bytes)  # 12 and 4 segments of a band of 2 frames
    assert len(group_normal._segment_bounds(120, structure.band, L)) - 1 == 233_280 // segment_bytes + 1
    streamed = solve(normal, right)
    dense = normal.dense()
    for x, rig_inverse in (kept, streamed):
        np.testing.assert_allclose(x, np.linalg.solve(dense, right), rtol=1e-9, atol=1e-12)
        first = structure.n_frames * L
        np.testing.assert_allclose(rig_inverse, np.linalg.inv(dense)[first:first + R, first:first + R], rtol=1e-9,
                                   atol=1e-14)
    np.testing.assert_allclose(streamed[0], kept[0], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("method", [FRAMES_FIRST, POINTS_FIRST])
@pytest.mark.parametrize("kind", ["shared", "own", "line"])
def test_the_rigs_columns_are_those_of_a_solve_of_its_unit_columns(kind, method):
    structure, normal, _, _ = random_normal(kind, 9, method)
    normal = with_priors(normal)
    first = structure.n_frames * L
    unit = np.zeros((structure.size, R))
    unit[first + np.arange(R), np.arange(R)] = 1.0
    columns, rig_inverse = group_normal.rig_columns(normal)
    expected = solve(normal, unit)
    np.testing.assert_allclose(columns, expected[0], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(rig_inverse, expected[1], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(columns, np.linalg.inv(normal.dense())[:, first:first + R], rtol=1e-9, atol=1e-14)


def test_a_group_whose_frames_system_would_not_fit_is_refused(monkeypatch):
    structure, normal, _, _ = random_normal("line", 120, POINTS_FIRST)
    monkeypatch.setattr(group_normal, "FACTOR_BYTES", 120 * L * 3 * L * 8 * 0.9)  # a band of 2 frames needs more
    with pytest.raises(DmaisError, match="too large to adjust at once: its frames are tied over 2 frames"):
        solve(with_priors(normal), np.ones((structure.size, 1)))


def two_camera_normal(n_frames: int, seed: int = 3):
    """A GroupNormal of a shared-points group with two cameras' jitter blocks (L = 12: a frame's pose, then
    3 columns per camera), random Jacobians and priors on every unknown, and its whole Jacobian."""
    rng = np.random.default_rng(seed)
    frame, point, n_points = observations(rng, "shared", n_frames)
    n, L2, R2 = len(frame), 12, 6
    camera = rng.integers(0, 2, n)
    local_cols = np.concatenate([np.broadcast_to(np.arange(6), (n, 6)), 6 + 3 * camera[:, None] + np.arange(3)],
                                axis=1)
    rig_cols = 3 * camera[:, None] + np.arange(3)
    structure = group_structure(frame, point, local_cols, rig_cols, n_frames, L2, R2, n_points, FRAMES_FIRST)
    local_J, rig_J, point_J = (rng.normal(size=(n, 2, k)) for k in (9, 3, 3))
    e = rng.normal(size=(n, 2))
    normal = assemble(structure, local_J, rig_J, point_J, e)
    J = np.zeros((2 * n, structure.size))
    rows = np.arange(2 * n).reshape(n, 2)
    first = n_frames * L2
    np.add.at(J, (rows[:, :, None], (frame[:, None] * L2 + local_cols)[:, None, :]), local_J)
    np.add.at(J, (rows[:, :, None], (first + rig_cols)[:, None, :]), rig_J)
    np.add.at(J, (rows[:, :, None], (first + R2 + 3 * point[:, None] + np.arange(3))[:, None, :]), point_J)
    A, Hpp, Hrr = normal.A.copy(), normal.Hpp.copy(), normal.Hrr.copy()
    A[:, np.arange(L2), np.arange(L2)] += 2.0
    Hpp[:, np.arange(3), np.arange(3)] += 2.0
    Hrr[np.diag_indices(R2)] += 2.0
    return structure, normal, GroupNormal(structure, A, normal.Wr, Hrr, Hpp, normal.Hpr, normal.Wp, normal.b_local,
                                          normal.b_rig, normal.b_point), J, e


def test_the_compiled_blocks_with_jitter_blocks_are_those_of_the_whole_jacobian():
    _, normal, _, J, e = two_camera_normal(6)
    np.testing.assert_allclose(normal.dense(), J.T @ J, rtol=0, atol=1e-10)
    np.testing.assert_allclose(normal.gradient, J.T @ e.ravel(), rtol=0, atol=1e-10)


@pytest.mark.parametrize("k", [1, 4])
def test_the_compiled_frames_first_equals_numpys(k, monkeypatch):
    """The compiled elimination (_group, Cholesky of each frame's block, dsyrk over chunks of frames) against
    numpy's inverted blocks and dense couplings (`_frames_first_numpy`), and both against a dense solve."""
    monkeypatch.setattr(group_normal, "CHUNK_NUMBERS", 3000)  # several chunks of frames
    structure, _, normal, _, _ = two_camera_normal(11)
    assert _group.local_layout(structure.local_cols, normal.A) == (6, 3)  # the poses, then the jitter blocks
    right = np.random.default_rng(2).normal(size=(structure.size, k))
    F, L2 = structure.n_frames, structure.local_size
    R2, P = structure.rig_size, structure.n_points
    r_local, r_rig, r_point = right[:F * L2].reshape(F, L2, k), right[F * L2:F * L2 + R2], right[F * L2 + R2:]
    compiled = group_normal._frames_first(normal, r_local, r_rig, r_point.reshape(P, 3, k))
    reference = group_normal._frames_first_numpy(normal, r_local, r_rig, r_point.reshape(P, 3, k))
    for a, b in zip(compiled, reference):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-13)
    x, _ = solve(normal, right)
    np.testing.assert_allclose(x, np.linalg.solve(normal.dense(), right), rtol=1e-9, atol=1e-12)


def test_right_sides_of_the_rig_alone_solve_as_the_dense_matrix():
    """Right sides without a frames' part (the covariance's rig columns) skip the frames' reduction of y."""
    structure, _, normal, _, _ = two_camera_normal(11)
    first = structure.n_frames * structure.local_size
    right = np.zeros((structure.size, structure.rig_size))
    right[first + np.arange(structure.rig_size), np.arange(structure.rig_size)] = 1.0
    x, rig_inverse = solve(normal, right)
    inverse = np.linalg.inv(normal.dense())
    np.testing.assert_allclose(x, inverse[:, first:first + structure.rig_size], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(rig_inverse, x[first:first + structure.rig_size], rtol=1e-12, atol=1e-15)
