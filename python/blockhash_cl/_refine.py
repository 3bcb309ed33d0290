"""float64 answers for float64 points (issue 40, part 2): the index searches its float32 copy of
the points, widened by the bound on what float32 storage and arithmetic can move a distance, and
each returned row is then recomputed in float64 from the caller's own points and re-sorted.

Why it is exact (for an exact search): a stored coordinate is the caller's (relative to the
index's origin, computed in float64) rounded once to float32, so it moves by at most half the
float32 spacing at its magnitude (ep for the points, eq for the query); the vector between a
query and a point moves by at most sqrt(3) (eq + ep), and the float32 distance the kernels
compute carries a few roundings more (relative, bounded by _REL here, about 30 ulp). So with
delta = sqrt(3) (eq + ep), every float32 distance d32 and the float64 distance D of the same pair
satisfy |d32 - D| <= delta + _REL max(d32, D) (the "widening" below). Hence:

* kNN: the float32 search returns kc >= k candidates; their float64 distances give U, the k-th
  smallest. A point the search did not return has d32 >= the last candidate's d32, so D >=
  lower(d32_last); where that exceeds U (or the search returned every point it could), no point
  outside the candidates can be among the k nearest in float64 and the row is final. The rows
  where it does not (near-ties at the last candidate: duplicate points) are searched again with
  twice the candidates, up to MAX_K, then by a radius search to upper(U).
* radius: the float32 search runs at upper(r), so every point within r in float64 is among its
  results; the float64 distances keep exactly those within r.

The cost (the float64 distances, the sorts, any repeated search) is in the stats: refine_s,
refine_share (of the call's wall time), refine_cpu_s and refine_cpu_share (of the process's CPU
time over the call, the device's host threads included: on a CPU shared with other work the wall
share swings with the load, the CPU share much less), refine_candidates, refine_requeried_rows,
refine_radius_rows.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np

from . import _core

_REL = 2.0 ** -19  # relative bound on the float32 distance arithmetic (about 30 ulp, generous)
_SQRT3 = float(np.sqrt(3.0))


def rounding_bound(stored: np.ndarray) -> float:
    """The largest rounding of a stored (float32) coordinate of these rows, in caller units: half
    the float32 spacing at their largest finite magnitude."""
    if stored.size == 0:
        return 0.0
    a = np.abs(stored)
    m = float(np.max(a, initial=0.0, where=np.isfinite(a)))
    return 0.5 * float(np.spacing(np.float32(m)))


def query_delta(q32: np.ndarray, point_rounding: float) -> np.ndarray:
    """Per query: sqrt(3) (eq + ep), the most float32 storage can move its distance to any point
    (eq: half the float32 spacing at the query's largest stored coordinate), times (1 + _REL),
    plus 1e-30. Non-finite queries (answered with empty rows) get eq = 0. One pass in the C++
    layer (_core.query_delta)."""
    if len(q32) == 0:
        return np.zeros(0)
    return _core.query_delta(np.ascontiguousarray(q32, np.float32), float(point_rounding), _SQRT3, _REL)


def _query_delta_numpy(q32: np.ndarray, point_rounding: float) -> np.ndarray:
    """query_delta in numpy, the definition the C++ layer's is tested against."""
    if len(q32) == 0:
        return np.zeros(0)
    with np.errstate(invalid="ignore"):
        eq = 0.5 * np.spacing(np.max(np.abs(q32), axis=1)).astype(np.float64)
    eq = np.where(np.isfinite(eq), eq, 0.0)
    return _SQRT3 * (eq + point_rounding) * (1 + _REL) + 1e-30


def upper(d: Any, delta: Any) -> Any:
    """The largest float32 distance a pair at float64 distance d can have (what a search must
    reach)."""
    return np.asarray(d, np.float64) * (1 + 2 * _REL) + delta


def lower(d32: Any, delta: Any) -> Any:
    """The smallest float64 distance a pair whose float32 distance is d32 can have."""
    return np.asarray(d32, np.float64) * (1 - 2 * _REL) - delta


def _share(part: float, rest: float) -> float:
    """part / (part + rest), 0 for nothing timed."""
    return part / (part + rest) if part + rest > 0 else 0.0


def dist2_64(q64: np.ndarray, owner: np.ndarray, p64: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Squared float64 distances (dx dx + dy dy) + dz dz of the pairs (q64[owner[j]],
    p64[ids[j]]) (the C++ layer, threads, GIL released); id -1 (missing) gives inf."""
    return _core.pair_dist2(np.ascontiguousarray(q64, np.float64), np.ascontiguousarray(owner, np.int64), p64,
                            np.ascontiguousarray(ids, np.int32))


def _refined_rows(q64: np.ndarray, p64: np.ndarray, ids: np.ndarray, k: int, limit: float, strict: bool,
                  final_test: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray, float]]) -> Tuple[np.ndarray, ...]:
    """The first k of each row of candidates by float64 (distance, id), missing (inf, -1) last,
    those beyond limit (squared; strict: at it too) missing, and each row's count of ids found
    (the C++ layer: threads, GIL released, the outputs from a reused pool). With final_test
    (the search's float32 d2, its counts, the rows' delta, max_radius or inf): a fourth output,
    whether each row is final (knn below)."""
    q = np.ascontiguousarray(q64, np.float64)
    ids = np.ascontiguousarray(ids, np.int32)
    if final_test is None:
        return _core.refine_knn(q, p64, ids, k, limit, strict)
    d2_32, counts, delta, max_radius = final_test
    return _core.refine_knn(q, p64, ids, k, limit, strict, np.ascontiguousarray(d2_32, np.float32),
                            np.ascontiguousarray(counts, np.int32), np.ascontiguousarray(delta, np.float64),
                            1 - 2 * _REL, max_radius)


def knn(search: Callable[[np.ndarray, int, Optional[float]], Tuple[np.ndarray, np.ndarray, np.ndarray, Dict[str, Any]]],
        radius: Callable[[np.ndarray, float], Tuple[np.ndarray, np.ndarray, np.ndarray]],
        q64: np.ndarray, q32: np.ndarray, p64: np.ndarray, point_rounding: float, k: int, max_k: int,
        max_radius: Optional[float], exact: bool, strict: bool = False
        ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Dict[str, Any]]:
    """The k nearest in float64. search(q32_rows, kc, max_radius) runs the float32 kNN (dist2,
    ids, counts, stats); radius(q32_rows, r) a float32 radius search (offsets, dist2, ids).
    max_radius: only neighbours within it (strict: closer than it, scipy's distance_upper_bound).
    exact False (a budgeted search): the returned rows are recomputed and re-sorted, no more.
    Returns (dist2 float64 (n, k), ids int32 (n, k), counts (n,), stats of the first search with
    the refine_* fields)."""
    n = len(q64)
    t_prep, c_prep = time.perf_counter(), time.process_time()
    delta = query_delta(q32, point_rounding)
    prep_s, prep_cpu = time.perf_counter() - t_prep, time.process_time() - c_prep
    kc = min(max_k, k + 1) if exact else k
    wide_r = None if max_radius is None else float(upper(max_radius, float(np.max(delta, initial=0.0))))
    t_search, c_search = time.perf_counter(), time.process_time()
    d2_32, ids32, counts, stats = search(q32, kc, wide_r)
    first_s, first_cpu = time.perf_counter() - t_search, time.process_time() - c_search
    t0, c0 = time.perf_counter(), time.process_time()
    searched = first_s
    # The first pass's rows become the output (no (n, k) arrays allocated and filled before);
    # the rows a later pass redoes are written over theirs.
    out_d2 = out_ids = found = None
    rows: Optional[np.ndarray] = None  # the rows this pass refines; None: all n (no copy of q64)
    requeried = 0
    radius_rows = 0
    candidates = kc
    limit = np.inf if max_radius is None else max_radius * max_radius
    while True:
        kk = min(k, ids32.shape[1])
        # Final where the float32 search returned fewer than it was asked (it found every point it
        # could) or no point it did not return can be nearer in float64 than the k-th: decided
        # per row in the C++ layer with the refinement (lower(last float32 candidate) above
        # min(k-th float64 distance, max_radius)), as the entries beyond max_radius dropped.
        final_test = None
        if exact and kk == k:
            final_test = (d2_32, counts, delta if rows is None else delta[rows],
                          np.inf if max_radius is None else float(max_radius))
        got = _refined_rows(q64 if rows is None else q64[rows], p64, ids32, kk, limit, strict, final_test)
        take_d2, take_ids, take_found = got[0], got[1], got[2]
        if rows is None:
            if kk == k:
                out_d2, out_ids, found = take_d2, take_ids, take_found
            else:  # fewer columns than k (not reached: k <= max_k, kc >= k): padded as missing
                out_d2, out_ids = np.full((n, k), np.inf), np.full((n, k), -1, np.int32)
                out_d2[:, :kk], out_ids[:, :kk], found = take_d2, take_ids, take_found
        if not exact:
            break
        if final_test is not None:
            done = got[3]
        else:  # fewer columns than k: a row is final where the search found every point it could
            done = np.asarray(counts) < ids32.shape[1]
        if rows is None:
            rows = np.arange(n)
        else:
            out_d2[rows[done], :kk], out_ids[rows[done], :kk] = take_d2[done], take_ids[done]
            found[rows[done]] = take_found[done]
        rest = np.flatnonzero(~done)
        # The rows still open: the k-th float64 distance so far (bounded by max_radius), which a
        # radius search to upper(u) below reaches past.
        u = np.sqrt(take_d2[rest, kk - 1]) if kk == k else np.full(len(rest), np.inf)
        if max_radius is not None:
            u = np.minimum(u, max_radius)
        rows = rows[rest]
        if not len(rows):
            break
        if kc < max_k:
            kc = min(max_k, 2 * kc)
            requeried += len(rows)
            t_s = time.perf_counter()
            d2_32, ids32, counts, _ = search(q32[rows], kc, wide_r)
            searched += time.perf_counter() - t_s
            candidates = max(candidates, kc)
            continue
        # MAX_K candidates and still a near-tie at the last one (many duplicate points): every
        # point within upper(u) in float32, by one radius search, refined the same way.
        radius_rows = len(rows)
        r = float(np.max(upper(u, delta[rows])))
        t_s = time.perf_counter()
        offsets, _, rids = radius(q32[rows], r)
        searched += time.perf_counter() - t_s
        owner = np.repeat(np.arange(len(rows)), np.diff(offsets))
        rd2 = dist2_64(q64[rows], owner, p64, rids)
        order = np.lexsort((rids, rd2, owner))
        owner, rd2, rids = owner[order], rd2[order], rids[order]
        rank = np.arange(len(owner)) - np.searchsorted(owner, np.arange(len(rows)))[owner]
        sel = rank < k
        if max_radius is not None:
            limit = max_radius * max_radius
            sel &= (rd2 < limit) if strict else (rd2 <= limit)
        out_d2[rows], out_ids[rows] = np.inf, -1
        out_d2[rows[owner[sel]], rank[sel]] = rd2[sel]
        out_ids[rows[owner[sel]], rank[sel]] = rids[sel]
        found[rows] = np.sum(out_ids[rows] >= 0, axis=1)
        break
    refine_s = time.perf_counter() - t0 + prep_s
    refine_cpu = time.process_time() - c0 + prep_cpu
    stats = dict(stats)
    stats.update(refined=True, refine_exact=bool(exact), refine_s=refine_s, refine_cpu_s=refine_cpu,
                 refine_cpu_share=_share(refine_cpu, first_cpu),
                 refine_share=refine_s / (first_s + refine_s) if first_s + refine_s > 0 else 0.0,
                 refine_search_s=searched - first_s, refine_candidates=int(candidates),
                 refine_requeried_rows=int(requeried), refine_radius_rows=int(radius_rows))
    return out_d2, out_ids, found, stats


def radius(search: Callable[[np.ndarray, float, int], Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Dict[str, Any]]],
           q64: np.ndarray, q32: np.ndarray, p64: np.ndarray, point_rounding: float,
           r2: np.ndarray, max_results: int, return_sorted: bool, exact: bool
           ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Dict[str, Any]]:
    """The points within sqrt(r2[i]) of each query in float64 (r2: squared radii, one per query,
    the caller's; d2 <= r2 is within). search(q32_rows, r, cap) runs the float32 radius search at
    radius r (not squared) with at most cap results per query (0: none), sorted: (offsets, dist2,
    ids, found, stats). Returns (offsets int64, dist2 float64, ids int32, found, stats)."""
    n = len(q64)
    t_prep, c_prep = time.perf_counter(), time.process_time()
    delta = query_delta(q32, point_rounding)
    prep_s, prep_cpu = time.perf_counter() - t_prep, time.process_time() - c_prep
    rq = np.sqrt(r2)
    r_search = float(np.max(upper(rq, delta), initial=0.0)) if n else 0.0
    if not exact:
        r_search = float(np.max(rq, initial=0.0))
    # A cap: the float32 search keeps a few more than asked, so that the float64 nearest are among
    # them; a capped slice whose last kept point could still be nearer than the cap-th is
    # searched again uncapped.
    cap = 0 if not max_results else max_results + max(8, max_results // 8)
    t_search, c_search = time.perf_counter(), time.process_time()
    offsets, d2_32, ids, found32, stats = search(q32, r_search, cap)
    first_s, first_cpu = time.perf_counter() - t_search, time.process_time() - c_search
    t0, c0 = time.perf_counter(), time.process_time()
    searched = 0.0
    if not cap:  # the common case: each slice filtered (and sorted) in the C++ layer
        new_offsets, d2, ids = _core.refine_radius(np.ascontiguousarray(q64, np.float64), p64,
                                                   np.ascontiguousarray(offsets, np.int64),
                                                   np.ascontiguousarray(ids, np.int32),
                                                   np.ascontiguousarray(r2, np.float64), bool(return_sorted))
        refine_s = time.perf_counter() - t0 + prep_s
        refine_cpu = time.process_time() - c0 + prep_cpu
        stats = dict(stats)
        stats["results"] = int(new_offsets[-1])
        stats.update(refined=True, refine_exact=bool(exact), refine_s=refine_s, refine_cpu_s=refine_cpu,
                 refine_cpu_share=_share(refine_cpu, first_cpu),
                     refine_share=refine_s / (first_s + refine_s) if first_s + refine_s > 0 else 0.0,
                     refine_search_s=0.0, refine_candidates=int(len(d2_32)), refine_requeried_rows=0,
                     refine_radius_rows=0)
        return new_offsets, d2, ids, np.diff(new_offsets), stats
    counts = np.diff(offsets)
    owner = np.repeat(np.arange(n), counts)
    d2 = dist2_64(q64, owner, p64, ids)
    keep = d2 <= r2[owner]
    again = np.zeros(0, np.int64)
    if cap:
        truncated = np.flatnonzero(np.asarray(found32) > counts)
        if len(truncated) and exact:
            # The max_results-th float64 distance among the kept, per truncated row, against the
            # last float32 candidate's lower bound.
            ends = offsets[truncated + 1] - 1
            kept_d2 = np.where(keep, d2, np.inf)
            part = [np.partition(kept_d2[offsets[i]:offsets[i + 1]], max_results - 1)[max_results - 1]
                    for i in truncated]
            u = np.sqrt(np.asarray(part, np.float64))
            low = lower(np.sqrt(d2_32[ends].astype(np.float64)), delta[truncated])
            again = truncated[~(low > u)]
    if len(again):
        t_s = time.perf_counter()
        o2, _, i2, _, _ = search(q32[again], r_search, 0)
        searched = time.perf_counter() - t_s
        # Replace those rows' results with the uncapped ones.
        drop = np.isin(owner, again)
        own2 = again[np.repeat(np.arange(len(again)), np.diff(o2))]
        d2b = dist2_64(q64, own2, p64, i2)
        owner = np.concatenate([owner[~drop], own2])
        d2 = np.concatenate([d2[~drop], d2b])
        ids = np.concatenate([ids[~drop], i2])
        keep = d2 <= r2[owner]
    owner, d2, ids = owner[keep], d2[keep], ids[keep]
    found = np.bincount(owner, minlength=n).astype(np.int64)
    if return_sorted or cap or len(again):
        order = np.lexsort((ids, d2, owner))
    else:
        order = np.argsort(owner, kind="stable")  # the method's order within each slice
    owner, d2, ids = owner[order], d2[order], ids[order]
    if max_results:
        starts = np.concatenate([[0], np.cumsum(found)[:-1]]) if n else np.zeros(0, np.int64)
        rank = np.arange(len(owner)) - starts[owner]
        sel = rank < max_results
        owner, d2, ids = owner[sel], d2[sel], ids[sel]
        # found: what lies within r in float64 (the truncated rows' count from the float32 search,
        # which saw them all, less what float64 moved outside among the points it returned).
        found = np.where(np.asarray(found32) > counts, np.asarray(found32), found)
    kept = np.bincount(owner, minlength=n)
    new_offsets = np.zeros(n + 1, np.int64)
    np.cumsum(kept, out=new_offsets[1:])
    refine_s = time.perf_counter() - t0 + prep_s
    refine_cpu = time.process_time() - c0 + prep_cpu
    stats = dict(stats)
    stats["results"] = int(new_offsets[-1])
    if max_results:
        stats["truncated_queries"] = int(np.sum(found > max_results))
    stats.update(refined=True, refine_exact=bool(exact), refine_s=refine_s, refine_cpu_s=refine_cpu,
                 refine_cpu_share=_share(refine_cpu, first_cpu),
                 refine_share=refine_s / (first_s + refine_s) if first_s + refine_s > 0 else 0.0,
                 refine_search_s=searched, refine_candidates=int(len(d2_32)),
                 refine_requeried_rows=int(len(again)), refine_radius_rows=0)
    return new_offsets, d2, ids.astype(np.int32), found, stats
