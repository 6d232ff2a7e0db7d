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

A process of the package's own loads numba's cached kernels without parsing the bitcode numba
keeps for linking (``start_numba``, ``defer_linking_modules``): the names each kernel defines come
from its object code's symbol table (``elf_defined_symbols``), checked against LLVM's own view of
objects the test compiles from IR of every linkage (llvmlite: the IR's defined names less its
internal and private ones), and, in a fresh process planning the paper's 2-DOF scene, against
LLVM's parse of every loaded kernel's bitcode; that process plans the same path as this one, none
of its kernels' bitcode parsed, and a kernel it compiles afterwards that calls a package kernel
(so that numba links the deferred module in) computes what NumPy computes.

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


@pytest.mark.parametrize("mode", [0o777, 0o775])
def test_a_temporary_directory_others_can_swap_entries_of_is_not_used(places, mode):
    os.makedirs(places["temp"])
    os.chmod(places["temp"], mode)                       # writable by others, not sticky
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"]) is None
    assert _chosen() is None and os.listdir(places["temp"]) == []
    os.chmod(places["temp"], mode | stat.S_ISVTX)        # sticky, as /tmp: others cannot rename ours
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"]) is not None


def test_a_temporary_directory_of_another_user_is_not_used(places):
    if os.geteuid() != 0:
        pytest.skip("needs root to give a directory to another user")
    os.makedirs(places["temp"])
    os.chown(places["temp"], 65534, 65534)
    os.chmod(places["temp"], 0o755)
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["temp"]) is None


@pytest.mark.skipif(os.name != "posix" or sys.platform == "darwin", reason="the rule written out is Linux's")
@pytest.mark.parametrize("xdg", [None, "/somewhere/xdg"])
def test_numbas_user_cache_directory_without_importing_numba(monkeypatch, xdg):
    from numba.misc.appdirs import AppDirs
    if xdg is None:
        monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    else:
        monkeypatch.setenv("XDG_CACHE_HOME", xdg)
    assert jit_cache._numba_user_cache_dir() == AppDirs(appname="numba", appauthor=False).user_cache_dir


def _kernel_files(directory: Path, stem: str, index: bytes, data: dict):
    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"{stem}.nbi").write_bytes(index)
    for n, payload in data.items():
        (directory / f"{stem}.{n}.nbc").write_bytes(payload)


def test_seeding_copies_what_the_cache_lacks_or_holds_another_of_and_leaves_no_partial_file(tmp_path):
    from numba.core.caching import _CacheLocator
    pkg, cache = tmp_path / "pkg", tmp_path / "cache"
    _kernel_files(pkg / "__pycache__", "mod.f-10.py311", b"index v2", {1: b"data v2"})
    _kernel_files(pkg / "sub" / "__pycache__", "sub.g-3.py311", b"g index", {1: b"g1", 2: b"g2"})
    assert jit_cache.seed_from_package(str(cache), str(pkg)) == 5
    dest = cache / _CacheLocator.get_suitable_cache_subpath(str(pkg / "__init__.py"))
    sub = cache / _CacheLocator.get_suitable_cache_subpath(str(pkg / "sub" / "__init__.py"))
    assert (dest / "mod.f-10.py311.nbi").read_bytes() == b"index v2"
    assert (sub / "sub.g-3.py311.2.nbc").read_bytes() == b"g2"
    # what numba added since is kept where the index is the same; nothing is copied again
    (sub / "sub.g-3.py311.3.nbc").write_bytes(b"compiled here")
    assert jit_cache.seed_from_package(str(cache), str(pkg)) == 0
    assert (sub / "sub.g-3.py311.3.nbc").exists()
    # an earlier install's index (an upgrade): the package's index and data replace it
    (dest / "mod.f-10.py311.nbi").write_bytes(b"index v1")
    (dest / "mod.f-10.py311.1.nbc").write_bytes(b"data v1")
    assert jit_cache.seed_from_package(str(cache), str(pkg)) == 2
    assert (dest / "mod.f-10.py311.1.nbc").read_bytes() == b"data v2"
    assert not [p for p in cache.rglob("*") if p.name.startswith(".seed-")]


def test_a_process_that_has_not_imported_numba_exports_the_directory(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    run = ("import os, sys\n"
           "from spacerobot_planner import jit_cache\n"
           "assert 'numba' not in sys.modules\n"
           "got = jit_cache.ensure_writable_cache(sys.argv[1], sys.argv[2], sys.argv[3])\n"
           "import numba\n"
           "print(got, os.environ['NUMBA_CACHE_DIR'], numba.config.CACHE_DIR)\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CACHE_DIR")}
    out = subprocess.run([sys.executable, "-c", run, str(blocker / "pkg"), str(blocker / "user"), str(tmp_path)],
                         capture_output=True, text=True, timeout=300, env=env, cwd=PACKAGE.parent)
    assert out.returncode == 0, out.stderr
    got, exported, config = out.stdout.split()
    assert got == exported == config == str(tmp_path / f"spacerobot_planner-numba-{os.getuid()}")


