"""Small derivations from bench results, each a script that prints its numbers."""
