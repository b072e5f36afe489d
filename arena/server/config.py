"""Server settings: command-line flags, an optional TOML file and the environment
(`settings_env`), the flags winning over the environment, which wins over the file."""

from __future__ import annotations

import ipaddress
import os
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from arena.protocol.errors import ArenaError, ErrorCode
from arena.server.settings_env import (
    API_KEY_FILE_ENV,
    CONFIG_ENV,
    read_key_file,
    settings_from_env,
)

if TYPE_CHECKING:
    from arena.fleet.node import FleetSettings
    from arena.ros2.bridge import Ros2Settings


@dataclass(frozen=True)
class ServerConfig:
    """Everything the server needs to start."""

    host: str = "127.0.0.1"
    port: int = 8080
    demo: bool = False
    #: A simulated leader arm of this robot type (on a pty the server owns), to attach as a
    #: usb-master and move from the dashboard or `PUT .../leader/joints` (None: none).
    sim_leader: str | None = None
    api_keys: tuple[str, ...] = ()
    viewer_keys: tuple[str, ...] = ()  # read-only keys (need api_keys to mean anything)
    open_reads: bool = False  # with keys configured, let GET requests through without one
    #: JSON Web Tokens (arena/server/identity.py): a shared secret's file (HS256) and/or a
    #: JWKS file of an identity provider's public keys (RS256, ES256).
    jwt_secret_file: str | None = None
    jwt_jwks: str | None = None
    jwt_issuer: str | None = None  # tokens must carry this `iss` when set
    jwt_audience: str | None = None  # ...and this `aud`
    jwt_leeway: float = 30.0  # seconds of clock skew allowed on `exp`
    insecure: bool = False  # allow binding beyond loopback without keys
    certfile: str | None = None
    keyfile: str | None = None
    heartbeat_interval: float = 30.0  # seconds between our heartbeats to each peer
    heartbeat_timeout: float = 90.0  # a peer silent this long is dropped
    #: A master's stamped command older than this (seconds) on arrival is dropped, never run
    #: late (0: none is). 0.4 s: ITU-T G.114's bound for interactive use, above a long link's
    #: delay and jitter (specs/remote-link.md).
    command_max_age: float = 0.4
    #: Seconds between the server's pings to each master (its round trip, for the link's
    #: quality and the commands' age; specs/remote-link.md says why not more often).
    link_ping_interval: float = 2.0
    joint_states_interval: float = 0.02  # at most 50 joint_states a second to each client
    shutdown_grace: float = 1.0
    record: bool = True  # record every robot to MCAP from the start
    recordings_dir: str = "recordings"
    calibration_dir: str = "calibration"  # one calibration file per robot (or per name)
    policy_dir: str = "policies"  # one folder per policy (each tenant's: policies/<tenant>/)
    script_dir: str = "scripts"  # the scripts a master may run (each tenant's: scripts/<tenant>/)
    #: The Python policy workers run in: one with LeRobot, torch and msgspec (a LeRobot newer
    #: than Arena's, say); None: Arena's own (specs/policy.md).
    policy_python: str | None = None
    recording_max_bytes: int = 256 << 20
    recording_max_seconds: float = 3600.0
    recording_retry_max: float = 30.0  # a failing disk is retried after 1 s, doubling to this
    #: Record Foxglove's view too: each robot's transforms, 3D model and log.
    record_foxglove: bool = True
    #: ...at most this many transforms a second per robot and tree (0: one per record).
    record_foxglove_rate: float = 30.0
    #: Serve the robots live over Foxglove's WebSocket protocol on this port (0: any).
    foxglove_port: int | None = None
    #: Bytes queued for one WebSocket peer before states keep only the newest and acks are
    #: counted as missed (a peer that stopped reading costs at most about this much).
    ws_queue_bytes: int = 16 * 1024
    #: An HTTP connection with no request under way is closed after this many seconds (one
    #: that sends nothing at all too); `Connection: close` closes it after its response.
    keep_alive_timeout: float = 5.0
    #: The most connections open at once (HTTP and WebSocket): in all, and from one client
    #: address. One more is answered 503 OVERLOADED and closed.
    max_connections: int = 1024
    max_connections_per_client: int = 256
    #: What one tenant may create, and the WebSockets one caller may hold open at once (on
    #: a server without keys every caller is the same anonymous one). More: LIMIT_REACHED.
    max_robots: int = 256
    max_groups: int = 256
    max_websockets_per_caller: int = 512
    #: Web pages (scheme://host:port) besides the server's own that may change anything.
    allowed_origins: tuple[str, ...] = field(default=())
    #: Names besides localhost and loopback addresses that a loopback server answers to.
    allowed_hosts: tuple[str, ...] = field(default=())
    #: This server's name in a fleet (specs/fleet.md); None: a server on its own.
    node: str | None = None
    fleet: str = "default"
    #: Zenoh endpoints to listen on and to connect to (a router is one more endpoint).
    fleet_listen: tuple[str, ...] = field(default=())
    fleet_connect: tuple[str, ...] = field(default=())
    fleet_scout: bool = False  # multicast scouting; off: explicit endpoints only
    fleet_lease_ms: int = 1000  # a node silent this long is gone
    #: A Zenoh configuration file to start from (TLS, access control); ours goes on top.
    fleet_zenoh_config: str | None = None
    #: Every robot a ROS 2 node over Zenoh (specs/ros2.md); the domain None: ROS_DOMAIN_ID.
    ros2: bool = False
    ros_domain: int | None = None
    ros2_listen: tuple[str, ...] = field(default=())
    ros2_connect: tuple[str, ...] = field(default=())
    #: The TOML file these settings came from: it may declare robots, their parts and groups
    #: too (`arena.server.declared`), brought up at start and again on SIGHUP.
    config_file: str | None = None

    @property
    def jwt_enabled(self) -> bool:
        """True when tokens can be verified."""
        return self.jwt_secret_file is not None or self.jwt_jwks is not None

    @property
    def auth_enabled(self) -> bool:
        """True when API keys or tokens are configured (every caller must then show one)."""
        return bool(self.api_keys) or self.jwt_enabled

    def check(self) -> None:
        """Refuse unsafe or inconsistent settings with a clear sentence."""
        if not self.auth_enabled and not self.insecure and not _is_loopback(self.host):
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Refusing to listen on {self.host} without API keys: anyone on the network "
                "could move the robot. Give --api-key KEY (or --jwt-secret-file FILE), or "
                "--insecure if you mean it.",
            )
        if not 0 <= self.jwt_leeway <= 600:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "jwt_leeway must be from 0 to 600 s.")
        if bool(self.certfile) != bool(self.keyfile):
            raise ArenaError(ErrorCode.INVALID_CONFIG, "TLS needs both --certfile and --keyfile.")
        if self.heartbeat_interval <= 0 or self.heartbeat_timeout <= 0:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "Heartbeat settings must be positive.")
        if not 0 <= self.command_max_age <= 60:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, "command_max_age must be from 0 (off) to 60 s."
            )
        if not 0.05 <= self.link_ping_interval <= 3600:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, "link_ping_interval must be from 0.05 to 3600 s."
            )
        if not 1024 <= self.ws_queue_bytes <= 64 << 20:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, "ws_queue_bytes must be from 1 KiB to 64 MiB."
            )
        if not 0 < self.keep_alive_timeout <= 3600:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, "keep_alive_timeout must be more than 0 s, at most 3600."
            )
        if not 1 <= self.max_connections_per_client <= self.max_connections:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                "max_connections_per_client must be from 1 to max_connections "
                f"({self.max_connections}).",
            )
        for name in ("max_robots", "max_groups", "max_websockets_per_caller"):
            if getattr(self, name) < 1:
                raise ArenaError(ErrorCode.INVALID_CONFIG, f"{name} must be 1 or more.")
        if self.foxglove_port is not None and not (
            _is_loopback(self.host) or (self.insecure and not self.auth_enabled)
        ):
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                "Foxglove's protocol has no API keys: --foxglove-port serves only on a loopback "
                "host (or with --insecure and no keys).",
            )
        if not 0 <= self.record_foxglove_rate <= 10_000:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG, "record_foxglove_rate must be from 0 to 10000."
            )
        if self.node is not None:
            self.fleet_settings().check()
        if self.ros2:
            settings = self.ros2_settings()
            exposed = [e for e in settings.endpoints() if not _is_loopback(_endpoint_host(e))]
            if exposed and not self.insecure:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG,
                    f"ROS 2 has no API keys: anyone who reaches {exposed[0]} could command the "
                    "robots. --ros2 uses loopback endpoints only, unless --insecure.",
                )
        if self.policy_python is not None and not (
            os.path.isfile(self.policy_python) and os.access(self.policy_python, os.X_OK)
        ):
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"policy_python {self.policy_python!r} is not a program: give the path of a "
                "Python with LeRobot, torch and msgspec (its virtualenv's bin/python).",
            )
        if self.recording_retry_max < 1.0:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "recording_retry_max must be 1 s or more.")

    def ros2_settings(self) -> Ros2Settings:
        """How the robots join the ROS graph (checked; only with `ros2`)."""
        from arena.ros2.bridge import Ros2Settings

        return Ros2Settings.from_options(self.ros_domain, self.ros2_listen, self.ros2_connect)

    def fleet_settings(self) -> FleetSettings:
        """How this node joins its fleet (only with `node`)."""
        from arena.fleet.node import FleetSettings

        assert self.node is not None
        return FleetSettings(
            self.node,
            self.fleet,
            self.fleet_listen,
            self.fleet_connect,
            self.fleet_scout,
            self.fleet_lease_ms,
            self.fleet_zenoh_config,
        )


