"""The nearest-point lookup table the registration's search screens with, and the fine fit's
stopping and acceleration: checked against the KD-tree and against the plain iteration."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import scanner_core.pose.fine as pose_fine
from scanner_core.pose.nearest_table import NearestMemo, NearestTable
from scanner_core.pose.registration import EdgeModel, PoseParams, SurfaceModel, register
from simulator.parts import block_with_holes_and_steps, centred_grasp
from test_pose import lobed_disc, misplacement, pose_error, synthetic_scan


@pytest.fixture(scope="module")
def surface():
    """A stepped block's surface samples (0.25 mm apart) and a KD-tree over them."""
    model = SurfaceModel.from_mesh(block_with_holes_and_steps())
    return model.points, cKDTree(model.points)


@pytest.mark.parametrize("spread_mm", [0.3, 3.0, 9.0])
def test_a_lookup_is_a_point_near_the_nearest(surface, spread_mm):
    points, tree = surface
    table = NearestTable(points, band_mm=12.5)
    rng = np.random.default_rng(1)
    queries = points[rng.choice(len(points), 3000)] + rng.normal(0, spread_mm, (3000, 3))
    dist, index = table.query(queries, bound=12.0)
    exact, _ = tree.query(queries, distance_upper_bound=12.0)
    found = np.isfinite(dist)
    # every point within the band finds one, at its true distance from what it found ...
    assert np.array_equal(found, np.isfinite(exact))
    assert np.allclose(dist[found], np.linalg.norm(queries[found] - points[index[found]], axis=1))
    # ... which is never nearer than the nearest, and at most two voxel half-diagonals farther
    extra = dist[found] - exact[found]
    assert extra.min() >= -1e-12
    assert extra.max() <= table.voxel_mm * np.sqrt(3.0) + 1e-9
    assert np.median(extra) < 0.25 * table.voxel_mm
    assert np.all(index[~found] == len(points))


def test_a_bound_is_honoured_and_beyond_the_band_the_tree_answers(surface):
    points, tree = surface
    calls = []

    def fallback(queries, bound):
        calls.append(len(queries))
        return tree.query(queries, distance_upper_bound=bound)

    table = NearestTable(points, band_mm=2.0, fallback=fallback)
    far = points[:200].copy()
    far[:, 2] = points[:, 2].max() + 5.0  # 5 mm above the block: off the table
    exact, nearest = tree.query(far)
    dist, index = table.query(far, bound=1.0)
    assert np.all(np.isinf(dist)) and not calls  # within a bound inside the band: no match
    dist, index = table.query(far, bound=20.0)   # a bound beyond the band: the tree's answer
    assert calls and np.allclose(dist, exact) and np.array_equal(index, nearest)


@pytest.mark.parametrize("step_mm", [0.0005, 0.02, 0.5])
def test_a_remembered_query_is_a_fresh_query(surface, step_mm):
    """Points moving as a fit's do (micrometres late, half a millimetre early), some far off
    the part, under bounds that shrink and grow: the memo answers as the tree does, and asks
    it again about fewer points the less they move."""
    points, tree = surface
    rng = np.random.default_rng(3)
    moving = points[rng.choice(len(points), 2000)] + rng.normal(0, 0.1, (2000, 3))
    moving[:100, 2] += 8.0  # above the block: no match within the smaller bounds
    memo = NearestMemo(tree)
    asked = []
    original = tree.query

    class Counting:  # the same tree, counting the points it is asked about
        n, data = tree.n, tree.data

        def query(self, queries, **kw):
            asked.append(len(queries))
            return original(queries, **kw)

    memo.tree = Counting()
    for bound in [5.5, 5.5, 3.0, 1.0, 0.6, 0.6, 9.0, 0.6, 0.45]:
        moving = moving + rng.normal(0, step_mm, moving.shape)
        dist, index = memo.query(moving, bound)
        exact, nearest = tree.query(moving, distance_upper_bound=bound)
        assert np.array_equal(np.isfinite(dist), np.isfinite(exact))
        found = np.isfinite(exact)
        assert np.array_equal(index[found], nearest[found])
        assert np.allclose(dist[found], exact[found], rtol=0, atol=1e-12)
        assert np.all(index[~found] == len(points))
    assert asked[0] == len(moving)
    if step_mm < 0.001:
        assert np.mean(asked[1:]) < 0.2 * len(moving)


