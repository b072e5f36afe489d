"""Run the server: the robot manager and the listener (hypercorn behind it) in one nursery."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import gc
import json
import logging
import resource
import socket
from pathlib import Path
from typing import Any

import trio
from hypercorn.config import Config as HypercornConfig
from hypercorn.config import Sockets

from arena.drivers.mock_slave import MockSlave, MockSlaveConfig
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.recorder import Recorder
from arena.robot.manager import open_manager
from arena.server import dashboard
from arena.server.app import create_app
from arena.server.base import ArenaApp
from arena.server.config import ServerConfig
from arena.server.declared import DeclaredSetup, read_setup, reload_on_sighup
from arena.server.listener import ArenaListener, ConnectionLimits
from arena.server.sensors_api import stream_route
from arena.server.setup_file import Setup
from arena.server.shutdown import leave_slaves_as_set, stop_on_signals
from arena.server.sim_leaders import SimLeaders
from arena.server.systemd import notify
from arena.server.ws.router import router

log = logging.getLogger(__name__)

DEMO_ROBOT_ID = "demo-arm"
#: File descriptors kept beside the connections' (recordings, serial ports, cameras, workers).
SPARE_FILES = 128
#: Hard cap on a WebSocket message. Messages up to it are read and answered MESSAGE_TOO_LARGE
#: when over the 64 KiB protocol limit; one over it closes the connection with 1009.
MAX_WEBSOCKET_MESSAGE = 16 * 1024 * 1024


def hypercorn_config(config: ServerConfig) -> HypercornConfig:
    """Hypercorn settings from ours."""
    hc = HypercornConfig()
    host = f"[{config.host}]" if ":" in config.host else config.host
    hc.bind = [f"{host}:{config.port}"]
    hc.graceful_timeout = config.shutdown_grace
    hc.keep_alive_timeout = config.keep_alive_timeout
    hc.accesslog = None
    hc.errorlog = logging.getLogger("hypercorn.error")
    if config.certfile and config.keyfile:
        hc.certfile, hc.keyfile = config.certfile, config.keyfile
    return hc


def bind(config: ServerConfig) -> Sockets:
    """The listening sockets, bound before anything else starts: a port in use is one
    sentence (`ArenaError(INVALID_CONFIG)`), and no recording is begun for a server that
    cannot listen. Foxglove's port is tried too (its server binds it later, in its thread)."""
    if config.foxglove_port:
        family = socket.AF_INET6 if ":" in config.host else socket.AF_INET
        with socket.socket(family) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((config.host, config.foxglove_port))
            except OSError as exc:
                port = config.foxglove_port
                raise _cannot_listen(exc, config.host, port, "--foxglove-port") from None
    try:
        return hypercorn_config(config).create_sockets()
    except OSError as exc:
        raise _cannot_listen(exc, config.host, config.port, "--port") from None


def _cannot_listen(exc: OSError, host: str, port: int, flag: str) -> ArenaError:
    if exc.errno == errno.EADDRINUSE:
        reason = f"port {port} is in use: pass {flag}"
        if flag == "--port":  # (`make run` passes its own: say how to choose it there)
            reason += " (make run PORT=9000)"
    else:
        reason = f"cannot listen on {host} port {port} ({flag}): {exc.strerror or exc}"
    return ArenaError(ErrorCode.INVALID_CONFIG, reason)


def _close(sockets: Sockets) -> None:
    for sock in [*sockets.secure_sockets, *sockets.insecure_sockets, *sockets.quic_sockets]:
        sock.close()


