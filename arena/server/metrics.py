"""Prometheus text-format metrics, without a client library: a few counters and a histogram."""

from __future__ import annotations

import bisect
import collections
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from arena.robot.handle import Robot
from arena.server.link_quality import QUALITY_LEVELS, LinkQuality

#: The roles of WebSocket peers.
ROLES = ("master", "slave", "viewer")
#: Upper bounds (seconds) of the message latency histogram buckets.
LATENCY_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.1, 1.0)


def _family(name: str, kind: str, text: str, samples: float | dict[str, float]) -> list[str]:
    """One metric family: its HELP and TYPE lines, then one value or a value per label set."""
    lines = [f"# HELP {name} {text}", f"# TYPE {name} {kind}"]
    if isinstance(samples, dict):
        lines += [f"{name}{{{labels}}} {value}" for labels, value in samples.items()]
    else:
        lines.append(f"{name} {samples}")
    return lines


def _label(value: str) -> str:
    """A label value as the exposition format writes it (a robot type names its joints)."""
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


#: A policy's figures shown on /metrics: (metric, type, its key in the figures, help).
POLICY_FIGURES = (
    (
        "arena_policy_inference_seconds",
        "gauge",
        "last_latency",
        "The policy's last inference, as its worker timed it, by robot.",
    ),
    (
        "arena_policy_chunk_actions",
        "gauge",
        "last_chunk",
        "Actions in the policy's last chunk, by robot.",
    ),
    ("arena_policy_inferences_total", "counter", "inferences", "The policy's inferences."),
    (
        "arena_policy_stalls_total",
        "counter",
        "stalls",
        "Times the policy's watchdog tripped (no action in time), by robot.",
    ),
)


def _flywheel_families(robots: list[Robot]) -> list[str]:
    """Each robot's corrections (interventions), in all and in its running episode, and the
    figures of the policy that drives it or waits for a correction to end."""
    total: dict[str, float] = {}
    episode: dict[str, float] = {}
    policies: dict[str, dict[str, float]] = {}
    for robot in robots:
        labels = f'robot="{robot.robot_id}"'
        total[labels] = robot.intervention_count
        running = robot.episodes.running_corrections()
        if running is not None:
            episode[labels] = running
        snapshot = robot.snapshot()
        for master in (snapshot.master, snapshot.paused_master):
            if master is not None and master.figures is not None and master.kind == "policy":
                policies[labels] = master.figures
    lines = [
        *_family(
            "arena_interventions_total",
            "counter",
            "Interventions (a human's corrections of a running master), by robot.",
            total,
        ),
        *_family(
            "arena_episode_corrections",
            "gauge",
            "Corrections in the robot's running episode.",
            episode,
        ),
    ]
    for name, kind, key, text in POLICY_FIGURES:
        values = {labels: figures.get(key, 0) for labels, figures in policies.items()}
        lines += _family(name, kind, text, values)
    return lines


def _robot_families(
    robots: list[Robot], servos: Callable[[Robot], list[tuple[str, float, float]]] | None
) -> list[str]:
    """Each robot's lasting faults by severity, and its servos' temperature and load."""
    faults: dict[str, float] = {}
    temperatures: dict[str, float] = {}
    loads: dict[str, float] = {}
    for robot in robots:
        snapshot = robot.snapshot()
        peers = [*snapshot.slaves, *([snapshot.master] if snapshot.master else [])]
        counts = collections.Counter(f.severity for peer in peers for f in peer.faults)
        for severity, n in sorted(counts.items()):
            faults[f'robot="{robot.robot_id}",severity="{severity}"'] = n
        for joint, temperature, load in servos(robot) if servos else []:
            labels = f'robot="{robot.robot_id}",joint="{_label(joint)}"'
            temperatures[labels], loads[labels] = temperature, load
    return [
        *_family(
            "arena_faults_active",
            "gauge",
            "Faults that last (a peer's, until it is over or a reset), by robot and severity.",
            faults,
        ),
        *_family(
            "arena_servo_temperature_celsius",
            "gauge",
            "Each hardware servo's temperature, by robot and joint.",
            temperatures,
        ),
        *_family(
            "arena_servo_load_percent",
            "gauge",
            "Each hardware servo's load in percent of its full torque, by robot and joint.",
            {labels: round(load, 1) for labels, load in loads.items()},
        ),
    ]


