"""Sensors attached to robots: cameras (capture threads, frames as recorded and streamed)."""
