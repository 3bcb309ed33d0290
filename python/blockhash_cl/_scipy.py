"""KDTree and cKDTree: scipy.spatial.KDTree's interface over a blockhash_cl Index (issue 40).

    from blockhash_cl import KDTree          # in place of: from scipy.spatial import KDTree
    tree = KDTree(points)                    # (n, 3)
    d, i = tree.query(x, k=10)               # Euclidean distances (float64), indices (intp)

Semantics are scipy's for 3-D data and p = 2: the same arguments, shapes, dtypes and missing-
neighbour convention (inf and index n), answers computed in float64 from the caller's points (the
index searches its float32 copy, widened so that no neighbour is lost, and each row is refined in
double: Index's refine=True), so distances agree with scipy's to the last bits and indices up to
exact ties. What the library does not do raises ValueError naming what is supported: data of
another dimension, p other than 2, boxsize (periodic boxes). eps >= 0 is accepted: kNN answers
exactly (an exact answer meets every eps bound), ball queries return every point within
r (1 + eps) (scipy's eps allows each of them); workers is checked as scipy checks it and
otherwise ignored (the library runs its own threads or device); leafsize is the kd-tree's leaf
size for method="kdtree", and compact_nodes and balanced_tree are accepted and ignored. The
attributes are data, n, m, leafsize, maxes, mins (scipy's tree and node views are not provided).
"""
from __future__ import annotations

import math
import operator
import os
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

_METHODS_EXACT = ("blockhash", "kdtree", "bruteforce", "flann")


def _unsupported(what: str) -> str:
    return (f"blockhash_cl.KDTree supports 3-dimensional data with p = 2 (Euclidean distance) and no "
            f"boxsize; {what} is not supported (use scipy.spatial.KDTree for it)")


def _check_p(p: Any) -> None:
    try:
        ok = float(p) == 2.0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(_unsupported(f"p = {p!r}"))


def _check_workers(workers: Any) -> None:
    w = operator.index(workers)
    if w == -1:
        if os.cpu_count() is None:
            raise NotImplementedError("Cannot determine the number of cpus using os.cpu_count(), "
                                      "cannot use -1 for the number of workers")
    elif w <= 0:
        raise ValueError(f"Invalid number of workers {w}, must be -1 or > 0")


def _check_eps(eps: Any) -> float:
    """eps as a float (>= 0). kNN answers exactly for every eps (an exact answer meets its bound);
    ball queries take every point within r (1 + eps), all of which scipy's eps allows (points
    within r always, none beyond r (1 + eps)): deterministic, and what scipy returns where a
    distance rounds just past r (its test_query_pairs_eps)."""
    e = float(eps)
    if not e >= 0:
        raise ValueError(f"eps must be non-negative, got {eps!r}")
    return e


def _points_arg(x: Any) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype.kind == "c":
        raise TypeError("KDTree does not work with complex data")
    if x.ndim == 0 or x.shape[-1] != 3:
        raise ValueError(f"x must consist of vectors of length 3 but has shape {x.shape}"
                         + ("" if x.ndim == 0 or x.shape[-1] == 3 else f" ({_unsupported(f'{x.shape[-1]}-dimensional queries')})"))
    return np.asarray(x, np.float64)


