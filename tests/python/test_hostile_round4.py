"""Issue 38 from Python: a damaged or crafted container of a kd-tree index raises blockhash_cl.Error
naming the file and the field (never zipfile.BadZipFile, AttributeError, TypeError), a NaN origin
is refused instead of answering every query empty, the numbers pass under a comma-decimal locale,
and select_device's digits past the integer range name no device (never 'stoul')."""

import json
import locale
import os
import subprocess
import zipfile

import numpy as np
import pytest

import blockhash_cl as bh


@pytest.fixture(scope="module")
def saved_kdtree(tmp_path_factory):
    rng = np.random.default_rng(7)
    pts = rng.random((500, 3)).astype(np.float32)
    path = str(tmp_path_factory.mktemp("container") / "kd.npz")
    index = bh.make_index("kdtree", pts)
    index.save(path)
    return pts, path, index


def _load_error(path, points=None):
    with pytest.raises(bh.Error) as e:
        bh.load(path, points)
    return str(e.value)


def test_container_truncated_or_bit_flipped_raises_error_naming_the_file(tmp_path, saved_kdtree):
    pts, path, _ = saved_kdtree
    data = open(path, "rb").read()
    bad = str(tmp_path / "bad.npz")
    cuts = [len(data) // 2, len(data) - 1, 30, 4]
    for cut in cuts:
        open(bad, "wb").write(data[:cut])
        assert bad in _load_error(bad)
    rng = np.random.default_rng(1)
    for at in rng.integers(0, len(data), 60):
        flipped = bytearray(data)
        flipped[int(at)] ^= 0x10
        open(bad, "wb").write(bytes(flipped))
        try:
            index = bh.load(bad)
        except bh.Error as e:
            assert bad in str(e)
            continue
        # A flip that survives (zip padding, a byte no field reads) answers as the saved index.
        q = pts[:20]
        assert np.array_equal(index.query(q, k=4)[1], saved_kdtree[2].query(q, k=4)[1])


def _write_container(path, **fields):
    base = dict(format=np.array("blockhash_cl.index/2"), method=np.array("kdtree"), options=np.array(json.dumps({})),
                origin=np.zeros(3), points=np.random.default_rng(2).random((50, 3)).astype(np.float32),
                removed=np.zeros(0, np.int32))
    base.update(fields)
    with open(path, "wb") as f:
        np.savez(f, **{k: v for k, v in base.items() if v is not None})


@pytest.mark.parametrize("field,value,says", [
    ("origin", np.array([np.nan, 0.0, 0.0]), "'origin'"),
    ("origin", np.zeros(2), "'origin'"),
    ("options", np.array("[1, 2]"), "'options'"),
    ("options", np.array("{not json"), "'options'"),
    ("options", np.array(json.dumps({"no_such_option": 3})), "'options'"),
    ("method", np.array(5), "'method'"),
    ("method", np.array("nosuchmethod"), "'method'"),
    ("points", np.zeros((4, 2), np.float32), "'points'"),
    ("points", np.full((4, 3), np.inf, np.float32), "'points'"),
    ("points", None, "'points'"),
    ("removed", np.array([5, 3], np.int32), "'removed'"),
    ("removed", np.array([0, 99], np.int32), "'removed'"),
    ("format", np.array(["a", "b"]), "'format'"),
])
def test_crafted_container_field_is_refused_naming_it(tmp_path, field, value, says):
    path = str(tmp_path / "crafted.npz")
    _write_container(path, **{field: value})
    message = _load_error(path)
    assert path in message and says in message, message


def test_container_declared_shape_beyond_its_bytes_allocates_nothing(tmp_path):
    # A member whose .npy header declares 2^40 rows: refused from the header, before numpy
    # would allocate the declared shape.
    path = str(tmp_path / "huge.npz")
    _write_container(path)
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    points = members["points.npy"]
    members["points.npy"] = points.replace(b"'shape': (50, 3)", b"'shape': (1099511627776, 3)")
    assert members["points.npy"] != points
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for n, d in members.items():
            z.writestr(n, d)
    message = _load_error(path)
    assert "'points'" in message and "declares shape" in message, message


def test_comma_decimal_locale_float_keywords_are_numbers(tmp_path, saved_kdtree):
    pts, _, _ = saved_kdtree
    locdir = tmp_path / "locales"
    locdir.mkdir()
    made = subprocess.run(["localedef", "-i", "de_DE", "-f", "UTF-8", str(locdir / "de_DE.UTF-8")],
                          capture_output=True).returncode
    if not (locdir / "de_DE.UTF-8" / "LC_NUMERIC").exists():
        pytest.skip(f"localedef cannot build de_DE.UTF-8 here (exit {made}; the locales package)")
    # The same calls in the C locale: the comma locale must read the numbers as the same numbers.
    c_index = bh.make_index("blockhash", pts, target_cell_points=20.5)
    c_rows = c_index.query(pts[:30], k=5, A=8.0)
    old_path = os.environ.get("LOCPATH")
    os.environ["LOCPATH"] = str(locdir)
    try:
        locale.setlocale(locale.LC_ALL, "de_DE.UTF-8")
        assert locale.localeconv()["decimal_point"] == ","
        index = bh.make_index("blockhash", pts, target_cell_points=20.5)
        r = index.query(pts[:30], k=5, A=8.0)
        assert np.array_equal(r[1], c_rows[1]) and np.array_equal(r[0], c_rows[0])
        assert index.build_info["cell_size"] == c_index.build_info["cell_size"]
        assert index.build_info["cell_size"] > 0  # a real number back through JSON (was "%.17g": "0,1..." here)
    finally:
        locale.setlocale(locale.LC_ALL, "C")
        if old_path is None:
            os.environ.pop("LOCPATH", None)
        else:
            os.environ["LOCPATH"] = old_path


def test_select_device_digits_past_the_integer_range_name_no_device():
    for spec in ("0:99999999999999999999", "99999999999999999999:0"):
        with pytest.raises(bh.Error) as e:
            bh.select_device(spec)
        assert "stoul" not in str(e.value) and spec in str(e.value)
