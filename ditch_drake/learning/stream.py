"""Training samples read from disk as batches need them, and the torch loader that batches them.

A training set on disk keeps each episode's frames once, (T, 128, 128) uint8 in a `.npy` file,
where the in-memory `ArraySet` holds every sample's stack of four frames (64 KiB a sample, each
frame four times). `LazyImageStack` stands in for that (N, 4, 128, 128) stack: it knows each
sample's episode and step, and builds the stacks of the rows it is asked for from the frames t,
t-1, t-2, t-3 (zeros before step 0, as `restack_images` does), reflected left to right where the
sample's flag says so (`ditch_drake.learning.mirror`). `ArraySet` takes it as its `image`; the
scalars, labels and demonstration ids (80 bytes a sample) stay in memory.

Frames are read with plain positioned reads (`os.preadv`) into the batch, not through memory
maps: a mapped page once touched counts in the process's resident memory for as long as the
map lives, so an epoch of random draws over mapped files would end up holding the whole data
set resident. Read, only the batch is. A bounded number of files is kept open
(`LazyImageStack.max_open`); each loader worker opens its own.

`SampleBatches` is the torch `Dataset` of the training loop: an item is a whole batch, the
samples at an array of positions, so one read gathers a batch; `batch_loader` wraps it in a
`DataLoader` (workers, pinned memory on CUDA) that yields the batches of a given list of
position arrays in order, so the batches are those of the in-memory path for the same seed.
"""

import multiprocessing
import os
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from ditch_drake.common.errors import DatasetError
from ditch_drake.spec.observation_layout import IMAGE_SHAPE, STACK_DEPTH

FrameSource = str | os.PathLike | Callable[[], np.ndarray]
"""An episode's frames: the path of a (T, 128, 128) uint8 `.npy` file, or a callable that returns
such an array (in memory, or memory-mapped)."""

BATCH_FIELDS = ("image", "imu", "distance", "bearing", "label")
# Rows written per call when a writer repeats one row many times (bounded temporaries).
_WRITE_CHUNK = 256


def _as_rows(index, length: int, what: str) -> tuple[np.ndarray, bool]:
    """An integer, a slice or an integer array as (rows >= 0, whether it was a single integer)."""
    if isinstance(index, slice):
        return np.arange(length)[index], False
    rows = np.asarray(index)
    scalar = rows.ndim == 0
    if rows.dtype == np.bool_:
        raise IndexError(f"{what}: index with integer rows, not a boolean mask (np.flatnonzero(mask))")
    if not np.issubdtype(rows.dtype, np.integer):
        raise IndexError(f"{what}: rows of dtype {rows.dtype}; expected integers")
    rows = rows.reshape(-1).astype(np.int64)
    if rows.size and (rows.min() < -length or rows.max() >= length):
        raise IndexError(f"{what}: rows {rows.min()}..{rows.max()} outside 0..{length - 1}")
    return np.where(rows < 0, rows + length, rows), scalar


