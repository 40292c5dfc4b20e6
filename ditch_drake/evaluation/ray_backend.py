"""Rollouts on a Ray cluster (the optional `ray` extra): the same records as the local pool.

Each rollout is a Ray task running `rollout_worker.run_rollout` with one CPU; its record comes back
to the calling process, which appends it to the results file, so resuming works exactly as
with the local pool. A Python exception inside a rollout is already a record with status
"error"; a task whose worker process dies is retried once by Ray (`max_retries`), then
recorded as an error here.
"""

from ditch_drake.common.errors import ConfigError
from ditch_drake.evaluation.results import RolloutRecord, RolloutSpec
from ditch_drake.evaluation.rollout_worker import error_record, run_rollout

# Ray retries a task this many times after its worker process died.
_MAX_RETRIES = 1


def _ray():
    try:
        import ray
    except ImportError as error:
        raise ConfigError("backend 'ray' needs Ray: pip install -e '.[ray]'") from error
    return ray


def run_on_ray(specs: list[RolloutSpec], address: str | None, max_in_flight: int | None, keep) -> None:
    """Runs `specs` as Ray tasks, passing each record to `keep` as it arrives.

    Args:
        specs: the rollouts.
        address: a running cluster's address; None or "local" starts Ray on this machine
            (and shuts it down afterwards).
        max_in_flight: at most this many tasks submitted at once (None or 0: all).
        keep: called with each `RolloutRecord`, in the order they finish.
    """
    ray = _ray()
    started_here = not ray.is_initialized()
    if started_here:
        local = address in (None, "", "local")
        ray.init(address=None if local else address, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
    in_flight: dict = {}
    try:
        remote = ray.remote(num_cpus=1, max_retries=_MAX_RETRIES)(run_rollout)
        queue = list(specs)
        limit = max_in_flight or len(queue)
        while queue or in_flight:
            while queue and len(in_flight) < limit:
                spec = queue.pop(0)
                in_flight[remote.remote(spec)] = spec
            finished, _ = ray.wait(list(in_flight), num_returns=1)
            spec = in_flight.pop(finished[0])
            try:
                record: RolloutRecord = ray.get(finished[0])
            except ray.exceptions.RayError as error:
                record = error_record(spec, f"Ray task failed after {_MAX_RETRIES} retry: {type(error).__name__}: "
                                             f"{str(error).splitlines()[0] if str(error) else ''}")
            keep(record)
    except KeyboardInterrupt:
        for reference in in_flight:
            ray.cancel(reference, force=True)
        raise
    finally:
        if started_here:
            ray.shutdown()
