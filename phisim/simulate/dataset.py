"""Datasets of simulations in The Well's layout, generated in parallel and resumable (``phisim simulate``).

A run resolves a configuration (:func:`resolve_config`: scenario defaults, a YAML/JSON file, flags), plans
``ceil(trajectories / trajectories_per_file)`` files and writes::

    OUT/config.json                 the resolved configuration (also in every file's /extras/config)
    OUT/stats.yaml                  normalisation statistics of the training split (The Well's loader reads it)
    OUT/data/train/<scenario>_00000.h5 ...   one file per chunk of trajectories
    OUT/data/valid/...  OUT/data/test/...

File ``i`` is simulated from a generator seeded with ``(seed, i)``: its parameters (the scenario's ranged
parameters, drawn once per file, stored as the file's scalars) and its trajectories' initial states depend
only on the seed and ``i``, so the files do not depend on the number of workers or ranks. Each file is
written under a temporary name and renamed when complete; rerunning the same command skips complete files
(a killed run continues where it stopped). ``workers`` runs files in parallel processes; under
``torchrun`` (``WORLD_SIZE`` > 1) rank ``r`` simulates the files ``i ≡ r (mod world_size)`` and rank 0
writes the statistics once all ranks are done (a gloo process group is started for the barrier when none
exists; ranks on several nodes need ``OUT`` on a file system they share).

Interrupts: SIGINT (Ctrl-C) and SIGTERM stop a run within about a second, workers included (they ignore the
terminal's SIGINT and are stopped by the main process with SIGTERM, then killed if they do not exit). Every
file already renamed to its final name is complete; unfinished ``.part`` files are removed, and rerunning the
same command continues with the missing files, which come out bit for bit as in an uninterrupted run.
"""

from __future__ import annotations

import difflib
import inspect
import json
import math
import multiprocessing as mp
import multiprocessing.connection
import os
import pickle
import shutil
import signal
import sys
import time
import traceback
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from phisim.checks import check_progress
from phisim.errors import FileFormatError, ParameterError
from phisim.io import SimulationWriter, write_statistics
from phisim.io.interrupts import Interrupted, check_interrupt, interruptible, uninterrupted
from phisim.io.journal import journal_path
from phisim.simulate.scenarios import COMMON_PARAMETERS, SCENARIOS, Scenario

__all__ = ["ChunkPlan", "get_scenario", "resolve_config", "load_config_file", "plan_chunks", "simulate_chunk",
           "simulate_dataset", "check_dataset_dir", "split_shortfall", "SPLITS"]

SPLITS = ("train", "valid", "test")
_DTYPES = {"float32": torch.float32, "float64": torch.float64}
_RUN_ONLY = ("device",)  # settings that may differ when a run is continued


