"""What an installed package needs: every module and the shipped data in the wheel, the data found
inside the package at run time, and a numba cache that never fails a command.

`make wheel-check` (run by CI after the tests) goes further: it installs the wheel into a fresh
venv and commissions the simulated drive from a folder outside the source tree.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from importlib import resources
from pathlib import Path

import pytest

from commission.config import load_config, recipe_names
from commission.drive.description import DRIVERS_ENV, drivers_dir, list_drives
from commission.jitcache import choose_cache_dir

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ["pyproject.toml", "README.md", "src", "sim_drive", "configs", "drivers"]  # as the Makefile's SHIPPED


def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts and ".egg-info" not in str(p)]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> set[str]:
    """Names in a wheel built from a copy of the shipped tree (as `make wheel-check` and the Dockerfile do)."""
    tmp = tmp_path_factory.mktemp("wheel")
    (tmp / "tree").mkdir()
    for name in SHIPPED:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, tmp / "tree" / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(src, tmp / "tree" / name)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--disable-pip-version-check", "--no-deps",
                           "--wheel-dir", str(tmp / "dist"), str(tmp / "tree")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    (built,) = (tmp / "dist").glob("*.whl")
    with zipfile.ZipFile(built) as z:
        return set(z.namelist())


def test_the_wheel_carries_every_module(wheel: set[str]) -> None:
    expected = {f"commission/{p.relative_to(ROOT / 'src' / 'commission').as_posix()}"
                for p in _files(ROOT / "src" / "commission") if p.suffix == ".py"}
    expected |= {f"sim_drive/{p.relative_to(ROOT / 'sim_drive').as_posix()}"
                 for p in _files(ROOT / "sim_drive") if p.suffix == ".py"}
    assert "commission/tuning/__init__.py" in expected
    assert expected <= wheel, sorted(expected - wheel)
    top = {name.split("/")[0] for name in wheel if not name.split("/")[0].endswith(".dist-info")}
    assert top == {"commission", "sim_drive"}


def test_the_wheel_carries_drivers_and_configs_inside_the_package(wheel: set[str]) -> None:
    for folder in ("drivers", "configs"):
        expected = {f"commission/{folder}/{p.relative_to(ROOT / folder).as_posix()}" for p in _files(ROOT / folder)}
        assert expected and expected <= wheel, sorted(expected - wheel)


def test_shipped_data_is_found_inside_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(DRIVERS_ENV, raising=False)
    shipped = resources.files("commission")
    assert drivers_dir() == shipped / "drivers"
    assert set(list_drives()) == {p.name for p in (ROOT / "drivers").iterdir() if (p / "description.yaml").is_file()}
    assert set(recipe_names()) == {p.stem for p in (ROOT / "configs").glob("*.yaml")}
    assert load_config(None) == load_config(ROOT / "configs" / "default.yaml")
    assert load_config("paper-literal") == load_config(ROOT / "configs" / "paper-literal.yaml")


# -- numba's cache ------------------------------------------------------------------------------
def test_numba_cache_falls_back_to_a_temporary_folder(tmp_path: Path) -> None:
    """A folder under a regular file cannot be created by anyone (root included): the unwritable case."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    unwritable, fallback = blocker / "pkg", tmp_path / "tmp" / "numba-cache"
    assert choose_cache_dir(tmp_path / "pkg", unwritable, fallback) is None  # beside the sources: numba's own
    assert choose_cache_dir(unwritable, tmp_path / "home" / "numba", fallback) is None  # the user's: numba's own
    assert choose_cache_dir(unwritable, blocker / "home", fallback) == fallback
    assert choose_cache_dir(unwritable, blocker / "home", blocker / "tmp") is None  # nothing writable: numba decides

