"""
numba's cache goes where it can be written (``jit_cache``), so a read-only install still runs.

- numba's own places (the package's ``__pycache__``, the user's cache directory) hold where
  either can be written, and so does a user's ``NUMBA_CACHE_DIR``;
- where neither can, a directory of the temporary directory private to this user, reused;
  never one that someone else could have made or can write, nor a link;
- with no temporary directory either, nothing is set (numba says what is wrong);
- end to end, where this test may make a private mount namespace (root): a copy of the package
  on a read-only mount, imported by a process whose home cannot be written, defines and runs a
  kernel, and numba's cache file lands in the temporary directory (before the change the
  import itself raised numba's "no locator available"); with the install's own cache in the
  copy's ``__pycache__``, the kernel is loaded from it, not compiled (numba's compile events).

A process of the package's own sets numba's target up without SciPy's BLAS check
(``start_numba_target``): a fresh process plans the paper's 2-DOF scene without importing it, to
the same path as this process, and a kernel of its own that uses ``np.dot`` afterwards still
runs (and imports it then).

A directory "that cannot be written" is one below a regular file: no one can make it, root
included.
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from spacerobot_planner import jit_cache

PACKAGE = Path(jit_cache.__file__).resolve().parent


@pytest.fixture
def places(tmp_path, monkeypatch):
    """Return writable places and places below a file (no one can make them); NUMBA_CACHE_DIR unset."""
    import numba.core.config as config
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(config, "CACHE_DIR", "")        # numba imported here: its config is what is set
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    return {"ok_pkg": str(tmp_path / "pkg"), "ok_user": str(tmp_path / "user"), "temp": str(tmp_path / "tmp"),
            "no_pkg": str(blocker / "pkg"), "no_user": str(blocker / "user"), "no_temp": str(blocker / "tmp")}


def _chosen():
    """Return the cache directory numba was pointed at (its config: numba is imported in this process)."""
    import numba.core.config as config
    assert "NUMBA_CACHE_DIR" not in os.environ            # the environment is left alone once numba is imported
    return config.CACHE_DIR or None


def _private(path: str) -> bool:
    st = os.lstat(path)
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and not st.st_mode & 0o077


def test_numbas_own_places_hold_where_either_is_writable(places):
    os.makedirs(places["temp"])
    assert jit_cache.ensure_writable_cache(places["ok_pkg"], places["no_user"], places["temp"]) is None
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["ok_user"], places["temp"]) is None
    assert _chosen() is None
    assert os.listdir(places["temp"]) == []


def test_a_users_choice_holds(places, monkeypatch):
    import numba.core.config as config
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/somewhere/chosen")
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"]) is None
    assert os.environ["NUMBA_CACHE_DIR"] == "/somewhere/chosen" and config.CACHE_DIR == ""
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr(config, "CACHE_DIR", "/set/in/code")
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"]) is None
    assert config.CACHE_DIR == "/set/in/code" and "NUMBA_CACHE_DIR" not in os.environ


def test_a_read_only_install_without_a_home_gets_a_private_temporary_cache(places, monkeypatch):
    os.makedirs(places["temp"])
    got = jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"])
    assert got == os.path.join(places["temp"], f"spacerobot_planner-numba-{os.getuid()}")
    assert _chosen() == got and _private(got)
    # the next process finds the same directory: the kernels compiled once
    import numba.core.config as config
    monkeypatch.setattr(config, "CACHE_DIR", "")
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"]) == got


@pytest.mark.parametrize("planted", ["open to all", "a link"])
def test_a_temporary_cache_someone_else_could_write_is_not_taken(places, planted, tmp_path):
    os.makedirs(places["temp"])
    name = os.path.join(places["temp"], f"spacerobot_planner-numba-{os.getuid()}")
    if planted == "open to all":
        os.mkdir(name)
        os.chmod(name, 0o777)
    else:
        os.mkdir(tmp_path / "elsewhere", 0o700)
        os.symlink(tmp_path / "elsewhere", name)
    got = jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"])
    assert got is not None and got != name
    assert os.path.dirname(got) == places["temp"] and _private(got)
    assert _chosen() == got


def test_with_no_temporary_directory_nothing_is_set(places):
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["no_temp"]) is None
    assert _chosen() is None


_READ_ONLY_RUN = r"""
set -e
mount --bind "$SRC" "$SRC"
mount -o remount,bind,ro "$SRC"
if touch "$SRC/spacerobot_planner/probe" 2>/dev/null; then echo "still writable"; exit 3; fi
exec "$PY" -c '
import glob, os, sys
from numba.core.event import install_recorder
import spacerobot_planner
assert spacerobot_planner.__file__.startswith(os.environ["SRC"]), spacerobot_planner.__file__
from spacerobot_planner.joint_space import wrap_angle_scalar_rad, wrap_angle_rad
import numpy as np
with install_recorder("numba:compile") as compiled:
    assert abs(wrap_angle_scalar_rad(7.0) - (7.0 - 2 * 3.141592653589793)) < 1e-12
    assert abs(wrap_angle_rad(np.array([7.0]))[0] - (7.0 - 2 * 3.141592653589793)) < 1e-12
