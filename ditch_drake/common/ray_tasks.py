"""Picklable calls run as Ray tasks (the optional `ray` extra), stopped and connected like the local pool.

`run_ray_tasks(function, calls, address, ...)` runs `function(*call)` for each call as a Ray task
with one CPU and hands each result to the caller the moment it arrives, in this process: a
worker on another node cannot write into this machine's folders, so whatever a job keeps
(`evaluate`'s records, `collect`'s episodes) is written here, and a rerun resumes exactly as
with the local pool (`ditch_drake.common.parallel`). A task whose worker process dies is
retried once by Ray (`MAX_RETRIES`), then handed to the caller's `failed`. The files a task
reads by path (an environments file, a checkpoint) must be at that path on every node, as
on a shared filesystem.

Stopping and connecting:

- An address is checked before Ray sees it: a malformed one, or one where nothing accepts a
  connection, is a `ConfigError` within seconds (Ray itself retries such an address for
  minutes, deaf to Ctrl-C while it waits in compiled code). An address that accepts but does
  not answer as Ray is given up by Ray within about 20 s (`_BOUNDED_CONNECT`).
- `ray.init` installs SIGTERM handlers of its own (which exit 1 after a 10 s drain, or with
  code 15); ours is put back as soon as it returns, so SIGTERM raises `Terminated` (143).
- On Ctrl-C or SIGTERM a Ray started here is shut down, not its tasks cancelled one by one
  (cancelling a task that was finishing aborted the process in Ray's task manager), and any of
  its processes still there a few seconds later (the raylet's agents outlived it) are killed.
  On a cluster of someone else's (or a Ray this process had started before), the tasks of
  this run are cancelled, on a stop or on an error raised while keeping a result.
"""

import contextlib
import importlib.util
import os
import signal
import socket
from collections.abc import Callable, Sequence

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import Terminated, deferred_interrupts

# Where a job's work items run: a process pool on this machine, or Ray.
BACKENDS = ("local", "ray")
# Ray retries a task this many times after its worker process died.
MAX_RETRIES = 1
# The addresses that start Ray on this machine (and shut it down afterwards).
LOCAL_ADDRESSES = (None, "", "local")
# A cluster's port must accept a TCP connection within this time.
_PROBE_TIMEOUT_S = 5.0
# Ray Client's port when a ray:// address names none.
_RAY_CLIENT_PORT = 10001
# Ray's own connection attempts to a cluster, bounded (a port that accepts but is not Ray's):
# one round of retries, each connection given 5 s. A value the user set is kept.
_BOUNDED_CONNECT = {"RAY_gcs_server_port_wait_time_s": "1", "RAY_py_gcs_connect_timeout_s": "5"}
# How often the wait for the next result wakes, so a signal's handler runs without delay.
_WAIT_S = 0.5
# How long the processes of a Ray started here get to exit after `ray.shutdown()`.
_EXIT_GRACE_S = 5.0
_RAY_EXTRA = "backend 'ray' needs Ray: pip install -e '.[ray]'"


def check_backend(backend: str, address: str | None, where: str = "backend") -> None:
    """Raises ConfigError unless `backend` is one of `BACKENDS` and, for "ray", Ray is
    installed and `address` passes `check_address`. Ray is not imported (seconds) here."""
    if backend not in BACKENDS:
        raise ConfigError(f"{where}={backend!r}: unknown backend; expected one of {list(BACKENDS)}")
    if backend == "ray":
        if importlib.util.find_spec("ray") is None:
            raise ConfigError(_RAY_EXTRA)
        check_address(address)


def cluster_endpoint(address: str | None) -> tuple[str, int] | None:
    """The (host, port) that must accept a connection for `address`, after checking its form;
    None where there is nothing to probe: a Ray started here, or "auto" (Ray finds the
    cluster, from RAY_ADDRESS when set).

    Raises:
        ConfigError: an address that is none of "local", "auto", host:port or ray://host[:port].
    """
    if address in LOCAL_ADDRESSES:
        return None
    if address == "auto":
        found = os.environ.get("RAY_ADDRESS", "")
        return cluster_endpoint(found) if found not in ("", "auto", "local") else None
    expected = ("expected host:port of a running Ray cluster (e.g. head-node:6379), ray://host:port, 'auto' "
                "(RAY_ADDRESS or the cluster running here) or 'local' (start Ray here)")
    text = str(address).strip()
    client = text.startswith("ray://")
    host_port = text[len("ray://"):] if client else text
    host, colon, port_text = host_port.rpartition(":")
    if not colon and client:
        host, port_text = host_port, str(_RAY_CLIENT_PORT)
    host = host.strip("[]")  # An IPv6 literal: [::1]:6379.
    if not host or any(c.isspace() or c in "/@?#" for c in host) or not port_text.isdigit() \
            or not 1 <= int(port_text) <= 65535:
        raise ConfigError(f"Ray address {address!r}: {expected}")
    return host, int(port_text)


