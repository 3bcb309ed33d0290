"""blockhash_cl from Python: batched k-nearest-neighbour queries on 3D points with OpenCL kernels.

    import numpy as np, blockhash_cl as bh
    index = bh.make_index("blockhash", points)          # (N, 3) float32 or float64
    dist2, ids = index.query(queries, k=10, A=8)        # (n, k) float32 and int32, FAISS order
    index.save("a.bhi"); index = bh.load("a.bhi", points)
    bh.devices()                                        # what `bhcl devices` lists

The result contract is the C++ library's: each row sorted by (squared distance, index), ties to
the lower index; missing neighbours (k > N, or fewer points within max_radius) are id -1 and
distance +inf; a query with a NaN/Inf coordinate gets an empty row. Distances are SQUARED.

Errors: every error of the library is raised as blockhash_cl.Error, a ValueError, with the
library's message (a failed OpenCL call as OpenCLError, also a RuntimeError); an array of the
wrong kind raises TypeError, one of the wrong shape ValueError, an option the method does not read
TypeError (as an unexpected keyword argument would).

Threads: queries and builds release the GIL, so several threads can query one index (or several)
at once; the library serialises what must be serialised.
"""
from __future__ import annotations

import io
import json
import operator
import os
import tempfile
import threading
from typing import Any, Dict, List, NamedTuple, Optional, Tuple, Union, overload

try:  # Python >= 3.8
    from typing import Literal
except ImportError:  # pragma: no cover
    from typing_extensions import Literal  # type: ignore

import numpy as np
import numpy.typing as npt

from . import _container, _core
from . import _refine
from ._base import _IndexFront, _checked_ids, _forwarded
from ._core import Error, OpenCLError, Runtime
# The method tables as keyword arguments and the checks of arrays and values (_checks.py).
from ._checks import (  # noqa: F401
    _TABLE, _scoped, _BUILD_OPTIONS, _SEARCH_OPTIONS, _RADIUS_OPTIONS, _SEARCH_COMMON, _INT32_MAX,
    _F32, _I32, method_names, build_options, _search_options, _option_text, _set_table_options,
    _options_doc, _refuse_unknown, _int, _float, _checked, _origin_for, _precision, _relative, _xyz,
    _own_copy, _MAX_POINTS, _check_count,
)

__all__ = [
    "Error", "OpenCLError", "Runtime", "Index", "RadiusResult", "RadiusResultWithStats", "make_index",
    "load", "devices", "select_device", "get_runtime", "method_names", "build_options", "MAX_K",
    "HAVE_FLANN", "HAVE_MPI", "__version__", "KDTree", "cKDTree", "DistributedIndex",
]

__version__: str = _core.__version__
MAX_K: int = _core.MAX_K  # the largest k any method answers
HAVE_FLANN: bool = _core.HAVE_FLANN  # whether the "flann" method was built in
HAVE_MPI: bool = _core.HAVE_MPI  # whether the MPI-distributed index (DistributedIndex) was built in


# One runtime (OpenCL context, queue, compiled kernels) per device spec, shared by every index
# built for it, so that kernels compile once per process.
_runtimes: Dict[str, Runtime] = {}
_runtimes_lock = threading.Lock()


def get_runtime(device: Union[None, str, Runtime] = None) -> Runtime:
    """The runtime for a device spec: "P:D", "cpu", "gpu" or a name fragment ("pocl",
    "nvidia:1"), as `bhcl devices` lists them; None (or "") reads BHCL_DEVICE now, else PoCL,
    else the first device. One runtime per spec is kept and shared. A Runtime passes through."""
    if isinstance(device, Runtime):
        return device
    if device is None:
        device = os.environ.get("BHCL_DEVICE", "")
    if not isinstance(device, str):
        raise TypeError(f"device must be a str, a Runtime or None, got {type(device).__name__}")
    key = device.strip().lower() or "default"
    with _runtimes_lock:
        rt = _runtimes.get(key)
        if rt is None:
            rt = _runtimes[key] = Runtime(key)
        return rt


def devices() -> List[Dict[str, Any]]:
    """Every OpenCL device, as `bhcl devices` lists them: dicts with "spec" ("P:D"), "platform",
    "device", "type", "compute_units", "global_mem_bytes", "version", "summary", "quirks", ...
    and "selected", True for the one device=None picks now (BHCL_DEVICE, else the default)."""
    devs = [dict(d) for d in _core.list_devices()]
    try:
        picked = _core.select_device(os.environ.get("BHCL_DEVICE", ""))["spec"]
    except Error:
        picked = None  # a BHCL_DEVICE that matches nothing: make_index will say so
    for d in devs:
        d["selected"] = d["spec"] == picked
    return devs


def select_device(spec: Optional[str] = None) -> Dict[str, Any]:
    """The device a spec picks (None: BHCL_DEVICE, else the default). Raises Error naming the
    spec and listing the devices when none matches."""
    return dict(_core.select_device("" if spec is None else spec))


_F32A = npt.NDArray[np.float32]
_I32A = npt.NDArray[np.int32]
_I64A = npt.NDArray[np.int64]


