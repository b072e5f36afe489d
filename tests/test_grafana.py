"""deploy/grafana/arena.json asks only for metrics /metrics serves; the servo and fault figures
it shows come from a real arm (the USB slave on the simulated bus)."""

from __future__ import annotations

import json
import re
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena.servo.sim_pty import PtySimBus
from tests.conftest import REPOSITORY, RunningServer, eventually
from tests.hardware import running_sim, servo_torque

StartServer = Callable[..., Awaitable[RunningServer]]
DASHBOARD = REPOSITORY / "deploy" / "grafana" / "arena.json"
#: A metric's name in a PromQL query (Arena's all begin so).
METRIC = re.compile(r"\barena_[a-z0-9_]+\b")


def queries(dashboard: dict[str, Any]) -> list[str]:
    """Every PromQL query of the dashboard: its panels' targets and its variables'."""
    found = [t["expr"] for panel in dashboard["panels"] for t in panel.get("targets", [])]
    found += [v["query"] for v in dashboard["templating"]["list"] if v["type"] == "query"]
    return found


def served(metrics_text: str) -> set[str]:
    """The series names a /metrics text can hold (a histogram's with its suffixes)."""
    names = set()
    for line in metrics_text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split()
            names.add(name)
            if kind == "histogram":
                names |= {f"{name}_bucket", f"{name}_sum", f"{name}_count"}
    return names


async def test_every_query_of_the_grafana_dashboard_names_a_metric_arena_serves(
    start_server: StartServer,
) -> None:
    dashboard = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    server = await start_server(demo=True)
    async with server.client() as http:
        text = (await http.get("/metrics")).text
    names = served(text)
    asked = {name for query in queries(dashboard) for name in METRIC.findall(query)}
    assert asked - names == set()
    # what the issue asks to see is there
    for wanted in (
        "arena_message_latency_seconds_bucket",
        "arena_estops_total",
        "arena_faults_active",
        "arena_recording_failing",
        "arena_auth_refused_total",
        "arena_master_rtt_seconds",
        "arena_stale_commands_total",
        "arena_servo_temperature_celsius",
        "arena_servo_load_percent",
        "arena_policy_inference_seconds",
        "arena_interventions_total",
    ):
        assert wanted in asked
    # each panel queries through the dashboard's data source, each query of it named apart
    for panel in dashboard["panels"]:
        assert panel["datasource"]["uid"] == "${datasource}"
        ids = [t["refId"] for t in panel["targets"]]
        assert ids and len(ids) == len(set(ids))


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


async def test_a_hot_servo_shows_its_temperature_and_its_fault_on_metrics(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server(calibration_dir=str(tmp_path / "calibration"))
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm"})).status_code == 201
        attached = await http.post(
            "/api/robots/arm/slaves", json={"type": "usb-slave", "port": str(sim.link)}
        )
        assert attached.status_code == 201, attached.text
        await eventually(lambda: all(servo_torque(sim).values()), what="torque on")

        async def metrics() -> str:
            return (await http.get("/metrics")).text

        async def shows(line: str) -> bool:
            return line in await metrics()

        await eventually(
            lambda: shows('arena_servo_temperature_celsius{robot="arm",joint="Pitch"} 3'),
            what="the servos' temperature (30 C and up)",
        )
        with sim.paused() as bus:
            bus.servo(2).temperature = 72.0  # Pitch: over its limit
        await eventually(
            lambda: shows('arena_servo_temperature_celsius{robot="arm",joint="Pitch"} 72'),
            what="Pitch hot",
        )
        await eventually(
            lambda: shows('arena_faults_active{robot="arm",severity="critical"} 1'),
            what="the overheat fault",
        )
        assert 'arena_servo_load_percent{robot="arm",joint="Pitch"} ' in await metrics()