def check_address(address: str | None) -> None:
    """Raises ConfigError unless `address` is well formed and, for a cluster, something
    accepts a connection there within `_PROBE_TIMEOUT_S` (this process's network only: no
    Ray is started or joined)."""
    endpoint = cluster_endpoint(address)
    if endpoint is None:
        return
    try:
        with socket.create_connection(endpoint, timeout=_PROBE_TIMEOUT_S):
            pass
    except OSError as error:
        reason = "no answer" if isinstance(error, TimeoutError) else (error.strerror or str(error))
        raise ConfigError(f"Ray address {address!r}: nothing accepts a connection at {endpoint[0]}:{endpoint[1]} "
                          f"({reason}); expected the address of a running Ray cluster, or 'local' to start Ray "
                          "here") from error


def failure_message(error: Exception) -> str:
    """One line saying why a task gave no result (`run_ray_tasks`'s `failed`)."""
    first_line = str(error).splitlines()[0] if str(error) else ""
    return f"Ray task failed after {MAX_RETRIES} retry: {type(error).__name__}: {first_line}"


def raised_by_task(error: Exception) -> BaseException | None:
    """The exception the task's function raised, for a failure that was one (Ray does not
    retry those); None where the task's worker died or Ray lost it."""
    import ray

    if isinstance(error, ray.exceptions.RayTaskError):
        return error.cause if isinstance(error.cause, BaseException) else error
    return None


def _ray():
    try:
        import ray
    except ImportError as error:
        raise ConfigError(_RAY_EXTRA) from error
    return ray


def _our_processes() -> list:
    """This process's descendants, as psutil processes ([] without psutil)."""
    try:
        import psutil  # Ray ships it: importing ray first puts its copy on the path.
    except ImportError:
        return []
    return psutil.Process().children(recursive=True)


def _end_processes(processes: list) -> None:
    """Waits up to `_EXIT_GRACE_S` for `processes` to exit, then kills those left."""
    if not processes:
        return
    import psutil

    _, alive = psutil.wait_procs(processes, timeout=_EXIT_GRACE_S)
    for process in alive:
        with contextlib.suppress(psutil.Error):
            process.kill()
    psutil.wait_procs(alive, timeout=_EXIT_GRACE_S)


def _start_ray(ray, address: str | None, num_cpus: int | None) -> None:
    """`ray.init` for `address`, with this process's SIGTERM handler kept and a failure to
    connect reported as a ConfigError."""
    local = address in LOCAL_ADDRESSES
    previous = signal.getsignal(signal.SIGTERM)
    try:
        ray.init(address="local" if local else address, include_dashboard=False, log_to_driver=False,
                 configure_logging=False, **({"num_cpus": num_cpus} if local and num_cpus else {}))
    except SystemExit as error:  # Ray's SIGTERM handler, installed by init, ran before init returned.
        raise Terminated() from error
    except ConnectionError as error:
        raise ConfigError(f"Ray address {address!r}: {error}") from error
    finally:
        with contextlib.suppress(ValueError, TypeError):  # Not the main thread, or no Python handler before.
            signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _environment_defaults(values: dict[str, str]):
    """Sets the variables of `values` that the environment lacks, for the block."""
    added = [name for name in values if name not in os.environ]
    os.environ.update({name: values[name] for name in added})
    try:
        yield
    finally:
        for name in added:
            os.environ.pop(name, None)


@contextlib.contextmanager
def _noting_sigterm():
    """Yields a list that SIGTERM's arrival appends to, the handler before it still run: Ray
    turns an exception raised by a handler inside its waits into a new KeyboardInterrupt, which
    would report SIGTERM as Ctrl-C."""
    received = []
    previous = signal.getsignal(signal.SIGTERM)

    def note(signum, frame):
        received.append(signum)
        if callable(previous):
            previous(signum, frame)

    try:
        signal.signal(signal.SIGTERM, note)
    except ValueError:  # Not the main thread: signals stay as they are.
        yield received
        return
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, previous)