class RadiusResult(NamedTuple):
    """Index.radius_search's result, FAISS's range_search layout: query i's neighbours are
    ids[offsets[i]:offsets[i+1]] with SQUARED distances dist2[offsets[i]:offsets[i+1]]. A tuple,
    so `offsets, dist2, ids = index.radius_search(q, r)` unpacks it."""

    offsets: _I64A  # (n + 1,) int64, offsets[0] == 0
    dist2: _F32A    # (total,) float32 squared distances, each slice sorted by (distance, id)
    ids: _I32A      # (total,) int32 indices into the points

    def slice(self, i: int) -> Tuple[_F32A, _I32A]:
        """(dist2, ids) of query i."""
        a, b = int(self.offsets[i]), int(self.offsets[i + 1])
        return self.dist2[a:b], self.ids[a:b]


class RadiusResultWithStats(NamedTuple):
    """radius_search(..., return_stats=True): RadiusResult's three arrays and the stats dict
    (n_queries, wall_s, results, truncated_queries, found, coordinates, ...)."""

    offsets: _I64A
    dist2: _F32A
    ids: _I32A
    stats: Dict[str, Any]


def _search_params(method: str, k: int, options: Dict[str, Any]) -> "_core.SearchParams":
    """kNN SearchParams of `method` from keyword arguments, refusing those it does not read."""
    _refuse_unknown(method, options, _search_options(method), "search parameter")
    p = _core.SearchParams()
    p.k = _int("k", k, 1, MAX_K)
    if options.get("A") is not None and options.get("recall_target") is not None:
        raise ValueError("A and recall_target both given: give one (recall_target picks A)")
    if options.get("max_radius") is not None:
        p.max_radius = _float("max_radius", options["max_radius"])
    _set_table_options(_core.set_search_option, p, method, _SEARCH_OPTIONS[method], options)
    if options.get("sort_queries") is not None:
        s = options["sort_queries"]
        p.sort_queries = int(s) if isinstance(s, bool) else _int("sort_queries", s, -1, 1)
    return p


def _radius_params(method: str, search: Dict[str, Any], max_results: Optional[int], return_sorted: bool,
                   sort_queries: Optional[Union[bool, int]]) -> "_core.RadiusParams":
    """RadiusParams of `method` from radius_search's keyword arguments, refusing those it does not read."""
    accepted = ("max_results", "sort_queries") + tuple(_RADIUS_OPTIONS.get(method, {}))
    _refuse_unknown(method, dict(search, max_results=max_results, sort_queries=sort_queries),
                    accepted, "search parameter")
    p = _core.RadiusParams()
    p.sorted = bool(return_sorted)
    if max_results is not None:
        p.max_results = _int("max_results", max_results, 0, 2**62)
    _set_table_options(_core.set_radius_option, p, method, _RADIUS_OPTIONS[method], search)
    if sort_queries is not None:
        p.sort_queries = int(sort_queries) if isinstance(sort_queries, bool) else _int(
            "sort_queries", sort_queries, -1, 1)
    return p


# The container Index.save writes for the methods whose structure the library does not save
# (their build takes well under the time of reading a structure back): the method, its build
# options and the points, rebuilt by load(). A zip (numpy's npz), told from a block-hash file by
# its first bytes.
# Format 2 adds "removed" (the ids removed by Index.remove, ascending; their rows of "points" hold a
# live point's coordinates, not the removed ones): load() builds over every row and removes them
# again, so the ids, id_bound and the answers are the saved index's. Format 1 (no removals) reads.
_NPZ_FORMAT = _container.FORMAT
_NPZ_FORMATS = _container.FORMATS