class Metrics:
    """Counters the server keeps at its edges; robot counters are read from the actors."""

    def __init__(self) -> None:
        self.connections: collections.Counter[str] = collections.Counter()  # open, by role
        #: Open connections by role and the robots each is a peer of.
        self._open_on: collections.Counter[tuple[str, tuple[str, ...]]] = collections.Counter()
        self.requests: collections.Counter[str] = collections.Counter()  # by status class
        self.messages: collections.Counter[str] = collections.Counter()  # in, by role
        self.message_errors: collections.Counter[str] = collections.Counter()  # by code
        #: Callers refused by `auth`, by reason (missing, invalid, expired, role, scope).
        self.auth_refused: collections.Counter[str] = collections.Counter()
        #: Messages a peer that stopped reading did not get, by kind (ack, joint_states...).
        self.dropped: collections.Counter[str] = collections.Counter()
        #: Masters' commands dropped for arriving too late, by robot.
        self.stale_commands: collections.Counter[str] = collections.Counter()
        self._latency_counts = [0] * (len(LATENCY_BUCKETS) + 1)
        self._latency_sum = 0.0
        self._retired: collections.Counter[str] = collections.Counter()  # deleted robots
        self._retired_estops = 0
        self._retired_superseded = 0

    def connection_opened(self, role: str, robots: tuple[str, ...]) -> None:
        """A WebSocket peer of `robots` is open."""
        self.connections[role] += 1
        self._open_on[role, robots] += 1

    def connection_closed(self, role: str, robots: tuple[str, ...]) -> None:
        """...and closed."""
        self.connections[role] -= 1
        self._open_on[role, robots] -= 1
        if not self._open_on[role, robots]:
            del self._open_on[role, robots]

    def connections_seen(self, sees: Callable[[str], bool]) -> dict[str, int]:
        """Open connections by role, of those whose every robot `sees` says a caller sees."""
        counts = dict.fromkeys(ROLES, 0)
        for (role, robots), n in self._open_on.items():
            if robots and all(sees(robot_id) for robot_id in robots):
                counts[role] = counts.get(role, 0) + n
        return counts

    def _server_families(self) -> list[str]:
        """Figures of the whole server, of no one robot."""
        return [
            *_family(
                "arena_messages_total",
                "counter",
                "WebSocket messages received, by role.",
                {f'role="{role}"': n for role, n in sorted(self.messages.items())},
            ),
            *_family(
                "arena_ws_dropped_total",
                "counter",
                "Messages not sent to a peer that stopped reading"
                " (superseded states, dropped acks), by kind.",
                {f'kind="{kind}"': n for kind, n in sorted(self.dropped.items())},
            ),
            *_family(
                "arena_message_errors_total",
                "counter",
                "Messages and requests refused at the edge.",
                {f'code="{code}"': n for code, n in sorted(self.message_errors.items())},
            ),
            *_family(
                "arena_auth_refused_total",
                "counter",
                "Callers refused: no credential, an invalid or expired one, a role too low, "
                "a robot out of scope or of another tenant.",
                {f'reason="{reason}"': n for reason, n in sorted(self.auth_refused.items())},
            ),
            *_family(
                "arena_http_requests_total",
                "counter",
                "HTTP requests by status class.",
                {f'status="{status}"': n for status, n in sorted(self.requests.items())},
            ),
        ]

    def observe_latency(self, seconds: float, count: int = 1) -> None:
        """Time from a message's arrival to its answer (`count` messages answered together)."""
        self._latency_counts[bisect.bisect_left(LATENCY_BUCKETS, seconds)] += count
        self._latency_sum += seconds * count

    def retire(self, robot: Robot) -> None:
        """Keep a deleted robot's counts in the totals."""
        self._retired.update(robot.command_counts)
        self._retired_estops += robot.estop_count
        self._retired_superseded += robot.targets_superseded
        self.stale_commands.pop(robot.robot_id, None)  # (a per-robot series ends with it)

    def render(
        self,
        robots: Iterable[Robot],
        queued_bytes: int = 0,
        recording: dict[str, Any] | None = None,
        connections: dict[str, int] | None = None,
        whole_server: bool = True,
        links: Mapping[str, Mapping[str, LinkQuality]] | None = None,
        servos: Callable[[Robot], list[tuple[str, float, float]]] | None = None,
    ) -> str:
        """The Prometheus exposition text of what a caller sees: `robots` (theirs),
        `connections` (open on those robots, by role; None: every one), `queued_bytes` (what
        those connections hold for their peers), `recording` (the recorder's status as the
        caller is told it). The server's own figures (deleted robots' counts, messages,
        requests, refusals, latency) only with `whole_server`. `links`: the robots' WebSocket
        masters' links, by robot (those of `robots` are shown); `servos`: a robot's servos'
        (joint, temperature C, load in percent of full torque)."""
        robots = list(robots)
        commands: collections.Counter[str] = collections.Counter()
        estops = superseded = 0
        if whole_server:
            commands.update(self._retired)
            estops, superseded = self._retired_estops, self._retired_superseded
        for robot in robots:
            commands.update(robot.command_counts)
            estops += robot.estop_count
            superseded += robot.targets_superseded
        if connections is None:
            connections = {role: self.connections[role] for role in ROLES}
        lines = [
            *_family("arena_robots", "gauge", "Robots that exist now.", len(robots)),
            *_family(
                "arena_connections",
                "gauge",
                "Open WebSocket connections by role.",
                {f'role="{r}"': connections.get(r, 0) for r in ROLES},
            ),
            *_family(
                "arena_commands_total",
                "counter",
                "Commands answered, by result (accepted or refusal code).",
                {f'result="{result}"': n for result, n in sorted(commands.items())},
            ),
            *_family(
                "arena_targets_superseded_total",
                "counter",
                "Targets replaced by a newer one before a slave took it"
                " (a slave slower than its master gets the newest only).",
                superseded,
            ),
            *_family("arena_estops_total", "counter", "Emergency stops.", estops),
            *_family(
                "arena_ws_queued_bytes",
                "gauge",
                "Bytes queued for WebSocket peers, over all connections.",
                queued_bytes,
            ),
        ]
        lines += self._link_families(robots, links or {})
        lines += _robot_families(robots, servos)
        lines += _flywheel_families(robots)
        if whole_server:
            lines += self._server_families()
        if recording is not None:
            active = bool(recording["active"])
            lines += [
                *_family(
                    "arena_recording_active", "gauge", "Recording is switched on.", int(active)
                ),
                *_family(
                    "arena_recording_failing",
                    "gauge",
                    "Recording is on but the disk refuses it.",
                    int(active and recording["error"] is not None),
                ),
                *_family(
                    "arena_recording_messages_total",
                    "counter",
                    "Messages written to recordings.",
                    recording["messages"],
                ),
                *_family(
                    "arena_recording_dropped_total",
                    "counter",
                    "Messages lost (full queues, disk errors).",
                    recording["dropped"],
                ),
                *_family(
                    "arena_recording_errors_total",
                    "counter",
                    "Failed attempts to write to the disk.",
                    recording["errors"],
                ),
            ]
        if whole_server:
            lines += self._latency_family()
        return "\n".join(lines) + "\n"

    def _link_families(
        self, robots: list[Robot], links: Mapping[str, Mapping[str, LinkQuality]]
    ) -> list[str]:
        """Each robot's WebSocket master's link (the one that drives it): round trip, jitter,
        quality, stale commands."""
        shown = []
        for robot in robots:
            master = robot.snapshot().master
            link = links.get(robot.robot_id, {}).get(master.peer_id) if master else None
            if link is not None:
                shown.append((robot.robot_id, link))
        timed = [(rid, link) for rid, link in shown if link.rtt is not None]
        return [
            *_family(
                "arena_master_rtt_seconds",
                "gauge",
                "Round trip of the server's last ping to the robot's WebSocket master.",
                {f'robot="{rid}"': link.rtt or 0.0 for rid, link in timed},
            ),
            *_family(
                "arena_master_jitter_seconds",
                "gauge",
                "Jitter of the master's link (RFC 3550's estimate, one way).",
                {f'robot="{rid}"': link.jitter for rid, link in shown},
            ),
            *_family(
                "arena_master_link_quality",
                "gauge",
                "The master's link: 0 unknown, 1 good, 2 fair, 3 poor (the dashboard's colours).",
                {f'robot="{rid}"': QUALITY_LEVELS[link.quality()] for rid, link in shown},
            ),
            *_family(
                "arena_stale_commands_total",
                "counter",
                "Masters' commands dropped for arriving older than command_max_age, by robot.",
                {f'robot="{r.robot_id}"': self.stale_commands[r.robot_id] for r in robots},
            ),
        ]

    def _latency_family(self) -> list[str]:
        lines = [
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
        return lines