class NpyRows:
    """The rows of a C-ordered `.npy` file, read with plain reads when indexed (nothing mapped).

    `shape`, `dtype`, `len()` and indexing by an integer, a slice or an integer array work as
    on the array; each index reads just those rows. The file is opened on the first read and
    kept open until `close()` (a copy made for another process opens its own).

    Raises:
        DatasetError: naming the file, when it is missing, not a `.npy` array, Fortran-ordered,
            of an object dtype, or shorter than its header says.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._descriptor = None
        try:
            with open(self.path, "rb") as file:
                version = np.lib.format.read_magic(file)
                read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                               (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                if read_header is None:
                    raise ValueError(f".npy format version {version}")
                shape, fortran_order, dtype = read_header(file)
                self._offset = file.tell()
                size = os.fstat(file.fileno()).st_size
        except FileNotFoundError as error:
            raise DatasetError(f"{self.path} is missing; expected a .npy array") from error
        except (OSError, ValueError, EOFError) as error:
            raise DatasetError(f"{self.path}: not a readable .npy array ({type(error).__name__}: {error})") from error
        if len(shape) == 0 or (fortran_order and len(shape) > 1) or dtype.hasobject:
            raise DatasetError(f"{self.path}: a {'Fortran-ordered ' if fortran_order else ''}array of shape {shape} "
                               f"and dtype {dtype}; expected a C-ordered array of rows of plain numbers")
        self.shape, self.dtype = tuple(int(s) for s in shape), np.dtype(dtype)
        self._row_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        if size < self._offset + self.shape[0] * self._row_bytes:
            raise DatasetError(f"{self.path}: {size} bytes, fewer than its header's shape {self.shape} and dtype "
                               f"{self.dtype} need ({self._offset + self.shape[0] * self._row_bytes}); a torn file")

    def __len__(self) -> int:
        return self.shape[0]

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_descriptor": None}  # A copy in another process opens its own.

    def close(self) -> None:
        """Closes the file (a later read opens it again)."""
        if self._descriptor is not None:
            os.close(self._descriptor)
            self._descriptor = None

    def __del__(self):
        self.close()

    def read_into(self, start: int, out: np.ndarray) -> None:
        """Reads rows start.. start + len(out) into `out` (C-contiguous, of this dtype)."""
        if self._descriptor is None:
            try:
                self._descriptor = os.open(self.path, os.O_RDONLY)
            except OSError as error:
                raise DatasetError(f"{self.path}: cannot be read ({error.strerror})") from error
        position = self._offset + start * self._row_bytes
        buffer = memoryview(out).cast("B")
        if hasattr(os, "preadv"):
            done = os.preadv(self._descriptor, [buffer], position)
        else:  # Without preadv (macOS before 11): a copy more.
            data = os.pread(self._descriptor, buffer.nbytes, position)
            buffer[: len(data)] = data
            done = len(data)
        if done != buffer.nbytes:
            raise DatasetError(f"{self.path}: rows {start}..{start + len(out) - 1} could not be read whole "
                               f"({done} of {buffer.nbytes} bytes); the file shrank while in use")

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, slice) and index.step in (None, 1):
            start, stop, _ = index.indices(len(self))
            out = np.empty((max(stop - start, 0), *self.shape[1:]), self.dtype)
            if len(out):
                self.read_into(start, out)
            return out
        rows, scalar = _as_rows(index, len(self), str(self.path))
        out = np.empty((len(rows), *self.shape[1:]), self.dtype)
        for i, row in enumerate(rows):
            self.read_into(int(row), out[i : i + 1])
        return out[0] if scalar else out


class NpyRowWriter:
    """Writes a `.npy` file of a known shape row block by row block, with plain writes (nothing
    mapped, so what was written does not stay resident), for rows made in order.

    Assign the next rows as to an array, `writer[start:stop] = values` (values broadcast over
    the rows, as numpy does), `start` being the rows written so far; `close()` checks that all
    were written. `shape`, `dtype` and `len()` are those of the array being written.
    """

    def __init__(self, path: str | os.PathLike, shape: tuple[int, ...], dtype: np.dtype):
        self.path, self.shape, self.dtype = Path(path), tuple(int(s) for s in shape), np.dtype(dtype)
        self._file = open(self.path, "wb")  # noqa: SIM115 (closed by close())
        np.lib.format.write_array_header_1_0(
            self._file, {"descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False, "shape": self.shape})
        self.written = 0

    def __len__(self) -> int:
        return self.shape[0]

    def __setitem__(self, index: slice, values) -> None:
        start, stop, step = index.indices(len(self)) if isinstance(index, slice) else (None, None, None)
        if start != self.written or step != 1:
            raise IndexError(f"{self.path}: rows are written in order; expected [{self.written}:...], got {index!r}")
        for chunk_start in range(start, stop, _WRITE_CHUNK):
            chunk_stop = min(stop, chunk_start + _WRITE_CHUNK)
            if np.ndim(values) == len(self.shape):
                chunk = values[chunk_start - start : chunk_stop - start]
            else:
                chunk = np.broadcast_to(values, (chunk_stop - chunk_start, *self.shape[1:]))
            self._file.write(np.ascontiguousarray(chunk, dtype=self.dtype).tobytes())
        self.written = stop

    def close(self) -> NpyRows:
        """Finishes the file; returns its rows to read.

        Raises:
            ValueError: fewer rows written than the shape says.
        """
        self._file.close()
        if self.written != self.shape[0]:
            raise ValueError(f"{self.path}: {self.written} of {self.shape[0]} rows written")
        return NpyRows(self.path)


class LazyImageStack:
    """(N, 4, 128, 128) uint8 image stacks built from per-episode frames when indexed.

    Sample i is the stack of frames `step[i]`, `step[i] - 1`, ... (newest first, zeros before
    step 0) of episode `episode[i]`, columns reversed where `reflect[i]` (the left-right
    reflection of `ditch_drake.learning.mirror`). Indexing by an integer, a slice or an
    integer array returns the stacks (a new array); nothing else is kept but the open files.

    Args:
        frames: each episode's frames, a `FrameSource`: a `.npy` path (read with plain reads,
            its header checked here: (T, 128, 128) uint8) or a callable opening an array (called
            when its frames are first needed).
        episode: (N,) index into `frames` of each sample.
        step: (N,) step of each sample in its episode.
        reflect: (N,) bool, reflect the sample's stack (default: none).
        max_open: most episodes kept open at once (least recently used closed first).

    Raises:
        DatasetError: a frame file of another shape or dtype, or a step beyond its episode.
        ValueError: arrays of different lengths, or an episode index outside `frames`.
    """

    def __init__(self, frames: Sequence[FrameSource], episode, step, reflect=None, max_open: int = 32):
        self.frames = list(frames)
        self.episode = np.asarray(episode, dtype=np.int64)
        self.step = np.asarray(step, dtype=np.int64)
        n = len(self.episode)
        self.reflect = np.zeros(n, np.bool_) if reflect is None else np.asarray(reflect, dtype=np.bool_)
        if self.episode.shape != (n,) or self.step.shape != (n,) or self.reflect.shape != (n,):
            raise ValueError(f"LazyImageStack: episode {self.episode.shape}, step {self.step.shape} and reflect "
                             f"{self.reflect.shape}; expected one value per sample each")
        if n and (self.episode.min() < 0 or self.episode.max() >= len(self.frames)):
            raise ValueError(f"LazyImageStack: episodes {self.episode.min()}..{self.episode.max()}; expected "
                             f"indices of the {len(self.frames)} frame sources")
        if n and self.step.min() < 0:
            raise ValueError(f"LazyImageStack: a step {self.step.min()} < 0")
        if max_open < 1:
            raise ValueError(f"LazyImageStack: max_open={max_open}; expected >= 1")
        self.max_open = max_open
        self.shape = (n, STACK_DEPTH, *IMAGE_SHAPE)
        self.dtype = np.dtype(np.uint8)
        self._open: OrderedDict[int, object] = OrderedDict()
        self._last_step = np.full(len(self.frames), -1, np.int64)
        np.maximum.at(self._last_step, self.episode, self.step)
        for index, source in enumerate(self.frames):
            if not callable(source) and self._last_step[index] >= 0:
                self._check(NpyRows(source), index)

    def _check(self, frames, index: int) -> None:
        last_step = int(self._last_step[index])
        where = frames.path if isinstance(frames, NpyRows) else f"frame source {index}"
        if tuple(frames.shape[1:]) != IMAGE_SHAPE or frames.dtype != np.uint8 or len(frames.shape) != 3:
            raise DatasetError(f"{where}: frames of shape {tuple(frames.shape)} and dtype {frames.dtype}; expected "
                               f"(T, {IMAGE_SHAPE[0]}, {IMAGE_SHAPE[1]}) uint8")
        if last_step >= frames.shape[0]:
            raise DatasetError(f"{where}: {frames.shape[0]} frames, but a sample is of step {last_step}")

    def __len__(self) -> int:
        return self.shape[0]

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_open": OrderedDict()}  # A worker process opens its own files.

    def close(self) -> None:
        """Closes every open episode."""
        for frames in self._open.values():
            if isinstance(frames, NpyRows):
                frames.close()
        self._open.clear()

    def _frames(self, index: int):
        frames = self._open.pop(index, None)
        if frames is None:
            source = self.frames[index]
            frames = source() if callable(source) else NpyRows(source)
            if callable(source):
                self._check(frames, index)
            while len(self._open) >= self.max_open:
                _, oldest = self._open.popitem(last=False)
                if isinstance(oldest, NpyRows):
                    oldest.close()
        self._open[index] = frames
        return frames

    def __getitem__(self, index) -> np.ndarray:
        rows, scalar = _as_rows(index, len(self), "LazyImageStack")
        out = np.zeros((len(rows), *self.shape[1:]), self.dtype)
        episodes = self.episode[rows]
        order = np.argsort(episodes, kind="stable")
        starts = np.flatnonzero(np.r_[True, episodes[order][1:] != episodes[order][:-1]]) if len(rows) else []
        for group in np.split(order, starts[1:]) if len(rows) else []:
            frames = self._frames(int(episodes[group[0]]))
            for i in group:
                step = int(self.step[rows[i]])
                first = max(0, step - STACK_DEPTH + 1)
                if isinstance(frames, NpyRows):
                    block = np.empty((step + 1 - first, *IMAGE_SHAPE), self.dtype)
                    frames.read_into(first, block)
                else:
                    block = np.asarray(frames[first : step + 1])
                out[i, : step + 1 - first] = block[::-1]
        reflect = self.reflect[rows]
        if reflect.any():
            out[reflect] = out[reflect][..., ::-1]
        return out[0] if scalar else out


class TrainingSamples:
    """What training draws from, by position: rows of an `ArraySet` (a row may repeat),
    followed by the samples of a second set (SMOTE's synthetic ones), if any.

    Args:
        arrays: the set (its images in memory, or a `LazyImageStack`).
        rows: its rows, in position order.
        extra: samples after them (an `ArraySet`), or None.
    """

    def __init__(self, arrays, rows: np.ndarray, extra=None):
        self.arrays, self.rows, self.extra = arrays, np.asarray(rows, dtype=np.int64), extra

    def __len__(self) -> int:
        return len(self.rows) + (0 if self.extra is None else len(self.extra))

    def labels(self) -> np.ndarray:
        """(len,) the label at each position."""
        extra = [] if self.extra is None else [self.extra.label]
        return np.concatenate([self.arrays.label[self.rows], *extra])

    def gather(self, positions: np.ndarray) -> dict[str, np.ndarray]:
        """The samples at `positions`, as arrays named after `ArraySet`'s fields."""
        positions = np.asarray(positions, dtype=np.int64)
        real = positions < len(self.rows)
        out = {}
        for name in BATCH_FIELDS:
            source = getattr(self.arrays, name)
            if real.all():
                out[name] = np.asarray(source[self.rows[positions]])
                continue
            extra = getattr(self.extra, name)
            values = np.empty((len(positions), *source.shape[1:]), dtype=source.dtype)
            values[real] = source[self.rows[positions[real]]]
            values[~real] = extra[positions[~real] - len(self.rows)]
            out[name] = values
        return out


class SampleBatches(Dataset):
    """A torch `Dataset` whose items are whole batches: `dataset[positions]` is the tuple
    (image, imu, distance, bearing, label) of CPU tensors of those positions of `samples` (a
    `TrainingSamples`); the image as stored (uint8 or float16), for `to_device`."""

    def __init__(self, samples: TrainingSamples):
        self.samples = samples

    def __getitem__(self, positions) -> tuple[torch.Tensor, ...]:
        values = self.samples.gather(positions)
        return tuple(torch.from_numpy(np.ascontiguousarray(values[name])) for name in BATCH_FIELDS)


def batch_loader(samples: TrainingSamples, batches: Iterable[np.ndarray], num_workers: int = 0,
                 pin_memory: bool = False) -> DataLoader:
    """A `DataLoader` yielding the batches of `samples` at each array of `batches`, in order.

    Args:
        samples: what to read.
        batches: position arrays, one a batch.
        num_workers: reading processes (0: read in this one); each opens its own files.
        pin_memory: page-lock the batches for fast copies to a GPU.
    """
    # Workers forked from this multi-threaded process can deadlock (Python 3.12 warns); a
    # forkserver's are clean, but each gets the samples pickled: cheap only when the images are
    # on disk, so in-memory images keep fork's shared pages.
    on_disk = not isinstance(samples.arrays.image, np.ndarray) and (
        samples.extra is None or not isinstance(samples.extra.image, np.ndarray))
    context = None
    if num_workers and on_disk:
        context = multiprocessing.get_context("forkserver")
        # Workers then fork from a server that imported torch and this module once, instead of
        # each importing them: a two-worker loader's first batch came 3.5x sooner.
        context.set_forkserver_preload([__name__])
    return DataLoader(SampleBatches(samples), batch_size=None, sampler=list(batches), num_workers=num_workers,
                      pin_memory=pin_memory, multiprocessing_context=context,
                      # Its own generator: a loader's first draw would otherwise advance the global
                      # torch generator, whose draws seed the dropout masks.
                      generator=torch.Generator())


def to_device(batch: tuple[torch.Tensor, ...], device: str) -> tuple[list[torch.Tensor], torch.Tensor]:
    """A loader's batch as the network's inputs on `device` (images float32 in [0, 1]) and labels."""
    image, *scalars, label = (tensor.to(device, non_blocking=tensor.is_pinned()) for tensor in batch)
    image = image.to(torch.float32).div_(255.0) if image.dtype == torch.uint8 else image.to(torch.float32)
    return [image, *scalars], label


def epoch_batches(order: np.ndarray, batch_size: int, max_batches: int | None = None) -> list[np.ndarray]:
    """`order` cut into batches of `batch_size` (at most `max_batches`), leaving out a last batch
    of fewer than 2 samples (BatchNorm needs two)."""
    steps = -(-len(order) // batch_size)
    if max_batches is not None:
        steps = min(steps, max_batches)
    batches = [order[step * batch_size : (step + 1) * batch_size] for step in range(steps)]
    return [batch for batch in batches if len(batch) >= 2]
