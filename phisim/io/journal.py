"""An append-only, checksummed sidecar journal that makes HDF5 output survive a kill at any moment.

HDF5 updates metadata in place (object headers, chunk indices, the superblock's end-of-file address),
and a process killed in the middle of a flush, or a file cut short by a power loss, can leave a file
that HDF5 rejects as a whole ("addr overflow", "truncated file") although the frames written before
were intact. A journal cannot be torn that way: it is only ever appended to, and every record carries
its length and a CRC-32, so any prefix of it (whatever moment the writer died at, wherever the file was
cut) decodes to the records that were complete, and a torn tail is recognised and skipped.

:class:`~phisim.io.SimulationWriter` and :class:`~phisim.io.traininglog.TrainingLog` write every frame and
record to ``<file>.journal`` before they write it to the HDF5 file, and delete the journal after the
HDF5 file was closed cleanly. A journal next to a file therefore means "not closed cleanly" (killed, or
still being written), and the readers then take the content from the journal.

Record layout (little endian): ``b"PHJ1"``, a type byte, 3 zero bytes, the payload length (uint64),
the CRC-32 of the payload (uint32), the payload. Types: ``S`` simulation header (JSON), ``F`` frame
(uint32 JSON length, JSON head, raw array bytes), ``L`` training-log snapshot of one method (JSON),
``R`` training record (JSON), ``A`` training-log attributes updated after its snapshot (JSON: the run's
completion mark), ``C`` constant fields (as a frame).

This is the lowest module of :mod:`phisim.io` (it imports no other one): :func:`load_journal` is what the
readers of both file kinds call first.
"""

from __future__ import annotations

import json
import os
import struct
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from phisim.errors import FileFormatError, IncompleteFileWarning, PhisimError

MAGIC = b"PHJ1"
_HEAD = struct.Struct("<4sB3xQI")
_U32 = struct.Struct("<I")


def journal_path(path) -> Path:
    """The journal belonging to an HDF5 file: ``<path>.journal``."""
    p = Path(path)
    if not p.name:  # '.', '/'
        p = p.absolute()
    return p.with_name((p.name or "root") + ".journal")


def write_failure(path, exc: BaseException, what: str) -> PhisimError:
    """A FileFormatError naming the file for an OS-level write failure (full disk, vanished folder...)."""
    reason = getattr(exc, "strerror", None) or str(exc)
    hint = ""
    errno = getattr(exc, "errno", None)
    if errno == 28 or "No space" in str(exc):
        hint = "; the disk is full: free space or write elsewhere"
    elif errno == 2 or "No such file" in str(exc):
        hint = "; the folder vanished while writing"
    elif errno == 13 or "ermission" in str(exc):
        hint = "; no write permission"
    return FileFormatError(f"cannot {what} {path}: {reason}{hint}")


#: Free space kept in reserve on the output file system: HDF5 metadata flushes must never meet a full disk,
#: because h5py cannot release a file whose flush failed (it crashes the interpreter when the objects are
#: freed), so a write that would leave less than this is refused beforehand with a FileFormatError.
DISK_RESERVE = 1 << 20


def check_space(path, nbytes: int) -> None:
    """Raise FileFormatError (before writing) if ``nbytes`` plus :data:`DISK_RESERVE` do not fit next to ``path``.

    Another process may still fill the disk between this check and the write; the margin covers HDF5's own
    metadata, not a race.
    """
    p = Path(path)
    try:
        st = os.statvfs(p.parent if p.parent.exists() else ".")
    except OSError:
        return  # no statvfs here (or the folder vanished: the write itself reports that)
    free = st.f_bavail * st.f_frsize
    if free < nbytes + DISK_RESERVE:
        raise FileFormatError(
            f"cannot write {p}: the disk is full ({free / 2**20:.1f} MiB free, {nbytes / 2**20:.2f} MiB needed plus "
            f"a {DISK_RESERVE >> 20} MiB reserve); free space or write elsewhere. Everything written so far stays "
            "readable"
        )


class Journal:
    """Append-only writer of journal records (see the module docstring)."""

    def __init__(self, path, *, fresh: bool):
        self.path = Path(path)
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | (os.O_TRUNC if fresh else 0)
        try:
            self._fd: int | None = os.open(self.path, flags, 0o644)
        except OSError as exc:
            raise write_failure(self.path, exc, "create the journal") from exc

    @property
    def closed(self) -> bool:
        """Whether the journal was closed."""
        return self._fd is None

    def write(self, kind: bytes, payload: bytes | bytearray | memoryview) -> None:
        """Append one record; the record is complete on disk when this returns (up to the OS cache)."""
        if self._fd is None:
            raise FileFormatError(f"journal {self.path} is closed")
        payload = memoryview(payload).cast("B")
        head = _HEAD.pack(MAGIC, kind[0], payload.nbytes, zlib.crc32(payload) & 0xFFFFFFFF)
        try:
            start = os.lseek(self._fd, 0, os.SEEK_END)
            _write_all(self._fd, head + bytes(payload) if payload.nbytes < 65536 else head)
            if payload.nbytes >= 65536:
                _write_all(self._fd, payload)
        except OSError as exc:
            try:  # drop the partial record, so records appended after the failure stay readable
                os.ftruncate(self._fd, start)
            except (OSError, UnboundLocalError):
                pass
            raise write_failure(self.path, exc, "append to the journal") from exc

    def write_json(self, kind: bytes, obj) -> None:
        """Append a record whose payload is JSON."""
        self.write(kind, json.dumps(obj, sort_keys=True, allow_nan=True).encode("utf-8"))

    def write_frame(self, head: dict, arrays: list[np.ndarray], kind: bytes = b"F") -> None:
        """Append a frame record (or, ``kind=b"C"``, the constant fields): a JSON head (array keys, shapes,
        dtypes in ``head['arrays']``) and the raw array bytes."""
        hb = json.dumps(head, sort_keys=True).encode("utf-8")
        parts = [_U32.pack(len(hb)), hb] + [np.ascontiguousarray(a).tobytes() for a in arrays]
        self.write(kind, b"".join(parts))

    def close(self, *, delete: bool) -> None:
        """Close the journal; ``delete`` removes it (the HDF5 file was closed cleanly)."""
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)
        if delete:
            try:
                self.path.unlink()
            except FileNotFoundError:
                pass


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view.nbytes:
        n = os.write(fd, view)
        view = view[n:]


