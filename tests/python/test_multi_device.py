"""make_index(..., devices=[...]): the library's multi-device index from Python (issue 40, part
3's first half). On a machine with one OpenCL device the copies share it (each on its own
runtime); the answers must equal one device's bit for bit, after updates and pickling too."""
import pickle

import numpy as np
import pytest

import blockhash_cl as bh

METHODS = ["kdtree", "blockhash", "bruteforce"]


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(43)
    return rng.random((8000, 3), dtype=np.float32), rng.random((3000, 3), dtype=np.float32)


@pytest.mark.parametrize("method", METHODS)
def test_two_copies_answer_as_one_device(data, method):
    pts, q = data
    one = bh.make_index(method, pts)
    two = bh.make_index(method, pts, devices=["pocl", "pocl"])
    assert len(two.devices) == 2 and abs(sum(two.weights) - 1) < 1e-9 and len(two) == len(one)
    for _ in range(2):  # the second call runs at the learnt split
        d1, i1 = one.query(q, k=10)
        d2, i2 = two.query(q, k=10)
        np.testing.assert_array_equal(i1, i2)
        np.testing.assert_array_equal(d1, d2)
    r1, r2 = one.radius_search(q, 0.05), two.radius_search(q, 0.05)
    for a, b in zip(r1, r2):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="squared"):
        two.radius_search(q, 0.0025, squared=True)
    # Updates on every copy, the same ids.
    more = np.random.default_rng(1).random((500, 3), dtype=np.float32)
    assert one.add(more).tolist() == two.add(more).tolist()
    one.remove(np.arange(0, 8000, 9))
    two.remove(np.arange(0, 8000, 9))
    np.testing.assert_array_equal(one.query(q, k=5)[1], two.query(q, k=5)[1])
    back = pickle.loads(pickle.dumps(two))
    assert len(back.devices) == 2
    np.testing.assert_array_equal(back.query(q, k=5)[1], two.query(q, k=5)[1])


def test_multi_device_refined_float64_and_arguments(data):
    pts, q = data
    base = np.array([512345.678, 4312345.678, 112.5])
    p64, q64 = base + pts * 50.0, base + q * 50.0
    one, two = bh.make_index("kdtree", p64), bh.make_index("kdtree", p64, devices=["pocl", "pocl"])
    assert two.refined
    d1, i1 = one.query(q64, k=8)
    d2, i2 = two.query(q64, k=8)
    np.testing.assert_array_equal(i1, i2)
    np.testing.assert_array_equal(d1, d2)
    with pytest.raises(TypeError, match="device or devices"):
        bh.make_index("kdtree", pts, device="pocl", devices=["pocl"])
    with pytest.raises(TypeError, match="list"):
        bh.make_index("kdtree", pts, devices="pocl")
    with pytest.raises(ValueError, match="at least one"):
        bh.make_index("kdtree", pts, devices=[])
