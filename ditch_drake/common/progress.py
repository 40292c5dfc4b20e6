"""A long command's progress lines on stderr."""

import sys

from tqdm import tqdm


def log_progress(progress: bool, line: str) -> None:
    """Writes `line` to stderr when `progress` is on; `tqdm.write` keeps it from breaking a
    progress bar that is being drawn."""
    if progress:
        tqdm.write(line, file=sys.stderr)
