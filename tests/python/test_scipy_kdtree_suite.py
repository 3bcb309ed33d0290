"""scipy's own KDTree tests (scipy/spatial/tests/test_kdtree.py, imported, not copied) run with
blockhash_cl.KDTree and blockhash_cl.cKDTree in place of scipy's classes.

Selected by name: the tests that apply to 3-D data with p = 2 and no boxsize, as scipy wrote them
(APPLICABLE); the tests written for 1-, 2-, 4- or 5-dimensional data, other p or periodic boxes
do not apply (docs/PYTHON.md lists them with the reason) and are checked instead to raise the
front's ValueError naming what it supports. docs/PYTHON.md has the counts.
"""
import numpy as np
import pytest

import blockhash_cl as bh

S = pytest.importorskip("scipy.spatial.tests.test_kdtree", reason="scipy's test suite is not installed")

TREES = [bh.KDTree, bh.cKDTree]


@pytest.fixture(params=TREES, ids=["KDTree", "cKDTree"])
def kdtree_type(request):
    """scipy's fixture of the same name, with our classes."""
    return request.param


# --- module-level tests taking the tree class from the kdtree_type fixture (3-D, p = 2)
test_short_knn = S.test_short_knn
test_query_ball_point_vector_r = S.test_query_ball_point_vector_r
test_query_ball_point_length = S.test_query_ball_point_length
test_discontiguous = S.test_discontiguous
test_kdtree_empty_input = S.test_kdtree_empty_input


@pytest.mark.parametrize("kdtree_class", TREES, ids=["KDTree", "cKDTree"])
def test_kdtree_count_neighbors_weighted(kdtree_class):
    S.test_kdtree_count_neighbors_weighted(kdtree_class)


# --- class-based tests (scipy's KDTreeTest makes one per tree class; here one per our class).
# Methods of an applicable class that use another p are removed (None: pytest does not collect
# them) and checked below to raise.
_NOT_P2 = {"test_points_near_l1": None, "test_points_near_linf": None}


def _per_tree(base, extra=None):
    for tree in TREES:
        name = base.__name__.lstrip("_") + "_" + tree.__name__
        globals()[name] = type(name, (base,), dict(extra or {}, kdtree_type=tree))


_per_tree(S._Test_small, _NOT_P2)
_per_tree(S._Test_small_nonleaf, _NOT_P2)


# scipy's vectorization tests build scipy's class in setup_method: rebuilt with ours over the
# same data.
class Test_vectorization_KDTree(S.Test_vectorization_KDTree):
    def setup_method(self):
        super().setup_method()
        self.kdtree = bh.KDTree(self.data)


class Test_vectorization_cKDTree(S.Test_vectorization_cKDTree):
    def setup_method(self):
        super().setup_method()
        self.kdtree = bh.cKDTree(self.data)


# --- outside 3-D / p = 2: the front's ValueError, naming what it supports
@pytest.mark.parametrize("method", ["test_points_near_l1", "test_points_near_linf"])
def test_other_p_raises(method):
    case = S._Test_small()
    case.kdtree_type = bh.KDTree
    case.setup_method()
    with pytest.raises(ValueError, match="supports 3-dimensional data with p = 2"):
        getattr(case, method)()


# --- 1-D and 2-D tests on the 3-D tree: scipy's points and queries with zero coordinates appended
# (Euclidean distances, hence every answer, are those of the original dimension). Listed apart
# in docs/PYTHON.md ("padded").
def _pad(a):
    a = np.asarray(a)
    if a.dtype.kind == "c" or a.ndim == 0 or a.shape[-1] >= 3:
        return a
    return np.concatenate([a.astype(np.float64), np.zeros(a.shape[:-1] + (3 - a.shape[-1],))], axis=-1)


def _padded(base):
    class Padded(base):
        def __init__(self, data, *args, **kw):
            super().__init__(_pad(data), *args, **kw)

        def query(self, x, *args, **kw):
            return super().query(_pad(x), *args, **kw)

        def query_ball_point(self, x, *args, **kw):
            return super().query_ball_point(_pad(x), *args, **kw)

    Padded.__name__ = Padded.__qualname__ = "Padded" + base.__name__
    return Padded


PADDED = [_padded(bh.KDTree), _padded(bh.cKDTree)]


@pytest.fixture(params=PADDED, ids=["KDTree", "cKDTree"])
def padded_type(request):
    return request.param


def _with_padded(test):
    def run(padded_type):
        test(padded_type)
    run.__name__ = test.__name__ + "_padded"
    return run


for _t in ("test_query_ball_point_multithreading", "test_query_pairs_single_node", "test_kdtree_query_pairs",
           "test_query_pairs_eps", "test_ball_point_ints", "test_kdtree_list_k",
           "test_kdtree_count_neighbous_multiple_r", "test_len0_arrays", "test_kdtree_noncumulative_nondecreasing"):
    globals()[_t + "_padded"] = _with_padded(getattr(S, _t))

for _base in (S._Test_count_neighbors, S._Test_sorted_query_ball_point):
    for _tree, _name in zip(PADDED, ("KDTree", "cKDTree")):
        _n = _base.__name__.lstrip("_") + "_padded_" + _name
        globals()[_n] = type(_n, (_base,), {"kdtree_type": _tree})


# --- the tests that do not apply (4-/5-dimensional data, periodic boxes, p != 2, 1-D data where
# padding cannot reach scipy's internals): each stops at the front's ValueError naming what it
# supports, never at a wrong answer.
NOT_APPLICABLE_FUNCTIONS = ["test_random_ball_vectorized", "test_onetree_query", "test_kdtree_build_modes",
                            "test_kdtree_pickle", "test_kdtree_pickle_boxsize", "test_kdtree_copy_data",
                            "test_kdtree_box", "test_kdtree_box_0boxsize", "test_kdtree_box_upper_bounds",
                            "test_kdtree_duplicated_inputs", "test_kdtree_weights"]
NOT_APPLICABLE_CLASSES = ["_Test_random", "_Test_random_far", "_Test_random_ball", "_Test_random_ball_periodic",
                          "_Test_random_ball_largep_issue9890", "_Test_random_ball_approx",
                          "_Test_random_ball_approx_periodic", "_Test_random_ball_far",
                          "_Test_random_ball_far_periodic", "_Test_random_ball_l1", "_Test_random_ball_linf",
                          "_Test_two_random_trees", "_Test_two_random_trees_periodic", "_Test_two_random_trees_far",
                          "_Test_two_random_trees_far_periodic", "_Test_two_random_trees_linf",
                          "_Test_two_random_trees_linf_periodic", "_Test_sparse_distance_matrix"]


@pytest.mark.parametrize("name", NOT_APPLICABLE_FUNCTIONS)
def test_not_applicable_function_raises_the_fronts_error(name):
    with pytest.raises(ValueError, match="supports 3-dimensional data with p = 2"):
        getattr(S, name)(bh.KDTree)


@pytest.mark.parametrize("name", NOT_APPLICABLE_CLASSES)
def test_not_applicable_class_raises_the_fronts_error(name):
    case = getattr(S, name)()
    case.kdtree_type = bh.KDTree
    with pytest.raises(ValueError, match="supports 3-dimensional data with p = 2"):
        case.setup_method()
        for t in sorted(a for a in dir(case) if a.startswith("test_")):
            getattr(case, t)()
