"""The container Index.save writes for the methods whose structure the library does not save (the
kd-tree, brute force, FLANN, ...): numpy's npz, a zip of .npy members. read_container parses one
with every field checked against the others before anything is used (issue 38: a truncated or
bit-flipped file raised zipfile.BadZipFile, crafted members AttributeError / TypeError, a NaN
origin loaded and answered every query empty). A file is either refused with one `error` naming
the file and the field, or gives the fields the saving index held.

Memory is bounded by the file's size before anything is allocated: each member must be stored
uncompressed (np.savez's way; no zip bomb expands), and its .npy header's shape must fit the
member's bytes (numpy's reader allocates the declared shape before reading).

Pure Python over numpy and the standard library, no import of the compiled module, so that the
atheris fuzz target (tests/fuzz/fuzz_container.py) loads it alone."""

import json
import math
import zipfile
from typing import Any, Dict, Optional, Tuple, Type

import numpy as np

FORMAT = "blockhash_cl.index/2"
FORMATS = ("blockhash_cl.index/1", FORMAT)
MAX_ROWS = 2**31 - 2  # the library's id range

# Each member: the dtype kinds and the number of dimensions accepted.
_MEMBERS = {
    "format": ("U", 0), "method": ("U", 0), "options": ("U", 0),
    "origin": ("f", 1), "points": ("f", 2), "removed": ("iu", 1), "points64": ("f", 2),
}
_REQUIRED = ("format", "method", "options", "origin", "points")


def _member(z: zipfile.ZipFile, name: str, path: str, error: Type[Exception]) -> np.ndarray:
    """One .npy member, its header checked against its bytes before numpy reads (allocates) it."""
    where = f"load: {path}: field '{name}'"
    try:
        info = z.getinfo(name + ".npy")
    except KeyError:
        raise error(f"{where} is missing (not a blockhash_cl index container)") from None
    if info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size:
        raise error(f"{where} is compressed (Index.save stores members uncompressed)")
    kinds, ndim = _MEMBERS[name]
    with z.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise error(f"{where} has .npy version {version}")
        read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                       (2, 0): np.lib.format.read_array_header_2_0}.get(version)
        if read_header is None:
            read_header = np.lib.format._read_array_header  # type: ignore[attr-defined]
            shape, fortran, dtype = read_header(f, version)
        else:
            shape, fortran, dtype = read_header(f)
        header_bytes = f.tell()
    if dtype.hasobject or dtype.kind not in kinds or len(shape) != ndim:
        raise error(f"{where} is a {len(shape)}-d {dtype} array, expected {ndim}-d of kind {kinds!r}")
    count = math.prod(shape)
    if count * dtype.itemsize != info.file_size - header_bytes:
        raise error(f"{where} declares shape {shape} ({count * dtype.itemsize} bytes), the member holds "
                    f"{info.file_size - header_bytes}")
    with z.open(info) as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def _text(z: zipfile.ZipFile, name: str, path: str, error: Type[Exception]) -> str:
    return str(_member(z, name, path, error)[()])


def read_container(path: str, error: Type[Exception] = ValueError) -> Tuple[str, Dict[str, Any], np.ndarray, np.ndarray,
                                                                       Optional[np.ndarray], Optional[np.ndarray]]:
    """(method, options, origin float64 (3,), points float32 (n, 3), removed int32 or None,
    points64 float64 (n, 3) or None) of a container, or `error` naming the file and the field."""
    try:
        with zipfile.ZipFile(path) as z:
            fmt = _text(z, "format", path, error)
            if fmt not in FORMATS:
                raise error(f"load: {path} has format {fmt!r}, this version reads {' and '.join(map(repr, FORMATS))}")
            names = set(z.namelist())
            fields = {n: _member(z, n, path, error) for n in ("origin", "points")}
            for n in ("removed", "points64"):
                fields[n] = _member(z, n, path, error) if n + ".npy" in names else None
            method = _text(z, "method", path, error)
            options_text = _text(z, "options", path, error)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, UnicodeDecodeError,
            NotImplementedError, RuntimeError, OverflowError, SyntaxError, TypeError, KeyError) as e:
        if isinstance(e, error):
            raise
        # The zip or .npy framing itself is damaged (a truncated or bit-flipped file).
        raise error(f"load: {path} is not a readable blockhash_cl index ({type(e).__name__}: {e})") from None
    return _checked_fields(path, error, method, options_text, fields)


def _checked_fields(path: str, error: Type[Exception], method: str, options_text: str,
                    f: Dict[str, Optional[np.ndarray]]) -> Tuple[str, Dict[str, Any], np.ndarray, np.ndarray,
                                                                 Optional[np.ndarray], Optional[np.ndarray]]:
    def bad(field: str, why: str) -> Exception:
        return error(f"load: {path}: field '{field}' {why}")

    if not method or not method.isprintable():
        raise bad("method", f"is {method!r}, not a method name")
    try:
        options = json.loads(options_text)
    except ValueError:
        raise bad("options", "is not JSON") from None
    if not isinstance(options, dict) or not all(isinstance(k, str) for k in options):
        raise bad("options", "is not an object of named options")
    origin, points = f["origin"], f["points"]
    assert origin is not None and points is not None
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise bad("origin", f"is not 3 finite numbers ({origin!r})")
    if points.shape[1:] != (3,) or not 1 <= len(points) <= MAX_ROWS:
        raise bad("points", f"has shape {points.shape}, expected (n, 3) with 1 <= n <= 2^31 - 2")
    points = np.ascontiguousarray(points, dtype=np.float32)
    if not np.all(np.isfinite(points)):
        raise bad("points", f"row {int(np.flatnonzero(~np.all(np.isfinite(points), axis=1))[0])} is not finite")
    removed = f["removed"]
    if removed is not None:
        if removed.size and (removed.min() < 0 or removed.max() >= len(points) or np.any(np.diff(removed) <= 0)):
            raise bad("removed", f"is not ascending ids of the {len(points)} rows")
        if removed.size >= len(points):
            raise bad("removed", f"removes all {len(points)} rows")
        removed = removed.astype(np.int32)
    points64 = f["points64"]
    if points64 is not None:
        if points64.shape != points.shape:
            raise bad("points64", f"has shape {points64.shape}, the points {points.shape}")
        points64 = np.array(points64, np.float64, order="C")
        if not np.all(np.isfinite(points64)):
            raise bad("points64", "holds a coordinate that is not finite")
    return method, options, np.array(origin, np.float64), points, removed, points64
