"""What the package's two index classes share (Index in __init__.py, DistributedIndex in
_distributed.py): the attributes they forward to the extension's index (`_impl`), the conversion
of caller coordinates to the stored ones, the result tuples query and radius_search return, and the
checks of update arguments. One place, so that the two classes cannot drift apart in what an
attribute means or in the shape of a result (issue 35: the forwarding stood twice).

A subclass sets `_impl` (the extension's index: method, exact, size, id_bound, removed_count),
`_origin` (float64 (3,): stored = caller - origin), `_coords` (the _precision dict) and
`last_stats`.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np
import numpy.typing as npt

from ._checks import _relative, _xyz


def _forwarded(name: str, doc: str) -> Any:
    """A read-only attribute that is the extension's index's attribute of the same name."""
    return property(lambda self: getattr(self._impl, name), doc=doc)


class _IndexFront:
    """The attributes and result assembly both index classes have (see the module)."""

    __slots__ = ()
    _impl: Any
    _origin: np.ndarray
    _coords: Dict[str, Any]
    last_stats: Optional[Dict[str, Any]]

    method = _forwarded("method", "The method's name (method_names()).")
    exact = _forwarded("exact", "Whether the method's answers are exact.")
    size = _forwarded("size", "Live points (over all ranks for a distributed index); also len().")
    id_bound = _forwarded("id_bound", "One past the largest id issued (the next add's first id).")
    removed_count = _forwarded("removed_count", "Ids removed so far (never issued again).")

    def __len__(self) -> int:
        return int(self._impl.size)

    @property
    def coordinates(self) -> Dict[str, Any]:
        """How the caller's coordinates are stored: origin (float64 input far from 0 for its size
        is stored in float32 relative to its box's centre, computed in double precision; else 0),
        max_abs_relative, float32_step and max_rounding (the largest rounding of a stored
        coordinate, in caller units), recentred. Distances are always in caller units."""
        return dict(self._coords)

    def _to_index(self, a: Any, what: str) -> "npt.NDArray[np.float32]":
        """Caller coordinates in the index's stored ones: as they are (no copy for C-contiguous
        float32) when the origin is 0, else relative to it, computed in float64."""
        if not np.any(self._origin):
            return _xyz(a, what)
        return _relative(a, self._origin, what)

    def _knn_result(self, dist2: Any, ids: Any, counts: Any, stats: Dict[str, Any], single: bool,
                    return_counts: bool, return_stats: bool) -> Tuple[Any, ...]:
        """query's return value: (dist2, ids), then counts and stats as asked (stats also in
        last_stats, with the coordinates); one query of shape (3,) loses the first axis."""
        stats["coordinates"] = dict(self._coords)
        self.last_stats = stats
        if single:
            dist2, ids, counts = dist2[0], ids[0], counts[0]
        out: Tuple[Any, ...] = (dist2, ids)
        if return_counts:
            out += (counts,)
        if return_stats:
            out += (stats,)
        return out

    def _radius_result(self, offsets: Any, dist2: Any, ids: Any, found: Any, stats: Dict[str, Any],
                       return_stats: bool) -> Any:
        """radius_search's return value: a RadiusResult, or with return_stats a
        RadiusResultWithStats whose stats (also in last_stats) hold found and the coordinates."""
        from . import RadiusResult, RadiusResultWithStats
        stats["found"] = found
        stats["coordinates"] = dict(self._coords)
        self.last_stats = stats
        if return_stats:
            return RadiusResultWithStats(offsets, dist2, ids, stats)
        return RadiusResult(offsets, dist2, ids)


def _checked_ids(ids: Any, lo: int, hi: int, call: str) -> np.ndarray:
    """remove's ids as a numpy integer array: 1-D, of an integer dtype (or empty), every value in
    [lo, hi] (the id type's range; which ids are live is the library's check, naming the id)."""
    arr = np.asarray(ids)
    if arr.ndim != 1 or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{call}: ids must be a 1-D array of integers, got shape {arr.shape} dtype {arr.dtype}")
    if arr.size and (int(arr.min()) < lo or int(arr.max()) > hi):
        raise ValueError(f"{call}: an id is outside the range of the ids [{lo}, {hi}]")
    return arr
