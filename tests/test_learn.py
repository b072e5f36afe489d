"""`arena learn reach`, small: a few expert episodes, a few training steps, two held-out targets.
It runs as a command of its own (torch never enters the test's process, which hosts a server),
and the policy it saves is loaded by a server's policy master with the target as its
`environment_state`, as a user would."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path

import httpx
import trio

from tests.conftest import REPOSITORY, RunningServer, need

Start = Callable[..., Awaitable[RunningServer]]
#: Bounds only a broken command reaches (torch and LeRobot take seconds to import).
RUN = 600.0
LOAD = 120.0


async def test_a_small_run_writes_a_policy_a_master_loads(
    start_server: Start, tmp_path: Path
) -> None:
    need("lerobot", "lerobot")
    need("gymnasium", "gym")
    need("mujoco", "physics")
    out = tmp_path / "reach"
    with trio.fail_after(RUN):
        done = await trio.run_process(
            [
                sys.executable,
                "-m",
                "arena",
                "learn",
                "reach",
                "-o",
                str(out),
                "--episodes",
                "3",
                "--steps",
                "20",
                "--targets",
                "2",
            ],
            capture_stdout=True,
            capture_stderr=True,
            check=False,
            env={**os.environ, "PYTHONPATH": str(REPOSITORY)},
        )
    said = done.stdout.decode()
    assert done.returncode == 0, said + done.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    assert report["episodes"] == 3 and report["frames"] > 30
    assert report["expert"] == 1.0  # the expert solves the held-out targets it is scored on
    for name in ("expert", "random", "policy"):
        assert f"{name}  " in said
    assert f"policy saved in {out / 'policy'}" in said
    assert (out / "dataset" / "meta" / "info.json").is_file()
    features = json.loads((out / "dataset" / "meta" / "info.json").read_text())["features"]
    assert features["observation.environment_state"]["shape"] == [3]

    server = await start_server(demo=True)
    async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
        body = {"type": "policy", "path": str(out / "policy")}
        refused = await http.post("/api/robots/demo-arm/master", json=body)
        assert refused.status_code == 422, refused.text  # the target is not something measured
        assert "observation.environment_state" in refused.json()["error"]["message"]
        body["environment_state"] = [0.0, -0.3, 0.2]
        attached = await http.post("/api/robots/demo-arm/master", json=body)
        assert attached.status_code == 201, attached.text
        assert attached.json()["id"].startswith("policy:act:")
        await http.delete("/api/robots/demo-arm/master")
