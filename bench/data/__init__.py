"""The pairs the benches merge: real logs and simulated runs cut into two robots' maps."""
