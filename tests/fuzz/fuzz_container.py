"""atheris (libFuzzer for Python) target: the container Index.save writes for the methods whose
structure the library does not save (the kd-tree, brute force, FLANN: an npz of the method, its
build options and its points) must be read by _container.read_container or refused with the
error class it is given, never another exception (issue 38: zipfile.BadZipFile, AttributeError,
TypeError), and what it accepts must be consistent: (n, 3) finite float32 points, a finite
origin, removed ids ascending inside the rows, a float64 copy of the points' shape.

Loads _container.py by its path (no compiled module needed). Usage, as .ci/fuzz runs it:
  python3 tests/fuzz/fuzz_container.py -max_total_time=20 CORPUS_DIR"""

import importlib.util
import os
import sys
import tempfile

import atheris

with atheris.instrument_imports():
    import numpy as np

_path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "python", "blockhash_cl", "_container.py")
_spec = importlib.util.spec_from_file_location("bhcl_container", _path)
container = importlib.util.module_from_spec(_spec)
assert _spec.loader is not None
_spec.loader.exec_module(container)  # instrumented below with atheris.instrument_func
container.read_container = atheris.instrument_func(container.read_container)
container._member = atheris.instrument_func(container._member)
container._checked_fields = atheris.instrument_func(container._checked_fields)


class Refused(Exception):
    """The one exception a refusal may raise (load() passes blockhash_cl.Error)."""


# In BHCL_FUZZ_TMPDIR (.ci/fuzz: a folder of the fuzz build it empties after the run; libFuzzer's
# exit at -max_total_time skips Python's atexit) or the system's temporary folder.
_fd, _file = tempfile.mkstemp(suffix=".npz", prefix="bhcl_fuzz_", dir=os.environ.get("BHCL_FUZZ_TMPDIR") or None)
os.close(_fd)


def one_input(data: bytes) -> None:
    with open(_file, "wb") as f:
        f.write(data)
    try:
        method, options, origin, points, removed, points64 = container.read_container(_file, Refused)
    except Refused:
        return
    assert isinstance(method, str) and method and isinstance(options, dict)
    assert origin.shape == (3,) and np.all(np.isfinite(origin))
    assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3 and len(points) >= 1
    assert np.all(np.isfinite(points))
    if removed is not None:
        assert removed.ndim == 1 and removed.size < len(points)
        assert removed.size == 0 or (removed.min() >= 0 and removed.max() < len(points) and np.all(np.diff(removed) > 0))
    if points64 is not None:
        assert points64.shape == points.shape and np.all(np.isfinite(points64))


def main() -> None:
    atheris.Setup(sys.argv, one_input)
    try:
        atheris.Fuzz()
    finally:
        os.unlink(_file)


if __name__ == "__main__":
    main()
