"""Arena's WebSocket endpoints over its own transport (`listener`, `ws_transport`).

`router` picks a handler by path (a robot here, or one of another node of the fleet); each
endpoint (`master`, `group_master`, `slave`, `viewer`) serves one kind of peer over a
`connection.Connection`, whose `backpressure` policy keeps a slow peer to the newest states.
"""
