"""`/healthz` and `/readyz`: what an orchestrator asks before sending work or restarting."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path

import trio

from arena.robot.links import SlaveLink
from tests.conftest import RunningServer

StartServer = Callable[..., Awaitable[RunningServer]]


class FlakySlave:
    """A slave whose hardware goes away when `lose` is set and comes back on `restore`."""

    kind = "flaky-slave"
    measures = False

    def __init__(self) -> None:
        self.lose = trio.Event()
        self.restore = trio.Event()

    async def run(self, link: SlaveLink) -> None:
        await link.report_joint_states(dict.fromkeys(link.robot.model.joint_names, 0.0))
        await self.lose.wait()
        await link.connection_lost("serial port unplugged")
        await self.restore.wait()
        await link.connection_restored()
        await trio.sleep_forever()


async def readiness(server: RunningServer) -> tuple[int, dict[str, object]]:
    async with server.client() as http:
        answer = await http.get("/readyz")
    return answer.status_code, answer.json()


async def test_readyz_says_which_slave_is_disconnected_until_it_returns(
    server: RunningServer,
) -> None:
    assert await readiness(server) == (200, {"status": "ready", "reasons": []})
    flaky = FlakySlave()
    robot = server.app.manager.get("demo-arm")
    await robot.attach_slave(flaky, "arm-usb")
    assert (await readiness(server))[0] == 200
    flaky.lose.set()
    with trio.fail_after(10):
        while (status := await readiness(server))[0] == 200:
            await trio.sleep(0.01)  # pacing only: the loop waits for the change
    code, body = status
    assert code == 503 and body["status"] == "not ready"
    assert body["reasons"] == [
        "robot demo-arm: slave arm-usb is disconnected (SLAVE_LOST: serial port unplugged)"
    ]
    async with server.client() as http:  # the process still answers
        alive = await http.get("/healthz")
        assert (alive.status_code, alive.json()) == (200, {"status": "ok"})
    flaky.restore.set()
    with trio.fail_after(10):
        while (status := await readiness(server))[0] == 503:
            await trio.sleep(0.01)
    assert status == (200, {"status": "ready", "reasons": []})


async def test_a_server_with_no_robots_is_ready(start_server: StartServer) -> None:
    server = await start_server()
    assert await readiness(server) == (200, {"status": "ready", "reasons": []})


async def test_readyz_is_503_while_the_recorder_cannot_write(
    start_server: StartServer, tmp_path: Path
) -> None:
    folder = tmp_path / "not-a-folder"
    folder.write_text("a file where the recordings should go")
    server = await start_server(demo=True, recordings_dir=str(folder))
    async with server.client() as http:
        with trio.fail_after(30):
            while (answer := await http.get("/readyz")).status_code == 200:
                await http.put(
                    "/api/robots/demo-arm/joints",
                    json={"joints": [{"name": "Rotation", "value": 3}]},
                )
                await trio.sleep(0.02)  # pacing only: the loop waits for the error
    assert answer.status_code == 503
    (reason,) = answer.json()["reasons"]
    assert reason.startswith("the recorder cannot write: ")


async def test_health_needs_no_key_and_says_nothing_secret(start_server: StartServer) -> None:
    server = await start_server(demo=True, api_keys=("s3cret-key",))
    async with server.client() as http:
        assert (await http.get("/api/robots")).status_code == 401  # keys are on
        for path in ("/healthz", "/readyz"):
            answer = await http.get(path)
            assert answer.status_code == 200, (path, answer.text)
            assert "s3cret" not in answer.text


async def test_readyz_is_503_once_the_server_is_stopping(server: RunningServer) -> None:
    server.app.shutting_down.set()  # as the shutdown trigger sets it, before the listener stops
    code, body = await readiness(server)
    assert (code, body["reasons"]) == (503, ["shutting down"])
