"""A resumable on-disk store for the column blocks of D.

The store is a work directory beside the bundle (``.NAME.work/``) holding

``compliance.npy``
    D itself, column-major, created at its full size up front (sparse, so a
    block costs disk only when it is written). A column block of a
    column-major array is one contiguous byte range: each block is written
    in place with ``pwrite`` (no memory map, so the writer's memory stays one
    block) and flushed to disk (``fdatasync``) before it counts as done.
``blocks/NNNNNN.json``
    One record per finished block, written atomically after its data is on
    disk: the cache key, the column range, the SHA-256 of the block's
    bytes, and the block's largest entry and largest rounding error (the
    cast from the solve's float64 to D's storage type: zero for float64). A block without a record, or whose record names another key,
    another range, or does not match the bytes, is not done and is computed
    again. So after a kill, a reboot or Ctrl-C a rerun computes only the
    missing blocks, and a block from another mesh or material is never used.
``work.json``
    The key, shape, storage type and block layout; a work directory of other
    inputs is cleared (its own files only) and started afresh.

D is stored as float64 or float32 (:data:`hailstorm.runtime.bundle.format.COMPLIANCE_DTYPES`).
Blocks are solved in float64 and each is rounded to the storage type as it is
written, so a float32 D is the float64 D rounded entry by entry, and the
solver's memory is the same for both. A float32 run's key differs from the
float64 run's (``options.dtype`` is in it), so a work directory of float64
blocks is never resumed as float32 (nor the other way round): it is started
afresh, like any other inputs'.

When every block is done, :meth:`BlockStore.finish` reads D once in order
(plain reads, so file pages do not count as the process's memory), computes
the bundle's content hash of the array (the same digest as
:func:`hailstorm.runtime.bundle.format.array_hash`) and checks it is finite; the file
then moves into the bundle unchanged (:class:`hailstorm.runtime.bundle.write.StagedArray`).
D is written once: there is no assembly copy and no second copy on disk.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from hailstorm.runtime.bundle.atomic import write_text_atomic
from hailstorm.runtime.bundle.format import COMPLIANCE_DTYPES, RoundedBlock, round_block
from hailstorm.runtime.bundle.write import StagedArray

log = logging.getLogger(__name__)

__all__ = ["BlockStore", "remove_work_dir", "work_dir"]

DATA = "compliance.npy"
META = "work.json"
RECORDS = "blocks"
#: the streamed H-matrix's checkpoint (:meth:`hailstorm.precompute.hstream.StreamedH.save`)
CHECKPOINT = "stream.npz"
#: bytes read at a time by :meth:`BlockStore.finish`
READ_CHUNK = 64 * 2**20


def work_dir(out: str | os.PathLike) -> Path:
    """The work directory of bundle ``out``: ``.NAME.work`` beside it."""
    out = Path(out).absolute()
    return out.parent / f".{out.name}.work"


class BlockStore:
    """Column blocks of a column-major D on disk, each finished block durable and tagged.

    Parameters
    ----------
    path
        The work directory (:func:`work_dir`); created if needed.
    key
        The bundle's cache key: every block is tagged with it.
    shape
        (n_rows, n_cols) of D.
    blocks
        (start, stop) column range of every block, covering 0..n_cols in order.
    dtype : {"float64", "float32"}
        D's storage type: :meth:`write` rounds each (float64) block to it.

    Opening a store with the same key, shape and blocks as the one on disk
    resumes it (:attr:`done`); anything else starts afresh.
    """

    def __init__(self, path: str | os.PathLike, key: str, shape: tuple[int, int],
                 blocks: Sequence[tuple[int, int]], dtype: str | np.dtype = "float64"):
        self.path = Path(path)
        self.key = key
        self.shape = (int(shape[0]), int(shape[1]))
        self.blocks = [(int(a), int(b)) for a, b in blocks]
        self.dtype = np.dtype(dtype)
        if self.dtype not in COMPLIANCE_DTYPES.values():
            raise ValueError(f"D cannot be stored as {dtype!r}: the storage types are {' and '.join(COMPLIANCE_DTYPES)}")
        #: per finished block: (largest |entry|, largest |rounding error|) of its float64 values
        self._rounding: dict[int, tuple[float, float]] = {}
        meta = {"key": key, "shape": list(self.shape), "dtype": self.dtype.str, "blocks": [list(b) for b in self.blocks]}
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / RECORDS).mkdir(exist_ok=True)
        old = self._read_meta()
        data = self.path / DATA
        if old != meta or not data.is_file():
            if old is not None:
                old = old if isinstance(old, dict) else {}
                log.info("work directory %s was for other inputs (key %s, D as %s); starting afresh", self.path,
                         str(old.get("key"))[:12], _dtype_name(old.get("dtype")))
            self._clear_records()
            data.unlink(missing_ok=True)
            np.lib.format.open_memmap(data, mode="w+", dtype=self.dtype, shape=self.shape, fortran_order=True)
            write_text_atomic(self.path / META, json.dumps(meta))
        with open(data, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            hdr_shape, fortran, dtype = read_header(fh)
            self.offset = fh.tell()
        if tuple(hdr_shape) != self.shape or not fortran or dtype != self.dtype:
            raise OSError(f"{data}: header does not match the work directory's record")
        self.done: set[int] = self._scan_records()

    # -- records
    def _read_meta(self):
        try:
            return json.loads((self.path / META).read_text())
        except (OSError, ValueError):
            return None

    def _record(self, i: int) -> Path:
        return self.path / RECORDS / f"{i:06d}.json"

    def _clear_records(self) -> None:
        for e in os.scandir(self.path / RECORDS):
            if e.name.endswith(".json") and e.name[:-5].isdigit():
                os.unlink(e.path)

    def _byte_range(self, i: int) -> tuple[int, int]:
        start, stop = self.blocks[i]
        col = self.shape[0] * self.dtype.itemsize
        return self.offset + start * col, (stop - start) * col

    def _scan_records(self) -> set[int]:
        """Blocks whose record has this key and range and whose bytes match its hash."""
        done = set()
        size = (self.path / DATA).stat().st_size
        with open(self.path / DATA, "rb") as fh:
            for i, (start, stop) in enumerate(self.blocks):
                try:
                    rec = json.loads(self._record(i).read_text())
                except FileNotFoundError:
                    continue
                except (OSError, ValueError):
                    log.warning("block %d: unreadable record; computing it again", i)
                    continue
                if not isinstance(rec, dict) or rec.get("key") != self.key:
                    log.warning("block %d: tagged with another cache key; refusing it and computing it again", i)
                    continue
                if rec.get("columns") != [start, stop]:
                    continue
                rounding = (rec.get("max_abs"), rec.get("max_abs_error"))
                if not all(isinstance(v, (int, float)) and np.isfinite(v) for v in rounding):
                    if self.dtype != np.float64:  # a rounded block must say by how much
                        log.warning("block %d: its record lacks its rounding error; computing it again", i)
                        continue
                    rounding = (0.0, 0.0)
                off, n = self._byte_range(i)
                if off + n > size or _sha256(fh, off, n) != rec.get("sha256"):
                    log.warning("block %d: its bytes do not match its record; computing it again", i)
                    continue
                done.add(i)
                self._rounding[i] = (float(rounding[0]), float(rounding[1]))
        return done

    @property
    def missing(self) -> list[int]:
        """Blocks still to compute, in column order."""
        return [i for i in range(len(self.blocks)) if i not in self.done]

    def write(self, i: int, values: np.ndarray | RoundedBlock) -> None:
        """Write block ``i`` durably, rounded to the storage type, then record it done.

        ``values``: its (n_rows, stop - start) float64 values, or a
        :class:`RoundedBlock` already in the storage type (cast where it was solved).

        Raises ``OSError`` (a full disk...) with the blocks written before intact, and
        ``ValueError`` if an entry does not fit in the storage type (overflow) or the
        block has the wrong shape or type.
        """
        start, stop = self.blocks[i]
        if isinstance(values, RoundedBlock):
            block = values
            if block.values.dtype != self.dtype:
                raise ValueError(f"block {i}: rounded to {block.values.dtype.name}, D is stored as {self.dtype.name}")
        else:
            try:
                block = round_block(values, self.dtype)
            except ValueError as exc:
                raise ValueError(f"block {i}: {exc}") from None
        stored, scale, err = block.values, block.max_abs, block.max_abs_error
        if stored.shape != (self.shape[0], stop - start):
            raise ValueError(f"block {i}: shape {stored.shape}, expected {(self.shape[0], stop - start)}")
        stored = np.asfortranarray(stored)
        raw = memoryview(stored.T.reshape(-1)).cast("B")  # column-major bytes
        off, n = self._byte_range(i)
        fd = os.open(self.path / DATA, os.O_WRONLY)
        try:
            done = 0
            while done < n:
                done += os.pwrite(fd, raw[done:], off + done)
            os.fdatasync(fd)
        finally:
            os.close(fd)
        rec = {"key": self.key, "columns": [start, stop], "sha256": hashlib.sha256(raw).hexdigest(),
               "max_abs": scale, "max_abs_error": err}
        write_text_atomic(self._record(i), json.dumps(rec))
        self.done.add(i)
        self._rounding[i] = (scale, err)

    @property
    def rounding(self) -> tuple[float, float]:
        """(largest |entry|, largest |rounding error|) of D's float64 values over the finished
        blocks: what storing D in :attr:`dtype` cost (zeros for float64)."""
        if not self._rounding:
            return 0.0, 0.0
        return max(v[0] for v in self._rounding.values()), max(v[1] for v in self._rounding.values())

    def finish(self) -> StagedArray:
        """Hash the finished D as the bundle does and check it is finite.

        Returns
        -------
        StagedArray
            The file, its shape, dtype and content hash, for
            :func:`hailstorm.runtime.bundle.write.write_bundle`.

        Raises
        ------
        ValueError
            If a block is missing or D holds NaN or inf.
        """
        if self.missing:
            raise ValueError(f"{len(self.missing)} blocks of D are not computed yet")
        h = hashlib.sha256()
        # the prefix of hailstorm.runtime.bundle.format.array_hash for a Fortran-ordered array
        h.update(self.dtype.str.encode())
        h.update(str(self.shape).encode())
        h.update(b"F")
        bad = 0
        total = self.shape[0] * self.shape[1] * self.dtype.itemsize
        buf = bytearray(min(READ_CHUNK, max(total, 1)))
        view = memoryview(buf)
        with open(self.path / DATA, "rb", buffering=0) as fh:
            fh.seek(self.offset)
            left = total
            while left:
                got = fh.readinto(view[:min(left, len(buf))])
                if not got:
                    raise OSError(f"{self.path / DATA} is shorter than D")
                h.update(view[:got])
                vals = np.frombuffer(buf, dtype=self.dtype, count=got // self.dtype.itemsize)
                bad += int(np.count_nonzero(~np.isfinite(vals)))
                left -= got
        if bad:
            raise ValueError(f"D holds {bad} non-finite (NaN or inf) values")
        return StagedArray(self.path / DATA, self.shape, self.dtype.str, h.hexdigest())

    @property
    def data_bytes(self) -> int:
        """Size of D on disk (header included)."""
        return self.offset + self.shape[0] * self.shape[1] * self.dtype.itemsize


def remove_work_dir(path: str | os.PathLike) -> None:
    """Delete a work directory's own files (after its D went into the bundle); anything
    else in it is left, with the directory."""
    path = Path(path)
    if not path.is_dir():
        return
    if (path / RECORDS).is_dir():
        for e in os.scandir(path / RECORDS):
            if e.name.endswith(".json") and e.name[:-5].isdigit():
                os.unlink(e.path)
        try:
            (path / RECORDS).rmdir()
        except OSError:
            pass
    for name in (DATA, META, CHECKPOINT):
        (path / name).unlink(missing_ok=True)
    try:
        path.rmdir()
    except OSError:
        log.warning("left %s: it holds files hailstorm did not write", path)


def _dtype_name(code) -> str:
    if not isinstance(code, str):
        return "?"
    try:
        return np.dtype(code).name
    except TypeError:
        return "?"


def _sha256(fh, offset: int, n: int) -> str:
    h = hashlib.sha256()
    fh.seek(offset)
    left = n
    while left:
        chunk = fh.read(min(left, READ_CHUNK))
        if not chunk:
            break
        h.update(chunk)
        left -= len(chunk)
    return h.hexdigest()
