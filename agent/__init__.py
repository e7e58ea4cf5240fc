"""The per-robot daemon and the CLI: the only package that touches Zenoh, files and time.

Modules, by what they hold:

- :mod:`agent.node` -- one robot's agent as a state machine with no I/O (the fleet core):
  admission, fetching, own-map publication, links, status; it returns :mod:`agent.actions`;
- :mod:`agent.daemon` -- the core's Zenoh host: session, declarations, threads, state files
  (``pgvd agent``, :mod:`agent.cli.agent`);
- :mod:`agent.worker` -- pairwise registration and global-map rebuilds off the Zenoh threads;
- :mod:`agent.globalmap` -- the global maps as a pure function of local maps and links;
- :mod:`agent.links` -- link cache, pairs still to register, whose turn it is;
- :mod:`agent.book` -- the latest map of each robot and the links, shared between threads;
- :mod:`agent.wire` -- the thin adapter over :mod:`protocol`;
- :mod:`agent.sources` -- ``carmen:`` log replay and ``map:`` file following;
- :mod:`agent.state` -- atomic persistence in ``--state-dir``; :mod:`agent.persister` -- the
  thread that writes it, own versions first and durably, peers' maps newest only;
- :mod:`agent.fetching`, :mod:`agent.status` -- the core's fetch timers and status pieces;
- :mod:`agent.keys`, :mod:`agent.zenoh_config`, :mod:`agent.counters`, :mod:`agent.inbox`;
- :mod:`agent.launcher`, :mod:`agent.evaluate`, :mod:`agent.scenario` -- local fleets, their
  ground truth and the log they replay, for ``pgvd demo``, the fleet tests and the benches;
- :mod:`agent.cli` -- the ``pgvd`` command line, one module per sub-command.
"""
