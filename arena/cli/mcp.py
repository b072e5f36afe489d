"""`arena mcp --url URL [--api-key KEY]`: serve a server's robots to an LLM agent as MCP tools
over stdio (specs/scripts.md)."""

from __future__ import annotations

import argparse
import sys

from arena.cli.common import Commands


def add(commands: Commands) -> None:
    """Declare `mcp`."""
    mcp = commands.add_parser(
        "mcp", help="serve a server's robots as MCP tools over stdio (for LLM agents)"
    )
    mcp.add_argument("--url", required=True, help="the server, e.g. http://robot-pc:8080")
    mcp.add_argument("--api-key", help="an API key (an operator's, to move robots)")
    mcp.add_argument("--id", default="mcp-agent", help="the master id the agent holds robots under")
    mcp.set_defaults(handler=mcp_command)


def mcp_command(args: argparse.Namespace) -> int:
    """Serve until the client closes stdin; 2 without the MCP SDK."""
    from arena.extras import require
    from arena.protocol.errors import ArenaError

    try:
        require("mcp", "arena mcp")
    except ArenaError as error:
        print(f"arena mcp: {error.code}: {error.message}", file=sys.stderr)
        return 2
    from arena.mcp.server import run

    run(args.url, args.api_key, args.id)
    return 0
