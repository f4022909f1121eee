"""Every code block of README.md and docs/*.md runs (issue 26, item 1).

What runs, and how:

* ```` ```python ```` blocks are executed with ``exec`` in a temporary working directory (files they write land
  there). Fences of Python blocks start in column 0: an indented block (inside a list item) would not run when
  pasted, so it fails here too.

  - ``README.md``: each block in a fresh namespace (each is a complete example). They run in one folder
    prepared as the README says: ``out/demo`` as ``bash run.sh demo`` writes it (``examples/demo.py``'s
    simulation, at 16 cells and 3 steps) and the files of the README's ``phisim`` lines, which run first.
  - ``docs/TUTORIAL_custom_physics.md``: one namespace, blocks in document order (they build on each other:
    functions, problem, training, loading), interleaved with the page's ``phisim`` lines; ``examples/`` is
    linked into the folder (the page runs from the repository root). Its problem must be the example file's.
  - every other document: each block in a fresh namespace, in a folder of its own.

* ```` ```bash ```` blocks: the lines that start with ``phisim`` run in a subprocess of this virtual
  environment (see :class:`Phisim`), in document order: the README's (its command-line training, then the
  "Daily workflows") and the tutorial's. Other shell lines (``bash run.sh``, ``python examples/...``,
  ``torchrun``) are long runs the examples' own tests cover.
* ```` ```yaml ```` blocks whose first line is ``# <file name>`` are written to that file when reached (the
  README's ``burgers.yaml``).
* ```` ```text ```` (and other languages) are listings: not run. Every fence names its language (the check
  skips ``docs/BENCHMARKS*.md``, whose tables and commands belong to the benchmarks).

Small sizes (the switch): the documents show realistic sizes; by default the test runs them smaller and
says exactly how, so the whole file takes about a minute on two cores:

* Python blocks: the text replacements of :data:`SMALL_EDITS` (each must match, so a changed snippet is
  noticed here rather than silently run at full size);
* ``phisim`` lines: the flags of :data:`SMALL_FLAGS`, keyed by the line's ``--out``, are appended (argparse
  keeps the last value of a flag; ``--set`` and ``--setting`` the last per key).

``PHISIM_DOCS_FULL=1 python -m pytest tests/test_docs.py`` runs the documents exactly as written, every
``phisim`` line in a process of its own (the README's dataset and training sizes: an hour or more on two
cores; not part of any default or ``slow`` run).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TUTORIAL = ROOT / "docs" / "TUTORIAL_custom_physics.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]

#: Text replacements of Python blocks for the default (small) run: ``{document: [(old, new), ...]}``.
SMALL_EDITS: dict[str, list[tuple[str, str]]] = {
    "README.md": [("iterations=100", "iterations=2"), ('resolution=(32, 32)', 'resolution=(16, 16)')],
    "docs/TUTORIAL_custom_physics.md": [("iterations=200", "iterations=2")],
}

_SIM = ["--trajectories", "2", "--trajectories-per-file", "2", "--workers", "1", "--quiet"]
_TRAIN = ["--iterations", "2", "--batch-size", "2", "--quiet"]

#: Flags appended to ``phisim`` lines for the default (small) run, keyed by the line's ``--out``.
SMALL_FLAGS: dict[str, list[str]] = {
    # README: training from the command line, then "Daily workflows"
    "out/poisson_cli.h5": ["--iterations", "2", "--resolution", "16", "16", "--quiet"],
    "data/smoke": [*_SIM, "--steps", "5", "--resolution", "16"],   # the loader block reads 4 + 1 frames
    "data/burgers": [*_SIM, "--steps", "2", "--resolution", "16"],
    "out/b.h5": [*_TRAIN, "--setting", "steps=2"],
    "data/later": [*_SIM, "--steps", "2"],
    "data/heat": [*_SIM, "--trajectories", "4", "--steps", "3", "--resolution", "8"],
    "out/w.h5": [*_TRAIN, "--setting", "levels=2", "--setting", "filters=4"],
    # the tutorial
    "out/burgers_cli.h5": [*_TRAIN, "--setting", "steps=2"],
    "data/burgers1d": [*_SIM, "--trajectories", "4", "--steps", "3"],
    "out/well.h5": [*_TRAIN, "--setting", "levels=2", "--setting", "filters=4"],
}

FULL = os.environ.get("PHISIM_DOCS_FULL", "") not in ("", "0")
FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<ticks>`{3,}|~{3,})(?P<lang>[^\s`]*)[^`]*$")


@dataclass
class Block:
    doc: str  # path relative to the repository root
    line: int  # first line of the content (1-based)
    lang: str
    indent: str
    text: str


def blocks(path: Path) -> list[Block]:
    """The fenced blocks of a markdown file, in order (content as written, indentation included)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        close = re.compile(rf"^[ \t]*{re.escape(m['ticks'][0])}{{{len(m['ticks'])},}}[ \t]*$")
        j = i + 1
        while j < len(lines) and not close.match(lines[j]):
            j += 1
        assert j < len(lines), f"{path.name}:{i + 1}: unclosed code fence"
        out.append(Block(str(path.relative_to(ROOT)), i + 2, m["lang"].lower(), m["indent"], "\n".join(lines[i + 1:j])))
        i = j + 1
    return out