def run_ray_tasks(function: Callable, calls: Sequence[tuple], address: str | None, max_in_flight: int | None,
                  keep: Callable[[tuple, object], None], failed: Callable[[tuple, Exception], None],
                  calls_per_worker: int = 0) -> None:
    """Runs `function(*call)` for each of `calls` as a Ray task, passing each result to `keep`
    as it arrives.

    Args:
        function: a module-level function (Ray's workers import it by name), its arguments and
            result picklable.
        calls: each task's positional arguments.
        address: a running cluster's address (host:port, ray://host:port, or "auto"); None or
            "local" starts Ray on this machine (and shuts it down afterwards).
        max_in_flight: at most this many tasks submitted at once (None or 0: all).
        keep: called with (call, result), in the order the tasks finish.
        failed: called with (call, error) instead for a task that gave no result: a Ray error
            (`failure_message` says it in a line; `raised_by_task` is the function's own
            exception, if that was it). It may raise, which stops the run as an error in
            `keep` does.
        calls_per_worker: a worker process exits after this many calls of `function` and a
            fresh one takes its place (Ray's `max_calls`), bounding what it leaks; 0: never.

    Raises:
        ConfigError: a malformed or unreachable address (`check_address`), or Ray not installed.
        KeyboardInterrupt: Ctrl-C, or `Terminated` for SIGTERM, after Ray's tasks were stopped.
    """
    with ray_session(address) as (ray, started_here), _noting_sigterm() as terminated:
        try:
            _submit_and_keep(ray, function, calls, max_in_flight, keep, failed, calls_per_worker,
                             cancel_on_stop=not started_here)
        except KeyboardInterrupt as error:
            if terminated and not isinstance(error, Terminated):
                raise Terminated() from error
            raise


@contextlib.contextmanager
def ray_session(address: str | None, num_cpus: int | None = None):
    """Ray, connected for the block: yields (the `ray` module, whether this block started it).

    A Ray already initialized in this process is used as it is. Otherwise `address` is
    checked (`check_address`) and joined, or for None or "local" a Ray is started on this
    machine with `num_cpus` (None: every core), and shut down as the block ends, any of its
    processes still there a few seconds later killed.

    Raises:
        ConfigError: a malformed or unreachable address, or Ray not installed.
    """
    check_address(address)
    started_here, before = False, set()
    try:
        # Only while connecting: a Ray started here later in this process needs its own defaults.
        with _environment_defaults(_BOUNDED_CONNECT if address not in LOCAL_ADDRESSES else {}):
            ray = _ray()  # Its import reads the C++ settings, `ray.init` the Python ones.
            started_here = not ray.is_initialized()
            before = {process.pid for process in _our_processes()}
            if started_here:
                _start_ray(ray, address, num_cpus)
        yield ray, started_here
    finally:
        if started_here:
            with deferred_interrupts():  # A second Ctrl-C must not leave Ray half shut down.
                ours = [process for process in _our_processes() if process.pid not in before]
                ray.shutdown()
                _end_processes(ours)


def _submit_and_keep(ray, function: Callable, calls: Sequence[tuple], max_in_flight: int | None, keep, failed,
                     calls_per_worker: int, cancel_on_stop: bool) -> None:
    """Submits `calls`, at most `max_in_flight` at once, and keeps each result as it comes;
    on a stop or an error cancels what is in flight if `cancel_on_stop` (a Ray of ours is shut
    down instead)."""
    options = {"num_cpus": 1, "max_retries": MAX_RETRIES}
    if calls_per_worker:
        options["max_calls"] = calls_per_worker
    remote = ray.remote(**options)(function)
    queue = list(calls)
    limit = max_in_flight or len(queue)
    in_flight: dict = {}
    try:
        while queue or in_flight:
            while queue and len(in_flight) < limit:
                call = queue.pop(0)
                in_flight[remote.remote(*call)] = call
            finished, _ = ray.wait(list(in_flight), num_returns=1, timeout=_WAIT_S)
            if not finished:
                continue
            call = in_flight.pop(finished[0])
            try:
                result = ray.get(finished[0])
            except ray.exceptions.RayError as error:
                failed(call, error)
                continue
            keep(call, result)
    except BaseException:
        if cancel_on_stop:
            with deferred_interrupts():
                for reference in in_flight:
                    ray.cancel(reference, force=True)
        raise