def test_with_no_temporary_directory_nothing_is_set(places):
    assert jit_cache.ensure_writable_cache(places["no_pkg"], places["no_user"], places["no_temp"]) is None
    assert _chosen() is None


_READ_ONLY_RUN = r"""
mount --bind "$SRC" "$SRC" && mount -o remount,bind,ro "$SRC" || { echo MOUNT-FAILED; exit 77; }
if touch "$SRC/spacerobot_planner/probe" 2>/dev/null; then echo "still writable"; exit 3; fi
exec "$PY" -c "$RUN"
"""

#: run in the copy (on the read-only mount, or before it to fill the install's cache): the two kernels
_KERNELS_RUN = r"""
import glob, os, sys
import spacerobot_planner              # first, as a program would: numba not imported yet
assert spacerobot_planner.__file__.startswith(os.environ["SRC"]), spacerobot_planner.__file__
from numba.core.event import install_recorder
from spacerobot_planner.joint_space import wrap_angle_scalar_rad, wrap_angle_rad
import numpy as np
with install_recorder("numba:compile") as compiled:
    assert abs(wrap_angle_scalar_rad(7.0) - (7.0 - 2 * 3.141592653589793)) < 1e-12
    assert abs(wrap_angle_rad(np.array([7.0]))[0] - (7.0 - 2 * 3.141592653589793)) < 1e-12
import numba
where = numba.config.CACHE_DIR
print(where or "-", os.environ.get("NUMBA_CACHE_DIR", "-"),
      len(glob.glob(os.path.join(where, "**", "*.nbi"), recursive=True)) if where else 0, len(compiled.buffer))
"""


@pytest.mark.parametrize("with_cache", [False, True], ids=["no cache in the install", "the install's cache"])
def test_a_read_only_install_with_no_home_runs_its_kernels(tmp_path, with_cache):
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare (a private mount namespace for a read-only mount)")
    src = tmp_path / "src"
    shutil.copytree(PACKAGE, src / "spacerobot_planner", ignore=shutil.ignore_patterns("__pycache__"))
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_CACHE_DIR", "XDG_CACHE_HOME"))}
    env.update(SRC=str(src), PY=sys.executable, PYTHONPATH=str(src), RUN=_KERNELS_RUN, PYTHONDONTWRITEBYTECODE="1")
    if with_cache:               # as an install fills it: the copy's own __pycache__, while it can be written
        warm = subprocess.run([sys.executable, "-c", _KERNELS_RUN], capture_output=True, text=True, timeout=600,
                              env=env, cwd=tmp_path)
        assert warm.returncode == 0, warm.stderr
        assert list((src / "spacerobot_planner" / "__pycache__").glob("joint_space.*.nbi"))
    env.update(HOME=str(blocker / "home"), TMPDIR=str(temp))
    out = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", _READ_ONLY_RUN],
                         capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    if "MOUNT-FAILED" in out.stdout or (out.returncode != 0 and "unshare" in out.stderr):
        pytest.skip(f"no read-only mount in a private namespace here: {out.stderr.strip()}")
    assert out.returncode == 0, out.stdout + out.stderr
    where, exported, files, compiled = out.stdout.split()
    assert where == exported == str(temp / f"spacerobot_planner-numba-{os.getuid()}")   # in the environment too
    assert int(files) >= 1                                   # numba's cache is there
    if with_cache:
        assert int(compiled) == 0, "the install's cache was not loaded: the kernels were compiled again"
    else:
        assert int(compiled) >= 2


def _fresh_process_json(code: str, *args) -> dict:
    """Run ``code`` in a fresh interpreter (the package's directory); return the JSON of its last line."""
    import json
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                         timeout=600, cwd=PACKAGE.parent)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


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
    import numpy as np
    from spacerobot_planner.planner import Planner
    config = PACKAGE.parent / "config" / "paper_2dof.yaml"
    got = _fresh_process_json(_TARGET_RUN, config)
    assert (got["first"], got["again"], got["ok"]) == (True, False, True)
    assert not got["blas_after_plan"]                       # the plan never needed it
    assert got["dot"] == 30.0 and got["blas_after_dot"]     # np.dot in a kernel: imported then, and right
    sc = paper_scenario(2)
    here = Planner(sc).plan(sc.start_rad, sc.goal_rad)
    assert np.array_equal(np.array(got["path"]), here.path_rad)


