"""The runtime layer (rank 5): what runs and hosts the control loop.

* :mod:`stagectl.runtime.requests` -- typed loop requests (move, stop, reset, retune, shutdown), each
  validated once when it is built; the CLI, the daemon's socket handlers and the loop all use them.
* :mod:`stagectl.runtime.status` -- :class:`LoopState`, the typed :class:`LoopStatus` snapshot,
  :class:`LoopResult` and the timing statistics.
* :mod:`stagectl.runtime.protocols` -- what the loop needs from a controller, a reference and a sink.
* :mod:`stagectl.runtime.host` -- :class:`LoopHost`, the one place that runs a loop in its own thread
  (``stagectl run`` and the daemon).

The scheduler itself stays in :mod:`stagectl.loop`. This package ``__init__`` imports nothing, so that
``stagectl.loop`` may import its modules without a cycle.
"""
