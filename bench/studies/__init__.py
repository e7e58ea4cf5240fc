"""The analyses behind the merge's design, most of them read from a merge bench run's records."""
