"""`arena serve`: the HTTP and WebSocket server."""

from __future__ import annotations

import argparse
import gc
from functools import partial

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `serve` and its options (server, security, recording, fleet)."""
    serve = commands.add_parser("serve", help="run the HTTP and WebSocket server")
    serve.add_argument("--host", default=None, help="address to bind (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="port (default 8080; 0: any)")
    serve.add_argument(
        "--demo",
        action="store_true",
        default=None,
        help="create robot demo-arm (so-arm100) with a mock slave",
    )
    serve.add_argument(
        "--sim-leader",
        nargs="?",
        const="so-arm100",
        default=None,
        metavar="TYPE",
        help="a simulated leader arm (default so-arm100), moved from the dashboard",
    )
    serve.add_argument("--config", help="a TOML file of server settings")
    serve.add_argument(
        "--api-key",
        action="append",
        default=[],
        dest="api_keys",
        help="an API key clients must present (repeatable)",
    )
    serve.add_argument("--api-key-file", help="API keys, one a line (kept out of `ps`)")
    serve.add_argument(
        "--viewer-key",
        action="append",
        default=[],
        dest="viewer_keys",
        help="a read-only key: GET requests and the state WebSocket only (repeatable)",
    )
    users = serve.add_argument_group("users: JSON Web Tokens (README, Operations)")
    users.add_argument(
        "--jwt-secret-file", metavar="FILE", help="a shared secret (HS256), first line of FILE"
    )
    users.add_argument(
        "--jwt-jwks", metavar="FILE", help="an identity provider's public keys (JWKS, RS256/ES256)"
    )
    users.add_argument("--jwt-issuer", help="tokens must carry this 'iss'")
    users.add_argument("--jwt-audience", help="tokens must carry this 'aud'")
    users.add_argument(
        "--jwt-leeway", type=float, metavar="SECONDS", help="clock skew allowed (default 30)"
    )
    serve.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="allow binding beyond loopback without API keys",
    )
    serve.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        dest="allowed_origins",
        metavar="ORIGIN",
        help="a web page origin (scheme://host:port) that may change things (repeatable)",
    )
    serve.add_argument(
        "--allow-host",
        action="append",
        default=[],
        dest="allowed_hosts",
        metavar="NAME",
        help="a host name a loopback server answers to besides localhost (repeatable)",
    )
    connections = serve.add_argument_group("connections (specs/api.md, Limits)")
    connections.add_argument(
        "--keep-alive-timeout",
        type=float,
        metavar="SECONDS",
        help="close an idle HTTP connection after this long (default 5)",
    )
    connections.add_argument(
        "--max-connections", type=int, metavar="N", help="connections open at once (default 1024)"
    )
    connections.add_argument(
        "--max-connections-per-client",
        type=int,
        metavar="N",
        help="connections open at once from one address (default 256)",
    )
    serve.add_argument("--certfile", help="TLS certificate (PEM)")
    serve.add_argument("--keyfile", help="TLS private key (PEM)")
    serve.add_argument(
        "--no-record",
        action="store_false",
        dest="record",
        default=None,
        help="do not record to MCAP (recording can be started over REST)",
    )
    serve.add_argument("--recordings-dir", help="where recordings go (default recordings/)")
    serve.add_argument(
        "--policy-dir",
        metavar="DIR",
        help="the policies a master may run, a folder each (default policies/; a tenant's: DIR/T/)",
    )
    serve.add_argument(
        "--script-dir",
        metavar="DIR",
        help="the scripts a master may run (default scripts/; a tenant's: DIR/T/)",
    )
    serve.add_argument(
        "--calibration-dir",
        metavar="DIR",
        help="the arms' calibration files (default calibration/; a tenant's: DIR/T/)",
    )
    serve.add_argument(
        "--policy-python",
        metavar="PATH",
        help="the Python policy workers run in: one with LeRobot, torch and msgspec, such as a "
        "LeRobot 0.6 virtualenv's (default: Arena's own)",
    )
    serve.add_argument(
        "--no-record-foxglove",
        action="store_false",
        dest="record_foxglove",
        default=None,
        help="leave Foxglove's view (transforms, 3D model, log) out of recordings",
    )
    serve.add_argument(
        "--foxglove-port",
        type=int,
        default=None,
        metavar="PORT",
        help="serve every robot live to Foxglove on ws://HOST:PORT (0: any port)",
    )
    fleet = serve.add_argument_group("fleet (specs/fleet.md)")
    fleet.add_argument("--node", help="this server's name in a fleet (joins it over Zenoh)")
    fleet.add_argument("--fleet", help="the fleet's name (default: default)")
    fleet.add_argument(
        "--fleet-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    fleet.add_argument(
        "--fleet-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="a node or router to connect to, e.g. tcp/10.0.0.2:7447 (repeatable)",
    )
    fleet.add_argument(
        "--fleet-scout", action="store_true", default=None, help="find nodes by multicast"
    )
    fleet.add_argument(
        "--fleet-zenoh-config",
        metavar="FILE",
        help="a Zenoh configuration (JSON5) to start from: TLS, access control",
    )
    ros2 = serve.add_argument_group("ROS 2 (specs/ros2.md)")
    ros2.add_argument(
        "--ros2", action="store_true", default=None, help="every robot a ROS 2 node (rmw_zenoh)"
    )
    ros2.add_argument("--ros-domain", type=int, help="ROS domain (default: ROS_DOMAIN_ID, else 0)")
    ros2.add_argument("--ros2-listen", action="append", default=[], metavar="ENDPOINT")
    ros2.add_argument(
        "--ros2-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh router or peer (default, with no endpoint: tcp/localhost:7447)",
    )
    serve.set_defaults(handler=serve_command)


def serve_command(args: argparse.Namespace) -> int:
    """`arena serve`: the options over the `--config` file's settings, checked, then served
    until Ctrl-C or SIGTERM."""
    import trio

    from arena.server.config import load_config
    from arena.server.run import run_server

    config = load_config(
        args.config,
        api_key_file=args.api_key_file,
        record=args.record,
        recordings_dir=args.recordings_dir,
        policy_dir=args.policy_dir,
        script_dir=args.script_dir,
        calibration_dir=args.calibration_dir,
        policy_python=args.policy_python,
        record_foxglove=args.record_foxglove,
        foxglove_port=args.foxglove_port,
        host=args.host,
        port=args.port,
        demo=args.demo,
        sim_leader=args.sim_leader,
        api_keys=tuple(args.api_keys),
        viewer_keys=tuple(args.viewer_keys) or None,
        insecure=args.insecure,
        jwt_secret_file=args.jwt_secret_file,
        jwt_jwks=args.jwt_jwks,
        jwt_issuer=args.jwt_issuer,
        jwt_audience=args.jwt_audience,
        jwt_leeway=args.jwt_leeway,
        certfile=args.certfile,
        keyfile=args.keyfile,
        keep_alive_timeout=args.keep_alive_timeout,
        max_connections=args.max_connections,
        max_connections_per_client=args.max_connections_per_client,
        allowed_origins=tuple(args.allowed_origins),
        allowed_hosts=tuple(args.allowed_hosts),
        node=args.node,
        fleet=args.fleet,
        fleet_listen=tuple(args.fleet_listen) or None,
        fleet_connect=tuple(args.fleet_connect) or None,
        fleet_scout=args.fleet_scout,
        fleet_zenoh_config=args.fleet_zenoh_config,
        ros2=args.ros2,
        ros_domain=args.ros_domain,
        ros2_listen=tuple(args.ros2_listen) or None,
        ros2_connect=tuple(args.ros2_connect) or None,
    )
    config.check()
    trio.run(partial(run_server, config, handle_signals=True, freeze_startup_objects=True))
    # The objects frozen at startup (`gc.freeze`) collected now, not left alive at the
    # interpreter's exit: native ones (Ruckig's, through nanobind) would each be reported as
    # a leak on the way out of every planned stop.
    gc.unfreeze()
    gc.collect()
    return 0
