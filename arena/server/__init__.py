"""The HTTP and WebSocket server: quart-trio on hypercorn."""
