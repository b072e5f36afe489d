"""The master endpoint, `/ws/master/{robot id}`: commands in; acknowledgments, joint states
and state changes out. (`endpoints` sends the id of a group to `group_master`.)"""

from __future__ import annotations

import time
from functools import partial

import trio

from arena.drivers.planned_move import PlannedMove
from arena.drivers.sequence_master import SequenceMaster
from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.stopped import StoppedData, StoppedNotice
from arena.robot.events import MasterNotice
from arena.robot.handle import Robot
from arena.robot.links import DETACHED_LINK, MasterLink
from arena.robot.motion import CommandResult
from arena.server import convert
from arena.server.base import ArenaApp
from arena.server.hand_api import command_pose
from arena.server.link_quality import LinkQuality
from arena.server.move_api import check_goal, move_straight
from arena.server.planned_moves import plan_move
from arena.server.ws.acks import AckCache
from arena.server.ws.backpressure import Outgoing
from arena.server.ws.connection import (
    BINARY_REFUSAL,
    CLOSE_FOR,
    CLOSE_NORMAL,
    Connection,
    flag,
    peer_ids,
)
from arena.server.ws.forwarder import FORWARDED, QUEUE_LENGTH, RobotEventForwarder
from arena.server.ws.hand_drive import HandDrive
from arena.server.ws.remote_policy import RemotePolicy
from arena.server.ws.sequence_player import SequencePlayer


async def serve(connection: Connection, robot_id: str) -> None:
    """A master: commands in, acknowledgments, joint states and state changes out."""
    robot = await connection.accept(robot_id)
    if robot is None:
        return
    app = connection.app
    intervene = flag(connection.args.get("intervene"))  # the running master waits, paused
    try:
        link = await robot.connect_master(
            connection.args.get("id") or f"ws-master-{next(peer_ids)}",
            kind="websocket",
            takeover=flag(connection.args.get("takeover")),
            heartbeat_timeout=app.arena_config.heartbeat_timeout,
            description="WebSocket client",
            intervene=intervene,
        )
    except ArenaError as error:
        await connection.refuse(error)
        return
    connection.count_open([robot_id])
    config = app.arena_config
    quality = LinkQuality(link.master_id, config.command_max_age, config.link_ping_interval)
    app.master_links.setdefault(robot_id, {})[link.master_id] = quality
    how = " (intervene)" if intervene else ""
    how = " (takeover)" if flag(connection.args.get("takeover")) else how
    robot.audit(connection.principal.audit_name(), "connect master" + how, link.master_id)
    try:
        await connection.send(convert.state(robot.snapshot()))
        with robot.subscribe(maxlen=QUEUE_LENGTH, kinds=FORWARDED) as events:
            player = SequencePlayer()
            forwarder = RobotEventForwarder(connection, robot, events)
            if connection.wants_joint_states:
                await connection.send(forwarder.joint_states.message())

            async def body(nursery: trio.Nursery) -> None:
                nursery.start_soon(forwarder.run)
                nursery.start_soon(_forward_master_notices, connection, link, player)
                nursery.start_soon(connection.heartbeats)
                nursery.start_soon(_ping, connection, quality)
                await _master_reader(
                    connection, robot, link, forwarder, app.acks, player, nursery, quality
                )

            await connection.run(body)
    finally:
        masters = app.master_links.get(robot_id, {})
        if masters.get(link.master_id) is quality:
            del masters[link.master_id]
            if not masters:
                del app.master_links[robot_id]
        try:
            await release_master(app, link)
        finally:  # counted closed once the robot has heard (tests wait on it)
            connection.count_closed()


async def _ping(connection: Connection, quality: LinkQuality) -> None:
    """Ping the master every `ping_interval` to time its round trip (a socket carried from
    another node of the fleet has no pings: its link is the tunnel's)."""
    ws = connection.ws
    ping = getattr(ws, "ping_nowait", None)
    if ping is None:
        return
    ws.on_pong = quality.pong  # type: ignore[attr-defined]
    while True:
        ping(quality.ping_payload())
        await trio.sleep(quality.ping_interval)


async def release_master(app: ArenaApp, link: MasterLink) -> None:
    """The socket of a master is gone: a shutdown detaches it, anything else loses it (the
    robot's loss policy applies) unless the robot let it go first."""
    with trio.CancelScope(shield=True):
        if app.shutting_down.is_set():
            await link.detach("server shutting down")
        elif not link.detached.is_set():
            await link.lost("connection closed")