async def run_server(
    config: ServerConfig,
    *,
    stop: trio.Event | None = None,
    handle_signals: bool = False,
    freeze_startup_objects: bool = False,
    task_status: Any = trio.TASK_STATUS_IGNORED,
) -> None:
    """Serve until `stop` is set (or, with `handle_signals`, SIGINT or SIGTERM arrives: a
    planned stop, see `arena.server.shutdown`; a second signal stops at once).

    `freeze_startup_objects` (for a server that owns its process): once the server is up, move
    every object alive into the garbage collector's permanent generation (`gc.freeze`).

    `task_status.started` receives `(app, urls)` once the sockets are bound; with port 0 the
    URLs carry the ports the system chose.
    """
    config.check()
    if config.node is not None:
        from arena.extras import require

        require("fleet", "A fleet node (--node)")
    if config.ros2:
        from arena.extras import require

        require("ros2", "ROS 2 (--ros2)")
    # The declared setup is read and checked whole before anything moves.
    setup = read_setup(config) if config.config_file is not None else None
    sockets = bind(config)
    stop = trio.Event() if stop is None else stop
    try:
        async with trio.open_nursery() as nursery:
            if handle_signals:  # a second signal cancels the whole run: cleanups are shielded
                nursery.start_soon(stop_on_signals, stop, nursery.cancel_scope)
            await _run(
                config, sockets, stop, freeze_startup_objects, task_status, setup, handle_signals
            )
            nursery.cancel_scope.cancel()
    finally:
        _close(sockets)  # those never listened on (the listener closes the others)


async def _run(
    config: ServerConfig,
    sockets: Sockets,
    stop: trio.Event,
    freeze_startup_objects: bool,
    task_status: Any,
    setup: Setup | None = None,
    handle_signals: bool = False,
) -> None:
    metadata = {"config": json.dumps(_public_settings(config))}
    if config.node is not None:  # each file names the node and fleet it was recorded on
        metadata.update(node=config.node, fleet=config.fleet)
    recorder = Recorder(
        Path(config.recordings_dir),
        metadata,
        max_bytes=config.recording_max_bytes,
        max_seconds=config.recording_max_seconds,
        active=config.record,
        retry_max=config.recording_retry_max,
        foxglove=config.record_foxglove,
        foxglove_rate=config.record_foxglove_rate,
    )
    # Simulated leader arms go last, once no usb-master reads them any more.
    with contextlib.closing(SimLeaders()) as sim_leaders:
        async with trio.open_nursery() as recording_nursery:
            await recording_nursery.start(recorder.run)
            async with open_manager() as manager:
                manager.on_create.append(recorder.follow)
                app = create_app(manager, config, recorder)
                app.sim_leaders = sim_leaders
                app.cameras.on_attach.append(
                    lambda camera: recorder.follow_frames(
                        camera.robot.robot_id, camera.subscribe(maxlen=2 * camera.spec.fps)
                    )
                )
                await recording_nursery.start(app.cameras.run)
                if config.node is not None:
                    from arena.fleet.node import FleetNode  # imports zenoh only for a fleet
                    from arena.server.fleet_api import install

                    fleet = FleetNode(config.fleet_settings())
                    await recording_nursery.start(fleet.run)
                    install(app, fleet)
                if config.ros2:
                    from arena.ros2.bridge import Ros2Bridge  # imports zenoh and rosbags

                    app.ros2 = Ros2Bridge(config.ros2_settings())
                    await recording_nursery.start(app.ros2.run)
                    manager.on_create.append(app.ros2.follow)
                if config.foxglove_port is not None:
                    from arena.server.foxglove_bridge import FoxgloveBridge  # loads the SDK

                    app.foxglove = FoxgloveBridge(config.host, config.foxglove_port)
                    manager.on_create.append(app.foxglove.follow)
                    bridge = app.foxglove
                    app.cameras.on_attach.append(
                        lambda camera: bridge.follow_frames(
                            camera.robot.robot_id, camera.spec.name, camera.subscribe(maxlen=2)
                        )
                    )
                    port = await recording_nursery.start(app.foxglove.run)
                    log.info("Foxglove: ws://%s:%d", config.host, port)
                if config.demo:
                    await _create_demo_robot(app)
                if config.sim_leader is not None:
                    leader = app.sim_leaders.start(config.sim_leader)
                    log.info("simulated leader arm (%s): %s", leader.robot_type, leader.port)
                app.declared = DeclaredSetup(app, config.config_file or "")
                if setup is not None:
                    await app.declared.apply(setup)  # in order; what cannot come up is retried
                if handle_signals:  # (SIGHUP's default would end the process)
                    recording_nursery.start_soon(reload_on_sighup, app.declared)
                if freeze_startup_objects:
                    tune_garbage_collector()
                await _serve(app, config, sockets, stop, task_status)
            recording_nursery.cancel_scope.cancel()  # robots are stopped: finish the file


