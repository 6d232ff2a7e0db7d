"""
Packaging of spacerobot_planner (ament_python: colcon and pip).

``setup.py install`` (what ``colcon build`` runs) ends with two steps of its own:

- ``build_interfaces``: the nested package ``interfaces/spacerobot_planner_interfaces``
  (the PlanCapture action, ament_cmake) configured, built and installed with CMake into
  the same prefix, with its own ament index entries.  colcon does not look for packages
  inside a package's folder, so a plain ``colcon build`` of a workspace with this
  repository in ``src/`` would otherwise never build it.  ``colcon build --symlink-install``
  (``setup.py develop``) runs it too.
- ``warm_numba_cache``: it runs ``python -m spacerobot_planner.worker --warm-cache`` on the
  scenario files of ``config/`` in the installed tree, so numba's cache (``__pycache__/*.nbi``, ``*.nbc``)
  and the package's bytecode (``*.pyc``) sit next to the installed sources and the first start
  loads the kernels instead of compiling them.
"""

import filecmp
import os
import shutil
import subprocess
import sys
from glob import glob

from setuptools import Command, find_packages, setup
from setuptools.command.develop import develop
from setuptools.command.install import install

PACKAGE = "spacerobot_planner"
HERE = os.path.dirname(os.path.abspath(__file__))
#: the scenario files whose routes the install compiles (all of config/: 2-D, 3-D and 4-D grids,
#: the free-floating capture)
WARM_CONFIGS = tuple(sorted(os.path.relpath(p, HERE) for p in glob(os.path.join(HERE, "config", "*.yaml"))))
#: set to 0 to skip the cache step (the first start then compiles, ~20 s)
WARM_ENV = "SPACEROBOT_PLANNER_WARM_CACHE"
#: colcon's PYTHONPATH entries for setup.py itself (its sitecustomize moves sys.prefix)
_COLCON_ONLY = ("prefix_override", "colcon_distutils_commands")
#: the nested interface package that ``install`` builds with CMake (see build_interfaces)
IFACE = "spacerobot_planner_interfaces"
# (the real path: `colcon build --symlink-install` runs a symlink to this file in its build folder)
IFACE_SRC = os.path.join(os.path.dirname(os.path.realpath(__file__)), "interfaces", IFACE)
#: set to 0 to skip building the interface package (then build it as a package of its own)
IFACE_ENV = "SPACEROBOT_PLANNER_BUILD_INTERFACES"


class warm_numba_cache(Command):
    """
    Fill numba's cache of the installed package (the last step of ``install``).

    numba finds a function's cache in the ``__pycache__`` beside its source file and
    takes it while that file keeps its mtime and size (the index holds both; the key
    is the signature, the machine and the bytecode, no path).  ``install`` copies the
    sources with their mtimes, so this first copies the source tree's cache files
    (``make venv`` fills them) beside each installed source that is the same file, then
    runs the warm-up in the installed tree with the interpreter that runs setup.py (the
    one the executables' shebang names): it loads what was copied and compiles only
    what is missing or stale.
    Skipped with ``--root`` (a staged install such as a wheel build: the files move
    afterwards) and when ``SPACEROBOT_PLANNER_WARM_CACHE=0``.  A failure is reported
    and does not fail the install (the first start then compiles).  The cache files and the
    package's bytecode (written by the warm-up also where ``PYTHONDONTWRITEBYTECODE`` kept
    ``install_lib`` from it) are listed in the install record (colcon's ``install.log``).
    """

    description = "compile the numba kernels into the installed package's __pycache__"
    user_options = []

    def initialize_options(self):
        self.install_dir = None
        self.root = None
        self.outputs = []

    def finalize_options(self):
        self.set_undefined_options("install", ("install_lib", "install_dir"), ("root", "root"))

    def run(self):
        if self.root:
            print(f"{self.get_command_name()}: skipped (staged install under --root {self.root})")
            return
        if os.environ.get(WARM_ENV, "1") == "0":
            print(f"{self.get_command_name()}: skipped ({WARM_ENV}=0)")
            return
        install_dir = os.path.abspath(self.install_dir)
        kept = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                if p and os.path.basename(os.path.normpath(p)) not in _COLCON_ONLY]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([install_dir] + kept))
        cmd = [sys.executable, "-m", f"{PACKAGE}.worker", "--warm-cache",
               *(os.path.join(HERE, c) for c in WARM_CONFIGS)]
        copied = _copy_numba_cache(os.path.join(HERE, PACKAGE), os.path.join(install_dir, PACKAGE))
        print(f"{self.get_command_name()}: {copied} cache files copied from the source tree; compiling what "
              f"is missing in {install_dir} (up to 20 s)")
        # cwd = the install dir: `-m` puts it first on sys.path, so the installed copy is imported
        r = subprocess.run(cmd, cwd=install_dir, env=env)
        if r.returncode:
            print(f"{self.get_command_name()}: WARNING: the warm-up failed (exit {r.returncode}); "
                  "the first start will compile the kernels", file=sys.stderr)
        pkg = os.path.join(install_dir, PACKAGE)
        self.outputs = sorted(p for pattern in ("*.nb[ic]", "*.pyc")       # numba's cache, the bytecode
                              for p in glob(os.path.join(pkg, "**", "__pycache__", pattern), recursive=True))

    def get_outputs(self):
        return self.outputs

    def get_inputs(self):
        return []


