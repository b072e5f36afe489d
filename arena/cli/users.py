"""`arena token`: mint a token from the server's own secret, for setups without an identity
provider."""

from __future__ import annotations

import argparse

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `token`."""
    token = commands.add_parser(
        "token", help="mint a JSON Web Token from the server's --jwt-secret-file"
    )
    token.add_argument("--sub", required=True, help="who the token is for (recorded on actions)")
    token.add_argument(
        "--role", choices=("viewer", "operator", "admin"), default="viewer", help="(default viewer)"
    )
    token.add_argument(
        "--robots",
        action="append",
        metavar="GLOB",
        help="robot ids it covers, e.g. 'lab-*' (repeatable or comma-separated; default all)",
    )
    token.add_argument(
        "--groups", action="append", metavar="GLOB", help="group ids it covers (as --robots)"
    )
    token.add_argument("--tenant", help="the tenant whose robots it reaches (default: default)")
    token.add_argument("--ttl", default="8h", help="how long it is valid: 90s, 15m, 8h, 7d")
    token.add_argument("--config", help="the server's TOML settings (for its secret file)")
    token.add_argument("--jwt-secret-file", metavar="FILE", help="the secret (as `serve`'s)")
    token.set_defaults(handler=token_command)


def _globs(values: list[str] | None) -> tuple[str, ...] | None:
    if values is None:
        return None
    return tuple(p.strip() for value in values for p in value.split(",") if p.strip())


def token_command(args: argparse.Namespace) -> int:
    """`arena token`: print a token signed with the server's secret (the flag, else
    `ARENA_JWT_SECRET_FILE`, else the config file's `jwt_secret_file`), with the server's
    issuer and audience if it checks them."""
    from arena.protocol.errors import ArenaError, ErrorCode
    from arena.server.config import load_config
    from arena.server.identity import Role, mint, parse_duration, read_secret

    config = load_config(args.config, jwt_secret_file=args.jwt_secret_file)
    if config.jwt_secret_file is None:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            "No secret to sign with: give --jwt-secret-file FILE (as the server has it).",
        )
    try:
        ttl = parse_duration(args.ttl)
        token = mint(
            read_secret(config.jwt_secret_file),
            args.sub,
            Role.named(args.role),
            ttl,
            robots=_globs(args.robots),
            groups=_globs(args.groups),
            tenant=args.tenant,
            issuer=config.jwt_issuer,
            audience=config.jwt_audience,
        )
    except ValueError as exc:
        raise ArenaError(ErrorCode.INVALID_VALUE, f"{exc}.") from None
    print(token)
    return 0
