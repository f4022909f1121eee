"""FFTW wisdom: isolated estimated plans (the default) and a per-machine wisdom file for measured ones (opt-in).

**Estimated plans (default, bit-reproducible).** ``FFTW_ESTIMATE`` chooses a plan from a fixed cost model, so
it depends only on the transform (sizes, strides, kinds), the buffers' alignment, the thread count and the
SIMD instructions of the CPU, with one exception: FFTW also uses any wisdom in the process's memory made with
at least the requested rigor, so an estimated plan made after a measured one (or after a library imported
wisdom) can differ from the same plan in a fresh process (seen: a 512² REDFT10 and a 256² float32 real FFT
changed their last bits). :func:`plan` therefore builds every estimated plan from an *empty* wisdom table
(the wisdom present is exported, forgotten, and imported back afterwards), and the estimated plan leaves no
wisdom behind. Estimated plans read and write no file.

**Measured plans (opt-in).** ``FFTW_MEASURE`` picks among candidate algorithms by timing them, so two processes
planning the same transform can pick different algorithms whose round-off differs (a 64x96 plume differed
from frame 3-5 on, 7e-7 growing to 1e-4). To narrow that, every measured plan is made under an exclusive
lock on a wisdom file, after importing the wisdom already in it: a transform planned before (by any process)
is rebuilt from that wisdom without timing anything, and a new one is measured once and its wisdom saved.
That makes processes *on one warm machine* agree, but not a machine without wisdom (or another machine, or a
loaded one measuring afresh) with a warm one: measured plans are not bit-reproducible across machines.

The file: ``$PHISIM_FFTW_WISDOM`` if set (``off`` disables it: measured plans are then made per process),
else ``~/.cache/phisim/fftw-wisdom-<machine>.bin`` (``$XDG_CACHE_HOME`` respected), keyed by CPU model, FFTW
and pyfftw versions (wisdom is not portable between machines). If the file cannot be used, measured plans
fall back to isolated estimated ones with a one-time warning.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import struct
import threading
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

_MAGIC = b"PHFW1"
_LOCK = threading.RLock()
_STATE: dict = {"path": None, "resolved": False, "saved": None, "warned": False, "empty": None}


def _machine_key(pyfftw) -> str:
    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    info = "|".join([platform.machine(), model, getattr(pyfftw, "__version__", "?"),
                     str(getattr(pyfftw, "_fftw_version", ""))])
    return hashlib.sha1(info.encode()).hexdigest()[:12]


def wisdom_path(pyfftw) -> Path | None:
    """The wisdom file of this machine, or None when disabled by ``PHISIM_FFTW_WISDOM=off``."""
    if not _STATE["resolved"]:
        env = os.environ.get("PHISIM_FFTW_WISDOM", "").strip()
        if env.lower() in ("off", "0", "none", "false"):
            path = None
        elif env:
            path = Path(env).expanduser()
        else:
            base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
            path = base / "phisim" / f"fftw-wisdom-{_machine_key(pyfftw)}.bin"
        _STATE.update(path=path, resolved=True)
    return _STATE["path"]


def _decode(data: bytes) -> tuple[bytes, ...] | None:
    if not data.startswith(_MAGIC):
        return None
    out, pos = [], len(_MAGIC)
    for _ in range(3):
        if pos + 8 > len(data):
            return None
        (n,) = struct.unpack_from("<Q", data, pos)
        pos += 8
        out.append(data[pos:pos + n])
        pos += n
    return tuple(out)


def _encode(wisdom: tuple[bytes, ...]) -> bytes:
    return _MAGIC + b"".join(struct.pack("<Q", len(w)) + w for w in wisdom)


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    import fcntl

    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(str(path) + ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def _estimate(pyfftw, build: Callable[[str], object]):
    """``build('FFTW_ESTIMATE')`` from an empty wisdom table; the wisdom held before is restored, none is added."""
    with _LOCK:
        held = tuple(pyfftw.export_wisdom())
        pyfftw.forget_wisdom()
        try:
            return build("FFTW_ESTIMATE")
        finally:
            pyfftw.forget_wisdom()
            if _STATE["empty"] is None:  # what export_wisdom gives for an empty table
                _STATE["empty"] = tuple(pyfftw.export_wisdom())
            if held != _STATE["empty"]:
                pyfftw.import_wisdom(held)


def plan(pyfftw, build: Callable[[str], object], effort: str):
    """Build an FFTW plan with ``build(effort)``.

    ``FFTW_ESTIMATE`` plans are built from an empty wisdom table (bit-reproducible, see the module notes). Other
    efforts go through the wisdom file; when it is disabled they are built as asked (not reproducible across
    processes), when it is unusable they fall back to isolated ``FFTW_ESTIMATE`` plans.
    """
    if effort == "FFTW_ESTIMATE":
        return _estimate(pyfftw, build)
    path = wisdom_path(pyfftw)
    if path is None:
        with _LOCK:
            return build(effort)
    with _LOCK:
        try:
            with _file_lock(path):
                try:
                    stored = _decode(path.read_bytes())
                except FileNotFoundError:
                    stored = None
                if stored is not None and stored != _STATE["saved"]:
                    pyfftw.import_wisdom(stored)
                fftw = build(effort)
                wisdom = tuple(pyfftw.export_wisdom())
                if wisdom != stored:
                    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
                    try:
                        tmp.write_bytes(_encode(wisdom))
                        os.replace(tmp, path)
                    finally:
                        tmp.unlink(missing_ok=True)
                _STATE["saved"] = wisdom
                return fftw
        except (OSError, ImportError) as exc:
            failure = exc
    if not _STATE["warned"]:
        _STATE["warned"] = True
        warnings.warn(
            f"phisim cannot use the FFTW wisdom file {path} ({failure}); planning with FFTW_ESTIMATE so that "
            "results stay identical across processes (slower for some transforms). Set "
            "PHISIM_FFTW_WISDOM to a writable file for measured plans.",
            RuntimeWarning,
            stacklevel=4,
        )
    return _estimate(pyfftw, build)