def _append_rows(buf: Optional[np.ndarray], view: np.ndarray, rows: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Appends rows to a read-only view of a growable store: (the store, the new read-only view).
    The store grows by half (at least to fit) when full, so n adds copy O(total) rows in all; a
    view handed out before stays valid (its rows are never written again)."""
    n, m = view.shape[0], rows.shape[0]
    if buf is None or buf.shape[0] < n + m or buf.dtype != view.dtype:
        grown = np.empty((max(n + m, n + n // 2), view.shape[1]), view.dtype)
        grown[:n] = view
        buf = grown
    buf[n:n + m] = rows
    out = buf[:n + m]
    out.flags.writeable = False
    return buf, out

class Index(_IndexFront):
    """A built index of one method over (N, 3) points. Made by make_index() or load().

    Attributes: method, exact, size (also len()), memory_bytes, build_seconds, device (a dict as
    devices() gives), build_info (the parameters a block-hash build used), coordinates (the origin
    float64 input is stored relative to and the rounding left), refined (answers in float64 from
    the caller's float64 points: make_index's refine), last_stats (the last query's
    stats dict, whichever thread ran it).

    Pickling (multiprocessing, dask) and save()/load() work for every method: a block-hash index
    travels as its saved structure plus its points, the others as their points and build options
    (rebuilt on arrival, the same answers). An unpickled index is built on the default device
    (BHCL_DEVICE, else PoCL). The index keeps a host copy of its points for this (12 bytes per
    point, counted in memory_bytes). After add() and remove() the copy holds a row per id issued
    and the removed ids travel with it: the arrival has the same ids, the same id_bound (its next
    add continues there) and the same answers.
    """

    __slots__ = ("_impl", "last_stats", "_origin", "_points_merged", "_points_parts", "_options", "_coords",
                 "_removed_sorted", "_points64", "_p_round", "_devices", "_points64_buf", "_removed_parts",
                 "_points_lock")

    def __init__(self, impl: "_core.Index", origin: Optional[np.ndarray] = None,
                 points: Optional[np.ndarray] = None, options: Optional[Dict[str, Any]] = None,
                 removed: Optional[np.ndarray] = None, points64: Optional[np.ndarray] = None,
                 devices: Optional[List[str]] = None) -> None:
        self._impl = impl
        # The device specs of a multi-device index (make_index's devices), None for one device.
        self._devices = devices
        # The caller's float64 points (a row per id issued) when answers are refined in float64,
        # and the largest rounding of a stored coordinate (the search's widening, _refine.py).
        self._points64 = points64
        self._p_round = _refine.rounding_bound(points) if points is not None else 0.0
        # The ids removed so far (ascending int32): their rows of _points are not live.
        self._removed_sorted = np.zeros(0, np.int32) if removed is None else np.asarray(removed, np.int32)
        self._removed_parts: List[np.ndarray] = []  # removes not yet merged into _removed_sorted
        # The growable store behind _points64 once an add appended to it (None before).
        self._points64_buf: Optional[np.ndarray] = None
        self.last_stats: Optional[Dict[str, Any]] = None
        self._origin = np.zeros(3, np.float64) if origin is None else np.asarray(origin, np.float64)
        # The host copy of the stored points (see _points): the rows up to the last merge and the
        # adds' rows since, one read-only array per add.
        self._points_merged = points
        self._points_parts: List[np.ndarray] = []
        self._points_lock = threading.Lock()  # an add's append against a merge in another thread
        self._options = dict(options or {})
        extent = float(np.max(np.abs(points))) if points is not None and points.size else 0.0
        self._coords = _precision(self._origin, extent)

    @property
    def memory_bytes(self) -> int:
        """Bytes this index holds, as the process's resident memory grows by them on PoCL (where
        device memory is host memory): the library's structure (device arrays, points included),
        its host copies (block hashing's structure, an exact method's copy of the points) and the
        package's host copy of the points (12 B each, for pickling and save)."""
        p64 = self._points64_buf if self._points64_buf is not None else self._points64
        own = sum(a.nbytes for a in [self._points_merged, p64] + self._points_parts if a is not None)
        return int(self._impl.memory_bytes) + int(self._impl.host_bytes) + own

    build_seconds = _forwarded("build_seconds", "Seconds the build took.")

    @property
    def _points(self) -> Optional[np.ndarray]:
        """The host copy of the stored points pickling and save send, a row per id issued,
        read-only (None: a loaded index without one): the rows of the adds since the last read
        merged into one array on this read, so that an add copies its own rows only."""
        with self._points_lock:
            if self._points_parts:
                merged = np.concatenate([self._points_merged] + self._points_parts)
                merged.flags.writeable = False
                self._points_merged, self._points_parts = merged, []
            return self._points_merged

    @property
    def device(self) -> Dict[str, Any]:
        """The device (of a multi-device index: the first copy's; see devices)."""
        return dict(self._impl.runtime.device)

    @property
    def devices(self) -> List[Dict[str, Any]]:
        """The device of each copy of the index: one for a single-device index, one per entry of
        make_index's devices for a multi-device one."""
        if self._devices is None:
            return [self.device]
        return [dict(r.device) for r in self._impl.runtimes]

    @property
    def weights(self) -> List[float]:
        """A multi-device index's current split of a batch among its devices (summing to 1; equal
        at first, then each device's measured throughput); [1.0] for one device."""
        return list(self._impl.weights) if self._devices is not None else [1.0]

    @property
    def build_info(self) -> Dict[str, Any]:
        """blockhash: the build parameters used (derived ones filled in) and the structure's
        figures; flann: the thread count; every method: "coordinates" (see coordinates)."""
        info = dict(self._impl.build_info)
        info["coordinates"] = dict(self._coords)
        return info

    @property
    def refined(self) -> bool:
        """Whether answers are refined in float64 from the caller's float64 points (make_index's
        refine): distances come back float64, each row recomputed and re-sorted in double."""
        return self._points64 is not None

    def _exact_search(self, options: Dict[str, Any]) -> bool:
        """Whether a search with these keyword arguments is exact (refinement then guarantees the
        float64 answer): the exact methods, and block hashing's grid without a budget."""
        if self._impl.exact:
            return True
        if self.method != "blockhash" or not self._impl.build_info.get("grid", False):
            return False
        a = options.get("A")
        return options.get("recall_target") is None and (a is None or a == 0 or a == float("inf"))

    def __repr__(self) -> str:
        return f"<blockhash_cl.Index {self.method} of {self.size} points on {self.device['summary']}>"

    def _search_params(self, k: int, options: Dict[str, Any]) -> "_core.SearchParams":
        """SearchParams from keyword arguments, refusing those this method does not read.
        kNN's; radius_search reads its own RadiusParams."""
        return _search_params(self.method, k, options)

    def query(
        self,
        queries: Any,
        k: int = 10,
        *,
        max_radius: Optional[float] = None,
        sort_queries: Optional[Union[bool, int]] = None,
        return_counts: bool = False,
        return_stats: bool = False,
        **search: Any,
    ) -> Tuple[Any, ...]:
        """The k nearest indexed points of each query.

        queries: (n, 3) array, or one query of shape (3,) (then each result loses its first
        axis: dist2 and ids (k,), counts a scalar, as scipy's cKDTree.query gives);
        C-contiguous float32 is used in place, anything else is converted to float32 once
        (relative to the index's origin, in float64, when its points were re-centred). k:
        1..MAX_K. max_radius: only neighbours within this Euclidean (not squared) distance.
        sort_queries: dispatch in Hilbert order (True/1, False/0, None: for large batches). The
        search keywords of each method's option table (A and recall_target exclude each other):
{search_options}

        Returns (dist2, ids): (n, k) float32 squared distances (caller units; float64, each row
        recomputed from the caller's points, when the index is refined: make_index's refine) and
        (n, k) int32 indices into the points, each row ascending (FAISS's order); then counts ((n,) int32,
        neighbours found per query) if return_counts, then the stats dict if return_stats (also
        in last_stats): n_queries, nonfinite_queries, batches, compile_s, sort_s, upload_s,
        query_s, download_s, unsort_s, wall_s, queries_per_s, coordinates (see
        Index.coordinates), and for blockhash the search options used. Block hashing with recall_target, or with neither A nor
        recall_target on a block layout (grid=0, the paper preset: target 0.95; the grid's
        default is exact), tunes A on a sample of THIS batch against exact answers, cached per
        k, target and the batch's distribution; the stats then say A, tuned_on ("queries"),
        tuned_sample_recall, tuned_reached (False: no A up to 1024 reaches the target there),
        tuning_sample, tuning_cached, tuning_distribution, tuning_s and tuning_share (of the
        call, compiles excluded). The GIL is released while it runs.
        """
        p = self._search_params(k, dict(search, max_radius=max_radius, sort_queries=sort_queries))
        a, single = _checked(queries, "queries", single_ok=True)
        q = self._to_index(a, "queries")
        if self._points64 is not None:
            dist2, ids, counts, stats = self._query64(a, q, p.k, max_radius, search, sort_queries)
        else:
            dist2, ids, counts, stats = self._impl.query(q, p)
        return self._knn_result(dist2, ids, counts, stats, single, return_counts, return_stats)

    def _query64(self, a: np.ndarray, q: np.ndarray, k: int, max_radius: Optional[float],
                 search: Dict[str, Any], sort_queries: Any, strict: bool = False) -> Tuple[Any, ...]:
        """query() refined in float64 (_refine.knn): (dist2 float64, ids, counts, stats)."""
        assert self._points64 is not None

        def run(rows: np.ndarray, kc: int, mr: Optional[float]) -> Tuple[Any, ...]:
            p = self._search_params(kc, dict(search, max_radius=mr, sort_queries=sort_queries))
            return self._impl.query(np.ascontiguousarray(rows), p)

        def ball(rows: np.ndarray, r: float) -> Tuple[Any, ...]:
            offsets, d2, ids, _, _ = self._impl.radius_search(np.ascontiguousarray(rows), r, False,
                                                              _core.RadiusParams())
            return offsets, d2, ids

        with np.errstate(invalid="ignore", over="ignore"):
            q64 = np.asarray(a, np.float64)
        return _refine.knn(run, ball, q64, q, self._points64, self._p_round, k, MAX_K, max_radius,
                           self._exact_search(search), strict)

    def _radius64(self, a: np.ndarray, q: np.ndarray, r2: np.ndarray, p: "_core.RadiusParams",
                  max_results: int, return_sorted: bool, exact: bool) -> Tuple[Any, ...]:
        """radius_search() refined in float64 (_refine.radius), r2 the squared radius per query:
        (offsets, dist2 float64, ids, found, stats)."""
        assert self._points64 is not None

        def run(rows: np.ndarray, r: float, cap: int) -> Tuple[Any, ...]:
            p.max_results = cap
            p.sorted = bool(cap)
            return self._impl.radius_search(np.ascontiguousarray(rows), r, False, p)

        with np.errstate(invalid="ignore", over="ignore"):
            q64 = np.asarray(a, np.float64)
        return _refine.radius(run, q64, q, self._points64, self._p_round, r2, max_results, return_sorted, exact)

    @overload
    def radius_search(self, queries: Any, r: float, *, squared: bool = ..., max_results: Optional[int] = ...,
                      return_sorted: bool = ..., sort_queries: Optional[Union[bool, int]] = ...,
                      return_stats: Literal[False] = ..., **search: Any) -> RadiusResult: ...

    @overload
    def radius_search(self, queries: Any, r: float, *, squared: bool = ..., max_results: Optional[int] = ...,
                      return_sorted: bool = ..., sort_queries: Optional[Union[bool, int]] = ...,
                      return_stats: Literal[True], **search: Any) -> RadiusResultWithStats: ...

    def radius_search(
        self,
        queries: Any,
        r: float,
        *,
        squared: bool = False,
        max_results: Optional[int] = None,
        return_sorted: bool = True,
        sort_queries: Optional[Union[bool, int]] = None,
        return_stats: bool = False,
        **search: Any,
    ) -> Union[RadiusResult, RadiusResultWithStats]:
        """Every indexed point within radius r of each query (scipy's query_ball_point, Open3D's
        fixed_radius_search, FAISS's range_search).

        queries: (n, 3), or (3,) for one query (n = 1). r: the Euclidean radius (>= 0; inf takes
        every point, as scipy's does); squared=True takes r as the squared radius (nanoflann's
        and FLANN's convention). A point is within when its squared distance <= r*r.
        max_results: at most this many per query, the nearest (None/0: no cap; stats count the
        truncated queries). return_sorted=False leaves each slice in the order the method found
        its points (scipy's return_sorted, Open3D's sort), sparing the sort; a capped slice still
        holds the nearest max_results. The radius keywords of each method's option table:
{radius_options}
        Exact methods, and block hashing's default (grid) layout, return exactly the points
        within r; a block-hash budget returns a subset. A query with a NaN/Inf coordinate gets
        an empty slice.

        Returns a RadiusResult (offsets, dist2, ids) in FAISS's layout: query i's results are
        dist2[offsets[i]:offsets[i+1]] (float32, SQUARED; float64 when the index is refined, the
        points within r in float64) and the same slice of ids (int32), each
        sorted by (distance, index) unless return_sorted=False; offsets is (n + 1,) int64. With
        return_stats, a RadiusResultWithStats whose stats are query's, plus results,
        truncated_queries and found (the (n,) counts before the cap). The GIL is released while
        it runs.
        """
        method = self.method
        p = _radius_params(method, search, max_results, return_sorted, sort_queries)
        radius = _float("r", r)
        a, _ = _checked(queries, "queries", single_ok=True)
        q = self._to_index(a, "queries")
        if self._points64 is not None:
            if radius < 0 or radius != radius:
                raise Error(f"radius_search: r = {radius!r} must be >= 0")
            r2 = np.full(len(q), radius if squared else radius * radius, np.float64)
            exact = self._exact_search(search) and not (method == "blockhash" and p.budget)
            offsets, dist2, ids, found, stats = self._radius64(a, q, r2, p, int(p.max_results), bool(return_sorted),
                                                               exact)
        else:
            offsets, dist2, ids, found, stats = self._impl.radius_search(q, radius, bool(squared), p)
        return self._radius_result(offsets, dist2, ids, found, stats, return_stats)

    def warm_up(self, k: int = 10, **search: Any) -> float:
        """Compiles the kernel variant the search parameters need and launches it once, so that
        later query timings exclude compilation. Returns the seconds it took (0 if done before)."""
        return self._impl.warm_up(self._search_params(k, search))

    def add(self, points: Any) -> "np.ndarray":
        """Adds (n, 3) points (float32 or float64) without a fresh build; returns their ids, an
        int32 array id_bound, id_bound + 1, ... (ids are stable: never reused after a remove).
        Waits for queries in progress on this index (updates are exclusive with queries).
        float64 points are stored relative to the index's origin, as the build's were."""
        stored = self._to_index(points, "points")
        ids = self._impl.insert(stored)
        # The copies pickling and save rebuild from (a row per id issued). The float32 one keeps
        # this add's rows as a part (a private copy only where `stored` is the caller's array),
        # merged when read: a copy of every row per add cost more than the library's insert (12 MB
        # per add at 1M points), and even a store grown by half copied them all on each growth
        # (6.5x the insert's time on that call; issue 39). The float64 one, which every refined
        # query reads, stays one array, appended in place into a store grown by half.
        if self._points_merged is not None:
            part = _own_copy(stored.reshape(-1, 3), points)
            with self._points_lock:
                self._points_parts.append(part)
        if self._points64 is not None:
            a, _ = _checked(points, "points")
            self._points64_buf, self._points64 = _append_rows(self._points64_buf, self._points64,
                                                              np.asarray(a, np.float64).reshape(-1, 3))
            # The search's widening, read by refined answers only: a pass over the new rows that
            # an unrefined index skips (0.15 ms per 100k rows, 4 % of a 10 % insert at 1M).
            self._p_round = max(self._p_round, _refine.rounding_bound(stored))
        return ids

    def remove(self, ids: Any) -> None:
        """Removes the points of these ids (a 1-D integer array or sequence). Raises Error for an
        id never issued, already removed or given twice, and for removing every point."""
        arr = _checked_ids(ids, -2**31, 2**31 - 1, "remove")
        self._impl.remove(np.ascontiguousarray(arr, dtype=np.int32))
        # The rows stay (ids are never reused); the removed ids travel with them (see the class).
        # Kept as the calls gave them and merged when read: a sorted union on every remove grew
        # with all the removes before it. The library refused repeats, so the parts are disjoint.
        self._removed_parts.append(arr.astype(np.int32))

    @property
    def _removed(self) -> np.ndarray:
        """The ids removed so far, ascending int32."""
        if self._removed_parts:
            self._removed_sorted = np.sort(np.concatenate([self._removed_sorted] + self._removed_parts)).astype(np.int32)
            self._removed_parts = []
        return self._removed_sorted

    def contains(self, id: int) -> bool:
        """True when id was issued and not removed."""
        return bool(self._impl.contains(int(id)))

    # --- travelling: save/load and pickling
    def _structure_bytes(self) -> bytes:
        """A block-hash index's saved structure (the library's file format) as bytes."""
        fd, tmp = tempfile.mkstemp(suffix=".bhi")
        os.close(fd)
        try:
            self._impl.save(tmp)
            with open(tmp, "rb") as f:
                return f.read()
        finally:
            os.unlink(tmp)

    def save(self, path: Union[str, "os.PathLike[str]"]) -> None:
        """Writes the index to a file that load() reads back, for every method. blockhash: the
        library's block-hash file (versioned, checksummed; load needs the same points, as bhcl
        --load-index). Other methods: a container of the method, its build options and its points
        (load() rebuilds the structure from them; the points are then optional)."""
        path = os.fspath(path)
        if self._impl.saves:
            self._impl.save(path)
            return
        if self._points is None:
            raise Error(f"save: this {self.method} index holds no copy of its points")
        # Written to a temporary beside the file and renamed when complete (as the library's files).
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), prefix=".bhcl-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                extra = {} if self._points64 is None else {"points64": self._travelling_points64()}
                np.savez(f, format=np.array(_NPZ_FORMAT), method=np.array(self.method),
                         options=np.array(json.dumps(self._options)), origin=self._origin,
                         points=self._travelling_points(), removed=self._removed, **extra)
            os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise

    def _travelling_points(self) -> np.ndarray:
        """The host copy as it travels: a row per id issued, a removed id's row overwritten by the
        first live point (a removed point's coordinates do not leave the process; the row is
        built over and removed again on arrival)."""
        assert self._points is not None
        if not self._removed.size:
            return self._points
        pts = np.array(self._points, np.float32)
        live = np.ones(len(pts), bool)
        live[self._removed] = False
        pts[self._removed] = pts[int(np.flatnonzero(live)[0])]
        return pts

    def _travelling_points64(self) -> Optional[np.ndarray]:
        """The float64 copy as it travels (refined indexes), removed rows as _travelling_points."""
        if self._points64 is None:
            return None
        if not self._removed.size:
            return self._points64
        pts = np.array(self._points64)
        live = np.ones(len(pts), bool)
        live[self._removed] = False
        pts[self._removed] = pts[int(np.flatnonzero(live)[0])]
        return pts

    def __getstate__(self) -> Dict[str, Any]:
        if self._points is None:
            raise Error(f"pickle: this {self.method} index holds no copy of its points")
        state: Dict[str, Any] = {"format": _NPZ_FORMAT, "method": self.method, "options": dict(self._options),
                                 "origin": self._origin.copy(), "points": self._travelling_points(),
                                 "removed": self._removed.copy(), "structure": None,
                                 "points64": self._travelling_points64(), "devices": self._devices}
        if self._impl.saves:
            state["structure"] = self._structure_bytes()
        return state

    def __setstate__(self, state: Dict[str, Any]) -> None:
        if not isinstance(state, dict) or state.get("format") not in _NPZ_FORMATS:
            raise Error("unpickle: not a blockhash_cl index state (format "
                        f"{state.get('format') if isinstance(state, dict) else type(state).__name__!r})")
        other = _rebuild(state["method"], state["points"], state["origin"], state["options"], state["structure"], None,
                         state.get("removed"), state.get("points64"), state.get("devices"))
        for name in Index.__slots__:
            setattr(self, name, getattr(other, name))


