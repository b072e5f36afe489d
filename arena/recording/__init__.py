"""Recording to MCAP, reading it back (truncated files too), replay, and offline tools."""
