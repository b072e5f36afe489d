"""Installing and starting: what `make` installs, what a missing extra says, a port in use."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

needs_make = pytest.mark.skipif(shutil.which("make") is None, reason="needs make")


def make_dry_run(target: str, venv: Path, *settings: str) -> list[str]:
    """The commands `make TARGET` would run (`make -n`) with the virtualenv at `venv`."""
    done = subprocess.run(
        ["make", "-n", "-C", str(ROOT), target, f"VENV={venv}", *settings],
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.splitlines()


def pip_installs(commands: list[str]) -> list[str]:
    """What each `pip install -e` of the commands installs."""
    return [
        line.split(" -e ", 1)[1].strip()
        for line in commands
        if "pip install" in line and " -e " in line
    ]


@needs_make
def test_make_run_installs_only_the_runtime_packages(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    commands = make_dry_run("run", venv)
    assert pip_installs(commands) == ["."]
    assert any(line.endswith("arena serve --demo --port 8080") for line in commands), commands


@needs_make
def test_make_test_after_make_run_adds_the_rest(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").touch()
    (venv / ".installed-runtime").touch()  # as `make run` leaves it
    assert pip_installs(make_dry_run("run", venv)) == []  # nothing more to serve
    test = make_dry_run("test", venv)
    assert pip_installs(test) == ["'.[dev]'"]
    assert not any("-m venv" in line for line in test)  # the same virtualenv
    assert pip_installs(make_dry_run("lint", venv)) == ["'.[dev]'"]


@needs_make
def test_make_run_and_fleet_take_a_port(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    run = make_dry_run("run", venv, "PORT=9100")
    assert any(line.endswith("arena serve --demo --port 9100") for line in run), run
    fleet = "\n".join(make_dry_run("fleet", venv, "PORT=9100", "ZENOH_PORT=7600"))
    assert "--node n0 --port 9100" in fleet
    assert "--port $((9100 + k))" in fleet
    assert "--fleet-listen tcp/127.0.0.1:7600" in fleet
    assert "'.[fleet]'" in fleet  # the fleet needs Zenoh, which `make run` does not install
