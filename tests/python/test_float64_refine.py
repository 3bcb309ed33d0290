"""Issue 40, part 2: float64 points answered in float64 (Index refine; KDTree always).

The UTM-like case of the issue at 20k points (bench/python_bench.py --utm measures 200k): points in
a 100 m patch at 4.3e6 m, every exact method, kNN and radius search, against scipy's cKDTree in
float64 at rel 1e-9; a row is right when its distances are within rel 1e-9 of scipy's and its
indices equal scipy's (where scipy's distances tie exactly, either order).
"""
import pickle

import numpy as np
import pytest
from scipy.spatial import cKDTree

import blockhash_cl as bh

EXACT = [m for m in ("bruteforce", "kdtree", "flann") if m in bh.method_names()] + ["blockhash"]
BASE = np.array([512345.678, 4312345.678, 112.5])


@pytest.fixture(scope="module")
def utm():
    rng = np.random.default_rng(40)
    pts = BASE + rng.random((20000, 3)) * 100.0
    q = BASE + rng.random((4000, 3)) * 100.0
    return pts, q, cKDTree(pts)


def rows_right(d, ids, ref_d, ref_i):
    close = np.abs(d - ref_d) <= 1e-9 * np.maximum(ref_d, 1e-300)
    same = (ids == ref_i) | np.isclose(ref_d, np.roll(ref_d, 1, axis=1), rtol=0, atol=0) \
        | np.isclose(ref_d, np.roll(ref_d, -1, axis=1), rtol=0, atol=0)
    return np.all(close & same, axis=1)


@pytest.mark.parametrize("method", EXACT)
@pytest.mark.parametrize("k", [1, 10, 50])
def test_utm_knn_rows_are_scipys_float64_rows(utm, method, k):
    pts, q, tree = utm
    ref_d, ref_i = tree.query(q, k=k)
    ref_d, ref_i = ref_d.reshape(len(q), k), ref_i.reshape(len(q), k)
    index = bh.make_index(method, pts)
    assert index.refined and index.coordinates["recentred"]
    d2, ids, st = index.query(q, k=k, return_stats=True)
    assert d2.dtype == np.float64 and ids.dtype == np.int32
    assert st["refined"] and st["refine_exact"] and st["refine_s"] >= 0 and 0 <= st["refine_share"] <= 1
    right = rows_right(np.sqrt(d2), ids, ref_d, ref_i)
    assert right.mean() >= 0.9999, (method, k, right.mean())
    # The same points without refinement: float32's rounding shows at rel 1e-9.
    d32, _ = bh.make_index(method, pts, refine=False).query(q, k=k)
    assert d32.dtype == np.float32
    assert rows_right(np.sqrt(d32.astype(np.float64)), ids, ref_d, ref_i).mean() < 0.5


@pytest.mark.parametrize("method", EXACT)
def test_utm_radius_is_scipys_float64_ball(utm, method):
    pts, q, tree = utm
    index = bh.make_index(method, pts)
    r = 2.5
    res, st = index.radius_search(q, r), index.last_stats
    assert res.dist2.dtype == np.float64 and st["refined"]
    truth = tree.query_ball_point(q, r)
    wrong = 0
    for j in range(len(q)):
        d2, ids = res.slice(j)
        ref = np.array(sorted(truth[j], key=lambda t: (np.sum((pts[t] - q[j]) ** 2), t)), dtype=np.int64)
        ref_d2 = np.sum((pts[ref] - q[j]) ** 2, axis=1) if len(ref) else np.zeros(0)
        wrong += not (np.array_equal(ids, ref) and np.allclose(d2, ref_d2, rtol=1e-12, atol=0))
    assert wrong / len(q) <= 1e-4
    # A point exactly on the float64 sphere is in (d2 <= r*r), one a hair outside is not.
    on = BASE + np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [3.0, 4.0 + 1e-7, 0.0]])
    idx = bh.make_index(method, np.concatenate([on, pts]))
    assert idx.radius_search(on[:1], 5.0).ids.tolist() == [0, 1]
    # max_results: the nearest in float64.
    capped = index.radius_search(q[:200], r, max_results=3)
    for j in range(200):
        assert np.array_equal(capped.slice(j)[1], res.slice(j)[1][:3])


