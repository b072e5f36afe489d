"""What `arena mcp`'s tools do, over Arena's public API only: REST to list and read robots and
to e-stop, a master's WebSocket (one per robot, opened at the agent's first move and held until
it releases the robot or `arena mcp` ends) for every move, so the server applies every rule of
a master to the agent's commands. Nothing here knows MCP (`arena.mcp.server` does).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, cast
from urllib.parse import quote

import trio

from arena.client import AsyncArena, MasterSession
from arena.client.errors import ArenaClientError
from arena.robot.cartesian import hand_for
from arena.robot.model import RobotModel, load_robot_model
from arena.script.master import MoveEnd

log = logging.getLogger(__name__)

#: Seconds between looks at the joints while a move runs.
POLL = 0.05
#: The longest a tool waits for a move to end beyond its own duration (seconds): it answers
#: then, saying the move goes on.
MOVE_WAIT = 30.0
#: Robots an agent may hold as master at once (each a WebSocket).
MAX_HELD = 16


class AgentError(Exception):
    """What the agent is told when a tool cannot do what it asked (the server's code and
    sentence, or why not here)."""


def _failed(error: ArenaClientError) -> AgentError:
    return AgentError(f"{error.code}: {error.message}")


@dataclass
class Held:
    """A robot the agent holds as its master: the session and what ends it."""

    session: MasterSession
    model: RobotModel
    done: trio.Event = field(default_factory=trio.Event)


class Agent:
    """The robots of the server at `url`, as the agent sees them."""

    def __init__(
        self, arena: AsyncArena, url: str, api_key: str | None, nursery: trio.Nursery, name: str
    ) -> None:
        self.arena = arena
        self.url = url
        self.api_key = api_key
        self.nursery = nursery
        self.name = name
        self.held: dict[str, Held] = {}

    async def _get(self, path: str) -> Any:
        response = await self.arena.http.get(path)
        if response.status_code >= 400:
            error = (response.json().get("error") or {}) if response.content else {}
            raise AgentError(f"{error.get('code', response.status_code)}: {error.get('message')}")
        return response.json()

    async def list_robots(self) -> list[dict[str, Any]]:
        """Every robot the API key sees: id, name, type, safety state, its master, and whether this
        agent holds it."""
        listed = await self._get("/api/robots")
        return [
            {
                "id": robot["id"],
                "name": robot.get("name"),
                "robot_type": robot.get("robot_type"),
                "state": robot.get("state"),
                "master": (robot.get("master") or {}).get("id"),
                "held_by_this_agent": robot["id"] in self.held,
            }
            for robot in listed
        ]

    async def read_joints(self, robot_id: str) -> dict[str, Any]:
        """Each joint: its commanded and measured value (degrees; the gripper in percent) and
        its limits; the robot's safety state."""
        robot = await self._get(f"/api/robots/{quote(robot_id)}")
        joints = {
            joint["name"]: {
                "commanded": joint.get("virtual_value"),
                "measured": joint.get("real_value"),
                "limits": [(joint.get("limits") or {}).get(k) for k in ("lower", "upper")],
            }
            for joint in robot.get("joints", [])
        }
        return {"robot": robot_id, "state": robot.get("state"), "joints": joints}

    async def read_pose(self, robot_id: str) -> dict[str, Any]:
        """The hand's pose, measured and commanded (metres in the robot's base frame, a
        quaternion x, y, z, w, the gripper)."""
        pose: dict[str, Any] = await self._get(f"/api/robots/{quote(robot_id)}/pose")
        return pose

    async def _hold(self, robot_id: str) -> Held:
        """The robot as this agent's master: the session it holds, opened if need be (refused
        MASTER_ACTIVE while another master drives it)."""
        held = self.held.get(robot_id)
        if held is not None and held.session.detached is None and not held.done.is_set():
            return held
        if held is not None:
            held.done.set()
            del self.held[robot_id]
        if len(self.held) >= MAX_HELD:
            raise AgentError(f"This agent holds {MAX_HELD} robots already: release one first.")
        robot = await self._get(f"/api/robots/{quote(robot_id)}")
        model = load_robot_model(robot["robot_type"])

        async def run(task_status: trio.TaskStatus[Held]) -> None:
            started: list[Held] = []
            try:
                async with MasterSession.open(
                    self.url, robot_id, master_id=self.name, api_key=self.api_key
                ) as session:
                    await session.wait_for(lambda s: bool(s.joints), timeout=10)
                    started.append(Held(session, model))
                    task_status.started(started[0])
                    await started[0].done.wait()
            except (ArenaClientError, OSError) as error:
                if not started:
                    raise  # (the tool that asked says why)
                # The link ended (the server went away): this robot is no longer held, and
                # `arena mcp` goes on serving the others.
                started[0].done.set()
                log.warning("%s: the master link to %r ended: %s", self.name, robot_id, error)

        try:
            held = cast(Held, await self.nursery.start(run))
        except ArenaClientError as error:
            raise _failed(error) from None
        self.held[robot_id] = held
        return held

    async def release(self, robot_id: str) -> dict[str, Any]:
        """Hand the robot back (it holds where it is)."""
        held = self.held.pop(robot_id, None)
        if held is None:
            return {"robot": robot_id, "released": False, "why": "this agent does not hold it"}
        try:
            if held.session.detached is None:
                await held.session.release(hold=True)
        except ArenaClientError as error:
            raise _failed(error) from None
        finally:
            held.done.set()
        return {"robot": robot_id, "released": True}

    async def move_joints(
        self, robot_id: str, joints: dict[str, float], duration: float | None = None
    ) -> dict[str, Any]:
        """Move the named joints (degrees; the gripper in percent) over `duration` seconds
        (None: as fast as the limits allow); answers once the move is over."""
        held = await self._hold(robot_id)
        extra = {} if duration is None else {"duration": duration * 1000.0}
        try:
            ack = await held.session.command(joints, metadata={"source": self.name}, **extra)
        except (ArenaClientError, ValueError) as error:
            raise _describe(error) from None
        targets = {n: _clamp(held.model, n, v) for n, v in joints.items()}
        finished = await self._settle(held, targets, duration)
        return self._moved(held, robot_id, ack, finished)

    async def move_to_pose(
        self,
        robot_id: str,
        position: list[float],
        orientation: list[float] | None = None,
        gripper: float | None = None,
        duration: float | None = None,
    ) -> dict[str, Any]:
        """Move the hand's tool point to `position`, turned to `orientation` if given; the
        server solves the joints and checks them (UNREACHABLE says how near it gets)."""
        held = await self._hold(robot_id)
        ms = None if duration is None else duration * 1000.0
        try:
            ack = await held.session.pose(position, orientation, gripper=gripper, duration=ms)
        except (ArenaClientError, ValueError) as error:
            raise _describe(error) from None
        finished = await self._settle(held, {}, duration)
        return self._moved(held, robot_id, ack, finished)

    async def plan_move(
        self,
        robot_id: str,
        joints: dict[str, float] | None = None,
        position: list[float] | None = None,
        orientation: list[float] | None = None,
    ) -> dict[str, Any]:
        """A move along a path planned around the table, the keep-out boxes and the arm
        itself, where the server plans moves."""
        if (joints is None) == (position is None):
            raise AgentError("Give either joints or a position.")
        held = await self._hold(robot_id)
        pose: dict[str, Any] = {"position": position}
        if orientation is not None:
            pose["orientation"] = orientation
        goal: dict[str, Any] = {"joints": joints} if joints is not None else {"pose": pose}
        try:
            ack = await held.session.move(goal, plan=True)
        except ArenaClientError as error:
            if error.code in ("UNKNOWN_MESSAGE_TYPE", "INVALID_MESSAGE"):
                raise AgentError(
                    "NOT_INSTALLED: this server plans no moves (planned paths are not part of "
                    "it): use move_joints or move_to_pose, the straight line the collision "
                    "guard checks."
                ) from None
            raise _failed(error) from None
        finished = await self._settle(held, {}, None)
        return self._moved(held, robot_id, ack, finished)

    async def gripper(self, robot_id: str, action: str | float) -> dict[str, Any]:
        """`open` (the top of the gripper joint's range), `close` (its bottom), or a number
        (its unit)."""
        robot = await self._get(f"/api/robots/{quote(robot_id)}")
        model = load_robot_model(robot["robot_type"])
        hand = hand_for(model)
        joint = hand.gripper if hand is not None else model.joint("gripper")
        if joint is None:
            raise AgentError(f"Robot {robot_id!r} has no gripper joint.")
        if action == "open":
            value = joint.upper
        elif action == "close":
            value = joint.lower
        else:
            try:
                value = float(action)
            except ValueError:
                raise AgentError(f"{action!r}: open, close or a number.") from None
            if not math.isfinite(value):
                raise AgentError(f"INVALID_VALUE: {action!r} is not a finite number.")
        return await self.move_joints(robot_id, {joint.name: value})

    async def estop(self, robot_id: str, reason: str) -> dict[str, Any]:
        """E-stop the robot (over REST: it answers whoever holds it)."""
        response = await self.arena.http.post(
            f"/api/robots/{quote(robot_id)}/estop", json={"reason": reason or "agent e-stop"}
        )
        if response.status_code >= 400:
            error = response.json().get("error") or {}
            raise AgentError(f"{error.get('code')}: {error.get('message')}")
        return {"robot": robot_id, "state": response.json().get("state")}

    async def _settle(self, held: Held, targets: dict[str, float], duration: float | None) -> bool:
        """Wait for the move to end (as a script's move: `MoveEnd`); False if the robot
        paused or let go of the agent, or the move still runs after its duration and
        `MOVE_WAIT`."""
        session = held.session
        ending = MoveEnd(targets, duration, trio.current_time(), lambda _, value: value)
        with trio.move_on_after((duration or 0.0) + MOVE_WAIT):
            while True:
                await trio.sleep(POLL)
                if session.paused or session.detached is not None:
                    return False
                values = {
                    name: float(entry["virtual_value"])
                    for name, entry in session.joints.items()
                    if entry.get("virtual_value") is not None
                }
                if ending.over(values, trio.current_time()):
                    return True
        return False

    def _moved(
        self, held: Held, robot_id: str, ack: dict[str, Any], finished: bool
    ) -> dict[str, Any]:
        data = ack.get("data") or {}
        joints = {
            name: round(float(entry.get("virtual_value") or 0.0), 3)
            for name, entry in held.session.joints.items()
        }
        answer: dict[str, Any] = {
            "robot": robot_id,
            "status": data.get("status", "accepted"),
            "finished": finished,
            "joints": joints,
        }
        if data.get("clamped"):
            answer["clamped"] = data["clamped"]
        if held.session.paused:
            answer["paused"] = "the robot paused this agent: it holds until resumed"
        return answer


def _clamp(model: RobotModel, name: str, value: float) -> float:
    joint = model.joint(name)
    return value if joint is None or not math.isfinite(value) else joint.clamp(value)


def _describe(error: ArenaClientError | ValueError) -> AgentError:
    if isinstance(error, ArenaClientError):
        return _failed(error)
    return AgentError(f"INVALID_VALUE: {error}")