def section(path: Path, heading: str) -> list[Block]:
    """The blocks between ``heading`` and the next heading of the same or a higher level (outside code)."""
    text = path.read_text(encoding="utf-8").splitlines()
    all_blocks = blocks(path)
    inside = {n for b in all_blocks for n in range(b.line - 1, b.line + b.text.count("\n") + 2)}  # 1-based
    level = len(heading) - len(heading.lstrip("#"))
    start = text.index(heading) + 1  # 1-based line of the heading
    end = next((k + 1 for k in range(start, len(text))
                if k + 1 not in inside and re.match(rf"^#{{1,{level}}} ", text[k])), len(text) + 1)
    return [b for b in all_blocks if start < b.line < end]


_used_edits: set[tuple[str, str]] = set()


def python_source(b: Block) -> str:
    assert b.indent == "", (f"{b.doc}:{b.line - 1}: the python fence is indented; pasted, the block raises "
                            "IndentationError: put it in column 0")
    text = b.text
    if not FULL:
        for old, new in SMALL_EDITS.get(b.doc, []):
            if old in text:
                text = text.replace(old, new)
                _used_edits.add((b.doc, old))
    return text


def run_python(b: Block, namespace: dict) -> None:
    code = compile(python_source(b), f"{b.doc}:{b.line}", "exec")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        exec(code, namespace)  # noqa: S102 - the documents' own code


def phisim_lines(b: Block) -> list[str]:
    """The ``phisim`` command lines of a bash block (continuations joined, comments kept for shlex to drop)."""
    joined, buf = [], ""
    for raw in b.text.splitlines():
        if raw.rstrip().endswith("\\"):
            buf += raw.rstrip()[:-1] + " "
            continue
        joined.append(buf + raw)
        buf = ""
    return [ln.strip() for ln in joined if ln.strip().startswith("phisim ")]


def phisim_command() -> list[str]:
    script = Path(sys.executable).with_name("phisim")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "inverse.cli"]


_RESULT = "@@phisim-docs-result@@"
_DRIVER = f"""
import contextlib, io, json, os, sys, traceback
from inverse.cli import main
for request in sys.stdin:
    req = json.loads(request)
    os.chdir(req["cwd"])
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(req["argv"])
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else 1
        except BaseException:
            rc = 99
            traceback.print_exc()
    print("{_RESULT}" + json.dumps({{"rc": rc, "out": out.getvalue(), "err": err.getvalue()}}), flush=True)
"""


class Phisim:
    """Runs ``phisim`` lines as subprocesses of this environment.

    By default one process per document runs its lines one after the other through ``inverse.cli.main`` (what
    the ``phisim`` script calls; torch is imported once instead of once per line); with ``PHISIM_DOCS_FULL=1``
    every line is a process of its own, as typed.
    """

    def __init__(self):
        self.proc = None

    def __call__(self, argv: list[str], cwd: Path) -> tuple[int, str, str]:
        env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONWARNINGS": "ignore::DeprecationWarning"}
        if FULL:
            r = subprocess.run([*phisim_command(), *argv], cwd=cwd, capture_output=True, text=True, env=env,
                               timeout=6 * 3600)
            return r.returncode, r.stdout, r.stderr
        if self.proc is None:
            self.proc = subprocess.Popen([sys.executable, "-c", _DRIVER], cwd=cwd, stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, text=True, env=env)
        self.proc.stdin.write(json.dumps({"argv": argv, "cwd": str(cwd)}) + "\n")
        self.proc.stdin.flush()
        for out in self.proc.stdout:
            if out.startswith(_RESULT):
                r = json.loads(out[len(_RESULT):])
                return r["rc"], r["out"], r["err"]
        return -1, "", f"the phisim process ended (status {self.proc.wait()})"

    def close(self) -> None:
        if self.proc is not None:
            self.proc.stdin.close()
            self.proc.wait(timeout=60)
            self.proc = None


_used_flags: set[str] = set()