_LINKAGES_IR = r"""
@g_ext = global i64 1
@g_int = internal global i64 2
@g_priv = private constant [3 x i8] c"ab\00"
@g_lo = linkonce_odr global i64 3
@g_common = common global i64 0
@g_decl = external global i64
declare i64 @f_decl(i64)
define internal i64 @f_int(i64 %x) {
  %v = load i64, ptr @g_int
  %s = add i64 %x, %v
  ret i64 %s
}
define linkonce_odr i64 @f_lo(i64 %x) {
  %v = load i64, ptr @g_decl
  %s = add i64 %x, %v
  ret i64 %s
}
define weak i64 @f_weak(i64 %x) {
  ret i64 %x
}
define i64 @f_ext(i64 %x) {
  %a = call i64 @f_decl(i64 %x)
  %b = call i64 @f_int(i64 %a)
  %c = call i64 @f_lo(i64 %b)
  %p = load i8, ptr @g_priv
  %q = zext i8 %p to i64
  %r = add i64 %c, %q
  ret i64 %r
}
"""


def _llvm_defined(module) -> set:
    """Return the names an LLVM module defines, less its internal and private ones (llvmlite's view of the IR)."""
    import llvmlite.binding as llvm
    return {g.name for g in list(module.functions) + list(module.global_variables)
            if not g.is_declaration and g.linkage not in (llvm.Linkage.internal, llvm.Linkage.private)}


def _object_of(ir: str):
    import llvmlite.binding as llvm
    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    module = llvm.parse_assembly(ir)
    return module, llvm.Target.from_default_triple().create_target_machine().emit_object(module)


