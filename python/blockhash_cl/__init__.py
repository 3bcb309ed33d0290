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

import operator
import os
import threading
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import _core
from ._core import Error, OpenCLError, Runtime

__all__ = [
    "Error", "OpenCLError", "Runtime", "Index", "make_index", "load", "devices", "select_device",
    "get_runtime", "method_names", "build_options", "MAX_K", "HAVE_FLANN", "__version__",
]

__version__: str = _core.__version__
MAX_K: int = _core.MAX_K  # the largest k any method answers
HAVE_FLANN: bool = _core.HAVE_FLANN  # whether the "flann" method was built in

# The method registry of the C++ library (factory.hpp): the keyword arguments each method reads
# come from the same entries as bhcl's options (a command-line name "leaf-size" is the keyword
# leaf_size), so a method or option the library gains appears here without a change. Anything
# else is refused, as bhcl refuses an option the chosen method does not read.
_TABLE: Dict[str, Dict[str, Any]] = {m["name"]: m for m in _core.method_table()}


def _scoped(scope: str) -> Dict[str, Dict[str, Dict[str, Any]]]:
    # File options are load() and save()'s business, not keyword arguments.
    return {name: {o["keyword"]: o for o in m["options"] if o[scope] and o["kind"] != "file"}
            for name, m in _TABLE.items()}


_BUILD_OPTIONS = _scoped("build")
_SEARCH_OPTIONS = _scoped("search")
_RADIUS_OPTIONS = _scoped("radius")
_SEARCH_COMMON: Tuple[str, ...] = ("max_radius", "sort_queries")

_INT32_MAX = 2**31 - 1
_F32 = npt.NDArray[np.float32]
_I32 = npt.NDArray[np.int32]


def method_names() -> List[str]:
    """The methods make_index accepts, in display order (flann only when it was built in)."""
    return list(_core.method_names())


def build_options(method: str) -> Dict[str, Dict[str, Any]]:
    """The build options `method` reads, by keyword: kind ("integer" or "choice"), lo and hi or
    choices, default (as text), help. From the library's method registry."""
    if method not in _BUILD_OPTIONS:
        raise Error(f"unknown method '{method}' (known: {', '.join(_BUILD_OPTIONS)})")
    return {k: dict(v) for k, v in _BUILD_OPTIONS[method].items()}


def _search_options(method: str) -> Tuple[str, ...]:
    return _SEARCH_COMMON + tuple(_SEARCH_OPTIONS.get(method, {}))


def _option_text(name: str, entry: Dict[str, Any], value: Any) -> str:
    """A keyword argument as the table's parser reads it (the range is the library's check)."""
    if entry["kind"] == "choice":
        if not isinstance(value, str):
            raise TypeError(f"{name} must be a str, got {type(value).__name__}")
        return value
    if entry["kind"] == "number":
        return repr(_float(name, value))
    return str(_int(name, value, -2**63, 2**63 - 1))


def _set_table_options(setter: Any, target: Any, method: str, table: Dict[str, Dict[str, Any]],
                       given: Dict[str, Any]) -> None:
    for name, value in given.items():
        if value is not None and name in table:
            setter(target, method, table[name]["name"], _option_text(name, table[name], value))


def _options_doc(table: Dict[str, Dict[str, Dict[str, Any]]]) -> str:
    """The keyword arguments of every method's table, for the docstrings."""
    lines = []
    for method, opts in table.items():
        for kw, o in opts.items():
            lines.append(f"      {method}: {kw} ({o['range']}, default {o['default'] or 'none'}): {o['help']}")
    return "\n".join(lines)


def _refuse_unknown(method: str, given: Dict[str, Any], accepted: Tuple[str, ...], kind: str) -> None:
    for name, value in given.items():
        if value is None or name in accepted:
            continue
        users = [m for m, opts in _BUILD_OPTIONS.items() if name in opts]
        users += [m for m in _BUILD_OPTIONS if name in _search_options(m) and m not in users]
        where = f" (only to {', '.join(users)})" if users else ""
        raise TypeError(f"{kind} '{name}' does not apply to method {method}{where}")


def _int(name: str, value: Any, lo: int = -_INT32_MAX - 1, hi: int = _INT32_MAX) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be an integer, got a bool")
    try:
        v = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}") from None
    if not lo <= v <= hi:
        raise ValueError(f"{name} = {v} is out of range: must be in [{lo}, {hi}]")
    return v


def _float(name: str, value: Any) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    return float(value)