def test_duplicates_force_more_candidates_and_the_radius_fallback():
    """Near-ties at the last candidate (duplicate points) are searched again: with more
    candidates, then (past MAX_K duplicates) by a radius search; the rows stay scipy's."""
    rng = np.random.default_rng(41)
    pts = BASE + rng.random((3000, 3)) * 10.0
    pts[100:500] = pts[100]          # 400 copies of one point
    pts[600:606] = pts[600]          # a few copies of another
    q = np.concatenate([pts[[100, 600]] + 1e-4, BASE + rng.random((50, 3)) * 10.0])
    index = bh.make_index("kdtree", pts)
    d2, ids, st = index.query(q, k=8, return_stats=True)
    assert st["refine_requeried_rows"] >= 1 and st["refine_radius_rows"] >= 1
    ref_d, ref_i = cKDTree(pts).query(q, k=8)
    np.testing.assert_allclose(np.sqrt(d2), ref_d, rtol=1e-12)
    assert ids[0].tolist() == list(range(100, 108))  # ties by index
    assert ids[1].tolist()[:6] == list(range(600, 606))


def test_refine_modes_max_radius_pickle_and_add():
    rng = np.random.default_rng(42)
    pts = BASE + rng.random((5000, 3)) * 50.0
    q = BASE + rng.random((300, 3)) * 50.0
    assert not bh.make_index("kdtree", pts, refine=False).refined
    assert not bh.make_index("kdtree", pts.astype(np.float32)).refined        # float32 in: float32 out
    assert not bh.make_index("kdtree", rng.random((100, 3))).refined          # around 0: as before
    assert bh.make_index("kdtree", rng.random((100, 3)), refine=True).refined
    with pytest.raises(TypeError, match="refine"):
        bh.make_index("kdtree", pts, refine="yes")
    index = bh.make_index("kdtree", pts)
    d2, ids = index.query(q, k=6, max_radius=2.0)
    ref_d, ref_i = cKDTree(pts).query(q, k=6, distance_upper_bound=np.nextafter(2.0, 3.0))
    np.testing.assert_array_equal(ids, np.where(ref_i == len(pts), -1, ref_i))
    np.testing.assert_allclose(np.sqrt(d2), ref_d, rtol=1e-12)
    back = pickle.loads(pickle.dumps(index))
    assert back.refined
    np.testing.assert_array_equal(back.query(q, k=6)[0], index.query(q, k=6)[0])
    more = BASE + rng.random((100, 3)) * 50.0
    index.add(more)
    allp = np.concatenate([pts, more])
    d2, ids = index.query(q, k=4)
    ref_d, ref_i = cKDTree(allp).query(q, k=4)
    np.testing.assert_array_equal(ids, ref_i)
    np.testing.assert_allclose(np.sqrt(d2), ref_d, rtol=1e-12)
    assert index.memory_bytes >= allp.nbytes  # the float64 copy is counted


def test_query_delta_in_cpp_equals_its_numpy_definition():
    """_core.query_delta (one pass in C++) gives _refine's numpy definition bit for bit, at the
    edges too: NaN, inf, 0, FLT_MAX (spacing inf), subnormals."""
    from blockhash_cl import _refine
    rng = np.random.default_rng(5)
    q = (rng.random((5000, 3)) * 2e6 - 1e6).astype(np.float32)
    q[:6] = [[np.nan, 0, 0], [np.inf, 1, 1], [0, 0, 0], [3.4028235e38, 0, 0], [1e-40, -1e-42, 0], [-7, 2, -9]]
    with np.errstate(over="ignore"):
        want = _refine._query_delta_numpy(q, 1.9e-6)
    np.testing.assert_array_equal(_refine.query_delta(q, 1.9e-6), want)


def test_refine_knn_counts_the_found_ids():
    """_core.refine_knn's third output: per row the ids >= 0 among its first k (missing last)."""
    from blockhash_cl import _core
    rng = np.random.default_rng(6)
    p64 = rng.random((50, 3))
    q64 = rng.random((7, 3))
    ids = rng.integers(0, 50, (7, 6)).astype(np.int32)
    ids[2, 3:] = -1
    ids[4, :] = -1
    d2, out_ids, found = _core.refine_knn(q64, p64, ids, 5)
    np.testing.assert_array_equal(found, np.sum(out_ids >= 0, axis=1))
    assert found[4] == 0 and found[2] == 3 and np.all(np.isinf(d2[4]))
    exact = np.sum((q64[:, None, :] - p64[np.maximum(ids, 0)]) ** 2, axis=2)
    np.testing.assert_allclose(d2[0], np.sort(exact[0])[:5], rtol=0, atol=0)


