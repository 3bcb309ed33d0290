"""The MPI-distributed index from Python (issue 40, part 3): blockhash_cl.DistributedIndex over the
library's bhcl::DistributedIndex (docs/DISTRIBUTED.md), one process per rank, under mpirun.

    from mpi4py import MPI                       # optional: comm=None takes MPI_COMM_WORLD
    import blockhash_cl as bh
    index = bh.DistributedIndex("kdtree", my_points, comm=MPI.COMM_WORLD)   # this rank's part
    dist2, ids = index.query(my_queries, k=10)   # this rank's rows; ids are global (int64)
    new_ids = index.add(my_new_points)           # collective, as every call; ids continue at id_bound
    index.remove(some_ids)                       # any live global ids, held by any rank

The communicator crosses to the C++ layer as its Fortran handle (mpi4py's Comm.py2f()): the package
needs mpi4py neither to build nor to import, and without it comm=None initialises MPI itself
(MPI_COMM_WORLD, finalised at exit). Every call is collective: each rank calls it with the same
parameters and its own points or queries (any split, none on some ranks). The checks this layer
makes before the library's are agreed over the ranks, so that a bad argument on one rank raises on
every rank (blockhash_cl.Error naming that rank; the rank itself raises its own TypeError or
ValueError) instead of leaving the others waiting in a collective.
"""
from __future__ import annotations

import atexit
import sys
import threading
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from . import _core
from ._base import _IndexFront, _checked_ids, _forwarded
from ._checks import (_BUILD_OPTIONS, _check_count, _checked, _float, _int, _origin_from_box, _precision,
                      _refuse_unknown, _set_table_options)

_finalize_registered = False
_finalize_lock = threading.Lock()


def _have_mpi() -> bool:
    """Whether this build of the package has the distributed index (the build found MPI)."""
    return bool(getattr(_core, "HAVE_MPI", False))


def _handle(comm: Any) -> int:
    """The communicator's Fortran handle: an mpi4py communicator's py2f(), an int handle as it is;
    None: MPI_COMM_WORLD, through mpi4py where it imports, else from the library (which then
    initialises MPI and finalises it at exit)."""
    if comm is None:
        mpi = sys.modules.get("mpi4py.MPI")
        if mpi is None:
            try:
                from mpi4py import MPI as mpi  # type: ignore
            except ImportError:
                mpi = None
        if mpi is not None:
            return int(mpi.COMM_WORLD.py2f())
        return _own_world()
    if hasattr(comm, "py2f"):
        return int(comm.py2f())
    if isinstance(comm, (int, np.integer)) and not isinstance(comm, (bool, np.bool_)):
        return int(comm)
    raise TypeError(f"comm must be an mpi4py communicator, its py2f() handle or None, got {type(comm).__name__}")


def _own_world() -> int:
    """MPI_COMM_WORLD without mpi4py: MPI initialised by the library, finalised at exit."""
    global _finalize_registered
    h = int(_core.mpi_world())
    with _finalize_lock:
        if not _finalize_registered:
            atexit.register(_core.mpi_finalize)
            _finalize_registered = True
    return h


