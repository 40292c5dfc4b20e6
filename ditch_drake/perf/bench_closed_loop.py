"""Repeats the bench's closed-loop measurement to show how much the shared host moves it.

Run: `python -m ditch_drake.perf.bench_closed_loop [repeats] [environment ...]`
(default 5 repeats, every environment). Each repeat is one `measure_closed_loops` over
the environments (the figures `ditch-drake bench --json` prints once) between two host
references (`measure_host_reference_ms`), printed as one JSON line as soon as it is done;
the last line sums them up: per environment the median and the range of
`observation_update_<env>_ms` and `closed_loop_<env>_rtf`, and in how many repeats each
met its target (3 ms, 25x). A single bench run is one sample of this distribution.
Ctrl-C stops it after the lines already printed, with the summary of those.
"""

import json
import sys
import time

import numpy as np
from tqdm import tqdm

from ditch_drake.perf.bench import measure_closed_loops, measure_host_reference_ms
from ditch_drake.world.environments import environment_names

# The perception issue's targets.
OBSERVATION_TARGET_MS = 3.0
CLOSED_LOOP_TARGET_RTF = 25.0


def sample_closed_loop(repeats: int, environments: list[str]) -> list[dict]:
    """`repeats` rounds of `measure_closed_loops` over `environments`, each printed as a JSON line."""
    if repeats < 1:
        raise ValueError(f"repeats={repeats!r} must be >= 1")
    samples = []
    try:
        for _ in tqdm(range(repeats), desc="closed-loop repeats", file=sys.stderr):
            sample = {
                "utc": time.strftime("%H:%M:%S", time.gmtime()),
                "host_reference_start_ms": measure_host_reference_ms(),
            }
            sample.update(measure_closed_loops(environments))
            sample["host_reference_end_ms"] = measure_host_reference_ms()
            print(json.dumps(sample), flush=True)
            samples.append(sample)
    except KeyboardInterrupt:
        print(f"interrupted after {len(samples)} repeats", file=sys.stderr)
    return samples


def summarize(samples: list[dict], environments: list[str]) -> dict:
    """Per environment: median, min and max of both figures and the repeats meeting each target."""
    summary: dict[str, float] = {"repeats": len(samples)}
    meets_every_target = np.ones(len(samples), dtype=bool)
    for name in environments:
        for key, target, meets in (
            (f"observation_update_{name}_ms", OBSERVATION_TARGET_MS, np.less_equal),
            (f"closed_loop_{name}_rtf", CLOSED_LOOP_TARGET_RTF, np.greater_equal),
        ):
            values = np.array([sample[key] for sample in samples])
            meets_target = meets(values, target)
            summary[f"{key}_median"] = float(np.median(values))
            summary[f"{key}_min"] = float(values.min())
            summary[f"{key}_max"] = float(values.max())
            summary[f"{key}_meets_target_count"] = int(meets_target.sum())
            meets_every_target &= meets_target
    summary["repeats_meeting_every_target"] = int(meets_every_target.sum())
    return summary


def main(argv: list[str]) -> None:
    repeats = int(argv[0]) if argv else 5
    environments = argv[1:] or environment_names()
    unknown = sorted(set(environments) - set(environment_names(variants=True)))
    if unknown:
        raise SystemExit(f"unknown environment(s) {unknown}; expected some of {environment_names(variants=True)}")
    samples = sample_closed_loop(repeats, environments)
    if samples:
        print(json.dumps({"summary": summarize(samples, environments)}))


if __name__ == "__main__":
    main(sys.argv[1:])