def _refine_knn_reference(q64, p64, ids, k):
    """refine_knn's definition in numpy: per row the candidates by (float64 distance, id), missing
    (id < 0) last as (inf, -1), the first k, and the count of ids found among them."""
    d = np.where(ids >= 0, np.sum((q64[:, None, :] - p64[np.maximum(ids, 0)]) ** 2, axis=2), np.inf)
    key = np.where(ids >= 0, ids, np.iinfo(np.int32).max)
    order = np.lexsort((key, d), axis=1)[:, :k]
    out_d = np.take_along_axis(d, order, axis=1)
    out_i = np.take_along_axis(ids, order, axis=1)
    out_i = np.where(out_i >= 0, out_i, -1).astype(np.int32)
    return out_d, out_i, np.sum(out_i >= 0, axis=1)


@pytest.mark.parametrize("in_order", ["1", "0"])
def test_refine_knn_ordered_and_shuffled_rows_vs_numpy(monkeypatch, in_order):
    """_core.refine_knn against its numpy definition, bit for bit, on rows the float32 order left
    in float64 order (copied out without a sort), rows out of order (shuffled: sorted), exact
    distance ties (sorted by id), missing ids (< 0, last) and rows of missing only; the same with
    BHCL_REFINE_IN_ORDER=0 (every row through the sort)."""
    from blockhash_cl import _core
    monkeypatch.setenv("BHCL_REFINE_IN_ORDER", in_order)
    rng = np.random.default_rng(7)
    p64 = rng.random((400, 3))
    p64[300:310] = p64[0]  # duplicates of point 0: exact ties
    q64 = rng.random((600, 3))
    q64[:20] = p64[0]
    kc, k = 12, 9
    d_all = np.sum((q64[:, None, :] - p64[None, :, :]) ** 2, axis=2)
    ids = np.argsort(d_all, axis=1, kind="stable")[:, :kc].astype(np.int32)  # in order
    shuffled = np.arange(100, 250)
    for r in shuffled:
        rng.shuffle(ids[r])
    ids[20:40, 1:] = ids[20:40, 1:][:, ::-1]  # the k + 1-th first: out of order past k too
    ids[250:260, 7:] = -1
    ids[260:265, :] = -1
    ids[265:270, 3] = -1  # a missing id inside a row: out of order
    for r in [0, 5, 10]:  # ties listed by descending id: out of order
        ids[r] = np.sort(ids[r])[::-1]
    got = _core.refine_knn(q64, p64, ids, k)
    want = _refine_knn_reference(q64, p64, ids, k)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    bad = ids.copy()
    bad[3, 2] = 400
    with pytest.raises(ValueError, match="id past the points"):
        _core.refine_knn(q64, p64, bad, k)


@pytest.mark.parametrize("method", EXACT)
def test_refined_max_radius_counts_are_the_ids_found_vs_scipy(utm, method):
    """A refined query with max_radius: each row's count is its ids found within it (rows with
    fewer than k there included: their missing entries are not subtracted again), the rows as
    scipy's distance_upper_bound gives them (scipy's is strict: its bound just above r)."""
    pts, q, tree = utm
    index = bh.make_index(method, pts)
    r, k = 5.0, 10
    d2, ids, counts = index.query(q, k=k, max_radius=r, return_counts=True)
    assert np.all(counts >= 0)
    np.testing.assert_array_equal(counts, np.sum(ids >= 0, axis=1))
    ref_d, ref_i = tree.query(q, k=k, distance_upper_bound=np.nextafter(r, np.inf))
    np.testing.assert_array_equal(counts, np.sum(np.isfinite(ref_d), axis=1))
    assert 0 < np.mean(counts < k) < 1  # rows short of k and full rows both met
    d = np.sqrt(d2)
    np.testing.assert_array_equal(np.isfinite(d), np.isfinite(ref_d))  # missing where scipy's are
    fin = np.isfinite(ref_d)
    d, ref_d = np.where(fin, d, 1.0), np.where(fin, ref_d, 1.0)  # missing entries compared as equal
    assert np.all(rows_right(d, np.where(ids >= 0, ids, len(pts)), ref_d, ref_i))