def _rebuild(method: str, pts: np.ndarray, origin: np.ndarray, options: Dict[str, Any],
             structure: Optional[bytes], device: Union[None, str, Runtime],
             removed: Optional[np.ndarray] = None, points64: Optional[np.ndarray] = None,
             devices: Optional[List[str]] = None) -> Index:
    """An index over stored (relative, float32) points, a row per id issued: rebuilt from its
    build options and the removed ids removed again, or for block hashing read from its saved
    structure (which holds the ids itself)."""
    pts = np.ascontiguousarray(pts, dtype=np.float32)
    removed = np.zeros(0, np.int32) if removed is None else np.ascontiguousarray(removed, dtype=np.int32)
    if removed.size and (removed.ndim != 1 or removed.min() < 0 or removed.max() >= len(pts)
                         or np.any(np.diff(removed) <= 0)):
        raise Error(f"load: the removed ids are not ascending ids of the {len(pts)} rows")
    opts = _core.MethodOptions()
    if structure is not None:
        fd, tmp = tempfile.mkstemp(suffix=".bhi")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(structure)
            opts.set("load-index", tmp)
            impl = _core.make_index(method, get_runtime(device), pts, opts)
        finally:
            os.unlink(tmp)
    else:
        table = _BUILD_OPTIONS.get(method, {})
        _refuse_unknown(method, options, tuple(table), "build option")
        _set_table_options(_core.set_build_option, opts, method, table, options)
        impl = _build(method, pts, opts, device, devices)
        if removed.size:
            impl.remove(removed)
    if impl.id_bound != len(pts) or impl.size != len(pts) - removed.size:
        raise Error(f"load: the {method} index holds {impl.size} points of ids 0 .. {impl.id_bound - 1}; the "
                    f"state has {len(pts)} rows of which {removed.size} removed")
    pts.flags.writeable = False
    if points64 is not None:
        points64 = np.array(points64, np.float64, order="C")
        if points64.shape != pts.shape:
            raise Error(f"load: the float64 copy has shape {points64.shape}, the points {pts.shape}")
        points64.flags.writeable = False
    return Index(impl, origin, pts, options, removed, points64, devices)