def test_the_table_stays_within_its_size():
    points = np.random.default_rng(2).uniform(-200, 200, (5000, 3))
    table = NearestTable(points, band_mm=25.0, max_voxels=200_000)
    assert table.table.size <= 200_000 and table.table.dtype == np.int32
    assert table.voxel_mm > 0.5
    dist, index = NearestTable(np.zeros((0, 3)), band_mm=5.0).query(np.ones((4, 3)), 3.0)
    assert np.all(np.isinf(dist)) and np.all(index == 0)


def test_the_fine_fit_stops_and_jumps_where_the_plain_iteration_would_end(monkeypatch):
    """A fit that creeps, or converges slowly along one line, ends where the plain iteration
    to ``max_iterations`` would (within a fraction of a micrometre), in fewer iterations."""
    mesh = lobed_disc()  # held in its plane by its lobes alone: a slow, linear convergence
    nominal = centred_grasp(mesh)
    model, edge_model = SurfaceModel.from_mesh(mesh), EdgeModel.from_mesh(mesh)
    truth = misplacement(0.5, -0.3, 0.2, 1.0, -1.0, 2.0) @ nominal
    pts, nrm, frames, edges, edge_frames = synthetic_scan(mesh, truth, seed=3,
                                                          frame_sigma_mm=0.005)

    def fit():
        calls = []
        linearise = pose_fine._linearise

        def counted(*args, **kwargs):
            calls.append(1)
            return linearise(*args, **kwargs)
        monkeypatch.setattr(pose_fine, "_linearise", counted)
        result = register(pts, nrm, model, nominal, frame_ids=frames, edges_t=edges,
                          edge_frame_ids=edge_frames, edge_model=edge_model,
                          params=PoseParams(max_points=3000))
        monkeypatch.setattr(pose_fine, "_linearise", linearise)
        return result, len(calls)

    fast, fast_calls = fit()
    monkeypatch.setattr(pose_fine, "_JUMP_RATIO", -1.0)     # never jump
    monkeypatch.setattr(pose_fine, "_CREEP_FACTOR", 0.0)    # run to the tolerance
    plain, plain_calls = fit()
    dt, dr = pose_error(fast.matrix, plain.matrix)
    assert np.abs(dt).max() < 5e-4 and np.abs(dr).max() < 5e-4, (dt, dr)
    # The sigmas within 3 %: the disc's rim is one edge curve that holds it in its plane
    # alone (leverage 0.998), and its leverage-corrected residuals (``pose_confidence
    # ._leverage_corrected``) scale up differences of a fraction of a micrometre (1.7 % on rz).
    assert np.allclose(fast.std, plain.std, rtol=0.03), (fast.std, plain.std)
    assert fast.act == plain.act and fast.free_axes == plain.free_axes
    assert fast_calls < plain_calls, (fast_calls, plain_calls)


def test_a_part_without_sharp_edges_is_prepared_and_its_edges_match_nothing():
    import trimesh

    from scanner_core.cad import part_from_mesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    edge_model = EdgeModel.from_mesh(sphere)
    assert len(edge_model.points) == 0
    dist, _ = edge_model.tree.query(np.zeros((3, 3)), distance_upper_bound=100.0)
    assert np.all(np.isinf(dist))
    dist, _ = edge_model.lookup.query(np.zeros((3, 3)), 100.0)
    assert np.all(np.isinf(dist))
    part = part_from_mesh(sphere, name="sphere")
    assert part.prepare() > 0.0
