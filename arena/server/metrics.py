"""Prometheus text-format metrics, without a client library: a few counters and a histogram."""

from __future__ import annotations

import bisect
import collections
from collections.abc import Iterable
from typing import Any

from arena.robot.actor import Robot

#: Upper bounds (seconds) of the message latency histogram buckets.
LATENCY_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.1, 1.0)


class Metrics:
    """Counters the server keeps at its edges; robot counters are read from the actors."""

    def __init__(self) -> None:
        self.connections: collections.Counter[str] = collections.Counter()  # open, by role
        self.requests: collections.Counter[str] = collections.Counter()  # by status class
        self.messages: collections.Counter[str] = collections.Counter()  # in, by role
        self.message_errors: collections.Counter[str] = collections.Counter()  # by code
        #: Messages a peer that stopped reading did not get, by kind (ack, joint_states...).
        self.dropped: collections.Counter[str] = collections.Counter()
        self._latency_counts = [0] * (len(LATENCY_BUCKETS) + 1)
        self._latency_sum = 0.0
        self._retired: collections.Counter[str] = collections.Counter()  # deleted robots
        self._retired_estops = 0
        self._retired_superseded = 0

    def observe_latency(self, seconds: float) -> None:
        """Time from a message's arrival to its answer."""
        self._latency_counts[bisect.bisect_left(LATENCY_BUCKETS, seconds)] += 1
        self._latency_sum += seconds

    def retire(self, robot: Robot) -> None:
        """Keep a deleted robot's counts in the totals."""
        self._retired.update(robot.command_counts)
        self._retired_estops += robot.estop_count
        self._retired_superseded += robot.targets_superseded

    def render(
        self,
        robots: Iterable[Robot],
        queued_bytes: int = 0,
        recording: dict[str, Any] | None = None,
    ) -> str:
        """The Prometheus exposition text; `queued_bytes` is what the WebSocket connections
        hold for their peers, `recording` the recorder's status."""
        robots = list(robots)
        commands = collections.Counter(self._retired)
        estops = self._retired_estops
        for robot in robots:
            commands.update(robot.command_counts)
            estops += robot.estop_count
        lines = [
            "# HELP arena_robots Robots that exist now.",
            "# TYPE arena_robots gauge",
            f"arena_robots {len(robots)}",
            "# HELP arena_connections Open WebSocket connections by role.",
            "# TYPE arena_connections gauge",
        ]
        for role in ("master", "slave", "viewer"):
            lines.append(f'arena_connections{{role="{role}"}} {self.connections[role]}')
        lines += [
            "# HELP arena_commands_total Commands answered, by result (accepted or refusal code).",
            "# TYPE arena_commands_total counter",
        ]
        for result, count in sorted(commands.items()):
            lines.append(f'arena_commands_total{{result="{result}"}} {count}')
        superseded = self._retired_superseded + sum(r.targets_superseded for r in robots)
        lines += [
            "# HELP arena_targets_superseded_total Targets replaced by a newer one before a"
            " slave took it (a slave slower than its master gets the newest only).",
            "# TYPE arena_targets_superseded_total counter",
            f"arena_targets_superseded_total {superseded}",
        ]
        lines += [
            "# HELP arena_estops_total Emergency stops.",
            "# TYPE arena_estops_total counter",
            f"arena_estops_total {estops}",
            "# HELP arena_messages_total WebSocket messages received, by role.",
            "# TYPE arena_messages_total counter",
        ]
        for role, count in sorted(self.messages.items()):
            lines.append(f'arena_messages_total{{role="{role}"}} {count}')
        lines += [
            "# HELP arena_ws_dropped_total Messages not sent to a peer that stopped reading"
            " (superseded states, dropped acks), by kind.",
            "# TYPE arena_ws_dropped_total counter",
        ]
        for kind, count in sorted(self.dropped.items()):
            lines.append(f'arena_ws_dropped_total{{kind="{kind}"}} {count}')
        lines += [
            "# HELP arena_ws_queued_bytes Bytes queued for WebSocket peers, over all connections.",
            "# TYPE arena_ws_queued_bytes gauge",
            f"arena_ws_queued_bytes {queued_bytes}",
        ]
        lines += [
            "# HELP arena_message_errors_total Messages and requests refused at the edge.",
            "# TYPE arena_message_errors_total counter",
        ]
        for code, count in sorted(self.message_errors.items()):
            lines.append(f'arena_message_errors_total{{code="{code}"}} {count}')
        lines += [
            "# HELP arena_http_requests_total HTTP requests by status class.",
            "# TYPE arena_http_requests_total counter",
        ]
        for status, count in sorted(self.requests.items()):
            lines.append(f'arena_http_requests_total{{status="{status}"}} {count}')
        if recording is not None:
            failing = recording["error"] is not None
            lines += [
                "# HELP arena_recording_active Recording is switched on.",
                "# TYPE arena_recording_active gauge",
                f"arena_recording_active {int(bool(recording['active']))}",
                "# HELP arena_recording_failing Recording is on but the disk refuses it.",
                "# TYPE arena_recording_failing gauge",
                f"arena_recording_failing {int(failing)}",
                "# HELP arena_recording_messages_total Messages written to recordings.",
                "# TYPE arena_recording_messages_total counter",
                f"arena_recording_messages_total {recording['messages']}",
                "# HELP arena_recording_dropped_total Messages lost (full queues, disk errors).",
                "# TYPE arena_recording_dropped_total counter",
                f"arena_recording_dropped_total {recording['dropped']}",
                "# HELP arena_recording_errors_total Failed attempts to write to the disk.",
                "# TYPE arena_recording_errors_total counter",
                f"arena_recording_errors_total {recording['errors']}",
            ]
        lines += [
            "# HELP arena_message_latency_seconds From a message's arrival to its answer.",
            "# TYPE arena_message_latency_seconds histogram",
        ]
        cumulative = 0
        for bound, count in zip(LATENCY_BUCKETS, self._latency_counts, strict=False):
            cumulative += count
            lines.append(f'arena_message_latency_seconds_bucket{{le="{bound}"}} {cumulative}')
        cumulative += self._latency_counts[-1]
        lines.append(f'arena_message_latency_seconds_bucket{{le="+Inf"}} {cumulative}')
        lines.append(f"arena_message_latency_seconds_sum {self._latency_sum}")
        lines.append(f"arena_message_latency_seconds_count {cumulative}")
        return "\n".join(lines) + "\n"
