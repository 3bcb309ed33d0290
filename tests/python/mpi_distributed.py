"""blockhash_cl.DistributedIndex under MPI (issue 40, part 3): run by every rank, e.g.

    mpirun -np 4 --oversubscribe python -m pytest -q -p no:cacheprovider tests/python/mpi_distributed.py

(.ci/python runs it at 2 and 4 ranks; tests/python/test_distributed.py at 1 rank without mpi4py).
Not named test_*.py: a plain `pytest tests/python` does not collect it, since every test here is
collective and must run on every rank of one job.

Each rank builds the one-process index over ALL the points (the same seed everywhere) and checks
its own queries' rows of the distributed index against it: exact methods bit for bit (ids,
float32 squared distances, counts). Every test makes all its collective calls first and asserts
afterwards, so a failing check on one rank cannot leave the others waiting in a collective.
BHCL_TEST_NO_MPI4PY=1 hides mpi4py (comm=None then initialises MPI in the library).
"""
import os
import sys

if os.environ.get("BHCL_TEST_NO_MPI4PY"):
    sys.modules["mpi4py"] = None  # type: ignore  # an import of mpi4py now raises ImportError

import numpy as np
import pytest

import blockhash_cl as bh

pytestmark = pytest.mark.skipif(not bh.HAVE_MPI, reason="blockhash_cl built without MPI")

METHODS = ["kdtree", "bruteforce", "blockhash"] + (["flann"] if bh.HAVE_FLANN else [])
N, NQ = 12000, 2500


def _comm():
    """mpi4py's COMM_WORLD, or None (the library's MPI_COMM_WORLD) when mpi4py is hidden or missing."""
    try:
        from mpi4py import MPI
    except ImportError:
        return None
    return MPI.COMM_WORLD


@pytest.fixture(scope="module")
def world():
    """(comm, rank, ranks) for this job."""
    comm = _comm()
    probe = bh.DistributedIndex("bruteforce", np.zeros((1, 3), np.float32), comm)
    return comm, probe.rank, probe.ranks


