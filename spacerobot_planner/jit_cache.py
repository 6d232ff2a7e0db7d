"""
Where numba caches the package's compiled kernels (a writable directory, whatever the install), and its start.

Every kernel is compiled with ``cache=True``.  numba keeps its cache next to the source, in the
package's ``__pycache__``, else in the user's cache directory (``~/.cache/numba`` on Linux), and
where neither can be written it refuses to define the kernel: ``RuntimeError: cannot cache
function ...: no locator available``, raised while the package is imported, so nothing of it
runs.  That is a read-only install run by a user whose home cannot be written either: a
container with a read-only root file system (Kubernetes ``readOnlyRootFilesystem``) or run as
an arbitrary user id with no home (OpenShift), or a system install for a service account.

So on import, where both of numba's places refuse a file and the user did not choose one
(``NUMBA_CACHE_DIR``), the package points numba at a directory of the system's temporary
directory of this user's own (:func:`ensure_writable_cache`).  numba reads no cache from a
``__pycache__`` it cannot write, so the cache an install filled there (``setup.py``'s
``warm_numba_cache``, ``make``) is copied over first (:func:`seed_from_package`: numba's index
holds a hash of the source's bytes, not its path, so a copy of the same source loads it), and
only what it lacks is compiled.  numba loads pickled code from its cache, so a directory that
another user could have made or can write is never taken (then a new private directory is made
for the process, compiled again at each start, but it runs), nor one in a temporary directory
where another user could swap it (writable by others and not sticky).

A process of the package's own (the CLI, the node, the planning process) also sets numba's CPU
target up itself, before its first kernel, without SciPy's BLAS (:func:`start_numba_target`):
numba's set-up imports ``scipy.linalg.cython_blas`` only to decide how ``np.correlate`` and
``np.convolve`` take inner products in kernels, which none of the package's kernels use, and
that import was 0.137 s of the CLI's start (one ``python -X importtime`` run).  ``np.dot`` and numba's linear algebra
still import it when a kernel first uses them.  It also loads numba's cached kernels without
parsing the LLVM bitcode numba keeps beside each one's machine code
(:func:`defer_linking_modules`): 0.19 of the 0.24 s the CLI's first plan spent loading its 50
kernels.  Neither is done on import: a user's own process keeps numba as numba makes it.

What numba does with that bitcode, and what is kept of it
---------------------------------------------------------
numba caches a kernel as its object code and, beside it, the bitcode of its module made fit
for linking (exported functions ``linkonce_odr``).  Loading a kernel, numba parses that bitcode
(0.13 s for the CLI's 50) and walks every function and global of it through LLVM's C API
(16 000 calls, 0.06 s) for one thing: the names the kernel defines, which its JIT engine's
``is_symbol_defined`` answers from (a kernel's entry points, another kernel's reference).  The
parsed module itself is used only to link the kernel into code compiled later in the process
(a new signature of a kernel that calls it).  Here the names come from the object code's own
symbol table (:func:`elf_defined_symbols`: the symbols an ELF object defines with global or
weak binding; on all 273 cached kernels of the package, exactly the bitcode's defined names
less its internal and private ones, which no lookup asks for), and the bitcode is parsed the
first time numba asks to link the kernel.  Only for the numba release this was read and tested
on (``_DEFER_NUMBA``, the one ``requirements.txt`` pins) and ELF objects; anything else loads
as numba loads it.
"""
from __future__ import annotations

import atexit
import filecmp
import os
import shutil
import stat
import struct
import sys
import tempfile

__all__ = ["defer_linking_modules", "elf_defined_symbols", "ensure_writable_cache", "import_numba",
           "seed_from_package", "start_numba", "start_numba_target", "writable"]

#: the module numba's CPU target set-up imports only to check for a BLAS (see the module docstring)
_BLAS_CHECK = "scipy.linalg.cython_blas"

#: numba releases whose loading of a cached kernel :func:`defer_linking_modules` replaces (read and tested)
_DEFER_NUMBA = ("0.68.1",)

_deferred = False               # defer_linking_modules has replaced numba's loading in this process


def writable(directory: str) -> bool:
    """Tell whether ``directory`` can be made (where it is missing) and a file created in it, as numba tries."""
    try:
        os.makedirs(directory, exist_ok=True)
        tempfile.TemporaryFile(dir=directory).close()
    except OSError:
        return False
    return True