async def _serve(
    app: ArenaApp,
    config: ServerConfig,
    sockets: Sockets,
    stop: trio.Event,
    task_status: Any,
) -> None:
    async def shutdown_trigger() -> None:
        await stop.wait()
        log.info("shutting down")
        app.shutting_down.set()
        notify("STOPPING=1")
        leave_slaves_as_set(app)

    listener = ArenaListener(
        app,
        hypercorn_config(config),
        router(app),
        MAX_WEBSOCKET_MESSAGE,
        stream_router=stream_route(app),
        queue_bytes=config.ws_queue_bytes,
        sockets=sockets,
        limits=connection_limits(config),
    )
    async with trio.open_nursery() as nursery:

        async def serve_then_stop(task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
            await listener.serve(shutdown_trigger, task_status=task_status)
            nursery.cancel_scope.cancel()

        urls: list[str] = await nursery.start(serve_then_stop)
        for url in urls:
            log.info("Arena listening on %s", url)
        page = f"{urls[0]}/ui/" if dashboard.is_built() else "not built (make ui)"
        log.info("dashboard: %s   REST API, to try: %s/docs", page, urls[0])
        app.own_url = urls[0]
        task_status.started((app, urls))
        notify(f"READY=1\nSTATUS=listening on {' '.join(urls)}")
        await stop.wait()
        # The WebSockets close themselves with 1001 at once; whatever HTTP requests are
        # still open after the grace period are cancelled.
        await trio.sleep(config.shutdown_grace + 1.0)
        nursery.cancel_scope.cancel()


def connection_limits(config: ServerConfig) -> ConnectionLimits:
    """The connection bounds of the settings, within the process's file limit: its soft limit
    raised (to its hard one at most) so that `max_connections` and `SPARE_FILES` fit; where
    they cannot, fewer connections, said in the log. The bound is what keeps a descriptor
    free for the e-stop."""
    needed = config.max_connections + SPARE_FILES
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < needed:
        raised = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (raised, hard))
            soft = raised
        except (ValueError, OSError):
            pass
    total = config.max_connections
    if soft != resource.RLIM_INFINITY and soft < needed:
        total = max(1, soft - SPARE_FILES)
        log.warning(
            "max_connections %d does not fit the file limit (%d): at most %d connections",
            config.max_connections,
            soft,
            total,
        )
    return ConnectionLimits(total, min(config.max_connections_per_client, total))


def tune_garbage_collector() -> None:
    """Make the cyclic garbage collector cheap for a long-running server.

    Measured under the soak (100 robots, 1,000 commands/s): with Python's defaults the
    collector took about 6 s of every minute and its full passes paused the server for up to
    160 ms (the p99 latency spikes). The imports (yourdfpy pulls trimesh and scipy) leave some
    60,000 objects that live forever: frozen, no collection walks them again. A young generation
    of 50,000 allocations instead of 700 lets the short-lived objects of each message die by
    reference counting before a collection ever sees them, so few reach the old generation:
    0.1 s of collection a minute, the longest pause 21 ms. Memory stayed the same.
    """
    gc.collect()
    gc.freeze()
    gc.set_threshold(50_000, 50, 100)


def _public_settings(config: ServerConfig) -> dict[str, Any]:
    """The settings worth keeping in a recording (never the API keys)."""
    settings = dataclasses.asdict(config)
    settings["api_keys"] = len(config.api_keys)
    settings["viewer_keys"] = len(config.viewer_keys)
    return settings


async def _create_demo_robot(app: ArenaApp) -> None:
    robot = await app.manager.create_robot("so-arm100", "Demo arm", DEMO_ROBOT_ID)
    await robot.attach_slave(
        MockSlave(MockSlaveConfig(simulate_latency=20, response_delay=10)), "demo-mock-slave"
    )
