"""The wire format, sans-I/O: typed messages to bytes and back, strictly validated."""
