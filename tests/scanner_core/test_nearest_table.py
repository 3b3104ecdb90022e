"""The nearest-point lookup table the registration's search screens with, the exact grid and
memo the fits query, and the fine fit's stopping and acceleration: checked against the
KD-tree and against the plain iteration."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import scanner_core.pose.fine as pose_fine
from scanner_core.pose.nearest_table import FAR_SHELLS, NearestGrid, NearestMemo, NearestTable
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


@pytest.mark.parametrize("k", [1, 2])
@pytest.mark.parametrize("spread_mm", [0.0, 0.05, 0.6, 4.0, 30.0])
@pytest.mark.parametrize("with_far", [True, False])
def test_the_grid_answers_as_the_tree(surface, k, spread_mm, with_far):
    """On the samples, near them, millimetres off, and far outside the grid's box, under
    bounds from a tenth of a millimetre to none: the same nearest points at the same
    distances as the KD-tree, whether the far points go to the tree or the grid searches on."""
    points, tree = surface
    far_calls = []

    def far(queries, kk, bound):
        far_calls.append(len(queries))
        return tree.query(queries, k=kk, distance_upper_bound=bound)

    grid = NearestGrid(points, far=far if with_far else None)
    rng = np.random.default_rng(int(spread_mm * 100) + k)
    queries = points[rng.choice(len(points), 1500)] + rng.normal(0, spread_mm, (1500, 3))
    for bound in (0.1, 1.0, 6.0, np.inf):
        dist, index = grid.query(queries, k=k, distance_upper_bound=bound)
        exact, nearest = tree.query(queries, k=k, distance_upper_bound=bound)
        assert np.array_equal(np.isfinite(dist), np.isfinite(exact))
        found = np.isfinite(exact)
        assert np.array_equal(dist[found], exact[found])
        assert np.array_equal(index[found], nearest[found])
        assert np.all(index[~found] == len(points))
    # a point farther than the grid's shells is the tree's when there is one
    assert bool(far_calls) == (with_far and spread_mm * 3 > FAR_SHELLS * grid.cell_mm)


def test_the_grid_sizes_its_cells_to_its_points():
    """A surface's samples and an edge's (a line of them) each get cells holding about a
    dozen; ties (a point on every sample of a regular grid) are answered at the tie's
    distance; a single point, a query a million kilometres off, a query that is no point
    (refused) and sets that are none are handled."""
    plane = np.stack(np.meshgrid(np.arange(0, 40, 0.25), np.arange(0, 30, 0.25), [0.0]),
                     axis=-1).reshape(-1, 3)
    line = np.stack([np.arange(0, 50, 0.1), np.zeros(500), np.zeros(500)], axis=1)
    for points in (plane, line):
        grid = NearestGrid(points)
        cells = np.floor((points - grid.origin) / grid.cell_mm).astype(int)
        per_cell = len(points) / len(np.unique(cells, axis=0))
        assert 6 <= per_cell <= 24, per_cell
    grid = NearestGrid(plane)
    queries = plane[::97] + [0.125, 0.125, 0.0]  # equidistant from four samples
    dist, index = grid.query(queries, k=2, distance_upper_bound=1.0)
    assert np.allclose(dist, np.hypot(0.125, 0.125), rtol=0, atol=1e-12)
    assert np.allclose(np.linalg.norm(plane[index] - queries[:, None], axis=2), dist)
    assert np.all(index[:, 0] != index[:, 1])
    one = NearestGrid(np.array([[1.0, 2.0, 3.0]]))
    dist, index = one.query(np.array([[1.0, 2.0, 5.0], [1e12, 0.0, 0.0]]), k=2)
    assert dist[0, 0] == 2.0 and index[0, 0] == 0 and np.isinf(dist[0, 1]) and index[0, 1] == 1
    assert dist[1, 0] == pytest.approx(1e12) and np.isinf(dist[1, 1]) and index[1, 1] == 1
    with pytest.raises(ValueError, match="k must be 1 or 2"):
        one.query(np.zeros((1, 3)), k=3)
    with pytest.raises(ValueError, match="finite"):  # refused, as the KD-tree refuses it
        one.query(np.array([[np.nan, 0.0, 0.0]]))
    for bad in (np.zeros((0, 3)), np.array([[0.0, np.inf, 0.0]]),
                np.array([[0.0] * 3, [1e200] * 3])):
        with pytest.raises(ValueError, match="grid"):
            NearestGrid(bad)


@pytest.mark.parametrize("step_mm", [0.0005, 0.02, 0.5])
@pytest.mark.parametrize("searched_by", ["tree", "grid"])
def test_a_remembered_query_is_a_fresh_query(surface, step_mm, searched_by):
    """Points moving as a fit's do (micrometres late, half a millimetre early), some far off
    the part, under bounds that shrink and grow: the memo answers as the tree does, and asks
    it again about fewer points the less they move."""
    points, tree = surface
    rng = np.random.default_rng(3)
    moving = points[rng.choice(len(points), 2000)] + rng.normal(0, 0.1, (2000, 3))
    moving[:100, 2] += 8.0  # above the block: no match within the smaller bounds
    search = tree if searched_by == "tree" else NearestGrid(points)
    memo = NearestMemo(search)
    asked = []
    original = search.query

    class Counting:  # the same search, counting the points it is asked about
        n, data = search.n, search.data

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
