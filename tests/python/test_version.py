"""The version (issue 40, part 4): blockhash_cl.__version__, the installed distribution's metadata,
`bhcl --version` and the project() VERSION of CMakeLists.txt all say CHANGELOG.md's latest
release (its first "## [X.Y.Z]" heading below [Unreleased])."""
import os
import re
import subprocess
from importlib import metadata

import pytest

import blockhash_cl as bh

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _latest_release():
    with open(os.path.join(ROOT, "CHANGELOG.md"), encoding="utf-8") as f:
        for line in f:
            m = re.match(r"## \[(\d+\.\d+\.\d+)\]", line)
            if m:
                return m.group(1)
    pytest.fail("CHANGELOG.md has no release heading '## [X.Y.Z]'")


def test_module_and_metadata_say_the_changelogs_latest_release():
    release = _latest_release()
    assert bh.__version__ == release
    assert metadata.version("blockhash_cl") == release
    with open(os.path.join(ROOT, "CMakeLists.txt"), encoding="utf-8") as f:
        m = re.search(r"project\(blockhash_cl VERSION (\d+\.\d+\.\d+)", f.read())
    assert m and m.group(1) == release


def test_bhcl_version_says_the_changelogs_latest_release():
    """The command-line tool of the build tree (BHCL_BIN, else build/host/bhcl: .ci/run's Release
    tree, which .ci/python follows); skipped where none was built."""
    exe = os.environ.get("BHCL_BIN", os.path.join(ROOT, "build", "host", "bhcl"))
    if not os.access(exe, os.X_OK):
        pytest.skip(f"no bhcl at {exe} (build the Release tree, or set BHCL_BIN)")
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == f"bhcl {_latest_release()}", out.stdout + out.stderr