@dataclass
class JournalContent:
    """What a journal holds: the simulation header, the complete frames and the training logs."""

    path: Path
    header: dict | None = None
    frames: list[tuple[dict, dict[str, np.ndarray]]] = field(default_factory=list)
    training: dict[str, dict] = field(default_factory=dict)
    constants: dict[str, np.ndarray] = field(default_factory=dict)
    torn_bytes: int = 0
    records: int = 0

    def training_curves(self) -> dict[str, dict[str, np.ndarray]]:
        """Method -> curve name -> 1-D array (``iteration`` int64, the rest float64), as ``read_training``."""
        out = {}
        for method, log in self.training.items():
            n = len(log["iteration"])
            curves = {"iteration": np.asarray(log["iteration"], dtype=np.int64)}
            for name, values in log["curves"].items():
                arr = np.full(n, np.nan)
                arr[: len(values)] = np.asarray(values, dtype=np.float64)
                curves[name] = arr
            out[method] = curves
        return out


def read_journal(path) -> JournalContent:
    """Decode every complete record of a journal; a torn or corrupt tail is counted in ``torn_bytes``.

    Raises:
        FileFormatError: If the file cannot be read or does not start like a journal.
    """
    p = Path(path)
    try:
        data = memoryview(p.read_bytes())
    except OSError as exc:
        raise FileFormatError(f"cannot read the journal {p}: {exc}") from exc
    out = JournalContent(p)
    pos = 0
    if len(data) >= 4 and bytes(data[:4]) != MAGIC:
        raise FileFormatError(f"{p} is not a phisim journal")
    while pos + _HEAD.size <= len(data):
        magic, kind, length, crc = _HEAD.unpack_from(data, pos)
        end = pos + _HEAD.size + length
        if magic != MAGIC or end > len(data):
            break
        payload = data[pos + _HEAD.size:end]
        if zlib.crc32(payload) & 0xFFFFFFFF != crc:
            break
        try:
            _apply(out, bytes([kind]), payload)
        except (ValueError, KeyError, TypeError) as exc:  # a record that passed the CRC but is malformed
            raise FileFormatError(f"{p}: malformed journal record at byte {pos}: {exc}") from exc
        out.records += 1
        pos = end
    out.torn_bytes = len(data) - pos
    return out


def _apply(out: JournalContent, kind: bytes, payload: memoryview) -> None:
    if kind == b"S":
        out.header = json.loads(bytes(payload))
        out.frames = []
    elif kind in (b"F", b"C"):
        (n,) = _U32.unpack_from(payload, 0)
        head = json.loads(bytes(payload[4:4 + n]))
        arrays = {}
        pos = 4 + n
        for key, shape, dtype in head["arrays"]:
            dt = np.dtype(dtype)
            size = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
            arrays[key] = np.frombuffer(payload[pos:pos + size], dtype=dt).reshape(shape)
            pos += size
        if pos != len(payload):
            raise ValueError("frame record length does not match its arrays")
        if kind == b"C":
            out.constants = arrays
        else:
            out.frames.append((head, arrays))
    elif kind == b"L":
        rec = json.loads(bytes(payload))
        out.training[rec["method"]] = {"attrs": rec.get("attrs", {}), "iteration": list(rec["iteration"]),
                                       "curves": {k: list(v) for k, v in rec["curves"].items()}}
    elif kind == b"A":
        rec = json.loads(bytes(payload))
        log = out.training.setdefault(rec["method"], {"attrs": {}, "iteration": [], "curves": {}})
        log["attrs"].update(rec["attrs"])
    elif kind == b"R":
        rec = json.loads(bytes(payload))
        log = out.training.setdefault(rec["method"], {"attrs": {}, "iteration": [], "curves": {}})
        n = len(log["iteration"])
        for name in rec["values"]:
            log["curves"].setdefault(name, [float("nan")] * n)
        for name, values in log["curves"].items():
            values.extend([float("nan")] * (n - len(values)))
            values.append(float(rec["values"].get(name, float("nan"))))
        log["iteration"].append(int(rec["iteration"]))
    else:
        raise ValueError(f"unknown record type {kind!r}")


def load_journal(p: Path) -> JournalContent | None:
    """The journal next to ``p`` decoded, with an :class:`~phisim.errors.IncompleteFileWarning`, or None when
    there is none (the file was closed cleanly).

    Raises:
        FileFormatError: If the journal is unreadable.
    """
    jp = journal_path(p)
    if not jp.exists():
        return None
    content = read_journal(jp)
    torn = f"; a torn tail of {content.torn_bytes} bytes (an unfinished record) was skipped" \
        if content.torn_bytes else ""
    warnings.warn(
        f"{p} was not closed cleanly (the writer was killed, ran out of disk, or is still running): reading its "
        f"{len(content.frames)} complete frame(s) and {len(content.training)} training log(s) from the journal "
        f"{jp.name}{torn}. phisim.io.recover_file rebuilds a clean file.",
        IncompleteFileWarning,
        stacklevel=3,
    )
    return content
