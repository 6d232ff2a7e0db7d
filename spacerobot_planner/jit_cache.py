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
still import it when a kernel first uses them.  Not done on import: a user's own process keeps
numba's set-up as numba makes it.
"""
from __future__ import annotations

import atexit
import filecmp
import os
import shutil
import stat
import sys
import tempfile

__all__ = ["ensure_writable_cache", "seed_from_package", "start_numba_target", "writable"]

#: the module numba's CPU target set-up imports only to check for a BLAS (see the module docstring)
_BLAS_CHECK = "scipy.linalg.cython_blas"


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
