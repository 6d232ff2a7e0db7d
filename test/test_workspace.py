"""
The repository in a colcon workspace: a plain ``colcon build`` builds all that ``ros2 run`` needs.

colcon stops looking for packages at a package's folder, so in ``<ws>/src/spacerobot_planner``
it finds only ``spacerobot_planner``, never ``interfaces/spacerobot_planner_interfaces``;
setup.py's install builds that one with CMake into the same prefix (``build_interfaces``).
The underlay is this virtualenv (the ROS 2 wheels' prefix), as a user who sourced the ROS
setup file would have it: AMENT_PREFIX_PATH, CMAKE_PREFIX_PATH and PATH name it.

The rosdep side: package.xml declares every third-party module the package imports.
"""

import ast
import json
import os
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = "spacerobot_planner"
IFACE = "spacerobot_planner_interfaces"
#: colcon from the interpreter that runs the tests (its setup.py runs with it, as `make` would have it)
COLCON = [sys.executable, "-c", "import sys; from colcon_core.command import main; sys.exit(main())"]

# run in the built workspace's environment: the interface package imported and its type
# support loaded (an action server and client of PlanCapture), and where each came from
_IFACE_CHECK = r"""
import json
import rclpy
from rclpy.action import ActionClient, ActionServer
from ament_index_python.packages import get_package_prefix
import spacerobot_planner, spacerobot_planner_interfaces
from spacerobot_planner_interfaces.action import PlanCapture
rclpy.init()
node = rclpy.create_node("workspace_check")
server = ActionServer(node, PlanCapture, "plan_capture_check", lambda goal: PlanCapture.Result())
client = ActionClient(node, PlanCapture, "plan_capture_check")
print(json.dumps({"iface": spacerobot_planner_interfaces.__file__, "pkg": spacerobot_planner.__file__,
                  "iface_prefix": get_package_prefix("spacerobot_planner_interfaces"),
                  "pkg_prefix": get_package_prefix("spacerobot_planner")}))
client.destroy()
server.destroy()
node.destroy_node()
rclpy.shutdown()
"""


def _need_colcon():
    try:
        import colcon_core  # noqa: F401
    except ImportError:
        if "colcon-common-extensions" in (ROOT / "requirements.txt").read_text():
            pytest.fail("requirements.txt names colcon-common-extensions but it is not installed: run `make venv`")
        pytest.skip("colcon is not installed (colcon-common-extensions in requirements.txt)")


def _copy_repository(dest: Path):
    """Copy what a clone of the working tree holds (tracked and untracked files git does not ignore)."""
    r = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                       capture_output=True, timeout=60)
    if r.returncode == 0:
        for name in r.stdout.decode().split("\0"):
            src = ROOT / name
            if name and src.is_file():
                (dest / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dest / name)
    else:  # not a git checkout (an exported tree): everything but what a build or a venv leaves
        shutil.copytree(ROOT, dest, ignore=shutil.ignore_patterns(
            ".venv", ".git", "build", "install", "log", "out", "__pycache__", "*.egg-info", ".pytest_cache",
            ".hypothesis", "*.nbi", "*.nbc"))


def _underlay_env(tmp_path: Path) -> dict:
    """Return the environment of a user who sourced the underlay (this virtualenv), not a workspace."""
    venv = Path(sys.prefix)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COLCON_", "AMENT_", "CMAKE_"))}
    env.pop("PYTHONPATH", None)
    env.update(AMENT_PREFIX_PATH=str(venv), CMAKE_PREFIX_PATH=str(venv),
               PATH=os.pathsep.join([str(venv / "bin"), os.environ.get("PATH", "")]),
               # no user defaults (~/.colcon); two CMake jobs on the shared 2-core machine
               COLCON_HOME=str(tmp_path / "colcon_home"), CMAKE_BUILD_PARALLEL_LEVEL="2",
               # numba's cache step is test_install's: here it would add ~20 s
               SPACEROBOT_PLANNER_WARM_CACHE="0")
    return env


