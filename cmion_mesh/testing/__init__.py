"""Harness for the tests and benchmarks: nothing a daemon or a client needs imports it.

* ``wait``: ``wait_for`` (``procs.wait_for``), a bounded wait on a condition that cannot be waited on directly
  (another process's state), and ``migrate_once_seen`` (a migration started once the companion's
  host sees the target).
* ``netns``: throw-away multi-host networks of Linux network namespaces, for tests that need
  real LANs (root only).
* ``simulation``: the migration handshake's real decisions through random schedules of faults,
  replays, crashes and a hostile former host (``python -m bench sim``).
"""