def run_phisim(line: str, cwd: Path, log: list, phisim: Phisim) -> None:
    argv = shlex.split(line, comments=True)[1:]
    out = argv[argv.index("--out") + 1] if "--out" in argv else None
    if not FULL and out in SMALL_FLAGS:
        argv += SMALL_FLAGS[out]
        _used_flags.add(out)
    t = time.perf_counter()
    rc, stdout, stderr = phisim(argv, cwd)
    log.append((line, rc, round(time.perf_counter() - t, 1)))
    assert rc == 0, f"`{line}` (run as phisim {' '.join(argv)}) failed:\n{stdout[-2000:]}\n{stderr[-3000:]}"


def write_file_block(b: Block, cwd: Path) -> None:
    first = b.text.splitlines()[0].strip() if b.text.strip() else ""
    m = re.match(r"^#\s*([\w./-]+\.\w+)\s*$", first)
    if m:
        (cwd / m[1]).write_text(b.text + "\n", encoding="utf-8")


def run_document(blocks_: list[Block], cwd: Path, namespace: dict | None, log: list,
                 errors: list | None = None, phisim: Phisim | None = None) -> None:
    """Run blocks in order in ``cwd``: python (one ``namespace``, or a fresh one each when None), phisim lines.

    With ``errors`` a failing ``phisim`` line is recorded there and the next lines still run (each failure is
    reported, not only the first); otherwise the first failure raises.
    """
    old = Path.cwd()
    os.chdir(cwd)
    own = phisim is None
    phisim = phisim or Phisim()
    try:
        for b in blocks_:
            if b.lang == "python":
                t = time.perf_counter()
                run_python(b, namespace if namespace is not None else {"__name__": "__docs__"})
                log.append((f"{b.doc}:{b.line} (python)", 0, round(time.perf_counter() - t, 1)))
            elif b.lang in ("bash", "sh", "console", "shell"):
                for line in phisim_lines(b):
                    try:
                        run_phisim(line, cwd, log, phisim)
                    except AssertionError as exc:
                        if errors is None:
                            raise
                        errors.append(str(exc))
            elif b.lang in ("yaml", "yml", "json"):
                write_file_block(b, cwd)
    finally:
        os.chdir(old)
        if own:
            phisim.close()


# ---- README -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def readme_dir(tmp_path_factory, load_example):
    """A folder with what the README's blocks read: the demo output, then every ``phisim`` line of the README in
    order (training from the command line, the Daily workflows) with the files they write."""
    cwd = tmp_path_factory.mktemp("readme")
    (cwd / "examples").symlink_to(ROOT / "examples")  # the commands run from the repository root
    # out/demo as `bash run.sh demo` (examples/demo.py) writes it; simulated at 16 cells and 3 steps
    load_example("demo").simulate_smoke(cwd / "out" / "demo", 48 if FULL else 16, 40 if FULL else 3)
    log: list = []
    errors: list = []  # reported by test_readme_phisim_lines_run_in_order; the python blocks still run
    workflow = [b for b in blocks(README) if b.lang != "python"]
    run_document(workflow, cwd, None, log, errors)
    return cwd, log, errors


def test_readme_phisim_lines_run_in_order(readme_dir):
    cwd, log, errors = readme_dir
    assert not errors, "\n\n".join(errors)
    lines = [ln for b in blocks(README) if b.lang == "bash" for ln in phisim_lines(b)]
    ran = [entry[0] for entry in log if not entry[0].endswith("(python)")]
    assert ran[:len(lines)] == lines and len(lines) >= 11
    workflows = [ln for b in section(README, "## Daily workflows") if b.lang == "bash" for ln in phisim_lines(b)]
    assert len(workflows) >= 8 and set(workflows) <= set(lines)
    assert (cwd / "burgers.yaml").is_file()  # written from the README's yaml block
    assert (cwd / "pred.h5").is_file() and any((cwd / "out" / "curves").glob("*.csv"))
    if not FULL:
        assert {"out/poisson_cli.h5", "data/smoke", "data/burgers", "out/b.h5", "data/later", "data/heat",
                "out/w.h5"} <= _used_flags
    print("\n".join(f"{t:6.1f} s  rc={rc}  {line}" for line, rc, t in log))


README_PYTHON = [b for b in blocks(README) if b.lang == "python"]


@pytest.mark.parametrize("block", README_PYTHON, ids=[f"README.md:{b.line}" for b in README_PYTHON])
def test_readme_python_block(block, readme_dir):
    cwd, log, _ = readme_dir
    run_document([block], cwd, {"__name__": "__docs__"}, log)


