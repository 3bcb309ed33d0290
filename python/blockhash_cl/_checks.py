"""The option tables of the library's methods as keyword arguments, and the checks of the arrays
and values the public functions take (blockhash_cl/__init__.py re-exports what it uses)."""
from __future__ import annotations

import operator
from typing import Any, Dict, List, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import _core
from ._core import Error

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


def _option_text(name: str, entry: Dict[str, Any], value: Any) -> Union[str, int, float]:
    """A keyword argument as the table's parser reads it (the range is the library's check).
    Numbers cross to the library as numbers (it writes and reads their text locale-free): text
    made here would follow no locale either, but one conversion place is what stays true."""
    if entry["kind"] == "choice":
        if not isinstance(value, str):
            raise TypeError(f"{name} must be a str, got {type(value).__name__}")
        return value
    if entry["kind"] == "number":
        return _float(name, value)
    return _int(name, value, -2**63, 2**63 - 1)


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
        # The same method reads it, in the other call: say where it goes instead of listing the
        # method itself as the one it applies to ("A does not apply to blockhash (only to
        # blockhash)" for make_index("blockhash", P, A=8)).
        if kind == "build option" and (name in _search_options(method) or name in _RADIUS_OPTIONS.get(method, {})):
            raise TypeError(f"'{name}' is a search parameter of method {method}, not a build option: "
                            f"pass it to query() or radius_search(), not make_index()")
        if kind == "search parameter" and name in _BUILD_OPTIONS.get(method, {}):
            raise TypeError(f"'{name}' is a build option of method {method}, not a search parameter: "
                            f"pass it to make_index()")
        build_users = [m for m, opts in _BUILD_OPTIONS.items() if name in opts]
        search_users = [m for m in _BUILD_OPTIONS if name in _search_options(m) or name in _RADIUS_OPTIONS.get(m, {})]
        where = []
        if build_users:
            where.append(f"a build option of {', '.join(build_users)}")
        if search_users:
            where.append(f"a search parameter of {', '.join(search_users)}")
        tail = f" (it is {' and '.join(where)})" if where else ""
        raise TypeError(f"{kind} '{name}' does not apply to method {method}{tail}")


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


def _checked(array: Any, what: str, single_ok: bool = False) -> Tuple[np.ndarray, bool]:
    """The array as numpy, its kind and shape checked: (n, 3), or (3,) for one query where
    single_ok (returned as (1, 3) with True)."""
    a = np.asarray(array)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{what} must be a float32 or float64 array, got dtype {a.dtype}")
    if single_ok and a.shape == (3,):
        return a.reshape(1, 3), True
    if a.ndim != 2 or a.shape[1] != 3:
        shapes = "(n, 3) or (3,)" if single_ok else "(n, 3)"
        raise ValueError(f"{what} must have shape {shapes}, got {a.shape}")
    return a, False


def _origin_for(a: np.ndarray) -> np.ndarray:
    """The origin float64 input is stored relative to: the centre of the finite coordinates'
    bounding box, computed in float64 and rounded to a float32 value (exact in either precision),
    where re-centring gains precision, i.e. where the largest |coordinate| is more than 4 times
    the largest |coordinate - centre| (two bits or more; a box far from 0 for its size:
    georeferenced data, UTM at 4.3e6 m). Elsewhere (a box around 0, float32 data cast up) the origin is 0, so that such input
    gives the float32 answer bit for bit. float32 and integer input: always 0. Non-finite
    coordinates are left to the library, which names the first such point."""
    zero = np.zeros(3, np.float64)
    if a.dtype.kind != "f" or a.dtype.itemsize <= 4 or a.size == 0:
        return zero
    fin = np.where(np.isfinite(a), a, np.nan).astype(np.float64)
    with np.errstate(invalid="ignore"):
        lo, hi = np.nanmin(fin, axis=0), np.nanmax(fin, axis=0)
    return _origin_from_box(lo, hi)


def _origin_from_box(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """_origin_for's rule on a box of finite float64 coordinates (lo, hi): its centre rounded to
    float32 where the box is more than 4 times farther from 0 than its own half-size, else 0. The
    distributed index applies it to the box of every rank's points."""
    zero = np.zeros(3, np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return zero
    with np.errstate(over="ignore"):
        c = (0.5 * lo + 0.5 * hi).astype(np.float32).astype(np.float64)
    if not np.all(np.isfinite(c)):
        return zero  # beyond the float32 range: _xyz names the row
    far = max(float(np.max(np.abs(lo))), float(np.max(np.abs(hi))))
    near = max(float(np.max(np.abs(lo - c))), float(np.max(np.abs(hi - c))))
    return c if far > 4.0 * near else zero


def _precision(origin: np.ndarray, extent: float) -> Dict[str, Any]:
    """What float32 storage leaves of the caller's coordinates: the origin they are relative to
    and the largest rounding of a stored coordinate (half the float32 spacing at the largest
    relative |coordinate|), in caller units."""
    step = float(np.spacing(np.float32(extent))) if np.isfinite(extent) else float("inf")
    return {"origin": [float(v) for v in origin], "max_abs_relative": float(extent),
            "float32_step": step, "max_rounding": 0.5 * step, "recentred": bool(np.any(origin != 0))}


def _relative(a: np.ndarray, origin: np.ndarray, what: str) -> "npt.NDArray[np.float32]":
    """a - origin computed in float64, then rounded once to C-contiguous float32: the coordinates
    the index stores and answers in (distances are differences, so they stay in caller units)."""
    with np.errstate(invalid="ignore", over="ignore"):
        rel = np.asarray(a, dtype=np.float64) - origin
    return _xyz(rel, what)


def _xyz(array: Any, what: str) -> "npt.NDArray[np.float32]":
    """An (n, 3) array as C-contiguous float32: the array itself when it already is one (no copy),
    else one converted copy. Integer input is converted; other kinds are refused."""
    a, _ = _checked(array, what)
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


def _own_copy(pts: np.ndarray, given: Any) -> np.ndarray:
    """The index's host copy of its stored points: `pts` itself when it is already a private
    conversion, else a copy (the caller's array may change after the build). Read-only."""
    if isinstance(given, np.ndarray) and np.shares_memory(pts, given):
        pts = pts.copy()
    pts.flags.writeable = False
    return pts


_MAX_POINTS = 2**31 - 2  # one index's ids are int32 (the library's limit, knn.cpp)


def _check_count(a: np.ndarray, method: str) -> None:
    """Refuses a point set one index cannot hold before anything is converted or allocated (a
    broadcast view of 2^31 rows costs nothing until it is copied)."""
    if a.shape[0] > _MAX_POINTS:
        raise Error(f"{method}: N = {a.shape[0]} points exceeds one index's int32 id range "
                    f"(N <= 2^31 - 2 = {_MAX_POINTS}); nothing was allocated")