def _numba_user_cache_dir() -> str:
    """
    Return numba's user-wide cache directory (its ``appdirs`` rule).

    On Linux and other Unixes but macOS without importing numba (``$XDG_CACHE_HOME/numba``, else
    ``~/.cache/numba``), so that the cache directory can still go in the environment, before
    numba reads it; elsewhere numba's own rule (it imports numba).
    """
    if os.name == "posix" and sys.platform != "darwin":
        return os.path.join(os.getenv("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "numba")
    from numba.misc.appdirs import AppDirs
    return AppDirs(appname="numba", appauthor=False).user_cache_dir


def _own_private(directory: str) -> bool:
    """Tell whether ``directory`` is a directory (not a link) of this user's that no one else can write."""
    if not hasattr(os, "getuid"):                 # no user ids (Windows): never a shared name's directory
        return False
    try:
        st = os.lstat(directory)
    except OSError:
        return False
    return (stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid()
            and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH))


def _safe_parent(directory: str) -> bool:
    """
    Tell whether no other user can swap entries of ``directory`` (the temporary directory).

    Owned by root or by this user, and not writable by others, or sticky (``/tmp``: others may
    add entries, not rename or remove this user's).  Without user ids (Windows), True.
    """
    if not hasattr(os, "getuid"):
        return True
    try:
        st = os.stat(directory)
    except OSError:
        return False
    if st.st_uid not in (0, os.getuid()):
        return False
    return bool(st.st_mode & stat.S_ISVTX) or not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)


