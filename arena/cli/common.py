"""What the command modules share: the type of the subcommand table they add to."""

from __future__ import annotations

import argparse
from typing import TypeAlias

#: `parser.add_subparsers(...)`: each command module's `add` declares its subcommands on it.
Commands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"
