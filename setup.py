"""
Packaging of spacerobot_planner (ament_python: colcon and pip).

``setup.py install`` (what ``colcon build`` runs) ends with ``warm_numba_cache``: it runs
``python -m spacerobot_planner.worker --warm-cache`` on the paper scenes in the installed
tree, so numba's cache (``__pycache__/*.nbi``, ``*.nbc``) sits next to the installed
sources and the first start loads the kernels instead of compiling them.
"""

import os
import subprocess
import sys
from glob import glob

from setuptools import Command, find_packages, setup
from setuptools.command.install import install

PACKAGE = "spacerobot_planner"
HERE = os.path.dirname(os.path.abspath(__file__))
#: the scenes whose default route the install compiles (both paper scenes)
WARM_CONFIGS = ("config/paper_3dof.yaml", "config/paper_2dof.yaml")
#: set to 0 to skip the cache step (the first start then compiles, ~20 s)
WARM_ENV = "SPACEROBOT_PLANNER_WARM_CACHE"
#: colcon's PYTHONPATH entries for setup.py itself (its sitecustomize moves sys.prefix)
_COLCON_ONLY = ("prefix_override", "colcon_distutils_commands")


class warm_numba_cache(Command):
    """
    Fill numba's cache of the installed package (the last step of ``install``).

    numba keys its cache on the source file's path (the index sits in the source's
    ``__pycache__``) and its mtime and size, so a cache built in the source tree is
    not used by an installed copy: this builds it in the installed tree, with the
    interpreter that runs setup.py (the one the executables' shebang names).
    Skipped with ``--root`` (a staged install such as a wheel build: the files move
    afterwards) and when ``SPACEROBOT_PLANNER_WARM_CACHE=0``.  A failure is reported
    and does not fail the install (the first start then compiles).  The cache files are
    listed in the install record (colcon's ``install.log``).
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
        print(f"{self.get_command_name()}: compiling numba kernels in {install_dir} (about 20 s)")
        # cwd = the install dir: `-m` puts it first on sys.path, so the installed copy is imported
        r = subprocess.run(cmd, cwd=install_dir, env=env)
        if r.returncode:
            print(f"{self.get_command_name()}: WARNING: the warm-up failed (exit {r.returncode}); "
                  "the first start will compile the kernels", file=sys.stderr)
        pkg = os.path.join(install_dir, PACKAGE)
        self.outputs = sorted(glob(os.path.join(pkg, "**", "__pycache__", "*.nb[ic]"), recursive=True))

    def get_outputs(self):
        return self.outputs

    def get_inputs(self):
        return []


class install_with_cache(install):
    """``install``, then :class:`warm_numba_cache` (a sub-command: its files are recorded)."""

    sub_commands = install.sub_commands + [("warm_numba_cache", None)]


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
    cmdclass={"install": install_with_cache, "warm_numba_cache": warm_numba_cache},
    zip_safe=True,
    maintainer="spacerobot_planner maintainers",
    maintainer_email="maintainers@spacerobot-planner.invalid",
    description="Laplace-potential capture planner for a space robot, as a ROS 2 node",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "planner_node = spacerobot_planner.ros.planner_node:main",
            "mock_arm_node = spacerobot_planner.ros.mock_arm_node:main",
            "spacerobot-plan = spacerobot_planner.tools.cli:main",
            "spacerobot-demo = spacerobot_planner.tools.demo:main",
        ],
    },
)
