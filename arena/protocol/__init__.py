"""Wire-level vocabulary shared by every layer: error codes now, message types later. No I/O."""

from arena.protocol.errors import ArenaError, ErrorCode, Severity

__all__ = ["ArenaError", "ErrorCode", "Severity"]