import numba
where = numba.config.CACHE_DIR
print(where, len(glob.glob(os.path.join(where, "**", "*.nbi"), recursive=True)), len(compiled.buffer))
'
"""


def _warm_package_cache():
    """Fill this tree's own cache of the two kernels the end-to-end test calls (as an install does)."""
    import numpy as np
    from spacerobot_planner.joint_space import wrap_angle_rad, wrap_angle_scalar_rad
    wrap_angle_scalar_rad(1.0)
    wrap_angle_rad(np.array([1.0]))


@pytest.mark.parametrize("with_cache", [False, True], ids=["no cache in the install", "the install's cache"])
def test_a_read_only_install_with_no_home_runs_its_kernels(tmp_path, with_cache):
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare (a private mount namespace for a read-only mount)")
    src = tmp_path / "src"
    if with_cache:
        _warm_package_cache()
        shutil.copytree(PACKAGE, src / "spacerobot_planner")
    else:
        shutil.copytree(PACKAGE, src / "spacerobot_planner", ignore=shutil.ignore_patterns("__pycache__"))
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_CACHE_DIR", "XDG_CACHE_HOME"))}
    env.update(SRC=str(src), PY=sys.executable, PYTHONPATH=str(src), HOME=str(blocker / "home"), TMPDIR=str(temp),
               PYTHONDONTWRITEBYTECODE="1")
    out = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", _READ_ONLY_RUN],
                         capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    if out.returncode != 0 and "unshare" in out.stderr and "Operation not permitted" in out.stderr:
        pytest.skip(f"no private mount namespace here: {out.stderr.strip()}")
    assert out.returncode == 0, out.stdout + out.stderr
    where, files, compiled = out.stdout.split()
    assert where == str(temp / f"spacerobot_planner-numba-{os.getuid()}")
    assert int(files) >= 1                                   # numba's cache is there
    if with_cache:
        assert int(compiled) == 0, "the install's cache was not loaded: the kernels were compiled again"
    else:
        assert int(compiled) >= 2


_TARGET_RUN = r"""
import json, sys
from spacerobot_planner.jit_cache import start_numba_target
first, again = start_numba_target(), start_numba_target()
import numpy as np
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
sc = load_scenario(sys.argv[1])
res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
blas_after_plan = "scipy.linalg.cython_blas" in sys.modules
import numba

@numba.njit
def dot(a, b):
    return np.dot(a, b)

v = np.arange(5.0)
print(json.dumps({"first": first, "again": again, "ok": res.ok, "path": res.path_rad.tolist(),
                  "blas_after_plan": blas_after_plan, "dot": float(dot(v, v)),
                  "blas_after_dot": "scipy.linalg.cython_blas" in sys.modules}))
"""


def test_a_process_of_its_own_plans_without_scipys_blas_and_np_dot_still_runs(paper_scenario):
    import json
    import numpy as np
    from spacerobot_planner.planner import Planner
    config = PACKAGE.parent / "config" / "paper_2dof.yaml"
    out = subprocess.run([sys.executable, "-c", _TARGET_RUN, str(config)], capture_output=True, text=True,
                         timeout=600, cwd=PACKAGE.parent)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert (got["first"], got["again"], got["ok"]) == (True, False, True)
    assert not got["blas_after_plan"]                       # the plan never needed it
    assert got["dot"] == 30.0 and got["blas_after_dot"]     # np.dot in a kernel: imported then, and right
    sc = paper_scenario(2)
    here = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert np.array_equal(np.array(got["path"]), here.path_rad)