def _copy64(a: np.ndarray, stored: np.ndarray, origin: np.ndarray, refine: Optional[bool]) -> Optional[np.ndarray]:
    """The float64 copy of the caller's points answers are refined from, or None: refine True
    always (any input, taken as float64), False never, None (auto) when the points are float64,
    re-centred (far from 0 for their size: georeferenced data, where float32 storage costs most)
    and their float32 storage rounded some coordinate (stored + origin != the caller's)."""
    if refine is False:
        return None
    if refine is None:
        if a.dtype.kind != "f" or a.dtype.itemsize <= 4 or a.size == 0 or not np.any(origin):
            return None
        with np.errstate(invalid="ignore", over="ignore"):
            lossless = np.array_equal(stored.astype(np.float64) + origin, a, equal_nan=True)
        if lossless:
            return None
    elif refine is not True:
        raise TypeError(f"refine must be True, False or None, got {refine!r}")
    p64 = np.array(a, np.float64, order="C")
    p64.flags.writeable = False
    return p64


def _device_specs(devices: Any) -> List[str]:
    """make_index's devices as specs ("P:D" for a Runtime), checked."""
    if isinstance(devices, (str, Runtime)) or not hasattr(devices, "__iter__"):
        raise TypeError("devices must be a list of device specs or Runtimes, e.g. ['pocl', 'nvidia']")
    specs = []
    for d in devices:
        if isinstance(d, Runtime):
            specs.append(d.device["spec"])
        elif isinstance(d, str) and d.strip():
            specs.append(d.strip())
        else:
            raise TypeError(f"devices: each entry must be a non-empty str or a Runtime, got {d!r}")
    if not specs:
        raise ValueError("devices must name at least one device")
    return specs


