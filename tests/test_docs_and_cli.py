"""The README's example and the `arena` command, run for real (on virtual time)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import trio
import trio.testing

from arena import cli
from tests.conftest import RunningServer

README = Path(__file__).resolve().parent.parent / "README.md"
CLIENT_SPEC = README.with_name("specs") / "client.md"


def test_readme_example_runs(capsys: pytest.CaptureFixture[str]) -> None:
    block = re.search(r"## In-process example\s+```python\n(.*?)```", CLIENT_SPEC.read_text(), re.S)
    assert block is not None
    source = block.group(1).replace("trio.run(main)", "")
    namespace: dict[str, Any] = {}
    exec(compile(source, "specs/client.md", "exec"), namespace)
    trio.run(namespace["main"], clock=trio.testing.MockClock(autojump_threshold=0))
    out = capsys.readouterr().out
    assert "accepted=True" in out
    # After the wave the simulated arm has followed: real equals virtual for every joint.
    last_six = out.strip().splitlines()[-6:]
    for line in last_six:
        name, virtual, real = re.match(r"(\w+): virtual=(\S+) real=(\S+)", line).groups()  # type: ignore[union-attr]
        assert float(virtual) == pytest.approx(float(real)), name


def test_demo_command_plays_and_finishes(capsys: pytest.CaptureFixture[str]) -> None:
    trio.run(
        cli.run_demo, ["small-scan"], False, 1.0, clock=trio.testing.MockClock(autojump_threshold=0)
    )
    out = capsys.readouterr().out
    assert out.startswith("robot demo-arm: playing small-scan")
    assert "Rotation= -25.0/ -25.0" in out  # the scan reached its left end, and the arm followed
    assert out.strip().endswith("done")


def test_demo_rejects_an_unknown_sequence() -> None:
    with pytest.raises(SystemExit):
        cli.main(["demo", "--sequence", "moonwalk"])


async def test_readme_agent_example_drives_the_demo_robot(
    server: RunningServer, capsys: pytest.CaptureFixture[str]
) -> None:
    block = re.search(r"## Agent example\s+```python\n(.*?)```", CLIENT_SPEC.read_text(), re.S)
    assert block is not None
    namespace: dict[str, Any] = {}
    exec(
        compile(block.group(1).replace("trio.run(agent)", ""), "specs/client.md", "exec"), namespace
    )
    await namespace["agent"](server.url, "demo-arm", 4)
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4
    assert all(line.split()[0] in ("accepted", "clamped") for line in lines), lines
    # The mock arm followed: by the last step the agent saw a real Rotation above zero.
    assert float(lines[-1].split()[1]) > 0


def test_a_missing_extra_is_skipped_with_its_reason_and_fails_in_ci(tmp_path: Path) -> None:
    # What `make test` shows (-rs) and what CI (CI=true) does when an extra is missing.
    import os
    import subprocess
    import sys

    (tmp_path / "test_extra.py").write_text(
        "from tests.conftest import need\n"
        "need('arena_no_such_extra', 'fleet')\n"
        "def test_it() -> None:\n"
        "    pass\n"
    )
    repository = Path(__file__).resolve().parent.parent
    base = {k: v for k, v in os.environ.items() if k != "CI"}
    base["PYTHONPATH"] = str(repository)
    command = [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider"]
    command += ["-p", "no:trio", "test_extra.py"]
    for ci in (None, "true"):
        env = base if ci is None else {**base, "CI": ci}
        run = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True)
        said = run.stdout + run.stderr
        if ci is None:
            assert run.returncode in (0, 5) and "1 skipped" in said, said  # 5: none ran
            assert "SKIPPED" in said and "pip install 'arena[fleet]'" in said
        else:
            assert run.returncode != 0 and "in CI, nothing may be missing" in said, said
