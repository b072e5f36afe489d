"""Live Foxglove: every robot's 3D twin, joints and log over Foxglove's WebSocket protocol.

`arena serve --foxglove-port PORT` starts the official `foxglove-sdk` server (it runs its own
thread). The channels are those of a recording (`recording/foxglove.py`): `/robots/{id}/tf`,
`/scene`, `/log` (protobuf) and `/targets`, `/joint_states` (Arena's JSON records), so one
Foxglove layout serves a live session and a file alike.

One mechanism joins trio and the SDK: a bounded queue into one publisher thread. The trio side
drains the robots' event queues every `interval`, keeps the newest targets and joint states of
each robot (latest wins: a viewer wants the pose now, not a backlog) and every other event,
and puts the batch on the queue without waiting (a full queue drops the batch and counts it).
The publisher thread does the costly part (forward kinematics and encoding) only for channels a
Foxglove client has subscribed to, so an unwatched bridge costs next to nothing. The SDK's
subscribe callback asks the same thread, through the same queue, to send a robot's 3D model.
Robot state is never touched from a foreign thread: the thread sees copies of events.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import foxglove
import msgspec
import trio
from foxglove.websocket import ChannelView, Client, ServerListener

from arena.recording import images
from arena.recording.foxglove import MESSAGE_TYPES, TREE_OF, Twin, pose_of
from arena.recording.mcap_file import channel_format
from arena.recording.records import KIND_OF_EVENT, camera_kind, record_of, topic
from arena.robot.events import CameraFrame, RobotEvent
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.robot.model import RobotModel

log = logging.getLogger(__name__)

#: Batches waiting for the publisher thread; beyond this the newest batch is dropped.
QUEUE_BATCHES = 64
#: Arena's JSON records that go live beside Foxglove's kinds (for plots of each joint): those
#: of the pose events.
JSON_KINDS = tuple(KIND_OF_EVENT[event] for event in TREE_OF)
_json = msgspec.json.Encoder()


@dataclass
class _Batch:
    """What happened to the robots since the last batch (newest poses only)."""

    robots: dict[str, RobotModel] = field(default_factory=dict)  # new robots
    gone: list[str] = field(default_factory=list)
    events: list[tuple[str, RobotEvent]] = field(default_factory=list)
    frames: list[CameraFrame] = field(default_factory=list)  # the newest of each camera
    cameras_gone: list[tuple[str, str]] = field(default_factory=list)


class FoxgloveBridge:
    """Follows robots (`follow`) and publishes them to Foxglove clients while `run` runs."""

    def __init__(self, host: str, port: int, *, interval: float = 0.02) -> None:
        self.host = host
        self.requested_port = port
        self.interval = interval
        #: The port the Foxglove server listens on (known once `run` has started).
        self.port: int | None = None
        #: Batches the publisher thread could not take in time.
        self.dropped = 0
        self._queue: queue.Queue[_Batch | str | None] = queue.Queue(QUEUE_BATCHES)
        self._followed: dict[EventQueue[RobotEvent], tuple[str, contextlib.ExitStack]] = {}
        self._cameras: dict[
            EventQueue[CameraFrame], tuple[tuple[str, str], contextlib.ExitStack]
        ] = {}
        self._pending = _Batch()

    def follow(self, robot: Robot) -> None:
        """Publish this robot from now on (a `RobotManager.on_create` callback)."""
        subscription = contextlib.ExitStack()
        events = subscription.enter_context(robot.subscribe(maxlen=4096))
        self._followed[events] = (robot.robot_id, subscription)
        self._pending.robots[robot.robot_id] = robot.model

    def follow_frames(
        self,
        robot_id: str,
        camera: str,
        frames: contextlib.AbstractContextManager[EventQueue[CameraFrame]],
    ) -> None:
        """Publish a camera's frames from now on (its subscription; only the newest of each
        batch goes out)."""
        subscription = contextlib.ExitStack()
        self._cameras[subscription.enter_context(frames)] = ((robot_id, camera), subscription)

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """Serve until cancelled; then stop the Foxglove server and the publisher thread."""
        publisher = _Publisher()
        context = publisher.context
        server = await trio.to_thread.run_sync(
            lambda: foxglove.start_server(
                name="arena",
                host=self.host,
                port=self.requested_port,
                server_listener=_Listener(self._offer),
                context=context,
            )
        )
        thread = threading.Thread(
            target=publisher.serve, args=(self._queue,), name="foxglove", daemon=True
        )
        thread.start()
        self.port = server.port
        try:
            task_status.started(self.port)
            while True:
                await trio.sleep(self.interval)
                self._offer(self._collect())
        finally:
            for _, subscription in self._followed.values():
                subscription.close()
            self._followed.clear()
            for _, subscription in self._cameras.values():
                subscription.close()
            self._cameras.clear()
            with contextlib.suppress(queue.Full):
                self._queue.put_nowait(None)  # the thread ends after what it holds
            server.stop()

    def _collect(self) -> _Batch:
        batch, self._pending = self._pending, _Batch()
        for events, (robot_id, subscription) in list(self._followed.items()):
            newest: dict[type, RobotEvent] = {}
            for event in events.drain():
                if type(event) in TREE_OF:  # a pose: the newest is all a viewer needs
                    newest[type(event)] = event
                else:
                    batch.events.append((robot_id, event))
            batch.events.extend((robot_id, event) for event in newest.values())
            if events.closed:
                del self._followed[events]
                subscription.close()
                batch.gone.append(robot_id)
        for frames, (key, frame_subscription) in list(self._cameras.items()):
            taken = frames.drain()
            if taken:
                batch.frames.append(taken[-1])
            if frames.closed:
                del self._cameras[frames]
                frame_subscription.close()
                batch.cameras_gone.append(key)
        return batch

    def _offer(self, item: _Batch | str) -> None:
        if isinstance(item, _Batch) and not (
            item.robots or item.gone or item.events or item.frames or item.cameras_gone
        ):
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1
            if isinstance(item, _Batch):  # robots new or gone must not be lost with it
                self._pending.robots.update(item.robots)
                self._pending.gone.extend(item.gone)
                self._pending.cameras_gone.extend(item.cameras_gone)


class _Listener(ServerListener):
    """The SDK's callbacks (its thread): a new subscriber to a scene gets the model."""

    def __init__(self, offer: Any) -> None:
        self._offer = offer

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        if channel.topic.endswith("/scene"):
            self._offer(channel.topic)