def _build(method: str, pts: np.ndarray, opts: "_core.MethodOptions", device: Union[None, str, Runtime],
           devices: Optional[List[str]]) -> Any:
    """The C++ index: one device's, or a MultiDeviceIndex with a copy on each of devices."""
    if devices is None:
        return _core.make_index(method, get_runtime(device), pts, opts)
    # Each copy on its own runtime (context and queue): a spec named twice gets a second one.
    runtimes: List[Runtime] = []
    for spec in devices:
        rt = get_runtime(spec)
        runtimes.append(rt if all(r is not rt for r in runtimes) else Runtime(spec))
    return _core.MultiDeviceIndex(runtimes, method, pts, opts)


def make_index(method: str, points: Any, *, device: Union[None, str, Runtime] = None,
               devices: Optional[List[Union[str, Runtime]]] = None, refine: Optional[bool] = None,
               **options: Any) -> Index:
    """Builds an index of `method` ("blockhash", "kdtree", "bruteforce", "flann"; see
    method_names()) over points, an (N, 3) array (float32 or float64; converted to float32 once
    when it is not C-contiguous float32; the index keeps its own copy, not the array). float64
    points far from 0 for their size (georeferenced data) are re-centred in double precision on
    their box and stored in float32 relative to it: queries are taken relative to the same origin
    and distances come back in caller units (Index.coordinates states the rounding left).

    Build options (keyword arguments; one the method does not read raises TypeError), from the
    library's method tables (build_options() lists them with ranges and defaults):
{build_options}
    device: a spec ("P:D", "cpu", "gpu", "pocl", "nvidia:1"), a Runtime, or None for
    BHCL_DEVICE, else PoCL, else the first device. The GIL is released during the build.

    devices (instead of device): a list of specs or Runtimes: the library's multi-device index,
    a copy built on each (concurrently); a batch is split among them by their measured throughput
    (Index.weights), the parts run at once and the rows come back in order, equal to one device's
    bit for bit. query, radius_search (not squared=True), add and remove, pickling (rebuilt on the
    same device specs) and save (the points; load builds one device's index) work as for one
    device.

    refine (float64 in, float64 out): None (default) refines when the points are float64 and
    re-centred (see above) and storing them in float32 rounded some coordinate; True always
    (any float64 data; the points taken as float64); False never. A refined index keeps a float64 copy of the points (24 B each, in
    memory_bytes) and answers query() and radius_search() in float64: its float32 search is
    widened by the stored rounding bound so that no true neighbour is lost, each row's distances
    are recomputed in double from the caller's points (queries taken in float64 too) and
    re-sorted, dist2 comes back float64; for every exact search (exact methods, block hashing's
    grid without a budget) the rows are the float64 answer. The stats say refined, refine_s,
    refine_share, refine_candidates, refine_requeried_rows, refine_radius_rows. By default
    float64 data around 0 (and float32 data cast up, bit for bit) gives the float32 answer.
    """
    if not isinstance(method, str):
        raise TypeError(f"method must be a str, got {type(method).__name__}")
    table = _BUILD_OPTIONS.get(method, {})
    _refuse_unknown(method, options, tuple(table), "build option")
    opts = _core.MethodOptions()
    _set_table_options(_core.set_build_option, opts, method, table, options)
    a, _ = _checked(points, "points")
    _check_count(a, method)
    origin = _origin_for(a)
    pts = _relative(a, origin, "points") if np.any(origin) else _xyz(a, "points")
    if devices is not None and device is not None:
        raise TypeError("give device or devices, not both")
    specs = None if devices is None else _device_specs(devices)
    p64 = _copy64(a, pts, origin, refine)
    impl = _build(method, pts, opts, device, specs)
    return Index(impl, origin, _own_copy(pts, points), {k: v for k, v in options.items() if v is not None},
                 None, p64, specs)