@pytest.mark.slow
def test_plain_colcon_build_of_a_clone_in_src_runs(tmp_path):
    """
    Check a plain ``colcon build`` of ``<ws>/src/spacerobot_planner``.

    The build finds the one package, and its install holds the interface package: in the
    workspace's environment (``install/setup.sh``) PlanCapture imports from the workspace and
    its type support loads, and the installed ``planner_node`` starts (it refuses a bad
    parameter with its reason, after importing everything the node needs).
    """
    _need_colcon()
    ws = tmp_path / "ws"
    src = ws / "src" / PKG
    src.mkdir(parents=True)
    _copy_repository(src)
    env = _underlay_env(tmp_path)

    r = subprocess.run(COLCON + ["list", "--names-only"], cwd=ws, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [PKG], "colcon is expected to find only the top-level package:\n" + r.stdout

    t0 = time.monotonic()
    r = subprocess.run(COLCON + ["build"], cwd=ws, env=env, capture_output=True, text=True, timeout=900)
    build_s = time.monotonic() - t0
    print(f"colcon build: {build_s:.1f} s")
    log = (ws / "log/latest_build" / PKG / "stdout_stderr.log")
    log_text = log.read_text() if log.is_file() else ""
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:] + log_text[-5000:]
    assert f"build_interfaces: {IFACE} -> {ws / 'install' / PKG}" in log_text, log_text[-3000:]
    prefix = ws / "install" / PKG
    assert (prefix / "share/ament_index/resource_index/packages" / IFACE).is_file()
    assert (prefix / "share/ament_index/resource_index/rosidl_interfaces" / IFACE).is_file()

    def in_workspace(cmd, timeout=120):
        # as a shell that sourced the workspace's setup file
        return subprocess.run(["sh", "-c", '. install/setup.sh && exec "$@"', "sh", *cmd], cwd=ws, env=env,
                              capture_output=True, text=True, timeout=timeout)

    r = in_workspace(["python", "-c", _IFACE_CHECK])
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    where = json.loads(r.stdout.strip().splitlines()[-1])
    assert Path(where["iface"]).is_relative_to(prefix), where
    assert Path(where["pkg"]).is_relative_to(prefix), where
    assert Path(where["iface_prefix"]) == prefix and Path(where["pkg_prefix"]) == prefix, where

    # `ros2 run spacerobot_planner planner_node`: the package's prefix from the ament index, then
    # lib/spacerobot_planner/planner_node; a refused parameter ends it right after the imports
    exe = prefix / "lib" / PKG / "planner_node"
    assert exe.read_text().splitlines()[0] == f"#!{sys.executable}"
    r = in_workspace([str(exe), "--ros-args", "-p", "safety_margin_m:=-1.0"])
    out = r.stdout + r.stderr
    assert "No module named" not in out, out[-3000:]
    assert r.returncode != 0 and "safety_margin_m" in out, out[-3000:]

    # a workspace that names the nested package too builds it first (colcon.pkg's dependency)
    # and this package's install then leaves it alone (setup.py, colcon_built_interfaces)
    r = subprocess.run(COLCON + ["list", "--names-only", "--topological-order", "--base-paths", f"src/{PKG}",
                                 f"src/{PKG}/interfaces"], cwd=ws, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [IFACE, PKG], r.stdout


def test_a_broken_interface_fails_the_install_with_what_to_do(tmp_path):
    """An interface package that does not build fails ``setup.py install`` early, saying what to run."""
    src = tmp_path / "src"
    src.mkdir()
    _copy_repository(src)
    action = next((src / "interfaces" / IFACE / "action").glob("*.action"))
    action.write_text("not_a_type broken_field\n---\n---\n")
    env = _underlay_env(tmp_path)
    cmd = [sys.executable, "setup.py", "egg_info", "--egg-base", str(tmp_path), "build", "--build-base",
           str(tmp_path / "build"), "install", "--prefix", str(tmp_path / "prefix"),
           "--single-version-externally-managed", "--record", str(tmp_path / "install.log")]
    r = subprocess.run(cmd, cwd=src, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode != 0
    assert f"CMake configure of {IFACE} failed" in r.stderr, r.stdout[-2000:] + r.stderr[-3000:]
    assert "rosdep install --from-paths src --ignore-src" in r.stderr
    assert "warm_numba_cache" not in r.stdout


# third-party modules the package imports and their rosdep keys (package.xml); llvmlite is numba's own
# dependency, installed with it (jit_cache reads numba's cached kernels with it)
_ROSDEP_KEYS = {"numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml",
                "matplotlib": "python3-matplotlib", "numba": "python3-numba", "llvmlite": "python3-numba",
                "dask": "python3-dask", "distributed": "python3-distributed", "pyarrow": "python3-pyarrow"}
#: imported only by the benchmarks, declared as test dependencies
_TEST_ONLY = {"toppra": "python3-toppra-pip", "ompl": "python3-ompl-pip"}


def test_package_xml_declares_every_imported_module():
    """
    Check package.xml against the package's imports (what rosdep installs).

    Every module from outside the standard library that ``spacerobot_planner`` imports is a
    run-time dependency (a ROS package of the same name, or the rosdep key of a Python package),
    and the nested interface package is not one (rosdep could not resolve it: colcon.pkg says it).
    """
    root = ET.parse(ROOT / "package.xml").getroot()
    run = {e.text.strip() for e in root if e.tag in ("exec_depend", "depend")}
    test = {e.text.strip() for e in root if e.tag in ("test_depend", "depend")}
    imported = {}
    for path in sorted((ROOT / PKG).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top not in (PKG, "__future__"):
                    imported.setdefault(top, path.relative_to(ROOT))
    assert "numba" in imported  # the check sees the package's imports
    missing = []
    for module, path in sorted(imported.items()):
        if module in _TEST_ONLY:
            assert path.parts[:2] == (PKG, "bench"), f"{module} is imported outside the benchmarks, by {path}"
            if _TEST_ONLY[module] not in test:
                missing.append(f"{_TEST_ONLY[module]} (test_depend; {module}, {path})")
        elif module == IFACE:
            assert IFACE not in run
        elif _ROSDEP_KEYS.get(module, module) not in run:
            missing.append(f"{_ROSDEP_KEYS.get(module, module)} ({module}, imported by {path})")
    assert not missing, "package.xml does not declare: " + ", ".join(missing)