def _copy_numba_cache(src_pkg, dst_pkg):
    """
    Copy numba's cache files of ``src_pkg`` to ``dst_pkg`` where the source beside them is the same.

    The same: equal bytes, size and mtime (what numba's index checks); others are left to
    the warm-up.  Returns the number of files copied.
    """
    copied = 0
    for cache in glob(os.path.join(src_pkg, "**", "__pycache__", "*.nb[ic]"), recursive=True):
        rel_dir = os.path.relpath(os.path.dirname(os.path.dirname(cache)), src_pkg)
        stem = os.path.basename(cache).split(".")[0]          # module.function-line.py311.nbi
        module = stem.split(".")[0] + ".py"
        src, dst = os.path.join(src_pkg, rel_dir, module), os.path.join(dst_pkg, rel_dir, module)
        if not (os.path.isfile(src) and os.path.isfile(dst)):
            continue
        s, d = os.stat(src), os.stat(dst)
        if (s.st_mtime, s.st_size) != (d.st_mtime, d.st_size) or not filecmp.cmp(src, dst, shallow=False):
            continue
        out_dir = os.path.join(dst_pkg, rel_dir, "__pycache__")
        os.makedirs(out_dir, exist_ok=True)
        shutil.copy2(cache, out_dir)
        copied += 1
    return copied


def _same_interface_sources(prefix):
    """Tell whether ``prefix`` holds an install of the interface package built from these sources."""
    share = os.path.join(prefix, "share", IFACE)
    sources = [os.path.join(IFACE_SRC, "package.xml")] + sorted(glob(os.path.join(IFACE_SRC, "action", "*.action")))
    for src in sources:
        installed = os.path.join(share, os.path.relpath(src, IFACE_SRC))
        if not (os.path.isfile(installed) and filecmp.cmp(src, installed, shallow=False)):
            return False
    return True


def colcon_built_interfaces(prefix):
    """
    Return the prefix where colcon built the interface package as a package of its own, or None.

    That is the case when the workspace names it (``colcon build --base-paths src/spacerobot_planner
    src/spacerobot_planner/interfaces``): colcon builds it first (colcon.pkg makes it a dependency
    of this package) and puts its prefix on AMENT_PREFIX_PATH.  Only a prefix of the same colcon
    install base (a sibling of ``prefix``, or ``prefix`` itself in a merged install) built from
    the same sources counts; an underlay's copy does not (this workspace's sources win).
    """
    prefix = os.path.realpath(prefix)
    for entry in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if not entry:
            continue
        entry = os.path.realpath(entry)
        if entry not in (prefix, os.path.join(os.path.dirname(prefix), IFACE)):
            continue
        marker = os.path.join(entry, "share", "colcon-core", "packages", IFACE)
        if os.path.isfile(marker) and _same_interface_sources(entry):
            return entry
    return None