def load(path: Union[str, "os.PathLike[str]"], points: Any = None, *,
         device: Union[None, str, Runtime] = None, refine: Optional[bool] = None) -> Index:
    """Reads an index Index.save() wrote. A block-hash file needs the (N, 3) points it was built
    from (the index refers to them by index; as bhcl --load-index; after add() and remove(), a row
    per id issued, id_bound rows: a removed id's row is not compared); a file that does not match
    them, or is missing, truncated or corrupt, raises Error naming the file and what differs. A
    file of another method holds its points: `points`, when given, must equal them."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise Error(f"load: cannot read {path}: {e.strerror}") from None
    if head[:2] == b"PK":
        # Every field checked against the others, memory bounded by the file (_container.py).
        method, options, origin, stored, removed, points64 = _container.read_container(path, Error)
        if points is not None:
            a, _ = _checked(points, "points")
            mine = _relative(a, origin, "points") if np.any(origin) else _xyz(a, "points")
            if mine.shape != stored.shape:
                raise Error(f"load: {path} holds {len(stored)} points, {len(mine)} given")
            differs = np.any(mine != stored, axis=1)
            if removed is not None and removed.size:
                differs[removed[(removed >= 0) & (removed < len(differs))]] = False  # not stored
            diff = np.flatnonzero(differs)
            if diff.size:
                raise Error(f"load: {path}: point {int(diff[0])} differs from the one it was built from")
        if method not in _BUILD_OPTIONS and method not in method_names():
            raise Error(f"load: {path}: field 'method' is {method!r}, not a method of this library")
        try:
            return _rebuild(method, stored, origin, options, None, device, removed, points64)
        except (TypeError, ValueError) as e:  # a crafted option's name or value
            raise Error(f"load: {path}: field 'options': {e}") from None
    if points is None:
        raise Error(f"load: {path} is a block-hash index file: give the points it was built from")
    a, _ = _checked(points, "points")
    origin = _origin_for(a)
    pts = _relative(a, origin, "points") if np.any(origin) else _xyz(a, "points")
    opts = _core.MethodOptions()
    opts.set("load-index", path)
    impl = _core.make_index("blockhash", get_runtime(device), pts, opts)
    removed = impl.removed_ids() if impl.removed_count else None  # a file saved after removals
    return Index(impl, origin, _own_copy(pts, points), {}, removed, _copy64(a, pts, origin, refine))


# The docstrings list what the option tables hold.
Index.query.__doc__ = (Index.query.__doc__ or "").replace("{search_options}", _options_doc(_SEARCH_OPTIONS))
Index.radius_search.__doc__ = (Index.radius_search.__doc__ or "").replace(
    "{radius_options}", _options_doc(_RADIUS_OPTIONS))
make_index.__doc__ = (make_index.__doc__ or "").replace("{build_options}", _options_doc(_BUILD_OPTIONS))

# scipy.spatial.KDTree's interface over an Index (_scipy.py).
from ._scipy import KDTree, cKDTree  # noqa: E402
# The MPI-distributed index (_distributed.py; mpi4py optional, imported only when a
# communicator is needed).
from ._distributed import DistributedIndex  # noqa: E402