def test_readme_small_edits_apply():
    """Every small-size replacement of the README matches its text (else the snippet changed: update the edit)."""
    text = "\n".join(b.text for b in README_PYTHON)
    for old, _ in SMALL_EDITS["README.md"]:
        assert old in text, f"SMALL_EDITS: {old!r} no longer in README.md's python blocks"


# ---- the tutorial ---------------------------------------------------------------------------------------------


def _tutorial_dir(tmp_path: Path) -> Path:
    cwd = tmp_path / "tutorial"
    cwd.mkdir()
    (cwd / "examples").symlink_to(ROOT / "examples")  # the page runs from the repository root
    return cwd


def _check_tutorial(ns: dict, cwd: Path, phisim: Phisim) -> None:
    import torch

    from inverse import get_problem, load_model

    # section 2 defines the example file's problem
    mine = ns["burgers_problem"](resolution=16, steps=2)
    example = get_problem(f"{ROOT / 'examples' / 'burgers_inverse.py'}:burgers_problem", resolution=16, steps=2)
    a, b = (p.sample(3, torch.Generator().manual_seed(5)) for p in (mine, example))
    assert torch.equal(a.x_true, b.x_true) and torch.equal(a.y_target, b.y_target)
    torch.manual_seed(0)
    na = mine.make_network()
    torch.manual_seed(0)
    nb = example.make_network()
    assert all(torch.equal(p, q) for p, q in zip(na.state_dict().values(), nb.state_dict().values(), strict=True))
    # section 6: the scenario's own step reproduces the stored frames to float32 round-off
    assert ns["mismatch"] < 1e-4, ns["mismatch"]
    # section 5 from another folder: the model file finds its factory
    elsewhere = cwd / "elsewhere"
    elsewhere.mkdir()
    old = Path.cwd()
    os.chdir(elsewhere)
    try:
        net = load_model(cwd / "out" / "burgers.h5.pg_inverse_gradient.model.pt")
    finally:
        os.chdir(old)
    with torch.no_grad():
        assert torch.equal(net(ns["u_T"]), ns["u0"])
    later = cwd / "data" / "later" / "data" / "train" / "burgers_00000.h5"
    run_phisim(f"phisim predict {cwd / 'out' / 'burgers.h5.adam.model.pt'} {later} --key t1_fields/velocity "
               f"--out {elsewhere / 'p.h5'}", elsewhere, [], phisim)


def test_tutorial_runs_end_to_end(tmp_path):
    cwd = _tutorial_dir(tmp_path)
    ns: dict = {"__name__": "__docs__"}
    log: list = []
    phisim = Phisim()
    try:
        run_document(blocks(TUTORIAL), cwd, ns, log, phisim=phisim)
        _check_tutorial(ns, cwd, phisim)
    finally:
        phisim.close()
    if not FULL:
        assert {"out/burgers_cli.h5", "data/later", "data/burgers1d", "data/heat", "out/well.h5"} <= _used_flags
        assert ("docs/TUTORIAL_custom_physics.md", "iterations=200") in _used_edits
    print("\n".join(f"{t:6.1f} s  rc={rc}  {line}" for line, rc, t in log))


# ---- every other document -------------------------------------------------------------------------------------

OTHER_PYTHON = [b for doc in DOCS if doc not in (README, TUTORIAL) for b in blocks(doc) if b.lang == "python"]


@pytest.mark.parametrize("block", OTHER_PYTHON, ids=[f"{b.doc}:{b.line}" for b in OTHER_PYTHON])
def test_other_python_block(block, tmp_path):
    run_document([block], tmp_path, {"__name__": "__docs__"}, [])


def test_every_fence_names_its_language():
    unlabeled = [f"{b.doc}:{b.line - 1}" for doc in DOCS if not doc.name.startswith("BENCHMARKS")
                 for b in blocks(doc) if not b.lang]
    assert not unlabeled, f"fences without a language (python, bash, yaml, text, ...): {unlabeled}"


def test_small_edits_all_match():
    for doc, edits in SMALL_EDITS.items():
        text = "\n".join(b.text for b in blocks(ROOT / doc) if b.lang == "python")
        for old, _ in edits:
            assert old in text, f"SMALL_EDITS: {old!r} no longer in {doc}'s python blocks"
    outs = set()
    for doc in (README, TUTORIAL):
        for b in blocks(doc):
            if b.lang == "bash":
                for line in phisim_lines(b):
                    argv = shlex.split(line, comments=True)
                    if "--out" in argv:
                        outs.add(argv[argv.index("--out") + 1])
    assert set(SMALL_FLAGS) <= outs, f"SMALL_FLAGS keys no document line writes: {set(SMALL_FLAGS) - outs}"