class build_interfaces(Command):
    """
    Build and install the nested interface package with CMake (a step of ``install`` and ``develop``).

    ``interfaces/spacerobot_planner_interfaces`` is an ament_cmake package of its own, and
    colcon stops looking for packages at a package's folder (this repository's root), so
    ``colcon build`` of a workspace with this repository in ``src/`` would not build it and
    ``ros2 run spacerobot_planner planner_node`` would fail on ``import
    spacerobot_planner_interfaces``.  This does what colcon-cmake would do: CMake configure,
    build and install into this install's prefix (colcon's ``install/spacerobot_planner``), with
    the prefix path of the environment colcon runs in (the sourced underlay).  The prefix then
    holds the interface package's ament index entries, libraries and Python module; colcon's
    hooks for this package put its ``lib`` on LD_LIBRARY_PATH, its site-packages on PYTHONPATH
    and the prefix on AMENT_PREFIX_PATH, where rclpy finds the type support.  The CMake build
    folder is ``<build-base>/spacerobot_planner_interfaces`` (colcon's ``build/spacerobot_planner/build``),
    kept between builds, so a rebuild only checks it.

    Skipped with ``--root`` (a staged install such as a wheel build; ``make`` builds the
    interfaces into the virtualenv itself), when ``SPACEROBOT_PLANNER_BUILD_INTERFACES=0``, and
    when colcon built the interface package as a package of its own in this workspace
    (``--base-paths`` naming both).  A failure fails the install, with what to run instead.
    """

    description = "build and install interfaces/spacerobot_planner_interfaces (CMake) into the prefix"
    user_options = []

    def initialize_options(self):
        self.prefix = None
        self.root = None
        self.build_base = None
        self.outputs = []

    def finalize_options(self):
        self.set_undefined_options("install", ("install_data", "prefix"), ("root", "root"))
        self.set_undefined_options("build", ("build_base", "build_base"))

    def _fail(self, what, log=None):
        tail = ""
        if log and os.path.isfile(log):
            with open(log, errors="replace") as f:
                tail = "".join(f.readlines()[-40:])
        raise SystemExit(
            f"{tail}\n{self.get_command_name()}: {what}" + (f" (full log: {log})" if log else "") + "\n"
            f"This package's install builds {IFACE} (interfaces/{IFACE}, the PlanCapture action)\n"
            "with CMake.  Install its build dependencies (ament_cmake, rosidl_default_generators and the\n"
            "message packages: `rosdep install --from-paths src --ignore-src -y` in the workspace), source\n"
            "the ROS 2 setup file (e.g. `source /opt/ros/kilted/setup.bash`) and build again.")

    def run(self):
        name = self.get_command_name()
        if self.root:
            print(f"{name}: skipped (staged install under --root {self.root})")
            return
        if os.environ.get(IFACE_ENV, "1") == "0":
            print(f"{name}: skipped ({IFACE_ENV}=0)")
            return
        prefix = os.path.abspath(self.prefix)
        own = colcon_built_interfaces(prefix)
        if own:
            print(f"{name}: skipped ({IFACE} is a package of this colcon build, in {own})")
            return
        cmake = shutil.which("cmake")
        if cmake is None:
            self._fail("cmake is not on PATH")
        build_dir = os.path.abspath(os.path.join(self.build_base, IFACE))
        os.makedirs(build_dir, exist_ok=True)
        log = os.path.join(build_dir, "build_interfaces.log")
        # as the Makefile and colcon-cmake: the underlay's prefixes (AMENT_PREFIX_PATH of a sourced
        # setup file) on CMake's prefix path besides its own CMAKE_PREFIX_PATH variable
        prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
        configure = [cmake, "-S", IFACE_SRC, "-B", build_dir, "-DBUILD_TESTING=OFF",
                     f"-DCMAKE_INSTALL_PREFIX={prefix}", f"-DPython3_EXECUTABLE={sys.executable}"]
        if prefixes:
            configure.append("-DCMAKE_PREFIX_PATH=" + ";".join(prefixes))
        jobs = os.environ.get("CMAKE_BUILD_PARALLEL_LEVEL") or str(os.cpu_count() or 1)
        # the interpreter that runs setup.py first on PATH: rosidl's generators run with it
        env = dict(os.environ)
        env["PATH"] = os.pathsep.join([os.path.dirname(sys.executable), env.get("PATH", "")])
        env["PYTHONPATH"] = os.pathsep.join(p for p in env.get("PYTHONPATH", "").split(os.pathsep)
                                            if p and os.path.basename(os.path.normpath(p)) not in _COLCON_ONLY)
        steps = (("configure", configure),
                 ("build", [cmake, "--build", build_dir, "--parallel", jobs]),
                 ("install", [cmake, "--install", build_dir]))
        print(f"{name}: {IFACE} -> {prefix} (CMake, build folder {build_dir})", flush=True)
        with open(log, "w") as out:
            for step, cmd in steps:
                out.write("$ " + " ".join(cmd) + "\n")
                out.flush()
                r = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
                if r.returncode:
                    self._fail(f"CMake {step} of {IFACE} failed (exit {r.returncode})", log)
        manifest = os.path.join(build_dir, "install_manifest.txt")
        if os.path.isfile(manifest):
            with open(manifest) as f:
                self.outputs = [line.strip() for line in f if line.strip()]
        print(f"{name}: installed {len(self.outputs)} files of {IFACE}")

    def get_outputs(self):
        return self.outputs

    def get_inputs(self):
        return []


class install_with_cache(install):
    """``install``, then :class:`build_interfaces` and :class:`warm_numba_cache` (sub-commands: files recorded)."""

    sub_commands = install.sub_commands + [("build_interfaces", None), ("warm_numba_cache", None)]


class develop_with_interfaces(develop):
    """``develop`` (``colcon build --symlink-install``), then :class:`build_interfaces`."""

    def run(self):
        super().run()
        if not getattr(self, "uninstall", False):
            self.run_command("build_interfaces")


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    # colcon installs these; a pip (editable) install gets them from
    # `python -m spacerobot_planner.tools.ament_install --prefix <venv>`
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
    ],
    install_requires=["setuptools"],
    # colcon runs `colcon test` with pytest only when pytest is a declared test dependency
    extras_require={"test": ["pytest", "hypothesis"]},
    cmdclass={"install": install_with_cache, "develop": develop_with_interfaces,
              "build_interfaces": build_interfaces, "warm_numba_cache": warm_numba_cache},
    zip_safe=True,
    maintainer="spacerobot_planner maintainers",
    maintainer_email="maintainers@spacerobot-planner.invalid",
    description="Laplace-potential capture planner for a space robot, as a ROS 2 node",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "planner_node = spacerobot_planner.tools.entry:planner_node",
            "mock_arm_node = spacerobot_planner.tools.entry:mock_arm_node",
            "spacerobot-plan = spacerobot_planner.tools.entry:plan",
            "spacerobot-demo = spacerobot_planner.tools.demo:main",
        ],
    },
)
