"""Installing and starting: what `make` installs, what a missing extra says, a port in use."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from arena import cli
from arena.server import dashboard
from tests.conftest import RunningServer

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
    assert any(line.endswith("arena serve --demo --sim-leader --port 8080") for line in commands), (
        commands
    )


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
    assert any(line.endswith("arena serve --demo --sim-leader --port 9100") for line in run), run
    fleet = "\n".join(make_dry_run("fleet", venv, "PORT=9100", "ZENOH_PORT=7600"))
    assert "--node n0 --port 9100" in fleet
    assert "--port $((9100 + k))" in fleet
    assert "--fleet-listen tcp/127.0.0.1:7600" in fleet
    assert "'.[fleet]'" in fleet  # the fleet needs Zenoh, which `make run` does not install


# -- a missing extra says what to install --------------------------------------------------

GOLDEN = ROOT / "recordings" / "golden"


async def test_a_physics_slave_without_mujoco_answers_the_install_line(
    server: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "mujoco", None)  # `import mujoco` fails as if not installed
    async with server.client() as http:
        answer = await http.post("/api/robots/demo-arm/slaves", json={"type": "physics-slave"})
        assert answer.status_code == 501
        error = answer.json()["error"]
        assert error["code"] == "NOT_INSTALLED"
        assert "pip install 'arena[physics]'" in error["message"]
        slaves = (await http.get("/api/robots/demo-arm")).json()["slaves"]
    assert [slave["type"] for slave in slaves] == ["mock-slave"]  # nothing was attached


@pytest.mark.parametrize(
    ("module", "argv", "line"),
    [
        ("matplotlib", ["plot", "{golden}", "-o", "{tmp}/joints.png"], "arena[plot]"),
        (
            "matplotlib",
            ["estop-test", "--offline", "{golden}", "--plot", "{tmp}/stops.png"],
            "arena[plot]",
        ),
        (
            "lerobot",
            ["export", "{golden}", "--format", "lerobot", "-o", "{tmp}/data"],
            "arena[lerobot]",
        ),
        ("lerobot", ["import-dataset", "{tmp}", "-o", "{tmp}/episode.mcap"], "arena[lerobot]"),
        ("zenoh", ["serve", "--node", "n1", "--port", "0"], "arena[fleet]"),
        ("zenoh", ["bench", "nodes"], "arena[fleet]"),
        ("mujoco", ["bench", "physics"], "arena[physics]"),
        ("rosbags", ["serve", "--ros2", "--port", "0"], "arena[ros2]"),
        (
            "rosbags",
            ["export", "{golden}", "--format", "ros2", "-o", "{tmp}/b.mcap"],
            "arena[ros2]",
        ),
    ],
)
def test_a_command_whose_extra_is_missing_says_what_to_install(
    module: str,
    argv: list[str],
    line: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setitem(sys.modules, module, None)
    recordings = tmp_path / "recordings"
    args = [a.format(golden=GOLDEN / "gentle-wave.mcap", tmp=tmp_path) for a in argv]
    if args[0] == "serve":
        args += ["--recordings-dir", str(recordings)]
    assert cli.main(args) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1, err  # one line
    assert err.startswith(f"arena {args[0]}: ") and f"pip install '{line}'" in err, err
    assert out == ""  # refused before any work
    assert not recordings.exists()


def test_every_optional_import_is_an_extra_of_the_package() -> None:
    """The extras that arena/extras.py names exist in pyproject.toml and bring the module."""
    from arena.extras import EXTRAS, install_line

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    optional = project["optional-dependencies"]
    for name, extra in EXTRAS.items():
        assert extra.extra in optional, name
        assert install_line(name) == f"{sys.executable} -m pip install 'arena[{extra.extra}]'"
    # and no runtime dependency is one of them
    runtime = " ".join(project["dependencies"])
    for extra in EXTRAS.values():
        for requirement in optional[extra.extra]:
            assert requirement.split(">")[0].split("<")[0] not in runtime


# -- starting: a port in use -----------------------------------------------------------------


@pytest.mark.parametrize("flag", ["--port", "--foxglove-port"])
def test_a_port_in_use_is_one_line_exit_2_and_no_recording(
    flag: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recordings = tmp_path / "recordings"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        ports = {"--port": "0", "--foxglove-port": "0", flag: str(port)}
        argv = ["serve", "--demo", "--recordings-dir", str(recordings)]
        status = cli.main([*argv, *(a for pair in ports.items() for a in pair)])
    assert status == 2
    how = " (make run PORT=9000)" if flag == "--port" else ""  # (make passes --port itself)
    assert capsys.readouterr().err == f"arena serve: port {port} is in use: pass {flag}{how}\n"
    assert not recordings.exists() or not any(recordings.iterdir())


def test_serve_says_where_the_dashboard_and_the_docs_are(tmp_path: Path) -> None:
    """`python -m arena serve`, a real process: the log names /ui/ (or how to build it) and
    /docs on the port it listens on."""
    process = subprocess.Popen(
        [sys.executable, "-m", "arena", "serve", "--port", "0", "--no-record"],
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT), "LOG_LEVEL": "INFO"},
    )
    try:
        assert process.stderr is not None
        lines = []
        for line in process.stderr:  # until the line that follows "listening on"
            lines.append(line)
            if "docs" in line or len(lines) > 50:
                break
        url = re.search(r"listening on (http://\S+)", "".join(lines))
        assert url is not None, lines
        page = f"{url.group(1)}/ui/" if dashboard.is_built() else "not built (make ui)"
        assert f"dashboard: {page}" in lines[-1] and f"{url.group(1)}/docs" in lines[-1]
    finally:
        process.send_signal(signal.SIGINT)
        process.wait(timeout=30)


# -- the repository keeps no run's recordings --------------------------------------------------


@pytest.mark.skipif(
    shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs the git checkout"
)
def test_the_repository_keeps_only_the_golden_recordings() -> None:
    def git(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)

    tracked = git("ls-files", "recordings").stdout.split()
    assert tracked and all(
        path == "recordings/.gitkeep" or path.startswith("recordings/golden/") for path in tracked
    ), tracked
    # what `arena serve` and `make fleet` leave is ignored; the golden recordings are not
    left = ["recordings/arena-20261123-154220-498.mcap", "recordings/n0/arena-1.mcap"]
    assert git("check-ignore", *left).stdout.split() == left
    assert git("check-ignore", "recordings/golden/new.mcap").returncode == 1
