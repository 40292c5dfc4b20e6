"""Rollouts on a Ray cluster (the optional `ray` extra): the same records as the local pool.

Each rollout is a Ray task running `rollout_worker.run_rollout` with one CPU
(`ditch_drake.common.ray_tasks`, which says how a run connects and stops); its record comes
back to the calling process, which appends it to the results file, so resuming works exactly
as with the local pool. A Python exception inside a rollout is already a record with status
"error"; a task whose worker process dies is retried once by Ray, then recorded as an error
here.
"""

from ditch_drake.common.ray_tasks import (
    LOCAL_ADDRESSES,
    MAX_RETRIES,
    check_address,
    cluster_endpoint,
    failure_message,
    run_ray_tasks,
)
from ditch_drake.evaluation.results import RolloutSpec
from ditch_drake.evaluation.rollout_worker import error_record, run_rollout

# Re-exported: evaluate's callers and tests find the address checks here.
__all__ = ["LOCAL_ADDRESSES", "MAX_RETRIES", "check_address", "cluster_endpoint", "run_on_ray"]


def run_on_ray(specs: list[RolloutSpec], address: str | None, max_in_flight: int | None, keep) -> None:
    """Runs `specs` as Ray tasks, passing each record to `keep` as it arrives.

    Args:
        specs: the rollouts.
        address: a running cluster's address (host:port, ray://host:port, or "auto"); None or
            "local" starts Ray on this machine (and shuts it down afterwards).
        max_in_flight: at most this many tasks submitted at once (None or 0: all).
        keep: called with each `RolloutRecord`, in the order they finish; a rollout whose task
            failed in Ray comes as an error record.

    Raises:
        ConfigError: a malformed or unreachable address (`check_address`), or Ray not installed.
        KeyboardInterrupt: Ctrl-C, or `Terminated` for SIGTERM, after Ray's tasks were stopped.
    """
    run_ray_tasks(run_rollout, [(spec,) for spec in specs], address, max_in_flight,
                  keep=lambda call, record: keep(record),
                  failed=lambda call, error: keep(error_record(call[0], failure_message(error))))