def ensure_writable_cache(package_dir: str | None = None, user_dir: str | None = None,
                          temp_dir: str | None = None) -> str | None:
    """
    Point numba's cache at a temporary directory where its own places cannot be written; return it, or None.

    None: ``NUMBA_CACHE_DIR`` is set, or the package's ``__pycache__`` (``package_dir``, this
    package's by default) or numba's user-wide cache directory (``user_dir``, numba's by default)
    can be written: numba's own choice holds.  Else ``<temp_dir>/spacerobot_planner-numba-<uid>``
    (``temp_dir``: the system's temporary directory by default, which no other user may swap
    entries of: :func:`_safe_parent`), made private to this user where missing, or a new private
    directory where that one is not this user's alone (removed when the process ends; its
    children, the planning process, use it meanwhile); set in the
    environment before numba's import (the planning process inherits it), in numba's config
    after it (a change to the environment would make numba read its whole config again, and
    drop what the user set in code; a ``CACHE_DIR`` set there holds).  None too where no
    temporary directory can be written (numba then raises its own error).
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    package_dir = package_dir or os.path.dirname(os.path.abspath(__file__))
    if writable(os.path.join(package_dir, "__pycache__")):
        return None
    if writable(user_dir or _numba_user_cache_dir()):
        return None
    temp_dir = temp_dir or tempfile.gettempdir()
    if not _safe_parent(temp_dir):
        return None                   # another user could swap the directory: numba's own error instead
    chosen = os.path.join(temp_dir, f"spacerobot_planner-numba-{os.getuid() if hasattr(os, 'getuid') else 'user'}")
    try:
        os.mkdir(chosen, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return None
    if not (_own_private(chosen) and writable(chosen)):
        try:
            chosen = tempfile.mkdtemp(prefix="spacerobot_planner-numba-", dir=temp_dir)
        except OSError:
            return None
        atexit.register(shutil.rmtree, chosen, True)     # this process's alone (its children inherit it)
    config = sys.modules.get("numba.core.config")
    if config is None:
        os.environ["NUMBA_CACHE_DIR"] = chosen
    elif not config.CACHE_DIR:
        config.CACHE_DIR = chosen     # not the environment: numba would read its whole config again
    else:
        return None                   # set in code by the user
    seed_from_package(chosen, package_dir)
    return chosen


def seed_from_package(cache_dir: str, package_dir: str) -> int:
    """
    Copy the package's own numba cache into ``cache_dir`` where it lacks it or holds another; return the files copied.

    Each ``__pycache__``'s kernels go where numba's ``NUMBA_CACHE_DIR`` locator looks for that
    directory's sources (numba's own sub-path rule).  A kernel's index (``*.nbi``) is copied with
    its data files (``<the index's name less .nbi>.<n>.nbc``) where the cache has no index of that
    name or a different one (an earlier install's: upgraded), the data first; an index the same
    byte for byte is left with what numba added since.  Every file is written under a temporary
    name and renamed (a copy cut short, a full disk or two processes seeding at once leave no
    partial file for numba to load).  0 where numba's rule cannot be found; a copy that fails
    stops the seeding there.
    """
    try:
        from numba.core.caching import _CacheLocator
        subpath = _CacheLocator.get_suitable_cache_subpath
    except (ImportError, AttributeError):
        return 0
    copied = 0
    for root, _, files in os.walk(package_dir):
        if os.path.basename(root) != "__pycache__":
            continue
        indexes = sorted(f for f in files if f.endswith(".nbi"))
        if not indexes:
            continue
        dest = os.path.join(cache_dir, subpath(os.path.join(os.path.dirname(root), "__init__.py")))
        try:
            os.makedirs(dest, exist_ok=True)
            for index in indexes:
                if _same_file(os.path.join(root, index), os.path.join(dest, index)):
                    continue
                stem = index[:-len(".nbi")] + "."
                data = [f for f in files if f.startswith(stem) and f.endswith(".nbc")]
                for name in data + [index]:            # the index last: it names the data
                    _copy_atomic(os.path.join(root, name), os.path.join(dest, name))
                    copied += 1
        except OSError:
            return copied
    return copied


def _same_file(a: str, b: str) -> bool:
    """Tell whether files ``a`` and ``b`` hold the same bytes (False where ``b`` cannot be read)."""
    try:
        return filecmp.cmp(a, b, shallow=False)
    except OSError:
        return False


def _copy_atomic(src: str, dst: str) -> None:
    """Copy ``src`` to ``dst`` through a temporary file in ``dst``'s directory and a rename."""
    fd, tmp = tempfile.mkstemp(prefix=".seed-", dir=os.path.dirname(dst))
    try:
        with os.fdopen(fd, "wb") as out, open(src, "rb") as inp:
            shutil.copyfileobj(inp, out)
        os.replace(tmp, dst)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def start_numba_target() -> bool:
    """
    Set numba's CPU target up now, without importing SciPy's BLAS; return whether it was set up here.

    For the package's own processes, before their first kernel and before they start threads
    (see the module docstring): the BLAS module is hidden from the import system during the
    set-up, and a thread importing ``scipy.linalg`` meanwhile would fail.  False where numba's
    target was already set up or SciPy's BLAS is already imported: nothing to save.
    """
    if "numba.np.arraymath" in sys.modules or _BLAS_CHECK in sys.modules:
        return False
    sys.modules[_BLAS_CHECK] = None            # an import of it fails at once: numba takes "no BLAS"
    try:
        from numba.core.registry import cpu_target
        cpu_target.target_context.refresh()     # numba's registries, its BLAS check among them
    finally:
        if _BLAS_CHECK in sys.modules and sys.modules[_BLAS_CHECK] is None:
            del sys.modules[_BLAS_CHECK]
    return True


def elf_defined_symbols(obj: bytes) -> frozenset | None:
    """
    Return the names an ELF object defines with global or weak binding; None where they cannot be read.

    ``obj``: the bytes of an object file (numba's cached machine code of a kernel on Linux
    x86-64 and aarch64).  A symbol is defined where its section index is not ``SHN_UNDEF``
    (common symbols count); local symbols (functions and constants private to the object) are
    left out.  More than 0xff00 sections (a count of 0 in the header) are counted from section
    0's size, as ELF says.  None where ``obj`` is not a 64-bit little-endian ELF object, has no
    symbol table, or a header, a table or a name lies outside its bytes or outside its table.
    """
    header = struct.Struct("<IIQQQQIIQQ")    # name, type, flags, addr, offset, size, link, info, addralign, entsize
    symbol = struct.Struct("<IBBHQQ")        # name, info, other, section index, value, size
    end = len(obj)
    try:
        if obj[:6] != b"\x7fELF\x02\x01":                      # magic, 64-bit, little-endian
            return None
        shoff, = struct.unpack_from("<Q", obj, 0x28)
        shentsize, shnum = struct.unpack_from("<HH", obj, 0x3A)
        if shentsize != header.size or not shoff:
            return None
        if shnum == 0:
            shnum = header.unpack_from(obj, shoff)[5]
        if shoff + shnum * header.size > end:
            return None
        headers = [header.unpack_from(obj, shoff + i * header.size) for i in range(shnum)]
        names, tables = set(), 0
        for _, kind, _, _, offset, size, link, _, _, entsize in headers:
            if kind != 2:                                       # SHT_SYMTAB
                continue
            if entsize != symbol.size or offset + size > end or link >= shnum:
                return None
            strings, strings_size = headers[link][4], headers[link][5]
            if strings + strings_size > end:
                return None
            tables += 1
            for j in range(1, size // entsize):                 # entry 0 is the null symbol
                name, info, _, shndx, _, _ = symbol.unpack_from(obj, offset + j * entsize)
                if shndx == 0 or info >> 4 == 0:                 # SHN_UNDEF, STB_LOCAL
                    continue
                stop = obj.find(b"\0", strings + name, strings + strings_size)
                if name >= strings_size or stop < 0:
                    return None
                names.add(obj[strings + name:stop].decode("utf-8", "surrogateescape"))
        return frozenset(names) if tables else None
    except (struct.error, IndexError, ValueError, OverflowError, MemoryError):
        return None


def defer_linking_modules() -> bool:
    """
    Load numba's cached kernels without parsing their linking bitcode; return whether it was set up here.

    For the package's own processes (see the module docstring, which says what numba does with
    the bitcode and what is kept of it): numba's loading of a cached library
    (``CPUCodeLibrary._unserialize``) is replaced by the same steps less the bitcode's parse and
    walk, its defined names taken from the object code (:func:`elf_defined_symbols`); the bitcode
    is kept and parsed when numba first asks for the library's module to link
    (``_get_module_for_linking``).  A library numba cached as bitcode alone, or whose object
    code's names cannot be read (not ELF, malformed) or are none, loads as numba loads it.
    False where it was set up before in this process, or numba is not a release this was
    tested on, or lacks what it replaces.
    """
    global _deferred
    if _deferred:
        return False
    import numba
    if numba.__version__ not in _DEFER_NUMBA:
        return False
    import llvmlite.binding as llvm
    from numba.core.codegen import CPUCodeLibrary
    unserialize = CPUCodeLibrary.__dict__.get("_unserialize")
    for_linking = CPUCodeLibrary.__dict__.get("_get_module_for_linking")
    if not isinstance(unserialize, classmethod) or for_linking is None:
        return False

    def _unserialize(cls, codegen, state):
        name, kind, data = state
        names = elf_defined_symbols(data[0]) if kind == "object" else None
        if not names:                          # not read, or none: numba's own loading
            return unserialize.__func__(cls, codegen, state)
        object_code, linking_bitcode = data
        self = codegen.create_library(name)
        assert isinstance(self, cls)
        self.enable_object_caching()
        self._set_compiled_object(object_code)
        self._deferred_linking_bitcode = linking_bitcode
        self._finalize_final_module()
        codegen._engine._defined_symbols |= names
        return self

    def _get_module_for_linking(self):
        bitcode = getattr(self, "_deferred_linking_bitcode", None)
        if bitcode is not None:
            if self._shared_module is None:
                self._ensure_finalized()
                self._shared_module = llvm.parse_bitcode(bitcode)     # its own error, where it fails
            self._deferred_linking_bitcode = None
        return for_linking(self)

    CPUCodeLibrary._unserialize = classmethod(_unserialize)
    CPUCodeLibrary._get_module_for_linking = _get_module_for_linking
    _deferred = True
    return True


def import_numba() -> bool:
    """
    Import numba for a process of the package's own, without its coverage support's import of ``coverage``.

    Return whether it was imported here.

    numba's ``misc.coverage_support`` imports ``coverage`` where it is installed (colcon's
    pytest-cov installs it with ``make``) only to report the lines of jitted code to a coverage
    measurement running in the process: 25 ms of the CLI's start.  Where ``coverage`` is not
    imported yet, no measurement runs (``coverage run`` and ``COVERAGE_PROCESS_START`` import it
    first), so numba is imported with it hidden, and it can be imported as usual afterwards.
    False where numba or ``coverage`` was imported before.  Before anything imports numba: the
    entry points (``tools.entry``) and the planning process call it first.
    """
    if "numba" in sys.modules or "coverage" in sys.modules:
        return False
    sys.modules["coverage"] = None               # an import of it fails at once: numba takes "no coverage"
    try:
        import numba  # noqa: F401
    finally:
        if "coverage" in sys.modules and sys.modules["coverage"] is None:
            del sys.modules["coverage"]
    return True


def start_numba() -> None:
    """
    Start numba for a process of the package's own: its cached kernels' loading, its target.

    :func:`defer_linking_modules`, then :func:`start_numba_target`.

    Before the process's first kernel and before it starts threads.
    """
    defer_linking_modules()
    start_numba_target()
