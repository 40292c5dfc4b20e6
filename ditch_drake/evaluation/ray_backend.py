"""Rollouts on a Ray cluster (the optional `ray` extra): the same records as the local pool.

Each rollout is a Ray task running `rollout_worker.run_rollout` with one CPU; its record comes back
to the calling process, which appends it to the results file, so resuming works exactly as
with the local pool. A Python exception inside a rollout is already a record with status
"error"; a task whose worker process dies is retried once by Ray (`max_retries`), then
recorded as an error here.

Stopping and connecting behave as with the local pool:

- An address is checked before Ray sees it: a malformed one, or one where nothing accepts a
  connection, is a `ConfigError` within seconds (Ray itself retries such an address for
  minutes, deaf to Ctrl-C while it waits in compiled code). An address that accepts but does
  not answer as Ray is given up by Ray within about 20 s (`_BOUNDED_CONNECT`).
- `ray.init` installs SIGTERM handlers of its own (which exit 1 after a 10 s drain, or with
  code 15); ours is put back as soon as it returns, so SIGTERM raises `Terminated` (143).
- On Ctrl-C or SIGTERM a Ray started here is shut down, not its tasks cancelled one by one
  (cancelling a task that was finishing aborted the process in Ray's task manager), and any of
  its processes still there a few seconds later (the raylet's agents outlived it) are killed.
  On a cluster of someone else's, the tasks of this run are cancelled.
"""

import contextlib
import os
import signal
import socket

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import Terminated, deferred_interrupts
from ditch_drake.evaluation.results import RolloutRecord, RolloutSpec
from ditch_drake.evaluation.rollout_worker import error_record, run_rollout

# Ray retries a task this many times after its worker process died.
_MAX_RETRIES = 1
# The addresses that start Ray on this machine (and shut it down afterwards).
LOCAL_ADDRESSES = (None, "", "local")
# A cluster's port must accept a TCP connection within this time.
_PROBE_TIMEOUT_S = 5.0
# Ray Client's port when a ray:// address names none.
_RAY_CLIENT_PORT = 10001
# Ray's own connection attempts to a cluster, bounded (a port that accepts but is not Ray's):
# one round of retries, each connection given 5 s. A value the user set is kept.
_BOUNDED_CONNECT = {"RAY_gcs_server_port_wait_time_s": "1", "RAY_py_gcs_connect_timeout_s": "5"}
# How often the wait for the next record wakes, so a signal's handler runs without delay.
_WAIT_S = 0.5
# How long the processes of a Ray started here get to exit after `ray.shutdown()`.
_EXIT_GRACE_S = 5.0


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


def _ray():
    try:
        import ray
    except ImportError as error:
        raise ConfigError("backend 'ray' needs Ray: pip install -e '.[ray]'") from error
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


def _start_ray(ray, address: str | None) -> None:
    """`ray.init` for `address`, with this process's SIGTERM handler kept and a failure to
    connect reported as a ConfigError."""
    local = address in LOCAL_ADDRESSES
    previous = signal.getsignal(signal.SIGTERM)
    try:
        ray.init(address="local" if local else address, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
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


def run_on_ray(specs: list[RolloutSpec], address: str | None, max_in_flight: int | None, keep) -> None:
    """Runs `specs` as Ray tasks, passing each record to `keep` as it arrives.

    Args:
        specs: the rollouts.
        address: a running cluster's address (host:port, ray://host:port, or "auto"); None or
            "local" starts Ray on this machine (and shuts it down afterwards).
        max_in_flight: at most this many tasks submitted at once (None or 0: all).
        keep: called with each `RolloutRecord`, in the order they finish.

    Raises:
        ConfigError: a malformed or unreachable address (`check_address`), or Ray not installed.
        KeyboardInterrupt: Ctrl-C, or `Terminated` for SIGTERM, after Ray's tasks were stopped.
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
                _start_ray(ray, address)
        with _noting_sigterm() as terminated:
            try:
                _run_tasks(ray, specs, max_in_flight, keep, cancel_on_stop=not started_here)
            except KeyboardInterrupt as error:
                if terminated and not isinstance(error, Terminated):
                    raise Terminated() from error
                raise
    finally:
        if started_here:
            with deferred_interrupts():  # A second Ctrl-C must not leave Ray half shut down.
                ours = [process for process in _our_processes() if process.pid not in before]
                ray.shutdown()
                _end_processes(ours)


def _run_tasks(ray, specs: list[RolloutSpec], max_in_flight: int | None, keep, cancel_on_stop: bool) -> None:
    """Submits `specs`, at most `max_in_flight` at once, and keeps each record as it comes;
    on a stop cancels what is in flight if `cancel_on_stop` (a Ray of ours is shut down instead)."""
    remote = ray.remote(num_cpus=1, max_retries=_MAX_RETRIES)(run_rollout)
    queue = list(specs)
    limit = max_in_flight or len(queue)
    in_flight: dict = {}
    try:
        while queue or in_flight:
            while queue and len(in_flight) < limit:
                spec = queue.pop(0)
                in_flight[remote.remote(spec)] = spec
            finished, _ = ray.wait(list(in_flight), num_returns=1, timeout=_WAIT_S)
            if not finished:
                continue
            spec = in_flight.pop(finished[0])
            try:
                record: RolloutRecord = ray.get(finished[0])
            except ray.exceptions.RayError as error:
                record = error_record(spec, f"Ray task failed after {_MAX_RETRIES} retry: {type(error).__name__}: "
                                             f"{str(error).splitlines()[0] if str(error) else ''}")
            keep(record)
    except KeyboardInterrupt:
        if cancel_on_stop:
            with deferred_interrupts():
                for reference in in_flight:
                    ray.cancel(reference, force=True)
        raise
