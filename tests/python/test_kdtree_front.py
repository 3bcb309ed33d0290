"""blockhash_cl.KDTree against scipy.spatial.KDTree on 3-D data: what scipy's own tests (the
subset test_scipy_kdtree_suite.py runs) reach only in 4-D (sparse_distance_matrix, pickling,
copy_data, workers), plus k past MAX_K, every exact method and the refusals."""
import pickle

import numpy as np
import pytest
from scipy.spatial import KDTree as SciKDTree

import blockhash_cl as bh

METHODS = [m for m in ("blockhash", "kdtree", "bruteforce", "flann") if m in bh.method_names()]


@pytest.fixture(scope="module")
def sets():
    rng = np.random.default_rng(400)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    return a, b, SciKDTree(a), SciKDTree(b)


@pytest.mark.parametrize("method", METHODS)
def test_query_shapes_and_values_match_scipy(sets, method):
    a, b, sa, _ = sets
    t = bh.KDTree(a, method=method)
    for k in (1, 5, [2], [1, 3, 7], 320):
        d, i = t.query(b, k=k)
        sd, si = sa.query(b, k=k)
        assert d.shape == sd.shape and i.shape == si.shape and i.dtype == si.dtype
        np.testing.assert_allclose(d, sd, rtol=1e-12)
        np.testing.assert_array_equal(i, si)
    d, i = t.query(b.reshape(4, 50, 3), k=3, distance_upper_bound=0.5)
    sd, si = sa.query(b.reshape(4, 50, 3), k=3, distance_upper_bound=0.5)
    np.testing.assert_array_equal(i, si)
    np.testing.assert_allclose(d, sd, rtol=1e-12)
    d, i = t.query(b[0], k=300 + 5, distance_upper_bound=1.0)  # k > MAX_K, bounded
    sd, si = sa.query(b[0], k=305, distance_upper_bound=1.0)
    np.testing.assert_array_equal(i, si)


def test_sparse_distance_matrix_every_output(sets):
    a, b, sa, sb = sets
    t1, t2 = bh.KDTree(a), bh.KDTree(b)
    ref = sa.sparse_distance_matrix(sb, 0.7).toarray()
    np.testing.assert_allclose(t1.sparse_distance_matrix(t2, 0.7).toarray(), ref, rtol=1e-14)
    coo = t1.sparse_distance_matrix(t2, 0.7, output_type="coo_matrix")
    assert coo.format == "coo" and coo.shape == (300, 200)
    np.testing.assert_allclose(coo.toarray(), ref, rtol=1e-14)
    dct = t1.sparse_distance_matrix(t2, 0.7, output_type="dict")
    assert dct.keys() == sa.sparse_distance_matrix(sb, 0.7, output_type="dict").keys()
    arr = t1.sparse_distance_matrix(t2, 0.7, output_type="ndarray")
    assert arr.dtype == sa.sparse_distance_matrix(sb, 0.7, output_type="ndarray").dtype
    with pytest.raises(ValueError, match="output type"):
        t1.sparse_distance_matrix(t2, 0.7, output_type="csr")


def test_pairs_counts_and_ball_tree(sets):
    a, b, sa, sb = sets
    t1, t2 = bh.KDTree(a), bh.KDTree(b)
    assert t1.query_pairs(0.4) == sa.query_pairs(0.4)
    np.testing.assert_array_equal(t1.query_pairs(0.4, output_type="ndarray"),
                                  np.array(sorted(sa.query_pairs(0.4))))
    r = [0.1, 0.5, 1.0, 3.0]
    np.testing.assert_array_equal(t1.count_neighbors(t2, r), sa.count_neighbors(sb, r))
    np.testing.assert_array_equal(t1.count_neighbors(t2, r, cumulative=False), sa.count_neighbors(sb, r, cumulative=False))
    assert t1.count_neighbors(t2, 0.5) == sa.count_neighbors(sb, 0.5)
    assert [sorted(x) for x in t1.query_ball_tree(t2, 0.5)] == [sorted(x) for x in sa.query_ball_tree(sb, 0.5)]
    got = t1.query_ball_point(b[:20], 0.6)
    ref = sa.query_ball_point(b[:20], 0.6)
    assert got.dtype == object and [list(x) for x in got] == [list(x) for x in ref]


def test_pickle_copy_data_workers_and_attributes(sets):
    a, b, _, _ = sets
    t = bh.KDTree(a, leafsize=4, method="kdtree")
    back = pickle.loads(pickle.dumps(t))
    np.testing.assert_array_equal(back.query(b, k=5)[1], t.query(b, k=5)[1])
    assert (t.n, t.m, t.leafsize) == (300, 3, 4) and t.data.dtype == np.float64
    np.testing.assert_array_equal(t.maxes, a.max(axis=0))
    own = a.copy()
    tc = bh.KDTree(own, copy_data=True)
    before = tc.query(b, k=3)[1]
    own[:] = 0
    np.testing.assert_array_equal(tc.query(b, k=3)[1], before)
    np.testing.assert_array_equal(t.query(b, k=2, workers=-1)[1], t.query(b, k=2, workers=4)[1])
    with pytest.raises(ValueError, match="workers"):
        t.query(b, workers=0)
    assert isinstance(bh.cKDTree(a).query(b[0])[1], int)
    assert isinstance(bh.KDTree(a).query(b[0])[1], np.intp) and isinstance(bh.KDTree(a).query(b[0])[0], float)
    assert t.last_stats["refined"]


def test_refusals_name_what_is_supported(sets):
    a, _, _, _ = sets
    msg = "supports 3-dimensional data with p = 2"
    with pytest.raises(ValueError, match=msg + ".*2-dimensional"):
        bh.KDTree(a[:, :2])
    with pytest.raises(ValueError, match=msg + ".*boxsize"):
        bh.KDTree(a, boxsize=1.0)
    t = bh.KDTree(a)
    for p in (1, np.inf, 3):
        with pytest.raises(ValueError, match=msg):
            t.query(a[:3], p=p)
        with pytest.raises(ValueError, match=msg):
            t.query_ball_point(a[:3], 0.1, p=p)
    with pytest.raises(ValueError, match="length 3"):
        t.query(a[:3, :2])
    with pytest.raises(TypeError, match="complex"):
        bh.KDTree(a.astype(complex))
    with pytest.raises(ValueError, match="exact methods"):
        bh.KDTree(a, method="nope")
    with pytest.raises(ValueError, match="grid"):
        bh.KDTree(a, grid=0)


def test_bounds_nan_queries_and_integer_data(sets):
    a, b, sa, _ = sets
    t = bh.KDTree(a)
    for dub in (-1.0, 0.0):
        d, i = t.query(b[:5], k=2, distance_upper_bound=dub)
        assert np.isinf(d).all() and (i == t.n).all()
    q = b[:4].copy()
    q[0, 1] = np.nan
    d, i = t.query(q, k=2)
    assert np.isinf(d[0]).all() and (i[0] == t.n).all()
    np.testing.assert_array_equal(i[1:], sa.query(q[1:], k=2)[1])
    ti = bh.KDTree(np.arange(30).reshape(10, 3).tolist())
    assert ti.data.dtype == np.float64 and ti.query([0, 0, 0], k=2)[1].tolist() == [0, 1]