class _Publisher:
    """The publisher thread's state: twins and channels per robot."""

    def __init__(self) -> None:
        self.context = foxglove.Context()
        self._twins: dict[str, Twin] = {}
        self._channels: dict[str, dict[str, foxglove.Channel]] = {}
        self._scene_topics: dict[str, str] = {}
        self._cameras: dict[tuple[str, str], foxglove.Channel] = {}

    def serve(self, batches: queue.Queue[_Batch | str | None]) -> None:
        while (item := batches.get()) is not None:
            try:
                if isinstance(item, str):
                    self._send_scene(self._scene_topics.get(item))
                else:
                    self._publish(item)
            except Exception:  # a bad message must not end live viewing for everyone
                log.exception("foxglove bridge: publishing failed")
        for channels in self._channels.values():
            for channel in channels.values():
                channel.close()
        for channel in self._cameras.values():
            channel.close()

    def _publish(self, batch: _Batch) -> None:
        for key in batch.cameras_gone:
            gone = self._cameras.pop(key, None)
            if gone is not None:
                gone.close()
        for frame in batch.frames:
            channel = self._camera_channel(frame.robot_id, frame.camera)
            if channel.has_sinks():  # JPEG bytes as they are: no work for an unwatched camera
                ns = int(frame.wall_time * 1e9)
                channel.log(images.encode(frame, ns), log_time=ns)
        for robot_id in batch.gone:
            self._twins.pop(robot_id, None)
            for channel in self._channels.pop(robot_id, {}).values():
                channel.close()
        for robot_id, model in batch.robots.items():
            self._add(robot_id, model)
        for robot_id, event in batch.events:
            twin, channels = self._twins.get(robot_id), self._channels.get(robot_id)
            if twin is None or channels is None:
                continue
            ns = int(event.wall_time * 1e9)
            kind = KIND_OF_EVENT[type(event)]
            if kind in channels and channels[kind].has_sinks():
                channels[kind].log(_json.encode(record_of(event)[1]), log_time=ns)
            pose = pose_of(event)
            if channels["log" if pose is None else "tf"].has_sinks():
                for view, data in twin.messages(event, ns):
                    channels[view].log(data, log_time=ns)
            elif pose is not None:  # unwatched: keep the pose, for a viewer still to come
                twin.update(*pose)

    def _add(self, robot_id: str, model: RobotModel) -> None:
        channels: dict[str, foxglove.Channel] = {}
        for kind in (*MESSAGE_TYPES, *JSON_KINDS):
            name, schema_encoding, data, encoding = channel_format(kind)
            channels[kind] = foxglove.Channel(
                topic(robot_id, kind),
                schema=foxglove.Schema(name=name, encoding=schema_encoding, data=data),
                message_encoding=encoding,
                context=self.context,
            )
        self._twins[robot_id] = Twin(robot_id, model)
        self._channels[robot_id] = channels
        self._scene_topics[topic(robot_id, "scene")] = robot_id

    def _camera_channel(self, robot_id: str, camera: str) -> foxglove.Channel:
        channel = self._cameras.get((robot_id, camera))
        if channel is None:
            kind = camera_kind(camera)
            name, schema_encoding, data, encoding = channel_format(kind)
            channel = foxglove.Channel(
                topic(robot_id, kind),
                schema=foxglove.Schema(name=name, encoding=schema_encoding, data=data),
                message_encoding=encoding,
                context=self.context,
            )
            self._cameras[(robot_id, camera)] = channel
        return channel

    def _send_scene(self, robot_id: str | None) -> None:
        twin = self._twins.get(robot_id or "")
        if twin is not None and robot_id is not None:
            ns = time.time_ns()
            self._channels[robot_id]["scene"].log(twin.scene(ns), log_time=ns)