def test_an_objects_defined_names_are_the_irs_less_its_internal_and_private_ones():
    import struct
    module, obj = _object_of(_LINKAGES_IR)
    if obj[:6] != b"\x7fELF\x02\x01":
        pytest.skip("this machine's objects are not 64-bit little-endian ELF")
    want = {"f_ext", "f_lo", "f_weak", "g_ext", "g_lo", "g_common"}
    assert _llvm_defined(module) == want                      # the test's IR says what it defines
    assert jit_cache.elf_defined_symbols(obj) == want
    # more than 0xff00 sections: the header's count 0, the real one in section 0's size (ELF's rule)
    shoff, = struct.unpack_from("<Q", obj, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", obj, 0x3A)
    extended = bytearray(obj)
    struct.pack_into("<H", extended, 0x3C, 0)
    struct.pack_into("<Q", extended, shoff + 32, shnum)       # section 0's sh_size
    assert jit_cache.elf_defined_symbols(bytes(extended)) == want
    # not ELF, another class, cut short: None (numba's own loading then)
    assert jit_cache.elf_defined_symbols(b"\xcf\xfa\xed\xfe" + obj[4:]) is None
    assert jit_cache.elf_defined_symbols(obj[:4] + b"\x01" + obj[5:]) is None
    assert jit_cache.elf_defined_symbols(obj[:len(obj) // 2]) is None
    # malformed: each None, at once (no exception, no loop over a made-up count)
    kinds = [struct.unpack_from("<I", obj, shoff + i * shentsize + 4)[0] for i in range(shnum)]
    table = shoff + kinds.index(2) * shentsize                  # the SHT_SYMTAB section's header
    strings = shoff + struct.unpack_from("<I", obj, table + 40)[0] * shentsize

    def changed(*edits):
        b = bytearray(obj)
        for fmt, at, value in edits:
            struct.pack_into(fmt, b, at, value)
        return bytes(b)

    for bad in (changed(("<Q", 0x28, 2 ** 63)),                           # section headers far past the end
                changed(("<Q", table + 24, 2 ** 63 + 5)),                  # the symbol table far past it
                changed(("<Q", strings + 24, 2 ** 64 - 1)),                # the string table too
                changed(("<Q", 0x28, 0), ("<H", 0x3C, 0)),                 # no section headers
                changed(("<I", table + 4, 11)),                            # no SHT_SYMTAB (a SHT_DYNSYM)
                changed(("<H", 0x3A, 0), ("<H", 0x3C, 0), ("<Q", shoff + 32, 2 ** 40)),   # 2**40 headers of 0 bytes
                changed(("<Q", strings + 32, 1))):                         # names past their table's end
        assert jit_cache.elf_defined_symbols(bad) is None


_DEFER_RUN = r"""
import json, sys
import llvmlite.binding as llvm
from spacerobot_planner import jit_cache
set_up, again = jit_cache.defer_linking_modules(), jit_cache.defer_linking_modules()
jit_cache.start_numba()
from numba.core.codegen import CPUCodeLibrary
loaded, parses = [], [0]
_unserialize = CPUCodeLibrary.__dict__["_unserialize"].__func__
def record(cls, codegen, state):
    if state[1] == "object":
        loaded.append(state[2])
    return _unserialize(cls, codegen, state)
CPUCodeLibrary._unserialize = classmethod(record)
_parse = llvm.parse_bitcode
def parse(data):
    parses[0] += 1
    return _parse(data)
llvm.parse_bitcode = parse
from spacerobot_planner.config import load_scenario
from spacerobot_planner.planner import Planner
sc = load_scenario(sys.argv[1])
res = Planner(sc).plan(sc.start_rad, sc.goal_rad)
parsed_in_plan = parses[0]
llvm.parse_bitcode = _parse
import numba
import numpy as np
from spacerobot_planner.joint_space import _wrap_rows
@numba.njit
def wrapped_sum(q, lower, per):
    _wrap_rows(q, lower, per)
    return q.sum()
q = np.array([[7.0, -7.0], [1.0, 20.0]])
lower = np.array([-np.pi, 0.0])
per = np.array([True, False])
linked = wrapped_sum(q.copy(), lower, per)
names = []
for obj, bitcode in loaded:
    elf = jit_cache.elf_defined_symbols(obj)
    module = llvm.parse_bitcode(bitcode)
    names.append([sorted(elf), sorted(g.name for g in list(module.functions) + list(module.global_variables)
                  if not g.is_declaration and g.linkage not in (llvm.Linkage.internal, llvm.Linkage.private))])
print(json.dumps({"set_up": set_up, "again": again, "ok": res.ok, "path": res.path_rad.tolist(),
                  "loaded": len(loaded), "parsed_in_plan": parsed_in_plan, "linked": linked, "names": names}))
"""


def test_a_process_of_its_own_loads_its_kernels_without_their_linking_bitcode(paper_scenario):
    import numba
    import numpy as np
    from spacerobot_planner.planner import Planner
    if numba.__version__ not in jit_cache._DEFER_NUMBA:
        pytest.skip(f"numba {numba.__version__}: loaded as numba loads it")
    _, obj = _object_of(_LINKAGES_IR)
    if obj[:6] != b"\x7fELF\x02\x01":
        pytest.skip("this machine's objects are not 64-bit little-endian ELF")
    sc = paper_scenario(2)
    here = Planner(sc).plan(sc.start_rad, sc.goal_rad)         # this process fills numba's cache if it must
    config = PACKAGE.parent / "config" / "paper_2dof.yaml"
    got = _fresh_process_json(_DEFER_RUN, config)
    assert (got["set_up"], got["again"], got["ok"]) == (True, False, True)
    assert np.array_equal(np.array(got["path"]), here.path_rad)
    assert got["loaded"] >= 10 and got["parsed_in_plan"] == 0
    for elf, llvm_names in got["names"]:
        assert elf == llvm_names and elf
    q = np.array([[7.0, -7.0], [1.0, 20.0]])
    q[:, 0] = -np.pi + (q[:, 0] + np.pi) % (2 * np.pi)          # the attitude column wrapped, NumPy's way
    assert got["linked"] == pytest.approx(q.sum(), abs=1e-12)


_COVERAGE_RUN = r"""
import json, sys
first = sys.argv[1] == "coverage_first"
if first:
    import coverage
import spacerobot_planner.tools.entry                      # the console scripts' module: nothing heavy
heavy = sorted(m for m in ("numba", "numpy", "coverage") if m in sys.modules)
from spacerobot_planner.jit_cache import import_numba
done = import_numba()
from numba.misc import coverage_support
hidden = "coverage" not in sys.modules
import coverage                                             # importable as usual afterwards
print(json.dumps({"heavy": heavy, "done": done, "available": coverage_support.coverage_available,
                  "hidden": hidden, "coverage": coverage.__name__}))
"""


@pytest.mark.parametrize("case", ["fresh", "coverage_first"])
def test_numba_is_imported_without_coverage_unless_a_measurement_could_run(case):
    """Where coverage is installed (make installs it with colcon): hidden from numba's import, unless imported."""
    pytest.importorskip("coverage")
    got = _fresh_process_json(_COVERAGE_RUN, case)
    if case == "fresh":
        assert got["heavy"] == [] and got["done"] and not got["available"] and got["hidden"], got
    else:                                   # a coverage measurement could run: numba as numba imports itself
        assert got["heavy"] == ["coverage"] and not got["done"] and got["available"], got
    assert got["coverage"] == "coverage"