async def _forward_master_notices(
    connection: Connection, link: MasterLink, player: SequencePlayer
) -> None:
    async for notice in link.notices:
        if notice.kind == "detached":
            await _send_detached(connection, notice)
            return
        if notice.kind == "paused":
            await connection.send(wire.PauseNotice(timestamp=wire.now_iso()))
        elif notice.kind == "resumed":
            await connection.send(wire.ResumeNotice(timestamp=wire.now_iso()))
        elif notice.kind == "stopped":  # the guard stopped its motion after accepting it
            blocked = None if notice.blocked is None else list(notice.blocked)
            data = StoppedData(str(notice.code), notice.message, blocked)
            await connection.send(StoppedNotice(timestamp=wire.now_iso(), data=data))
    if player.releasing:
        return  # the reader answers the release and closes
    # The robot closed the link (deleted, or detached without a word).
    await connection.close(CLOSE_NORMAL, "robot link closed")


async def _send_detached(connection: Connection, notice: MasterNotice) -> None:
    code = notice.code or ErrorCode.MASTER_LOST
    by = notice.by
    taken_by = None if by is None else wire.TakenBy(by.master_id, by.kind, by.description)
    await connection.send(  # queued even to a peer that is behind: it is the last word
        wire.DetachedMessage(
            timestamp=wire.now_iso(), data=wire.DetachedData(str(code), notice.message, taken_by)
        )
    )
    await connection.close(CLOSE_FOR.get(code, CLOSE_NORMAL), notice.message)


async def send_released(connection: Connection, data: wire.ReleasedData) -> None:
    """Answer a `release` (queued even to a peer that is behind) and close normally."""
    await connection.send(wire.ReleasedMessage(timestamp=wire.now_iso(), data=data))
    await connection.close(CLOSE_NORMAL, "released")


async def _master_reader(
    connection: Connection,
    robot: Robot,
    link: MasterLink,
    forwarder: RobotEventForwarder,
    acks: AckCache,
    player: SequencePlayer,
    nursery: trio.Nursery,
    quality: LinkQuality,
) -> None:
    """A master's messages until it leaves; errors are answered, not fatal.

    The frames of a burst that are in hand together are taken at once, and each run of
    commands among them is decided in one pass (`decide_commands`). Every command is still
    decided, recorded and acknowledged on its own and in order; what a run shares is the
    forwarder's hold and one write of the answers. A stamped command that arrives older than
    `command_max_age` is refused STALE_COMMAND instead (it still shows the master is there).
    """
    policy = RemotePolicy(robot, link)
    drive = HandDrive(connection, robot, link)
    handle = partial(
        _handle_master_message, connection, robot, link, player, policy, nursery, drive
    )
    run: list[wire.CommandData] = []

    async def decide_run(burst_goes_on: bool) -> bool:
        """Decide the commands in hand, if any; False once the robot is gone."""
        if not run:
            return True
        policy.commanded()
        return await decide_commands(connection, link, forwarder, run, burst_goes_on, acks)

    while True:
        raw = await connection.receive_text()
        if raw is None:
            return
        started = time.perf_counter()
        frames, closed = connection.in_hand(raw)
        run = []
        for frame in frames:
            message: wire.MasterMessage | ArenaError
            if isinstance(frame, bytes):
                message = ArenaError(ErrorCode.BINARY_NOT_SUPPORTED, BINARY_REFUSAL)
            else:
                try:
                    message = wire.decode_master(frame)
                except ArenaError as error:
                    message = error
            if isinstance(message, wire.CommandMessage):
                if quality.admit(message.data.timestamp):
                    run.append(message.data)
                    continue
                if not await decide_run(True):
                    return
                run = []
                link.alive()
                connection.app.metrics.stale_commands[robot.robot_id] += 1
                await connection.send(acks.ack(stale_refusal(quality)))
                continue
            if not await decide_run(True):
                return
            run = []
            if isinstance(message, ArenaError):
                await connection.send_error(message.code, message.message)
                continue
            try:
                await handle(message)
            except ArenaError as error:
                if not await connection.answer_error(error):
                    return
        if not await decide_run(connection.ws.holds_more()):
            return
        connection.app.metrics.observe_latency(time.perf_counter() - started, len(frames))
        if closed:
            return


def stale_refusal(quality: LinkQuality) -> CommandResult:
    """The answer to a command that came too late."""
    age = quality.last_age or 0.0
    return CommandResult.refused(
        ErrorCode.STALE_COMMAND,
        f"The command arrived {age * 1000:.0f} ms after it was sent, more than "
        f"command_max_age ({(quality.max_age or 0) * 1000:.0f} ms): dropped, not run late.",
    )


