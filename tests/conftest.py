"""Runs that several test modules read: each is made once per test run, by whichever worker asks first (a
default `commission --sim` run costs seconds, and reading its outputs is what most command-line tests do)."""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import pytest

from commission.cli import main
from commission.ident.twomass import TwoMassParameters


@dataclass(frozen=True)
class CliRun:
    """One `commission` invocation in this process: exit code, what it printed, where it wrote."""

    code: int
    stdout: str
    stderr: str
    out: Path

    @property
    def doc(self) -> dict:
        """The --json document on stdout."""
        return json.loads(self.stdout)


def run_cli(*argv: str | Path, out: Path | None = None) -> CliRun:
    """``commission ARGV [--out OUT]`` in-process, stdout and stderr captured (not a TTY)."""
    args = [str(a) for a in argv] + ([] if out is None else ["--out", str(out)])
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(args)
    return CliRun(code, stdout.getvalue(), stderr.getvalue(), Path(out) if out is not None else Path())


def _made_once(tmp_path_factory: pytest.TempPathFactory, name: str, *argv: str) -> CliRun:
    """``commission ARGV`` made by the first pytest-xdist worker that asks for it; the others read its
    directory and what it printed (a run costs seconds on every worker otherwise). The lock keeps a
    worker from reading a run another is still making."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # not under xdist: this process's own temporary folder
        return run_cli(*argv, out=tmp_path_factory.mktemp(name))
    root = tmp_path_factory.getbasetemp().parent  # shared by this run's workers, new for every run
    done = root / f"{name}.json"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            run = run_cli(*argv, out=root / name)
            done.write_text(json.dumps({"code": run.code, "stdout": run.stdout, "stderr": run.stderr}))
    d = json.loads(done.read_text())
    return CliRun(d["code"], d["stdout"], d["stderr"], root / name)


@pytest.fixture(scope="session")
def default_sim_run(tmp_path_factory: pytest.TempPathFactory) -> CliRun:
    """`commission --sim --out DIR --json` with the shipped default recipe (the paper's 10 s experiment)."""
    run = _made_once(tmp_path_factory, "default-sim", "--sim", "--json")
    assert run.code == 0, run.stderr
    return run


@pytest.fixture(scope="session")
def quick_sim_run(tmp_path_factory: pytest.TempPathFactory) -> CliRun:
    """`commission --sim --config quick --json`: the shipped 2 s recipe, for modes that only need a run."""
    run = _made_once(tmp_path_factory, "quick-sim", "--sim", "--config", "quick", "--json")
    assert run.code == 0, run.stderr
    return run


def two_mass_plant(ratio: float, f_r: float, zeta: float, B_l: float | None = None,
                   J_m: float = 4.78e-4) -> TwoMassParameters:
    """bench/bench_identify.py's parameterisation of the spread of plants: J_l = ratio·J_m, K for
    the resonance f_r [Hz], D for the damping ratio ζ, B_l scaled with the load unless given."""
    J_l = ratio * J_m
    w = 2 * math.pi * f_r
    return TwoMassParameters(J_m=J_m, J_l=J_l, B_m=0.84e-2,
                             B_l=B_l if B_l is not None else 0.53e-2 * math.sqrt(ratio / 0.4),
                             K=w * w * J_l / (1 + ratio), D=2 * zeta * w / (1 / J_m + 1 / J_l))


#: The files that take longest (a third of the suite's time between them; `pytest --durations=0`), run
#: first: with ``--dist loadfile`` a file stays on one worker, and one started last holds the others idle.
SLOWEST_FIRST = ("test_identify.py", "test_hybrid.py", "test_family_records.py", "test_serial_e2e.py",
                 "test_safety.py", "test_cli.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order
