"""The per-robot daemon and the CLI: the only package that touches Zenoh, files and time."""
