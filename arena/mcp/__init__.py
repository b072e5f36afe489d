"""`arena mcp`: an Arena server's robots as tools of the Model Context Protocol, so that an LLM
agent drives them as a master like any other, under every rule (specs/scripts.md)."""
