"""
A zygote that forks the tests' planning processes already warm (test aid; the package never uses it).

Every in-process node graph of the suite needs a planning process.  Started as the node
starts one (a fresh interpreter: imports, then numba's kernels loaded from the cache), each
costs about 1.5 s of CPU, and the suite makes over a hundred of them on a 2-core machine.
This zygote does that work once per test process: it imports the planning core and runs
``worker.warm_up`` on the paper scenes, then forks a planning process on request.  A fork
runs the same ``worker.child_main`` as a started one: its own pid, its own ``Planner`` and
caches, its own warm-up (about 0.1 s: the kernels are already loaded), the same socket
protocol; only how it begins differs.

Run as ``python planning_zygote.py PACKAGE_PARENT CONFIG_DIR CONTROL_FD``; the test process
(``node_helpers.ZygoteBackend``) sends one byte on the control socket with the planning
process's socket end attached (SCM_RIGHTS) and reads back the new pid (8 bytes).  The
zygote forks twice and the middle process exits at once, so the planning process is
re-parented to the test process (a child subreaper, ``PR_SET_CHILD_SUBREAPER``), which
waits for it as it would for a child it started.

numba's default threading layer on Linux (GNU OpenMP) is not safe across a fork once its
threads exist, so the zygote and its forks use numba's fork-safe ``workqueue`` layer
(``NUMBA_THREADING_LAYER``, set by the test process): the parallel kernels split their
work into the same chunks either way.
"""

from __future__ import annotations

import atexit
import ctypes
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback

#: the scenes whose default routes the zygote loads (node_helpers.SCENES: file, cells per joint)
WARM = (("paper_2dof.yaml", [180, 180]), ("paper_3dof.yaml", [36, 36, 36]))


def _warm(config_dir: str) -> None:
    from dataclasses import replace

    from spacerobot_planner.config import load_params_file, scenario_from_params
    from spacerobot_planner.planner import Planner
    from spacerobot_planner.worker import warm_up
    for name, cells in WARM:
        sc = scenario_from_params(load_params_file(os.path.join(config_dir, name)))
        sc = replace(sc, grid=sc.grid.with_cells(cells))
        warm_up(Planner(sc, trajectory=False))


def _planning_process(fd: int) -> None:
    """Run the grandchild: a planning process on socket ``fd``; never returns."""
    code = 0
    try:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        from spacerobot_planner.worker import child_main
        child_main(fd)
    except BaseException:      # noqa: BLE001 - report, then leave with a failure status
        traceback.print_exc()
        code = 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def serve(control: socket.socket) -> None:
    """Fork one planning process per request on ``control`` until it closes."""
    while True:
        try:
            _, fds, _, _ = socket.recv_fds(control, 1, 1)
        except OSError:
            return
        if not fds:                 # the test process closed its end
            return
        fd = fds[0]
        r, w = os.pipe()
        middle = os.fork()
        if middle == 0:             # the middle process: fork the planning process, tell its pid, exit
            os.close(r)
            grandchild = os.fork()
            if grandchild == 0:
                os.close(w)
                control.close()
                _planning_process(fd)
            os.write(w, grandchild.to_bytes(8, "little"))
            os._exit(0)
        os.close(w)
        os.close(fd)
        pid = int.from_bytes(os.read(r, 8), "little")
        os.close(r)
        os.waitpid(middle, 0)       # once it is gone the planning process is the test process's child
        control.sendall(pid.to_bytes(8, "little"))


# ================================================================== the test process's side
#: prctl(2) option: orphaned descendants are re-parented to this process
_PR_SET_CHILD_SUBREAPER = 36


class ForkedProcess:
    """A planning process forked by the zygote, now this process's child: ``subprocess.Popen``'s interface."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode = None

    def poll(self):
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout=None):
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(f"planning process {self.pid}", timeout)
            time.sleep(0.005)
        return self.returncode

    def send_signal(self, sig) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class PlanningZygote:
    """This test process's zygote: started at the first :meth:`fork`, ended when the process exits."""

    #: the first fork waits for the zygote's own warm-up (seconds; a loaded machine)
    START_TIMEOUT_S = 120.0

    def __init__(self, package_parent: str, config_dir: str):
        self._args = (package_parent, config_dir)
        self._lock = threading.Lock()
        self._proc = None
        self._control = None
        self._forked = []            # every ForkedProcess handed out
        atexit.register(self.close)

    @property
    def pid(self):
        """Return the zygote's process id (None before the first fork)."""
        return None if self._proc is None else self._proc.pid

    def _start(self) -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")
        ours, theirs = socket.socketpair()
        env = dict(os.environ, NUMBA_THREADING_LAYER="workqueue")
        self._proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), *self._args, str(theirs.fileno())],
                                      pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, env=env)
        theirs.close()
        ours.settimeout(self.START_TIMEOUT_S)
        self._control = ours

    def fork(self, fd: int) -> ForkedProcess:
        """Return a new planning process serving socket ``fd`` (``worker.child_main``)."""
        with self._lock:
            if self._proc is None or self._proc.poll() is not None:
                self._start()
            socket.send_fds(self._control, [b"f"], [fd])
            answer = b""
            while len(answer) < 8:
                chunk = self._control.recv(8 - len(answer))
                if not chunk:
                    raise RuntimeError(f"the planning zygote exited (code {self._proc.wait()})")
                answer += chunk
        pid = int.from_bytes(answer, "little")
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read()
        ppid = int(stat[stat.rfind(")") + 2:].split()[1])
        if ppid != os.getpid():
            raise RuntimeError(f"planning process {pid} has parent {ppid}, not this process {os.getpid()}")
        child = ForkedProcess(pid)
        with self._lock:
            self._forked.append(child)
        return child

    def running(self) -> list:
        """Return the pids of the planning processes forked here that have not exited."""
        with self._lock:
            forked = list(self._forked)
        return [c.pid for c in forked if c.poll() is None]

    def close(self) -> None:
        with self._lock:
            if self._control is not None:
                self._control.close()
                self._control = None
            if self._proc is not None:
                try:
                    self._proc.wait(5)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait()


def main() -> None:
    package_parent, config_dir, control_fd = sys.argv[1], sys.argv[2], int(sys.argv[3])
    sys.path.insert(0, package_parent)                  # the copy of the package the tests import
    signal.signal(signal.SIGINT, signal.SIG_IGN)       # the test process decides when it ends
    _warm(config_dir)
    serve(socket.socket(fileno=control_fd))


if __name__ == "__main__":
    main()