@pytest.fixture(scope="module")
def data():
    """Points in two clusters and a uniform background, queries on them and over the box (the
    same on every rank)."""
    rng = np.random.default_rng(40)
    a = rng.normal(0.25, 0.03, (N // 3, 3))
    b = rng.normal(0.7, 0.05, (N // 3, 3))
    c = rng.random((N - 2 * (N // 3), 3))
    pts = np.concatenate([a, b, c]).astype(np.float32)
    rng.shuffle(pts)
    q = np.concatenate([pts[rng.integers(0, N, NQ // 2)] + 0.002, rng.random((NQ - NQ // 2, 3)) * 1.2 - 0.1])
    return pts, q.astype(np.float32)


def _split(n, ranks, rank, skew=True):
    """This rank's slice of n items: uneven parts (rank 0 the most), the last rank none when skew
    and there are several ranks (any split must give the same answers)."""
    if ranks == 1:
        return slice(0, n)
    w = np.arange(ranks, 0, -1, dtype=np.float64)
    if skew:
        w[-1] = 0
    cuts = np.concatenate([[0], np.round(np.cumsum(w) / w.sum() * n).astype(int)])
    return slice(int(cuts[rank]), int(cuts[rank + 1]))


def _mine(world, data):
    """(this rank's points: a skewed split, its queries: an even split)."""
    _, rank, ranks = world
    pts, q = data
    return pts[_split(N, ranks, rank)], q[_split(NQ, ranks, rank, skew=False)]


def _assert_same_knn(got, one, queries, k, **search):
    """(dist2, ids, counts) of the distributed index equal one process's, bit for bit."""
    e_d2, e_ids, e_counts = one.query(queries, k=k, return_counts=True, **search)
    np.testing.assert_array_equal(got[1], e_ids.astype(np.int64))
    np.testing.assert_array_equal(got[0], e_d2)
    np.testing.assert_array_equal(got[2], e_counts)


def _assert_same_radius(got, exp):
    """A RadiusResult of the distributed index equals one process's, bit for bit."""
    np.testing.assert_array_equal(got.offsets, exp.offsets)
    np.testing.assert_array_equal(got.ids, exp.ids.astype(np.int64))
    np.testing.assert_array_equal(got.dist2, exp.dist2)


@pytest.mark.parametrize("method", METHODS)
def test_knn_equals_one_process(world, data, method):
    comm, rank, ranks = world
    pts, q = data
    mine_p, mine_q = _mine(world, data)
    index = bh.DistributedIndex(method, mine_p, comm)
    got = {k: index.query(mine_q, k=k, return_counts=True, return_stats=True) for k in (1, 10, 50)}
    capped = index.query(mine_q, k=16, max_radius=0.02, return_counts=True)
    one = bh.make_index(method, pts)
    assert index.size == N and index.ranks == ranks and index.exact == one.exact
    assert sum(index.build_stats["shard_points_all"]) == N
    for k, (d2, ids, counts, stats) in got.items():
        assert ids.dtype == np.int64 and d2.dtype == np.float32 and ids.shape == (len(mine_q), k)
        _assert_same_knn((d2, ids, counts), one, mine_q, k)
        assert stats["n_queries"] == len(mine_q) and stats["owner"].shape == (len(mine_q),)
        assert np.all(stats["ranks_visited"] >= 1) and np.all(stats["ranks_visited"] <= ranks)
        assert {"phase1_s", "phase2_s", "multi_rank_queries", "bytes_sent", "wall_s"} <= set(stats)
        assert np.all((stats["owner"] >= 0) & (stats["owner"] < ranks))
        if index.shard_size == 0:  # the last rank of a skewed split: every query answered elsewhere
            assert stats["owner_sent"] == len(mine_q) and np.all(stats["owner"] != rank)
    _assert_same_knn(capped, one, mine_q, 16, max_radius=0.02)


@pytest.mark.parametrize("method", METHODS)
def test_radius_equals_one_process(world, data, method):
    comm = world[0]
    pts, _ = data
    mine_p, mine_q = _mine(world, data)
    index = bh.DistributedIndex(method, mine_p, comm)
    full = index.radius_search(mine_q, 0.03, return_stats=True)
    cap = index.radius_search(mine_q, 0.03, max_results=5)
    one = bh.make_index(method, pts)
    e_full, e_cap = one.radius_search(mine_q, 0.03, return_stats=True), one.radius_search(mine_q, 0.03, max_results=5)
    for got, exp in ((full, e_full), (cap, e_cap)):
        _assert_same_radius(got, exp)
    np.testing.assert_array_equal(full.stats["found"], e_full.stats["found"])
    assert full.stats["results"] == e_full.stats["results"] > 0


def test_float64_far_from_origin_recentred_on_all_ranks(world, data):
    comm, rank, ranks = world
    pts, q = data
    base = np.array([512345.678, 4312345.678, 112.5])
    p64, q64 = base + pts.astype(np.float64) * 100.0, base + q.astype(np.float64) * 100.0
    mine_q = q64[_split(NQ, ranks, rank, skew=False)]
    index = bh.DistributedIndex("kdtree", p64[_split(N, ranks, rank)], comm)
    d2, ids = index.query(mine_q, k=10)
    # float64 points added later are stored relative to the same origin, as make_index's add does.
    more = base + np.random.default_rng(7).random((500, 3)) * 100.0
    index.add(more[_split(len(more), ranks, rank)])
    after = index.query(mine_q, k=10, return_counts=True)
    one = bh.make_index("kdtree", p64, refine=False)
    e_d2, e_ids = one.query(mine_q, k=10)
    assert index.coordinates["recentred"] and index.coordinates["origin"] == one.coordinates["origin"]
    assert index.coordinates["max_rounding"] == one.coordinates["max_rounding"]
    np.testing.assert_array_equal(ids, e_ids.astype(np.int64))
    np.testing.assert_array_equal(d2, e_d2)
    one.add(more)
    _assert_same_knn(after, one, mine_q, 10)


def test_all_points_on_rank0_id_base_and_single_query(world, data):
    comm, rank, ranks = world
    pts, q = data
    index = bh.DistributedIndex("kdtree", pts if rank == 0 else np.zeros((0, 3), np.float32), comm,
                                id_base=1000, boxes_per_rank=4)
    d2, ids = index.query(q[rank], k=7)  # one query of shape (3,) per rank
    none_d2, none_ids = index.query(np.zeros((0, 3), np.float32), k=3)
    one = bh.make_index("kdtree", pts)
    e_d2, e_ids = one.query(q[rank], k=7)
    assert ids.shape == (7,) and none_ids.shape == (0, 3) and none_d2.shape == (0, 3)
    np.testing.assert_array_equal(ids, e_ids.astype(np.int64) + 1000)
    np.testing.assert_array_equal(d2, e_d2)
    assert index.id_base == 1000 and index.id_bound == 1000 + N
    assert np.all(np.diff(index.shard_ids) > 0) and index.shard_size == len(index.shard_ids)


def test_a_bad_argument_on_one_rank_raises_on_every_rank(world, data):
    comm, rank, ranks = world
    pts, q = data
    index = bh.DistributedIndex("kdtree", _mine(world, data)[0], comm)
    last = ranks - 1
    bad = q[:10, :2] if rank == last else q[:10]  # the last rank passes (n, 2) queries
    with pytest.raises(ValueError) as shape_err:
        index.query(bad, k=5)
    with pytest.raises(ValueError) as k_err:
        index.query(q[:10], k=5 if rank != last else 0)
    # A NaN point on the last rank: the library's check, on every rank.
    p = pts[_split(N, ranks, rank)].copy()
    if rank == last:
        p = np.concatenate([p, [[np.nan, 0, 0]]]).astype(np.float32)
    with pytest.raises(bh.Error) as nan_err:
        bh.DistributedIndex("kdtree", p, comm)
    # The index still answers after the refused calls (no rank was left behind).
    d2, ids = index.query(q[:10], k=3)
    if rank == last:
        assert "shape" in str(shape_err.value) and "k" in str(k_err.value)
    else:
        assert isinstance(shape_err.value, bh.Error) and f"rank {last}" in str(shape_err.value)
        assert f"rank {last}" in str(k_err.value)
    assert "nan" in str(nan_err.value).lower() or "finite" in str(nan_err.value).lower()
    assert ids.shape == (10, 3)


def test_refused_without_collective_work(world, data):
    comm, rank, ranks = world
    pts, _ = data
    with pytest.raises(bh.Error, match="refine"):
        bh.DistributedIndex("kdtree", pts[:100], comm, refine=True)
    with pytest.raises(TypeError, match="comm"):
        bh.DistributedIndex("kdtree", pts[:100], comm="world")
    index = bh.DistributedIndex("bruteforce", pts[:100], comm)
    import pickle
    with pytest.raises(TypeError, match="pickle"):
        pickle.dumps(index)


def _catch(fn):
    """The exception fn raises, or None: every rank makes all its collective calls first and
    asserts afterwards."""
    try:
        fn()
    except Exception as e:  # noqa: BLE001 (asserted by the caller)
        return e
    return None


@pytest.mark.parametrize("method", METHODS)
def test_add_remove_equals_one_process(world, data, method):
    comm, rank, ranks = world
    pts, _ = data
    mine_p, mine_q = _mine(world, data)
    rng = np.random.default_rng(39)  # the same updates on every rank
    # 10 % of N over and beyond the box (so that every rank's region gets some), the last rank
    # adding none; then 10 % of the ids removed (old and new ones), each rank passing part of the
    # list in another rank's place (ids held by any rank); then a small add on rank 0 alone.
    new = (rng.random((N // 10, 3)) * 1.2 - 0.1).astype(np.float32)
    gone = rng.choice(N + len(new), size=N // 10, replace=False)
    again = (rng.random((200, 3)) * 0.5 + 0.25).astype(np.float32)
    index = bh.DistributedIndex(method, mine_p, comm)
    ids_new = index.add(new[_split(len(new), ranks, rank)])
    add_stats = dict(index.last_update_stats)
    index.remove(gone[_split(len(gone), ranks, (rank + 1) % ranks, skew=False)])
    remove_stats = dict(index.last_update_stats)
    got = {k: index.query(mine_q, k=k, return_counts=True) for k in (1, 10, 50)}
    got_r = index.radius_search(mine_q, 0.03)
    ids_again = index.add(again if rank == 0 else np.zeros((0, 3), np.float32))
    got_again = index.query(mine_q, k=10, return_counts=True)
    size, bound, removed = index.size, index.id_bound, index.removed_count
    live = index.shard_live_ids

    one = bh.make_index(method, pts)
    e_new = one.add(new)
    one.remove(gone)
    for k, g in got.items():
        _assert_same_knn(g, one, mine_q, k)
    _assert_same_radius(got_r, one.radius_search(mine_q, 0.03))
    e_again = one.add(again)
    _assert_same_knn(got_again, one, mine_q, 10)
    np.testing.assert_array_equal(ids_new, e_new[_split(len(new), ranks, rank)].astype(np.int64))
    np.testing.assert_array_equal(ids_again, e_again.astype(np.int64) if rank == 0 else np.zeros(0, np.int64))
    assert ids_new.dtype == np.int64 and (size, bound, removed) == (one.size, one.id_bound, len(gone))
    assert add_stats["n_global"] == len(new) and add_stats["applied"] > 0  # the add landed on this rank
    assert remove_stats["n_global"] == len(gone) and remove_stats["wall_s"] >= 0
    assert not np.isin(live, gone).any() and np.all(np.diff(live) > 0)


def test_update_errors_raise_on_every_rank(world, data):
    comm, rank, ranks = world
    pts, q = data
    mine_p, mine_q = _mine(world, data)
    last = ranks - 1
    index = bh.DistributedIndex("kdtree", mine_p, comm)
    fresh = np.full((5, 3), 0.5, np.float32)
    twice = [7, 7] if ranks == 1 else [7] if rank in (0, last) else []  # anywhere in the call
    err = {
        "shape": _catch(lambda: index.add(fresh[:, :2] if rank == last else fresh)),
        "nan": _catch(lambda: index.add(np.array([[np.nan, 0, 0]], np.float32) if rank == last else fresh)),
        "empty add": _catch(lambda: index.add(np.zeros((0, 3), np.float32))),
        "unknown": _catch(lambda: index.remove([index.id_bound + 5] if rank == last else [])),
        "kind": _catch(lambda: index.remove(np.array([1.5]) if rank == last else [0])),
        "twice": _catch(lambda: index.remove(twice)),
    }
    index.remove([3] if rank == 0 else [])
    err["removed"] = _catch(lambda: index.remove([3] if rank == last else []))
    err["empty remove"] = _catch(lambda: index.remove(np.zeros(0, np.int64)))
    if ranks > 1:  # rank 0 in add while the others query: the same calls in the same order is the rule
        err["not collective"] = _catch(lambda: index.add(fresh) if rank == 0 else index.query(mine_q[:5], k=3))
    after = index.query(mine_q, k=10, return_counts=True)

    one = bh.make_index("kdtree", pts)
    one.remove([3])
    _assert_same_knn(after, one, mine_q, 10)  # every refused call left the index unchanged
    assert index.size == N - 1 and index.id_bound == N
    own = {"shape": ValueError, "kind": ValueError}
    for name, e in err.items():
        assert isinstance(e, own.get(name, bh.Error) if rank == last else bh.Error), (name, e)
    assert ("shape" in str(err["shape"])) if rank == last else f"rank {last}" in str(err["shape"])
    assert "finite" in str(err["nan"]).lower() and f"rank {last}" in str(err["nan"])
    assert "no points on any rank" in str(err["empty add"]) and "no ids on any rank" in str(err["empty remove"])
    assert str(N + 5) in str(err["unknown"]) and "already removed" in str(err["removed"])
    assert "twice" in str(err["twice"])
    if ranks > 1:
        msg = str(err["not collective"])
        assert "not in the same collective call" in msg and "rank 0 in DistributedIndex.add" in msg
        assert "rank 1 in DistributedIndex.query" in msg


@pytest.mark.parametrize("method", ["bruteforce", "kdtree"])
def test_memory_bytes_counts_host_arrays(world, data, method):
    comm = world[0]
    pts, _ = data
    index = bh.DistributedIndex(method, _mine(world, data)[0], comm)
    before = index.memory_bytes
    index.add(pts[:300] + np.float32(0.001))
    grown = index.memory_bytes
    # This rank's local index as one process's over the same points, less the package's own
    # copy (12 B a point), which the distributed index does not keep.
    shard = np.ascontiguousarray(pts[index.shard_ids[index.shard_ids < N]])
    local = bh.make_index(method, shard)
    local_bytes = local.memory_bytes - shard.nbytes
    host = len(shard) * (8 + 12 + 2)  # global id, float32 copy, sub-run of each point
    assert local_bytes + host <= before <= local_bytes + 2 * host + 4096, (before, local_bytes, host)
    assert grown > before


def test_a_shard_emptied_by_removes_then_refilled(world, data):
    comm, rank, ranks = world
    pts, _ = data
    mine_p, mine_q = _mine(world, data)
    index = bh.DistributedIndex("kdtree", mine_p, comm)
    last = ranks - 1
    # The last rank removes its whole shard (at one rank: half of it, not every point).
    gone = index.shard_live_ids if rank == last else np.zeros(0, np.int64)
    if ranks == 1:
        gone = gone[::2]
    index.remove(gone)
    emptied = (index.shard_size, index.device, index.memory_bytes, len(index.shard_live_ids))
    got = index.query(mine_q, k=10, return_counts=True)
    refill = pts[:200] + np.float32(0.0005)  # points near old ones, wherever their owner is now
    ids = index.add(refill if rank == 0 else np.zeros((0, 3), np.float32))
    got_after = index.query(mine_q, k=10, return_counts=True)
    all_gone = np.concatenate(comm.allgather(gone)) if comm is not None else gone
    one = bh.make_index("kdtree", pts)
    one.remove(all_gone)
    _assert_same_knn(got, one, mine_q, 10)
    e_ids = one.add(refill)
    _assert_same_knn(got_after, one, mine_q, 10)
    if rank == 0:
        np.testing.assert_array_equal(ids, e_ids.astype(np.int64))
    if rank == last and ranks > 1:
        shard_size, device, memory, live = emptied
        assert shard_size == 0 and device is None and live == 0
        assert memory > 0  # the host arrays stay (ids are never reused)