def _xyz(array: Any, what: str) -> "npt.NDArray[np.float32]":
    """An (n, 3) array as C-contiguous float32: the array itself when it already is one (no copy),
    else one converted copy. Integer input is converted; other kinds are refused."""
    a = np.asarray(array)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{what} must be a float32 or float64 array, got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must have shape (n, 3), got {a.shape}")
    if a.dtype.kind == "f" and a.dtype.itemsize > 4:
        # A finite float64 beyond the float32 range would become inf in the cast: named, not
        # called non-finite (points) or answered with an empty row (queries).
        with np.errstate(over="ignore"):
            a32 = np.ascontiguousarray(a, dtype=np.float32)
        beyond = np.isinf(a32) & np.isfinite(a)
        if beyond.any():
            i = int(np.flatnonzero(beyond.any(axis=1))[0])
            x, y, z = (float(v) for v in a[i])
            raise ValueError(f"{what}: row {i} ({x!r}, {y!r}, {z!r}) has a coordinate beyond the float32 "
                             f"range (|x| <= {float(np.finfo(np.float32).max)!r}); the library stores float32")
        return a32
    return np.ascontiguousarray(a, dtype=np.float32)


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


class Index:
    """A built index of one method over (N, 3) points. Made by make_index() or load().

    Attributes: method, exact, size (also len()), memory_bytes, build_seconds, device (a dict as
    devices() gives), build_info (the parameters a block-hash build used), last_stats (the last
    query's stats dict, whichever thread ran it).
    """

    __slots__ = ("_impl", "last_stats")

    def __init__(self, impl: "_core.Index") -> None:
        self._impl = impl
        self.last_stats: Optional[Dict[str, Any]] = None

    @property
    def method(self) -> str:
        return self._impl.method

    @property
    def exact(self) -> bool:
        return self._impl.exact

    @property
    def size(self) -> int:
        return self._impl.size

    def __len__(self) -> int:
        return self._impl.size

    @property
    def memory_bytes(self) -> int:
        """Bytes of the structure (device memory, points included; host memory for flann)."""
        return self._impl.memory_bytes

    @property
    def build_seconds(self) -> float:
        return self._impl.build_seconds

    @property
    def device(self) -> Dict[str, Any]:
        return dict(self._impl.runtime.device)

    @property
    def build_info(self) -> Dict[str, Any]:
        """blockhash: the build parameters used (derived ones filled in) and the structure's
        figures; flann: the thread count; other methods: {}."""
        return dict(self._impl.build_info)

    def __repr__(self) -> str:
        return f"<blockhash_cl.Index {self.method} of {self.size} points on {self.device['summary']}>"

    def _search_params(self, k: int, options: Dict[str, Any]) -> "_core.SearchParams":
        """SearchParams from keyword arguments, refusing those this method does not read.
        kNN's; radius_search reads its own RadiusParams."""
        _refuse_unknown(self.method, options, _search_options(self.method), "search parameter")
        p = _core.SearchParams()
        p.k = _int("k", k, 1, MAX_K)
        if options.get("A") is not None and options.get("recall_target") is not None:
            raise ValueError("A and recall_target both given: give one (recall_target picks A)")
        if options.get("max_radius") is not None:
            p.max_radius = _float("max_radius", options["max_radius"])
        _set_table_options(_core.set_search_option, p, self.method, _SEARCH_OPTIONS[self.method], options)
        if options.get("sort_queries") is not None:
            s = options["sort_queries"]
            p.sort_queries = int(s) if isinstance(s, bool) else _int("sort_queries", s, -1, 1)
        return p

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

        queries: (n, 3) array; C-contiguous float32 is used in place, anything else is converted
        to float32 once. k: 1..MAX_K. max_radius: only neighbours within this Euclidean (not
        squared) distance. sort_queries: dispatch in Hilbert order (True/1, False/0, None: for
        large batches). The search keywords of each method's option table (A and recall_target
        exclude each other):
{search_options}

        Returns (dist2, ids): (n, k) float32 squared distances and (n, k) int32 indices into the
        points, each row ascending (FAISS's order); then counts ((n,) int32, neighbours found per
        query) if return_counts, then the stats dict if return_stats (also in last_stats): n_queries,
        nonfinite_queries, batches, compile_s, upload_s, query_s, download_s, wall_s,
        queries_per_s, and for blockhash the search options used (with recall_target: the A
        tuned and the recall it reached on the tuning sample). The GIL is released while it runs.
        """
        p = self._search_params(k, dict(search, max_radius=max_radius, sort_queries=sort_queries))
        q = _xyz(queries, "queries")
        dist2, ids, counts, stats = self._impl.query(q, p)
        self.last_stats = stats
        out: Tuple[Any, ...] = (dist2, ids)
        if return_counts:
            out += (counts,)
        if return_stats:
            out += (stats,)
        return out

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
    ) -> Tuple[Any, ...]:
        """Every indexed point within radius r of each query (scipy's query_ball_point, Open3D's
        fixed_radius_search, FAISS's range_search).

        r: the Euclidean radius (finite, >= 0); squared=True takes r as the squared radius
        (nanoflann's and FLANN's convention). A point is within when its squared distance <= r*r.
        max_results: at most this many per query, the nearest (None/0: no cap; stats count the
        truncated queries). return_sorted=False leaves each slice in the order the method found
        its points (scipy's return_sorted, Open3D's sort), sparing the sort; a capped slice still
        holds the nearest max_results. The radius keywords of each method's option table:
{radius_options}
        Exact methods return
        exactly the points within r; block hashing a subset (its recall is measured in
        docs/ACCURACY.md). A query with a NaN/Inf coordinate gets an empty slice.

        Returns (offsets, dist2, ids) in FAISS's layout: query i's results are
        dist2[offsets[i]:offsets[i+1]] (float32, SQUARED) and the same slice of ids (int32), each
        sorted by (distance, index) unless return_sorted=False; offsets is (n + 1,) int64. With return_stats, a stats dict
        too (as query's, plus results, truncated_queries and found, the (n,) counts before the
        cap). The GIL is released while it runs.
        """
        method = self.method
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
        radius = _float("r", r)
        q = _xyz(queries, "queries")
        offsets, dist2, ids, found, stats = self._impl.radius_search(q, radius, bool(squared), p)
        stats["found"] = found
        self.last_stats = stats
        out: Tuple[Any, ...] = (offsets, dist2, ids)
        if return_stats:
            out += (stats,)
        return out

    def warm_up(self, k: int = 10, **search: Any) -> float:
        """Compiles the kernel variant the search parameters need and launches it once, so that
        later query timings exclude compilation. Returns the seconds it took (0 if done before)."""
        return self._impl.warm_up(self._search_params(k, search))

    def add(self, points: Any) -> "np.ndarray":
        """Adds (n, 3) points (float32 or float64) without a fresh build; returns their ids, an
        int32 array id_bound, id_bound + 1, ... (ids are stable: never reused after a remove).
        Waits for queries in progress on this index (updates are exclusive with queries)."""
        return self._impl.insert(_xyz(points, "points"))

    def remove(self, ids: Any) -> None:
        """Removes the points of these ids (a 1-D integer array or sequence). Raises Error for an
        id never issued, already removed or given twice, and for removing every point."""
        arr = np.asarray(ids)
        if arr.ndim != 1 or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"remove: ids must be a 1-D array of integers, got shape {arr.shape} dtype {arr.dtype}")
        if arr.size and (arr.min() < -2**31 or arr.max() >= 2**31):
            raise ValueError("remove: an id is outside the int32 range")
        self._impl.remove(np.ascontiguousarray(arr, dtype=np.int32))

    @property
    def id_bound(self) -> int:
        """One past the largest id issued (the next add's first id)."""
        return self._impl.id_bound

    def contains(self, id: int) -> bool:
        """True when id was issued and not removed."""
        return bool(self._impl.contains(int(id)))

    def save(self, path: Union[str, "os.PathLike[str]"]) -> None:
        """Writes a block-hash index to a file (versioned, checksummed); load() reads it back.
        Other methods raise Error (they rebuild quickly)."""
        self._impl.save(os.fspath(path))


def make_index(method: str, points: Any, *, device: Union[None, str, Runtime] = None,
               **options: Any) -> Index:
    """Builds an index of `method` ("blockhash", "kdtree", "bruteforce", "flann"; see
    method_names()) over points, an (N, 3) array (float32 or float64; converted to float32 once
    when it is not C-contiguous float32; the index keeps its own copy, not the array).

    Build options (keyword arguments; one the method does not read raises TypeError), from the
    library's method tables (build_options() lists them with ranges and defaults):
{build_options}
    device: a spec ("P:D", "cpu", "gpu", "pocl", "nvidia:1"), a Runtime, or None for
    BHCL_DEVICE, else PoCL, else the first device. The GIL is released during the build.
    """
    if not isinstance(method, str):
        raise TypeError(f"method must be a str, got {type(method).__name__}")
    table = _BUILD_OPTIONS.get(method, {})
    _refuse_unknown(method, options, tuple(table), "build option")
    opts = _core.MethodOptions()
    _set_table_options(_core.set_build_option, opts, method, table, options)
    pts = _xyz(points, "points")
    return Index(_core.make_index(method, get_runtime(device), pts, opts))


def load(path: Union[str, "os.PathLike[str]"], points: Any, *,
         device: Union[None, str, Runtime] = None) -> Index:
    """Reads a block-hash index saved by Index.save(). points must be the (N, 3) points it was
    built from (the index refers to them by index); a file that does not match them, or is
    missing, truncated or corrupt, raises Error naming the file and what differs."""
    opts = _core.MethodOptions()
    opts.set("load-index", os.fspath(path))
    pts = _xyz(points, "points")
    return Index(_core.make_index("blockhash", get_runtime(device), pts, opts))


# The docstrings list what the option tables hold.
Index.query.__doc__ = (Index.query.__doc__ or "").replace("{search_options}", _options_doc(_SEARCH_OPTIONS))
Index.radius_search.__doc__ = (Index.radius_search.__doc__ or "").replace(
    "{radius_options}", _options_doc(_RADIUS_OPTIONS))
make_index.__doc__ = (make_index.__doc__ or "").replace("{build_options}", _options_doc(_BUILD_OPTIONS))