async def decide_commands(
    connection: Connection,
    link: MasterLink,
    forwarder: RobotEventForwarder,
    run: list[wire.CommandData],
    burst_goes_on: bool,
    acks: AckCache,
) -> bool:
    """Decide commands in order and send their answers in one write; False (and the socket
    closed) if the robot is gone. `burst_goes_on`: more frames follow the last of them."""
    out: list[Outgoing] = []
    stopped = False
    commands = [convert.command_from_wire(d.joints, d.duration, d.metadata) for d in run]
    wants_acks, ack = connection.wants_acks, acks.ack
    with forwarder.handling_command():
        # Each command counts as a heartbeat (the robot notes the time of each).
        index, last = 0, len(commands) - 1
        while index <= last:
            rest = commands[index:] if index else commands
            results = link.command_run_now(rest, burst_goes_on=burst_goes_on)
            if results is not None:
                out.extend([ack(result) for result in results if wants_acks or not result.accepted])
                break
            # The actor is busy (most often a motion tick is due): this command goes through
            # its inbox, after which the actor is idle again for the rest.
            try:
                in_burst = burst_goes_on or index < last
                result = await link.command(commands[index], in_burst=in_burst)
            except ArenaError as error:
                if error.code is ErrorCode.ROBOT_STOPPED:
                    stopped = True
                    break
                out.append(connection.error(error.code, error.message))
            else:
                if wants_acks or not result.accepted:
                    out.append(ack(result))
            index += 1
        # The joint states the commands caused ride along: one write instead of two.
        out.extend(forwarder.take_due())
    if out:
        await connection.send(*out, whole=True)
    if stopped:
        await connection.close(CLOSE_NORMAL, "robot deleted")
    return not stopped


async def _play_planned(
    connection: Connection,
    robot: Robot,
    link: MasterLink,
    player: SequencePlayer,
    data: wire.MoveData,
) -> None:
    """Plan a `move` (in a thread, the messages go on meanwhile), say so with an `ack` (its
    message: the corners and the duration) or an `error`, then play the path as this
    master's commands; a new sequence or move, an e-stop or a release stops it."""
    with trio.CancelScope() as scope:
        player.scope = scope
        try:
            path = await plan_move(connection.app, robot, data, link.master_id)
        except ArenaError as error:
            await connection.send_error(error.code, error.message)
            return
        what = f"planned: {len(path.waypoints)} corners, {path.duration:.2f} s"
        await connection.send(
            wire.AckMessage(timestamp=wire.now_iso(), data=wire.AckData("accepted", message=what))
        )
        await PlannedMove(path, source="move").run(link)


async def _handle_master_message(
    connection: Connection,
    robot: Robot,
    link: MasterLink,
    player: SequencePlayer,
    policy: RemotePolicy,
    nursery: trio.Nursery,
    drive: HandDrive,
    message: wire.MasterMessage,
) -> None:
    """Any message of a master but a command (those go to `decide_commands`)."""
    link.alive()
    if isinstance(message, wire.SequenceMessage):
        sequence = convert.sequence_from_wire(message.data)
        sequence.check_against(robot.model)
        player.stop()
        nursery.start_soon(player.play, link, SequenceMaster([sequence], loop=sequence.loop))
        await connection.send(
            wire.AckMessage(timestamp=wire.now_iso(), data=wire.AckData("accepted"))
        )
    elif isinstance(message, wire.EStopMessage):
        player.stop()
        reason = (message.data.reason if message.data else None) or "e-stop from master"
        await robot.estop(reason)
        robot.audit(connection.principal.audit_name(), "estop over WebSocket", link.master_id)
    elif isinstance(message, wire.ResetMessage):
        await robot.reset()  # (a refused reset changed nothing: not recorded)
        robot.audit(connection.principal.audit_name(), "reset over WebSocket", link.master_id)
    elif isinstance(message, wire.InferenceMessage):
        policy.inferred(message.data)
    elif isinstance(message, wire.PolicyMessage):
        policy.declare(message.data, nursery)
        robot.audit(
            connection.principal.audit_name(),
            f"remote policy at {message.data.fps:g} fps",
            link.master_id,
        )
        await connection.send(
            wire.AckMessage(timestamp=wire.now_iso(), data=wire.AckData("accepted"))
        )
    elif isinstance(message, wire.EeVelocityMessage):
        drive.velocity(message.data, nursery)
    elif isinstance(message, wire.PoseMessage):
        result, _ = await command_pose(robot, message.data, link.command, "pose")
        await connection.send(convert.ack(result))
    elif isinstance(message, wire.MoveMessage):
        check_goal(message.data)
        if message.data.plan:
            player.stop()  # (as a new sequence does; this one is stopped alike)
            nursery.start_soon(_play_planned, connection, robot, link, player, message.data)
        else:
            result, _ = await move_straight(robot, message.data, link.command, "move")
            await connection.send(convert.ack(result))
    elif isinstance(message, wire.HeartbeatMessage):
        await connection.send(wire.HeartbeatMessage(timestamp=wire.now_iso()))
    elif isinstance(message, wire.ReleaseMessage):
        if link.detached.is_set():  # taken over or stopped meanwhile: its notice says why
            raise ArenaError(ErrorCode.NOT_OWNER, DETACHED_LINK.message)
        player.stop()
        player.releasing = True
        await link.release(hold=message.data is not None and message.data.hold)
        robot.audit(connection.principal.audit_name(), "release over WebSocket", link.master_id)
        snapshot = robot.snapshot()
        await send_released(connection, wire.ReleasedData(robot.robot_id, str(snapshot.mode)))