def _suggest(name: str, valid) -> str:
    close = difflib.get_close_matches(str(name), list(valid), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def get_scenario(name: str) -> Scenario:
    """The scenario called ``name``.

    Raises:
        ParameterError: Unknown name (the closest is suggested).
    """
    if name not in SCENARIOS:
        raise ParameterError(f"unknown scenario {name!r}{_suggest(name, SCENARIOS)} (choose from "
                             f"{', '.join(SCENARIOS)})")
    return SCENARIOS[name]


def load_config_file(path: str | os.PathLike) -> dict:
    """Read a configuration file: JSON (``.json``) or YAML (``.yaml``/``.yml``, needs PyYAML).

    Raises:
        FileFormatError: Missing or unparsable file, or not a mapping at the top level.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"config file {path} does not exist")
    text = path.read_text(encoding="utf-8")
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError as exc:
                raise FileFormatError(f"{path}: reading YAML needs PyYAML (pip install pyyaml); "
                                      "or write the config as JSON") from exc
            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
    except (ValueError, Exception) as exc:  # noqa: BLE001 - yaml/json parse errors
        if isinstance(exc, FileFormatError):
            raise
        raise FileFormatError(f"cannot parse config file {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise FileFormatError(f"config file {path} must hold a mapping of settings, got {type(data).__name__}")
    return data


def _check_int(cfg: dict, key: str, low: int) -> None:
    v = cfg[key]
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
        raise ParameterError(f"{key} must be an integer >= {low}, got {v!r}")
    cfg[key] = int(v)


def resolve_config(scenario: str, config: Mapping[str, Any] | None = None, **overrides) -> dict:
    """The complete configuration of a run: scenario defaults, then ``config``, then ``overrides``.

    Keys are the :data:`~phisim.simulate.scenarios.COMMON_PARAMETERS` and the scenario's parameters. A
    ranged scenario parameter left unset stays ``None`` (drawn per file when ``randomize`` is on).

    Args:
        scenario: Scenario name (a ``scenario`` key in ``config`` must agree).
        config: Settings, e.g. from :func:`load_config_file`.
        **overrides: Settings from flags (``None`` values are ignored).

    Returns:
        The configuration (a plain JSON-serialisable dict, ``scenario`` included).

    Raises:
        ParameterError: Unknown scenario or key (the closest valid name is suggested) or an invalid value.
    """
    sc = get_scenario(scenario)
    if not sc.available:
        sc.build({}, {}, 0, None, None, None)  # raises the scenario's own explanation
    merged = dict(config or {})
    if "scenario" in merged and merged.pop("scenario") != scenario:
        raise ParameterError(f"the config file is for scenario {config['scenario']!r}, not {scenario!r}")
    merged.update({k: v for k, v in overrides.items() if v is not None})
    valid = {**COMMON_PARAMETERS, **sc.parameters}
    for key in merged:
        if key not in valid:
            raise ParameterError(f"unknown setting {key!r} for scenario {scenario!r}{_suggest(key, valid)}")
    cfg: dict[str, Any] = {"scenario": scenario}
    for key, par in valid.items():
        cfg[key] = merged.get(key, None if (par.low is not None and key in sc.parameters) else par.default)
    cfg["dim"] = sc.dims[0] if cfg["dim"] is None else cfg["dim"]
    if cfg["dim"] not in sc.dims:
        raise ParameterError(f"scenario {scenario!r} runs in {' or '.join(f'{d}-D' for d in sorted(sc.dims))}, not "
                             f"dim={cfg['dim']!r}")
    cfg["resolution"] = sc.resolution if cfg["resolution"] is None else cfg["resolution"]
    r = cfg["resolution"]
    rs = [r] if isinstance(r, (int, np.integer)) and not isinstance(r, bool) else list(r) if isinstance(
        r, (list, tuple)) else None
    if not rs or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 4 for v in rs):
        raise ParameterError(f"resolution must be an integer >= 4 or a list of them, got {r!r}")
    cfg["resolution"] = int(rs[0]) if isinstance(r, (int, np.integer)) else [int(v) for v in rs]
    cfg["dt"] = sc.dt if cfg["dt"] is None else float(cfg["dt"])
    cfg["steps"] = sc.steps if cfg["steps"] is None else cfg["steps"]
    if not (math.isfinite(cfg["dt"]) and cfg["dt"] > 0):
        raise ParameterError(f"dt must be finite and > 0, got {cfg['dt']}")
    for key, low in (("seed", 0), ("trajectories", 1), ("trajectories_per_file", 1), ("steps", 1),
                     ("save_every", 1)):
        _check_int(cfg, key, low)
    for key in ("valid_fraction", "test_fraction"):
        v = cfg[key]
        if not isinstance(v, (int, float)) or not 0 <= v < 1:
            raise ParameterError(f"{key} must be in [0, 1), got {v!r}")
    if cfg["valid_fraction"] + cfg["test_fraction"] >= 1:
        raise ParameterError("valid_fraction + test_fraction must leave files for training (< 1)")
    if cfg["dtype"] not in _DTYPES:
        raise ParameterError(f"dtype must be one of {sorted(_DTYPES)}, got {cfg['dtype']!r}")
    cfg["randomize"] = bool(cfg["randomize"])
    for key, par in sc.parameters.items():
        v = cfg[key]
        if v is not None and not isinstance(v, (bool, int, float)):
            raise ParameterError(f"{key} must be a number, got {v!r}")
        if isinstance(par.default, bool):
            cfg[key] = bool(v) if v is not None else None
    return cfg


@dataclass(frozen=True)
class ChunkPlan:
    """One output file.

    Attributes:
        index: File index (seeds its generator).
        split: ``'train'``, ``'valid'`` or ``'test'``.
        trajectories: Number of trajectories in the file.
        path: Path relative to the dataset folder (``data/<split>/<scenario>_<index>.h5``).
    """

    index: int
    split: str
    trajectories: int
    path: str


def plan_chunks(cfg: Mapping[str, Any]) -> list[ChunkPlan]:
    """The files of a run: sizes, splits (train first, then valid, then test) and paths.

    With at least three files, a non-zero fraction gets at least one file.
    """
    per, total = cfg["trajectories_per_file"], cfg["trajectories"]
    n = math.ceil(total / per)

    def count(frac):
        k = round(frac * n)
        return max(1, k) if frac > 0 and n >= 3 else k

    n_valid, n_test = count(cfg["valid_fraction"]), count(cfg["test_fraction"])
    n_train = n - n_valid - n_test
    if n_train < 1:
        raise ParameterError(f"{n} file(s) leave none for training; lower valid/test_fraction or add trajectories")
    chunks = []
    for i in range(n):
        split = "train" if i < n_train else "valid" if i < n_train + n_valid else "test"
        size = min(per, total - i * per)
        chunks.append(ChunkPlan(i, split, size, f"data/{split}/{cfg['scenario']}_{i:05d}.h5"))
    return chunks


def split_shortfall(cfg: Mapping[str, Any], chunks: Sequence[ChunkPlan] | None = None) -> str | None:
    """What a run's plan leaves out of its splits, in words, or None when every split it asks for gets files.

    Splits are made of whole files, and below three files no file goes to ``valid`` or ``test``: with the
    defaults (8 trajectories, 4 per file) every file lands in ``train``. Training on such a dataset then has
    no held-out data of its own.
    """
    chunks = plan_chunks(cfg) if chunks is None else chunks
    missing = [sp for sp, frac in (("valid", cfg["valid_fraction"]), ("test", cfg["test_fraction"]))
               if frac > 0 and not any(c.split == sp for c in chunks)]
    if not missing:
        return None
    n, per, total = len(chunks), cfg["trajectories_per_file"], cfg["trajectories"]
    empty = " and ".join(f"data/{m}" for m in missing) + (" stays" if len(missing) == 1 else " stay") + " empty"
    if n >= 3:
        hint = "raise valid_fraction / test_fraction or add trajectories"
    elif total >= 3:
        hint = (f"a split gets a file only from 3 files on: e.g. --trajectories {3 * per} or "
                f"--trajectories-per-file {total // 3}")
    else:
        hint = f"a split gets a file only from 3 files on: e.g. --trajectories {3 * per}"
    return (f"{total} trajectories make {n} file(s) of up to {per}, and splits are whole files: {empty} "
            f"({hint}); training on this dataset has no held-out data of its own")


def _generator(seed: int, index: int) -> torch.Generator:
    g = torch.Generator(device="cpu")
    g.manual_seed((int(seed) * 1_000_003 + 7919 * int(index) + 1) % (2**63 - 1))
    return g


def _draw_parameters(sc: Scenario, cfg: Mapping[str, Any], g: torch.Generator) -> dict:
    params = {}
    for key, par in sc.parameters.items():  # always draw, so fixing one parameter leaves the others' draws
        u = float(torch.rand((), generator=g, dtype=torch.float64)) if par.low is not None else None
        v = cfg[key]
        if v is None:
            v = par.low + (par.high - par.low) * u if cfg["randomize"] else par.default
        params[key] = v
    return params


def _writer_supports(name: str) -> bool:
    return name in inspect.signature(SimulationWriter.__init__).parameters


def _part_path(root: str | os.PathLike, chunk: ChunkPlan) -> Path:
    final = Path(root) / chunk.path
    return final.with_name(final.name + ".part")


def _remove_part(root: str | os.PathLike, chunk: ChunkPlan) -> None:
    """Delete the unfinished temporary file of a chunk (and its journal)."""
    tmp = _part_path(root, chunk)
    tmp.unlink(missing_ok=True)
    journal_path(tmp).unlink(missing_ok=True)


def simulate_chunk(cfg: Mapping[str, Any], chunk: ChunkPlan, root: str | os.PathLike) -> Path:
    """Simulate one file of a dataset and write it (under a temporary name, renamed when complete).

    Args:
        cfg: Resolved configuration (:func:`resolve_config`).
        chunk: The file (:func:`plan_chunks`).
        root: The dataset folder.

    Returns:
        The path of the written file.

    An exception (an interrupt included) removes the temporary file: the final name only ever holds a
    complete file.
    """
    sc = get_scenario(cfg["scenario"])
    g = _generator(cfg["seed"], chunk.index)
    params = _draw_parameters(sc, cfg, g)
    dtype, device = _DTYPES[cfg["dtype"]], torch.device(cfg["device"])
    sim = sc.build(cfg, params, chunk.trajectories, g, dtype, device)
    final = Path(root) / chunk.path
    tmp = _part_path(root, chunk)
    fields = dict(sim.fields)
    kwargs = {}
    constants = {k: v.detach().cpu().numpy() for k, v in sim.constant_fields.items()}
    if constants and _writer_supports("constant_fields"):
        kwargs["constant_fields"] = constants
        constants = {}
    else:  # written per frame when the writer has no constant fields
        fields.update({k: "scalar" for k in constants})
    interval = cfg["dt"] * cfg["save_every"]
    if _writer_supports("output_interval"):
        kwargs["output_interval"] = interval
    file_cfg = {**dict(cfg), "file_index": chunk.index, "split": chunk.split, "drawn_parameters": params}
    numeric = {k: (int(v) if isinstance(v, bool) else v) for k, v in params.items()}

    def frame(state):
        out = sim.frame(state)
        for k, v in constants.items():
            out[k] = np.broadcast_to(v, (chunk.trajectories, *sim.grid.resolution))
        return out

    state = sim.state
    try:
        with SimulationWriter(tmp, sim.grid, sim.boundary, dataset_name=f"phisim_{cfg['scenario']}", fields=fields,
                              parameters=numeric, batch_size=chunk.trajectories, config=file_cfg,
                              dtype=dtype, **kwargs) as w:
            w.append(0.0, **frame(state))
            with torch.no_grad():
                for k in range(1, cfg["steps"] + 1):
                    check_interrupt()  # a SIGTERM recorded by a worker (or swallowed by a callback) stops here
                    state = sim.step(state)
                    if k % cfg["save_every"] == 0:
                        w.append((k // cfg["save_every"]) * interval, **frame(state))
        with uninterrupted():
            os.replace(tmp, final)
    except BaseException:
        _remove_part(root, chunk)
        raise
    return final


# ---- worker processes ------------------------------------------------------------------------------------

#: Seconds the main process waits for stopped workers to clean up before it kills them.
STOP_GRACE = 0.8


def _worker(cfg: dict, root: str, threads: int, conn) -> None:
    """Worker-process entry: simulate the chunks received on ``conn`` until ``None`` (or the main process
    closes it); report each as done (or failed) on ``conn``.

    The terminal's SIGINT is ignored (the main process decides); SIGTERM stops the chunk at its next step
    (:func:`~phisim.io.interrupts.check_interrupt` in :func:`simulate_chunk`), which removes the unfinished file.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # blocked while the process started
    torch.set_num_threads(max(1, threads))
    with interruptible(raise_now=False):
        try:
            _work(cfg, root, conn)
        except (Interrupted, EOFError, OSError):  # stopped, or the main process is gone
            pass
    conn.close()
    # Every file is closed or removed: end without the interpreter's teardown of torch (a second or more on a
    # busy machine), so the main process need not wait for it.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _work(cfg: dict, root: str, conn) -> None:
    while True:
        chunk = conn.recv()
        if chunk is None:
            return
        try:
            simulate_chunk(cfg, chunk, root)
        except Interrupted:
            raise
        except BaseException as exc:  # noqa: BLE001 - reported to the main process, which raises it
            try:
                pickle.dumps(exc)
            except Exception:  # noqa: BLE001 - an exception that cannot travel: its text does
                exc = RuntimeError(f"{type(exc).__name__}: {exc}")
            conn.send(("error", chunk.index, exc, traceback.format_exc()))
            return
        conn.send(("done", chunk.index, chunk.trajectories, None))


def _run_workers(cfg: dict, todo: Sequence[ChunkPlan], root: Path, workers: int, bar) -> None:
    """Simulate ``todo`` in ``workers`` spawned processes, each fed one chunk at a time through a pipe; on any
    exception (an interrupt included) stop them within :data:`STOP_GRACE` seconds (SIGTERM and closed pipes,
    then SIGKILL) and remove their unfinished files."""
    ctx = mp.get_context("spawn")
    n = min(workers, len(todo))
    threads = max(1, (os.cpu_count() or 1) // workers)
    pipes = [ctx.Pipe() for _ in range(n)]
    procs = [ctx.Process(target=_worker, args=(cfg, str(root), threads, child), daemon=True)
             for _, child in pipes]
    conns = [parent for parent, _ in pipes]
    waiting = list(todo)
    try:
        blocked = hasattr(signal, "pthread_sigmask")
        if blocked:  # workers start with SIGINT blocked (a Ctrl-C meant for the main process is not theirs)
            old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            for p in procs:
                p.start()
        finally:
            if blocked:
                signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
            for _, child in pipes:
                child.close()
        active = list(conns)  # the workers working on a chunk
        for conn in conns:
            _feed(conn, waiting, active)
        remaining = len(todo)
        while remaining:
            ready = multiprocessing.connection.wait(active, timeout=0.5)
            for conn in ready:
                try:
                    kind, index, value, tb = conn.recv()
                except EOFError:
                    codes = [p.exitcode for p in procs]
                    raise RuntimeError(f"a simulation worker process ended unexpectedly (exit codes {codes})"
                                       ) from None
                if kind == "error":
                    if isinstance(value, BaseException):
                        raise value
                    raise RuntimeError(f"file {index}: {value}\n{tb}")
                remaining -= 1
                if bar is not None:
                    bar.update(value)
                _feed(conn, waiting, active)
        deadline = time.monotonic() + 5.0  # all done: the workers took their end marks and exit
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
    finally:
        _stop(procs, conns)
        for c in todo:
            if not (root / c.path).exists():
                _remove_part(root, c)


def _feed(conn, waiting: list, active: list) -> None:
    """Send a worker its next chunk, or its end mark (it then leaves ``active``)."""
    if waiting:
        conn.send(waiting.pop(0))
    else:
        conn.send(None)
        active.remove(conn)


def _stop(procs: list, conns: list) -> None:
    """Stop worker processes: SIGTERM and closed pipes, then SIGKILL for those still alive after the grace."""
    for p in procs:
        if p.is_alive():
            p.terminate()
    for conn in conns:
        conn.close()
    deadline = time.monotonic() + STOP_GRACE
    for p in procs:
        if p.pid is not None:
            p.join(max(0.0, deadline - time.monotonic()))
    for p in procs:
        if p.is_alive():
            p.kill()
            p.join()


def _rank_world() -> tuple[int, int, bool]:
    """(rank, world size, whether this call initialised the process group)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), False
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and dist.is_available() and "MASTER_ADDR" in os.environ:
        dist.init_process_group("gloo")
        return dist.get_rank(), dist.get_world_size(), True
    return int(os.environ.get("RANK", "0")), world, False


def _prepare_root(root: Path, cfg: dict, overwrite: bool, rank: int) -> None:
    if root.exists() and not root.is_dir():
        raise FileFormatError(f"{root} exists and is not a folder")
    saved = root / "config.json"
    if saved.exists():
        try:
            old = json.loads(saved.read_text(encoding="utf-8"))
        except ValueError as exc:
            raise FileFormatError(f"{saved} is not valid JSON: {exc}") from exc
        same = {k: v for k, v in old.items() if k not in _RUN_ONLY} == {
            k: v for k, v in cfg.items() if k not in _RUN_ONLY}
        if not same and not overwrite:
            diff = sorted(k for k in set(old) | set(cfg) if k not in _RUN_ONLY and old.get(k) != cfg.get(k))
            raise ParameterError(f"{root} holds a dataset with other settings ({', '.join(diff)}); continue it "
                                 "with the same settings, choose another output folder or pass --overwrite")
        if not same and overwrite and rank == 0:
            shutil.rmtree(root / "data", ignore_errors=True)
            (root / "stats.yaml").unlink(missing_ok=True)
    elif root.is_dir() and (root / "data").exists() and rank == 0:
        if not overwrite:
            raise ParameterError(f"{root}/data exists but {saved.name} does not: not a phisim dataset folder; "
                                 "choose another output folder or pass --overwrite")
        shutil.rmtree(root / "data")
    if rank == 0:
        for split in SPLITS:
            (root / "data" / split).mkdir(parents=True, exist_ok=True)
        tmp = saved.with_name("config.json.tmp")
        tmp.write_text(json.dumps(cfg, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        os.replace(tmp, saved)


def _write_statistics(root: Path) -> Path:
    """The loader's ``stats.yaml`` over the training split (:func:`phisim.io.stats.write_statistics`)."""
    return write_statistics(root)


def simulate_dataset(
    out: str | os.PathLike,
    cfg: Mapping[str, Any],
    *,
    workers: int = 1,
    progress: bool | None = None,
    overwrite: bool = False,
) -> dict:
    """Generate (or continue) a dataset folder for a resolved configuration.

    Args:
        out: The dataset folder.
        cfg: Configuration from :func:`resolve_config`.
        workers: Parallel worker processes on this machine (each gets ``cpu_count // workers`` threads).
        progress: Show a progress bar over trajectories on stderr (None: when stderr is a terminal).
        overwrite: Replace a dataset with other settings in ``out``.

    Returns:
        ``{'root', 'files', 'written', 'skipped', 'trajectories', 'stats', 'files_per_split'}``
        (``files_per_split``: ``{'train': n, 'valid': n, 'test': n}``).

    Warns:
        UserWarning: The run is too small for its splits: ``valid_fraction`` or ``test_fraction`` asks for
            files that fewer than three files cannot give (:func:`split_shortfall`), so the split stays empty.

    Raises:
        ParameterError: Bad ``workers``, or ``out`` holds another dataset.
        FileFormatError: ``out`` is not a folder.
        KeyboardInterrupt: SIGINT, or SIGTERM (:class:`phisim.io.interrupts.Interrupted`): the run stopped,
            workers included; finished files are complete, unfinished ones removed. Rerun to continue.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ParameterError(f"workers must be an integer >= 1, got {workers!r}")
    progress = check_progress(progress)
    with interruptible():  # SIGTERM stops the run as Ctrl-C does
        return _simulate_dataset(out, cfg, workers, progress, overwrite)


def _simulate_dataset(out, cfg, workers: int, progress: bool, overwrite: bool) -> dict:
    cfg = dict(cfg)
    root = Path(out)
    rank, world, own_group = _rank_world()
    _prepare_root(root, cfg, overwrite, rank)
    if world > 1:
        _barrier()
    chunks = plan_chunks(cfg)
    shortfall = split_shortfall(cfg, chunks)
    if shortfall and rank == 0:
        warnings.warn(shortfall, UserWarning, stacklevel=3)
    mine = [c for c in chunks if c.index % world == rank]
    todo = [c for c in mine if not (root / c.path).exists()]
    done_traj = sum(c.trajectories for c in mine) - sum(c.trajectories for c in todo)
    bar = None
    if progress and rank == 0:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(c.trajectories for c in mine), initial=done_traj, unit="traj",
                   desc=f"simulate {cfg['scenario']}")
    try:
        if workers == 1 or len(todo) <= 1:
            for c in todo:
                simulate_chunk(cfg, c, root)
                if bar is not None:
                    bar.update(c.trajectories)
        else:
            _run_workers(cfg, todo, root, workers, bar)
    finally:
        if bar is not None:
            bar.close()
    if world > 1:
        _barrier()
    stats = None
    if rank == 0:
        stats = _write_statistics(root)
    if own_group:
        import torch.distributed as dist

        dist.destroy_process_group()
    return {"root": root, "files": len(chunks), "written": len(todo), "skipped": len(mine) - len(todo),
            "trajectories": cfg["trajectories"], "stats": stats,
            "files_per_split": {sp: sum(c.split == sp for c in chunks) for sp in SPLITS}}


def _barrier() -> None:
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def check_dataset_dir(path: str | os.PathLike, split: str | None = None) -> list[Path]:
    """The HDF5 files of a dataset folder in The Well's layout (``<path>/data/<split>/*.h5``).

    Args:
        path: The dataset folder.
        split: One split, or None for all three.

    Returns:
        The files, sorted.

    Raises:
        FileFormatError: The folder or split does not exist or holds no ``.h5``/``.hdf5`` file.
    """
    root = Path(path)
    if not root.is_dir():
        raise FileFormatError(f"dataset folder {root} does not exist")
    splits = SPLITS if split is None else (split,)
    if split is not None and split not in SPLITS:
        raise ParameterError(f"split must be one of {SPLITS}, got {split!r}")
    files: list[Path] = []
    for s in splits:
        folder = root / "data" / s
        if folder.is_dir():
            files += sorted([*folder.glob("*.h5"), *folder.glob("*.hdf5")])
    if not files:
        where = f"data/{split}" if split else "data/{train,valid,test}"
        raise FileFormatError(f"{root} is not a dataset in The Well's layout: no .h5 files in {where}/ "
                              "(expected <dataset>/data/<split>/*.h5, e.g. from `phisim simulate`)")
    return files
