"""Sensors attached to robots: cameras (capture processes, frames as recorded and streamed)."""