class DistributedIndex(_IndexFront):
    """An index of one method over the points of every rank of an MPI communicator: the points
    sharded by Hilbert-key range (balanced by count), a local index of `method` per rank, queries
    routed to the ranks whose shards can hold their neighbours (the library's DistributedIndex;
    docs/DISTRIBUTED.md). Exact methods answer as one process over all the points does, bit for
    bit (same ids, float32 squared distances, counts), whatever the number of ranks and the split.

    DistributedIndex(method, points, comm=None, *, device=None, boxes_per_rank=16,
    border_factor=2.0, deadline_s=None, id_base=0, **build_options): collective. points: THIS
    rank's (n, 3) part (float32 or float64; n may be 0 on some ranks, not on all); a point's id is
    id_base + its place in the concatenation of the ranks' parts in rank order (int64). comm: an
    mpi4py communicator, its py2f() handle, or None for MPI_COMM_WORLD. device: this rank's OpenCL
    device (as make_index's). boxes_per_rank, border_factor, deadline_s (seconds a collective step
    may wait for a rank before the job ends naming it; None: BHCL_MPI_DEADLINE_S, else 600),
    id_base: the library's DistributedBuildParams. float64 points far from 0 for their size are
    re-centred on the box of ALL ranks' points (in double, as make_index does on one rank), and
    queries taken relative to it: distances stay in caller units. Answers are float32 (no float64
    refinement: refine=True raises).

    Calls (collective): query, radius_search, add and remove, as Index's, with int64 global ids.
    Attributes: method, exact, size (live points over all ranks; len()), rank, ranks, shard_size
    (live points in this rank's shard), shard_ids (the global ids of its local index, removed ones
    included), shard_live_ids, id_base, id_bound, removed_count, build_stats (the sharding:
    n_global, shard sizes, balance, times), memory_bytes (this rank's), device, coordinates,
    last_stats, last_update_stats. The library's distributed index has no save or pickling: none
    is offered here.
    """

    __slots__ = ("_impl", "_comm", "_origin", "_coords", "last_stats", "last_update_stats", "__weakref__")

    def __init__(self, method: str, points: Any, comm: Any = None, *, device: Any = None,
                 boxes_per_rank: int = 16, border_factor: float = 2.0, deadline_s: Optional[float] = None,
                 id_base: int = 0, refine: Optional[bool] = None, **options: Any) -> None:
        if not _have_mpi():
            raise _core.Error("DistributedIndex: this build of blockhash_cl has no MPI (CMake found none; "
                              "Debian: libopenmpi-dev, then reinstall)")
        deadline = -1.0 if deadline_s is None else _float("deadline_s", deadline_s)
        self._comm = _core.MpiComm(_handle(comm), deadline)
        self._impl = None
        self.last_stats: Optional[Dict[str, Any]] = None
        self.last_update_stats: Optional[Dict[str, Any]] = None
        a = None
        opts = _core.MethodOptions()

        def check_args() -> None:
            nonlocal a
            if not isinstance(method, str):
                raise TypeError(f"method must be a str, got {type(method).__name__}")
            if refine:
                raise _core.Error("DistributedIndex: refine (float64 answers) is not available for a distributed "
                                  "index: its answers are float32 (make_index refines on one process)")
            table = _BUILD_OPTIONS.get(method, {})
            _refuse_unknown(method, options, tuple(table), "build option")
            _set_table_options(_core.set_build_option, opts, method, table, options)
            _int("boxes_per_rank", boxes_per_rank)
            _float("border_factor", border_factor)
            _int("id_base", id_base, 0, 2**62)
            a, _ = _checked(points, "points")
            _check_count(a, method)

        self._agreed(check_args, "DistributedIndex")
        assert a is not None
        self._origin = self._global_origin(a)

        pts = self._agreed(lambda: self._to_index(a, "points"), "DistributedIndex")
        from . import get_runtime  # the package's runtimes, one per device spec
        rt = self._agreed(lambda: get_runtime(device), "DistributedIndex")
        self._impl = _core.DistributedIndex(self._comm, rt, pts, method, opts, int(boxes_per_rank),
                                            float(border_factor), deadline, int(id_base))
        extent = self._comm.box(*self._local_extent(pts))[1][0]
        self._coords = _precision(self._origin, float(extent))

    # --- agreement over the ranks
    def _agreed(self, fn: Any, what: str) -> Any:
        """fn() on this rank, its failure agreed over the ranks: every rank raises when any rank's
        fn raised (this rank its own exception, the others blockhash_cl.Error naming it)."""
        err, out, exc = "", None, None
        try:
            out = fn()
        except Exception as e:  # reported to every rank, then raised here
            err, exc = f"{type(e).__name__}: {e}", e
        try:
            self._comm.agree(err, what)
        except _core.Error:
            if exc is not None:
                raise exc from None
            raise
        return out

    def _global_origin(self, a: np.ndarray) -> np.ndarray:
        """make_index's origin rule (_origin_from_box) over the box of every rank's finite points,
        applied where every rank with points passed float64 (the same origin on every rank)."""
        inf = float("inf")
        lo, hi = [inf] * 3, [-inf] * 3
        size = inf  # itemsize of this rank's float input (inf: no points, no say)
        if a.size:
            size = float(a.dtype.itemsize if a.dtype.kind == "f" else 0)
            fin = np.where(np.isfinite(a), a, np.nan).astype(np.float64) if a.dtype.kind == "f" else a.astype(
                np.float64)
            with np.errstate(invalid="ignore"), _warnings_off():
                lo = [float(v) if np.isfinite(v) else inf for v in np.nanmin(fin, axis=0)]
                hi = [float(v) if np.isfinite(v) else -inf for v in np.nanmax(fin, axis=0)]
        glo, ghi = self._comm.box(lo, hi)
        smallest = self._comm.box([size, inf, inf], [-inf, -inf, -inf])[0][0]
        if not smallest > 4:
            return np.zeros(3, np.float64)
        return _origin_from_box(np.asarray(glo, np.float64), np.asarray(ghi, np.float64))

    @staticmethod
    def _local_extent(pts: np.ndarray) -> Tuple[List[float], List[float]]:
        """(lo, hi) for Comm.box whose hi[0] is this rank's largest |stored coordinate|."""
        inf = float("inf")
        m = float(np.max(np.abs(pts), initial=0.0, where=np.isfinite(pts))) if pts.size else 0.0
        return [inf, inf, inf], [m, -inf, -inf]

    # --- attributes (method, exact, size, id_bound, removed_count, coordinates: _IndexFront)
    rank = _forwarded("rank", "This process's rank in the communicator.")
    ranks = _forwarded("ranks", "The communicator's size.")
    shard_size = _forwarded("shard_size", "Live points in this rank's shard.")
    shard_ids = _forwarded("shard_ids", "The global ids of this rank's local index, ascending (int64): its local "
                           "id i is shard_ids[i]; removed ones stay (local ids are never reused), see shard_live_ids.")
    shard_live_ids = _forwarded("shard_live_ids", "The live global ids of this rank's shard, ascending (int64).")
    id_base = _forwarded("id_base", "The first point's global id (the build's id_base).")

    @property
    def build_stats(self) -> Dict[str, Any]:
        return dict(self._impl.build_stats)

    @property
    def memory_bytes(self) -> int:
        """Bytes this rank holds, counted as Index.memory_bytes counts them: its local index's
        structure (device arrays, points included) and host copies, and the distributed index's
        own host arrays (the shard's global ids, its float32 copy of the points for the routing
        boxes after a remove, their sub-runs and removed marks). The package keeps no copy of the
        points here (no pickling or save), so nothing of its own is added."""
        return int(self._impl.memory_bytes)

    @property
    def device(self) -> Optional[Dict[str, Any]]:
        """This rank's device (None when its shard is empty: fewer points than ranks)."""
        rt = self._impl.runtime
        return None if rt is None else dict(rt.device)

    def __repr__(self) -> str:
        return (f"<blockhash_cl.DistributedIndex {self.method} of {self.size} points, rank {self.rank} of "
                f"{self.ranks} ({self.shard_size} in its shard)>")

    def __reduce__(self) -> Any:
        raise TypeError("a DistributedIndex cannot be pickled: it lives on every rank of its communicator "
                        "(build one per job from the points)")

    # --- searches
    def _queries(self, queries: Any) -> Tuple[np.ndarray, bool]:
        a, single = _checked(queries, "queries", single_ok=True)
        return self._to_index(a, "queries"), single

    def query(self, queries: Any, k: int = 10, *, max_radius: Optional[float] = None,
              sort_queries: Optional[Union[bool, int]] = None, return_counts: bool = False,
              return_stats: bool = False, **search: Any) -> Tuple[Any, ...]:
        """Collective: the k nearest points (over all ranks) of each of THIS rank's queries, as
        Index.query: (dist2 (n, k) float32 squared, ids (n, k) int64 global ids), then counts
        and stats as asked. Stats: this rank's QueryStats (n_queries, wall_s, ...; the local
        index's work for every rank's queries it answered) and the routing: owner and
        ranks_visited (per query), multi_rank_queries, owner_sent/received, extra_sent/received,
        reanswered, answered, bytes_sent/received, phase1_s, phase2_s."""
        from . import _search_params

        def prepare() -> Tuple[Any, np.ndarray, bool]:
            p = _search_params(self.method, k, dict(search, max_radius=max_radius, sort_queries=sort_queries))
            q, single = self._queries(queries)
            return p, q, single

        p, q, single = self._agreed(prepare, "DistributedIndex.query")
        dist2, ids, counts, stats = self._impl.query(q, p)
        return self._knn_result(dist2, ids, counts, stats, single, return_counts, return_stats)

    def radius_search(self, queries: Any, r: float, *, max_results: Optional[int] = None,
                      return_sorted: bool = True, sort_queries: Optional[Union[bool, int]] = None,
                      return_stats: bool = False, **search: Any) -> Any:
        """Collective: every point (over all ranks) within Euclidean radius r of each of THIS rank's
        queries, as Index.radius_search (a RadiusResult: offsets, float32 squared dist2, int64
        ids; each slice sorted by (distance, id); max_results keeps the nearest). Every rank must
        pass the same r and options. Stats as query's, plus results, truncated_queries, found."""
        from . import _radius_params

        def prepare() -> Tuple[Any, float, np.ndarray]:
            p = _radius_params(self.method, search, max_results, return_sorted, sort_queries)
            radius = _float("r", r)
            if not radius >= 0:
                raise _core.Error(f"radius_search: r = {radius!r} must be >= 0")
            q, _ = self._queries(queries)
            return p, radius, q

        p, radius, q = self._agreed(prepare, "DistributedIndex.radius_search")
        offsets, dist2, ids, found, stats = self._impl.radius_search(q, radius, p)
        return self._radius_result(offsets, dist2, ids, found, stats, return_stats)

    # --- updates
    def add(self, points: Any) -> np.ndarray:
        """Collective: adds THIS rank's new points ((n, 3) float32 or float64; n may be 0 on some
        ranks, not on all) without a fresh build, as Index.add; returns their global ids (int64):
        the call's points over all ranks take id_bound, id_bound + 1, ... in rank order (this
        rank's i-th point: its first id + i), never reused after a remove. Each point goes to the
        rank owning its region (clamped for points outside the build's box). float64 points are
        stored relative to the index's origin, as the build's were. Raises on every rank for a
        wrong shape on any rank (that rank its own ValueError / TypeError), a non-finite point
        (named by the id it would take and its rank) and no points on any rank; the index is then
        unchanged. last_update_stats: n_global, n_input, applied (points this rank's shard
        took), sent, bytes_sent/received, route_s, local_s, boxes_s, wall_s."""
        pts = self._agreed(lambda: self._to_index(points, "points"), "DistributedIndex.add")
        first, self.last_update_stats = self._impl.insert(pts)
        return np.arange(first, first + len(pts), dtype=np.int64)

    def remove(self, ids: Any) -> None:
        """Collective: removes the points of THIS rank's list of global ids (1-D integers; any
        live ids, held by any rank; none on some ranks, not on all), as Index.remove. Raises on
        every rank, the index unchanged, for ids of the wrong shape or kind on any rank, an id
        never issued, already removed or given twice (anywhere in the call: both places named),
        and removing every point. last_update_stats as add's (applied: removed from this shard)."""
        what = "DistributedIndex.remove"
        arr = self._agreed(lambda: _checked_ids(ids, -2**63, 2**63 - 1, what), what)
        self.last_update_stats = self._impl.remove(np.ascontiguousarray(arr, dtype=np.int64))


class _warnings_off:
    """numpy's RuntimeWarning of nanmin over an all-NaN column (a rank whose points are all
    non-finite: the library names them)."""

    def __enter__(self) -> None:
        import warnings
        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: Any) -> None:
        self._w.__exit__(*exc)