class KDTree:
    """scipy.spatial.KDTree's interface for 3-D points (p = 2) over a blockhash_cl index; see the
    module's docstring. Keyword-only extras: method (an exact method: "blockhash", exact by
    default on its grid; "kdtree", "bruteforce", "flann"), device, and the method's build
    options."""

    _scalar_index = staticmethod(np.intp)  # scipy's KDTree returns a numpy integer for one query

    def __init__(self, data: Any, leafsize: int = 10, compact_nodes: bool = True, copy_data: bool = False,
                 balanced_tree: bool = True, boxsize: Any = None, *, method: str = "blockhash",
                 device: Any = None, **build: Any) -> None:
        from . import make_index  # the package imports this module
        arr = np.asarray(data)
        if arr.dtype.kind == "c":
            raise TypeError("KDTree does not work with complex data")
        if boxsize is not None:
            raise ValueError(_unsupported(f"boxsize = {boxsize!r} (a periodic box)"))
        arr = np.array(arr, dtype=np.float64, order="C", copy=bool(copy_data))
        if arr.ndim != 2 or arr.shape[1] != 3:
            dim = f"{arr.shape[1]}-dimensional data" if arr.ndim == 2 else f"data of shape {arr.shape}"
            raise ValueError(_unsupported(dim))
        leafsize = operator.index(leafsize)
        if leafsize < 1:
            raise ValueError("leafsize must be at least 1")
        if method not in _METHODS_EXACT:
            raise ValueError(f"method must be one of the exact methods {', '.join(_METHODS_EXACT)}, got {method!r}")
        self.data = arr
        self.n, self.m = int(arr.shape[0]), 3
        self.leafsize = leafsize
        self.maxes = np.amax(arr, axis=0) if self.n else np.full(3, -np.inf)
        self.mins = np.amin(arr, axis=0) if self.n else np.full(3, np.inf)
        self._method, self._device, self._build = method, device, dict(build)
        self.index = None
        if self.n:
            opts = dict(build)
            if method == "kdtree" and "leaf_size" not in opts:
                opts["leaf_size"] = min(leafsize, 1024)
            self.index = make_index(method, arr, device=device, refine=True, **opts)
            if method == "blockhash" and not self.index.build_info.get("grid", False):
                raise ValueError("blockhash_cl.KDTree answers exactly: method 'blockhash' needs its grid layout "
                                 "(leave grid unset), the block layouts are approximate")

    # --- pickling: the data and the parameters; the index is rebuilt on arrival (same answers)
    def __getstate__(self) -> Dict[str, Any]:
        return {"data": self.data, "leafsize": self.leafsize, "method": self._method, "build": self._build}

    def __setstate__(self, state: Dict[str, Any]) -> None:
        self.__init__(state["data"], state["leafsize"], method=state["method"], **state["build"])  # type: ignore[misc]

    def __repr__(self) -> str:
        return f"<blockhash_cl.{type(self).__name__} of {self.n} points, method {self._method}>"

    @property
    def last_stats(self) -> Optional[Dict[str, Any]]:
        """The underlying index's last stats (refine_s, refine_share, wall_s, ...)."""
        return None if self.index is None else self.index.last_stats

    # --- searches in float64 over the index (Index._query64 / _radius64)
    def _knn(self, xs: np.ndarray, k: int, dub: float) -> Tuple[np.ndarray, np.ndarray]:
        """(n, k) float64 squared distances and int64 ids (-1 missing), nearer than dub."""
        from . import MAX_K, _core
        nq = len(xs)
        if self.index is None or nq == 0 or not dub > 0:  # nothing is nearer than 0 (or a negative bound)
            return np.full((nq, k), np.inf), np.full((nq, k), -1, np.int64)
        q = self.index._to_index(xs, "x")
        mr = None if math.isinf(dub) else dub
        if k <= MAX_K:
            d2, ids, _, stats = self.index._query64(xs, q, k, mr, {}, None, strict=True)
            self.index.last_stats = stats
            return d2, ids.astype(np.int64)
        # k past the kernels' limit: a radius search capped at the k nearest (all points within
        # dub, or every point: each query then examines them all).
        r2 = np.full(nq, np.inf if mr is None else mr * mr)
        offsets, d2s, ids_s, _, stats = self.index._radius64(xs, q, r2, _core.RadiusParams(), k, True, True)
        self.index.last_stats = stats
        owner = np.repeat(np.arange(nq), np.diff(offsets))
        rank = np.arange(len(owner)) - offsets[owner]
        keep = d2s < r2[owner] if mr is not None else np.ones(len(owner), bool)
        d2 = np.full((nq, k), np.inf)
        ids = np.full((nq, k), -1, np.int64)
        d2[owner[keep], rank[keep]] = d2s[keep]
        ids[owner[keep], rank[keep]] = ids_s[keep]
        return d2, ids

    def _ball(self, xs: np.ndarray, r: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points within r[i] (<=, float64) of each query: (offsets int64, dist2 float64, ids
        int64), each slice by (distance, index). Queries whose radii differ by more than 2x are
        searched apart (the float32 search takes one radius per call)."""
        from . import _core
        nq = len(xs)
        r = np.asarray(r, np.float64)
        if self.index is None or nq == 0:
            return np.zeros(nq + 1, np.int64), np.zeros(0), np.zeros(0, np.int64)
        q = self.index._to_index(xs, "x")
        valid = r >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            group = np.where(valid & (r > 0) & np.isfinite(r), np.floor(np.log2(np.where(r > 0, r, 1))), -2000.0)
        group = np.where(np.isinf(r) & valid, 4000.0, group)
        group = np.where(r == 0, -3000.0, group)
        counts = np.zeros(nq, np.int64)
        parts: List[Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        for g in np.unique(group[valid]):
            rows = np.flatnonzero(valid & (group == g))
            offs, d2, ids, _, stats = self.index._radius64(xs[rows], q[rows], r[rows] * r[rows], _core.RadiusParams(),
                                                           0, True, True)
            self.index.last_stats = stats
            counts[rows] = np.diff(offs)
            parts.append((rows, offs, d2, ids))
        offsets = np.zeros(nq + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        d2_all = np.empty(int(offsets[-1]))
        ids_all = np.empty(int(offsets[-1]), np.int64)
        for rows, offs, d2, ids in parts:
            if len(parts) == 1 and len(rows) == nq:
                d2_all, ids_all = d2, ids.astype(np.int64)
                break
            dest = np.repeat(offsets[rows], np.diff(offs)) + (np.arange(len(ids)) - np.repeat(offs[:-1], np.diff(offs)))
            d2_all[dest], ids_all[dest] = d2, ids
        return offsets, d2_all, ids_all

    # --- scipy's API
    def query(self, x: Any, k: Any = 1, eps: float = 0, p: float = 2, distance_upper_bound: float = np.inf,
              workers: int = 1) -> Tuple[Any, Any]:
        """scipy.spatial.KDTree.query: the k nearest neighbours (k an int, or a sequence of the
        k-th neighbours wanted, from 1), Euclidean distances (float64) and indices (intp) in x's
        shape + (k,), the last axis dropped for an int k = 1; missing neighbours are inf and
        index n; only neighbours nearer than distance_upper_bound."""
        if k is None:
            raise ValueError("k must be an integer or a sequence of integers")
        _check_p(p)
        _check_eps(eps)
        _check_workers(workers)
        xa = _points_arg(x)
        if isinstance(k, (int, np.integer)) and not isinstance(k, (bool, np.bool_)):
            kk = int(k)
            if kk < 1:
                raise ValueError(f"k must be at least 1, got {kk}")
            cols, squeeze = np.arange(kk), kk == 1
        else:
            ks = np.asarray(k)
            if ks.ndim != 1 or ks.size == 0 or ks.dtype.kind not in "iu":
                raise ValueError("k must be an integer or a sequence of integers")
            if np.any(ks < 1):
                raise ValueError(f"k must be at least 1, got {ks.tolist()}")
            kk, cols, squeeze = int(ks.max()), ks.astype(np.intp) - 1, False
        dub = float(distance_upper_bound)
        xs = xa.reshape(-1, 3)
        d2, ids = self._knn(xs, kk, dub)
        d = np.sqrt(d2[:, cols])
        i = ids[:, cols]
        i[i < 0] = self.n
        i = i.astype(np.intp)
        shape = xa.shape[:-1] + (() if squeeze else (len(cols),))
        d, i = d.reshape(shape), i.reshape(shape)
        if d.ndim == 0:
            return float(d), self._scalar_index(i)
        return d, i

    def query_ball_point(self, x: Any, r: Any, p: float = 2., eps: float = 0, workers: int = 1,
                         return_sorted: Optional[bool] = None, return_length: bool = False) -> Any:
        """scipy.spatial.KDTree.query_ball_point: the indices of the points within r (<=) of each
        point of x (r broadcast to x's shape less its last axis): a list for one point, else an
        object array of lists; sorted by index when return_sorted (None: for several points
        only); with return_length the counts instead."""
        _check_p(p)
        e = _check_eps(eps)
        _check_workers(workers)
        xa = _points_arg(x)
        rb = np.broadcast_to(np.asarray(r, np.float64) * (1 + e), xa.shape[:-1])
        xs = xa.reshape(-1, 3)
        offsets, _, ids = self._ball(xs, rb.reshape(-1))
        counts = np.diff(offsets)
        if return_length:
            out = counts.astype(np.intp).reshape(xa.shape[:-1])
            return int(out) if out.ndim == 0 else out
        sort = return_sorted if return_sorted is not None else xa.ndim > 1
        lists = [ids[offsets[j]:offsets[j + 1]] for j in range(len(xs))]
        if sort:
            lists = [np.sort(s) for s in lists]
        if xa.ndim == 1:
            return lists[0].tolist()
        res = np.empty(len(xs), dtype=object)
        for j, s in enumerate(lists):
            res[j] = s.tolist()
        return res.reshape(xa.shape[:-1])

    def _other(self, other: Any) -> "KDTree":
        if not isinstance(other, KDTree):
            raise TypeError(f"other must be a blockhash_cl.KDTree, got {type(other).__name__}")
        return other

    def query_ball_tree(self, other: "KDTree", r: float, p: float = 2., eps: float = 0) -> List[List[int]]:
        """scipy.spatial.KDTree.query_ball_tree: for each point of this tree, the indices of
        other's points within r (each list sorted)."""
        _check_p(p)
        e = _check_eps(eps)
        other = self._other(other)
        offsets, _, ids = other._ball(self.data, np.full(self.n, float(r) * (1 + e)))
        return [np.sort(ids[offsets[j]:offsets[j + 1]]).tolist() for j in range(self.n)]

    def query_pairs(self, r: float, p: float = 2., eps: float = 0, output_type: str = "set") -> Any:
        """scipy.spatial.KDTree.query_pairs: the pairs (i, j), i < j, within r: a set of tuples,
        or with output_type="ndarray" an (n_pairs, 2) intp array (sorted)."""
        _check_p(p)
        e = _check_eps(eps)
        if output_type not in ("set", "ndarray"):
            raise ValueError(f"Invalid output type {output_type!r}")
        offsets, _, ids = self._ball(self.data, np.full(self.n, float(r) * (1 + e)))
        owner = np.repeat(np.arange(self.n), np.diff(offsets))
        m = ids > owner
        pairs = np.stack([owner[m], ids[m]], axis=1).astype(np.intp)
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))] if len(pairs) else np.zeros((0, 2), np.intp)
        if output_type == "ndarray":
            return pairs
        return set(map(tuple, pairs.tolist()))

    def _pairs(self, other: "KDTree", rmax: float, chunk: int = 1 << 16):
        """(i in self, j in other, squared distance) of the pairs within rmax, by chunks of self."""
        for s in range(0, self.n, chunk):
            xs = self.data[s:s + chunk]
            offsets, d2, ids = other._ball(xs, np.full(len(xs), rmax))
            yield s + np.repeat(np.arange(len(xs)), np.diff(offsets)), ids, d2

    def count_neighbors(self, other: "KDTree", r: Any, p: float = 2., weights: Any = None,
                        cumulative: bool = True) -> Any:
        """scipy.spatial.KDTree.count_neighbors: the number (or weight) of pairs (x1 of self, x2
        of other) with distance <= r, for a scalar r or each of a 1-D r; cumulative=False: per
        bin (r[i-1], r[i]] (r non-decreasing). Materialises the pairs within max(r), a chunk of
        self's points at a time."""
        _check_p(p)
        other = self._other(other)
        ra = np.asarray(r, np.float64)
        if ra.ndim > 1:
            raise ValueError("r must be either a single value or a one-dimensional array of values")
        rr = ra.reshape(-1)
        if not cumulative and np.any(np.diff(rr) < 0):
            raise ValueError("r must be non-decreasing for non-cumulative counting.")
        w1 = w2 = None
        if weights is not None:
            if isinstance(weights, tuple):
                w1, w2 = weights
            else:
                if other is not self:
                    raise ValueError("Two different trees are used. Specify weights for both in a tuple.")
                w1 = w2 = weights
            w1 = None if w1 is None else np.asarray(w1, np.float64)
            w2 = None if w2 is None else np.asarray(w2, np.float64)
            if w1 is not None and w1.shape != (self.n,):
                raise ValueError("weights[0] must have one weight per point of self")
            if w2 is not None and w2.shape != (other.n,):
                raise ValueError("weights[1] must have one weight per point of other")
        weighted = weights is not None
        r2 = np.where(rr < 0, -1.0, rr * rr)
        total = np.zeros(len(rr), np.float64 if weighted else np.int64)
        rmax = float(np.max(rr)) if len(rr) and np.max(rr) >= 0 else -1.0
        if rmax >= 0 and self.n and other.n:
            for i, j, d2 in self._pairs(other, rmax):
                order = np.argsort(d2, kind="stable")
                d2s = d2[order]
                pos = np.searchsorted(d2s, r2, side="right")
                if weighted:
                    w = np.ones(len(d2s))
                    if w1 is not None:
                        w = w * w1[i[order]]
                    if w2 is not None:
                        w = w * w2[j[order]]
                    cw = np.concatenate([[0.0], np.cumsum(w)])
                    total += cw[pos]
                else:
                    total += pos
        if not cumulative:
            total = np.diff(np.concatenate([np.zeros(1, total.dtype), total]))
        if ra.ndim == 0:
            return total[0].item() if weighted else int(total[0])
        return total if weighted else total.astype(np.intp)

    def sparse_distance_matrix(self, other: "KDTree", max_distance: float, p: float = 2.,
                               output_type: str = "dok_matrix") -> Any:
        """scipy.spatial.KDTree.sparse_distance_matrix: the distances (float64) of the pairs
        (i of self, j of other) within max_distance, as a scipy.sparse dok_matrix (default),
        coo_matrix, a dict {(i, j): d} or a structured ndarray of fields i, j, v."""
        _check_p(p)
        other = self._other(other)
        if output_type not in ("dok_matrix", "coo_matrix", "dict", "ndarray"):
            raise ValueError(f"Invalid output type {output_type!r}: one of 'dok_matrix', 'coo_matrix', 'dict', 'ndarray'")
        ii, jj, vv = [np.zeros(0, np.intp)], [np.zeros(0, np.intp)], [np.zeros(0)]
        if self.n and other.n:
            for i, j, d2 in self._pairs(other, float(max_distance)):
                ii.append(i.astype(np.intp))
                jj.append(j.astype(np.intp))
                vv.append(np.sqrt(d2))
        i, j, v = np.concatenate(ii), np.concatenate(jj), np.concatenate(vv)
        if output_type == "ndarray":
            out = np.empty(len(i), dtype=np.dtype([("i", np.intp), ("j", np.intp), ("v", np.float64)], align=True))
            out["i"], out["j"], out["v"] = i, j, v
            return out
        if output_type == "dict":
            return dict(zip(zip(i.tolist(), j.tolist()), v.tolist()))
        from scipy.sparse import coo_matrix  # scipy's containers: only these outputs need scipy
        coo = coo_matrix((v, (i, j)), shape=(self.n, other.n))
        return coo if output_type == "coo_matrix" else coo.todok()


class cKDTree(KDTree):
    """scipy.spatial.cKDTree's spelling of KDTree: the same class, but one query's index comes
    back a Python int (as cKDTree's does) and the default leafsize is 16."""

    _scalar_index = staticmethod(int)

    def __init__(self, data: Any, leafsize: int = 16, compact_nodes: bool = True, copy_data: bool = False,
                 balanced_tree: bool = True, boxsize: Any = None, **kw: Any) -> None:
        super().__init__(data, leafsize, compact_nodes, copy_data, balanced_tree, boxsize, **kw)