def _endpoint_host(endpoint: str) -> str:
    """The host of a Zenoh endpoint (`tcp/127.0.0.1:7447` -> `127.0.0.1`)."""
    address = endpoint.partition("/")[2].partition("#")[0]
    return address.rpartition(":")[0] or address


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def load_config(
    path: str | None,
    environ: Mapping[str, str] | None = None,
    api_key_file: str | None = None,
    **overrides: Any,
) -> ServerConfig:
    """Defaults, then the TOML file at `path` (or `$ARENA_CONFIG`), then the environment
    (`ARENA_` and a setting's name in capitals; `environ`, default `os.environ`), then
    `overrides` (the flags; None: not given). API keys add up from every source, the key file
    (`api_key_file` or `$ARENA_API_KEY_FILE`) included."""
    environ = os.environ if environ is None else environ
    path = path or environ.get(CONFIG_ENV) or None
    config = ServerConfig()
    if path:
        config = replace(config, **_read_file(path), config_file=path)
    fields = typing.get_type_hints(ServerConfig)
    del fields["config_file"]  # (ARENA_CONFIG names the file)
    from_env = settings_from_env(fields, environ)
    env_keys = from_env.pop("api_keys", ())
    config = replace(config, **from_env, api_keys=config.api_keys + env_keys)
    key_file = api_key_file or environ.get(API_KEY_FILE_ENV)
    if key_file:
        config = replace(config, api_keys=config.api_keys + read_key_file(key_file))
    for key in ("allowed_origins", "allowed_hosts"):  # flags add to the file's list
        extra = overrides.pop(key, None) or ()
        config = replace(config, **{key: getattr(config, key) + tuple(extra)})
    extra_keys = overrides.pop("api_keys", ())
    config = replace(config, **{k: v for k, v in overrides.items() if v is not None})
    if extra_keys:
        config = replace(config, api_keys=config.api_keys + tuple(extra_keys))
    return config


def _read_file(path: str) -> dict[str, Any]:
    """The settings of a TOML file; unknown names and unreadable files are refused."""
    from arena.server.setup_file import parse_setup, read_toml

    text, data = read_toml(path)
    known = set(ServerConfig.__dataclass_fields__) - {"config_file"}
    setup = parse_setup(path, text, data, known)  # the robots it declares too, whole
    data = dict(setup.settings)
    for key in (
        "api_keys",
        "viewer_keys",
        "allowed_origins",
        "allowed_hosts",
        "fleet_listen",
        "fleet_connect",
        "ros2_listen",
        "ros2_connect",
    ):
        if key in data:
            data[key] = tuple(data[key])
    return data
