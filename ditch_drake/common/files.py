"""Writing files so that nothing half-written is ever mistaken for a result.

`atomic_output(path)` opens a temporary file beside `path`, named with this process's id, and
renames it over `path` only when the block finishes: a reader sees the old file or the new
one, never part of one. The file and its folder are synced before and after the rename, so a
crash or a power cut leaves the same choice. A process killed inside the block leaves its
temporary behind; `remove_stale_temporaries` deletes those whose process is gone, so a rerun
cleans up after a `kill -9` without touching the temporaries of a job still running in the
same folder.
"""

import contextlib
import os
import re
import secrets
from pathlib import Path

_TEMPORARY = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{12}\.tmp$")


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike):
    """Yields a binary file to write `path`'s new contents into; a clean exit puts it in place.

    The file gets the mode a plain `open()` gives (0666 less the umask): it is created with
    `os.open(..., 0o666)`, which the kernel masks, not with `tempfile.mkstemp` (always 0600)
    plus a chmod, whose umask lookup would briefly change the process-wide umask.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp")
        try:
            descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(descriptor, "wb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    fsync_folder(path.parent)


def prepare_output(path: str | os.PathLike, what: str, folder: bool = False) -> Path:
    """`path`, after creating the folder it is written into (`path` itself with `folder`) and
    checking that this process may write there: a command refuses an unwritable output before
    its work, not with a traceback after it.

    Raises:
        ConfigError: the folder cannot be created (a part of the path is a file, no
            permission) or is not writable, or a file's path is a folder, naming `what` and `path`.
    """
    from ditch_drake.common.errors import ConfigError

    path = Path(path)
    target = path if folder else path.parent
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"{what} {path}: cannot create the folder {target} ({error.strerror or error}); expected "
                          "a path in a writable folder") from error
    if not os.access(target, os.W_OK | os.X_OK):
        raise ConfigError(f"{what} {path}: the folder {target} is not writable; expected a path in a writable folder")
    if not folder and path.is_dir():
        raise ConfigError(f"{what} {path} is a folder; expected a file's path")
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Writes `data` to `path` atomically; returns `path`."""
    with atomic_output(path) as file:
        file.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Writes `text` (UTF-8) to `path` atomically; returns `path`."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def save_figure(figure, path: str | os.PathLike, dpi: int = 80) -> Path:
    """Saves a matplotlib figure as a PNG at `path` atomically, closes it and returns `path`."""
    import matplotlib.pyplot as plt

    with atomic_output(path) as file:
        figure.savefig(file, format="png", dpi=dpi)
    plt.close(figure)
    return Path(path)


def fsync_folder(folder: Path) -> None:
    """Makes a rename into `folder` durable (POSIX); a no-op where folders cannot be opened."""
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def process_exists(pid: int) -> bool:
    """Whether a process with this id is running (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Deletes the `atomic_output` temporaries in `folder` whose writing process has died."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for candidate in folder.iterdir():
        match = _TEMPORARY.match(candidate.name)
        if match and candidate.is_file() and not process_exists(int(match.group(1))):
            candidate.unlink(missing_ok=True)
            removed.append(candidate)
    return removed


@contextlib.contextmanager
def exclusive_use(path: str | os.PathLike, what: str):
    """Holds `<path>.lock` (an advisory `flock`) for the block, so that two runs never append to
    one file at once; the lock file says which process holds it and is removed as the block ends.

    Raises:
        ConfigError: another process holds it, naming `what`, `path` and that process.
    """
    import fcntl
    import shlex
    import sys

    from ditch_drake.common.errors import ConfigError

    lock = Path(f"{path}.lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        descriptor = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(descriptor, 4096).decode("utf-8", "replace").strip() or "a process"
            os.close(descriptor)
            raise ConfigError(f"{what} {path} is being written by another run ({holder}, holding {lock}); expected "
                              "one run per file: wait for that one to end, or write to another file") from None
        try:
            same = os.fstat(descriptor).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        # The holder removed the file between our open and our lock: this lock guards nothing.
        os.close(descriptor)
    try:
        os.ftruncate(descriptor, 0)
        os.write(descriptor, f"process {os.getpid()}: {shlex.join(sys.argv)}\n".encode())
        yield
    finally:
        # Removed while still locked: a run that opened it meanwhile finds it gone (the inode check) and makes anew.
        lock.unlink(missing_ok=True)
        os.close(descriptor)
