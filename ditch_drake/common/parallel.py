"""Worker process pools that stop promptly and never outlive the process that made them.

Every long job (evaluation, demonstration collection, calibration) runs its work items in a
`WorkerPool`. Three things make a stop clean:

- Ctrl-C reaches every process of the terminal's process group, workers included. The
  workers ignore it: stopping is the parent's decision, and a worker's KeyboardInterrupt
  would only print a traceback from inside a simulation.
- The parent, on Ctrl-C (KeyboardInterrupt) or SIGTERM (`Terminated`, installed by
  `terminate_as_interrupt`), kills its workers at once (`WorkerPool.kill`) instead of letting
  the executor wait for the running items, which took a minute or more.
- A worker asks the kernel to kill it when its parent dies (Linux `PR_SET_PDEATHSIG`), so a
  `kill -9` of the main process leaves no worker computing for nobody.

What a job keeps is what its parent had written before the stop (records and files are
written by the parent as each item ends, or atomically by the worker), so a rerun continues.
"""

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
from concurrent.futures import ProcessPoolExecutor

from ditch_drake.common.errors import ConfigError

# linux/prctl.h
_PR_SET_PDEATHSIG = 1


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that the same handlers keep what finished; `exit_code` 143."""

    exit_code = 128 + signal.SIGTERM


def interrupt_exit_code(error: KeyboardInterrupt) -> int:
    """The shell's exit code for a stop by this signal: 130 for SIGINT, 143 for SIGTERM."""
    return getattr(error, "exit_code", 128 + signal.SIGINT)


@contextlib.contextmanager
def terminate_as_interrupt():
    """While inside, SIGTERM raises `Terminated` in the main thread (restored afterwards)."""

    def raise_terminated(signum, frame):
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, raise_terminated)
    except ValueError:  # Not the main thread: signals stay as they are.
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def deferred_interrupts():
    """Holds Ctrl-C and SIGTERM back inside the block (a record being written and counted), so
    that a stop lands before or after it, never halfway: a signal that came meanwhile is
    handed to the previous handler as the block ends. Outside the main thread it changes
    nothing. (Python-level handlers, not a thread's signal mask: the kernel may deliver a
    process's signal to any thread that does not block it.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    previous = {signum: signal.signal(signum, lambda number, frame: received.append(number))
                for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if received and callable(previous[received[0]]):
            previous[received[0]](received[0], None)


def check_workers(workers: int | None, where: str = "workers") -> None:
    """Raises ConfigError unless `workers` is None (every core) or an integer >= 0."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise ConfigError(f"{where}={workers!r}: workers must be >= 0 (0: in this process)")


def worker_count(workers: int | None) -> int:
    """Processes for `workers`: None is one per core; 0 means the caller works in its own process."""
    check_workers(workers)
    return (os.cpu_count() or 1) if workers is None else workers


def _die_with_parent(parent_pid: int) -> None:
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    # The parent may have died before the request took effect.
    if os.getppid() != parent_pid:
        os._exit(1)


def _initialize_worker(parent_pid: int, initializer, initargs) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    if initializer is not None:
        initializer(*initargs)


class WorkerPool(ProcessPoolExecutor):
    """A spawned `ProcessPoolExecutor` whose workers ignore Ctrl-C, die with their parent, and
    are killed, not awaited, when the `with` block ends by an interruption or error.

    Spawned, not forked: a fork of a process whose torch/OpenMP threads are running can
    deadlock in the child.
    """

    def __init__(self, max_workers: int, initializer=None, initargs=()):
        super().__init__(max_workers=max_workers, mp_context=multiprocessing.get_context("spawn"),
                         initializer=_initialize_worker, initargs=(os.getpid(), initializer, tuple(initargs)))

    def kill(self) -> None:
        """Cancels what has not started and kills the workers; returns when they are gone."""
        # Python 3.14 has ProcessPoolExecutor.kill_workers(); 3.11 keeps the processes here.
        processes = list((self._processes or {}).values())
        self.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            with contextlib.suppress(ProcessLookupError, AttributeError, ValueError):
                process.kill()
        for process in processes:
            with contextlib.suppress(AttributeError, ValueError):
                process.join(timeout=5)
        self.shutdown(wait=True)

    def __exit__(self, exc_type, exc, traceback):
        if exc_type is not None:
            self.kill()
            return False
        return super().__exit__(exc_type, exc, traceback)
