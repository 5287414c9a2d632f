"""What the campaign workers' fork server imports before it forks anything (:data:`bench.campaign.workers.WORKER_PRELOAD`).

Ports:
    in: nothing (imported once, by the fork server, before its first fork);
    out: every module a case needs loaded, and the objects they made moved out of the garbage
    collector's generations (``gc.freeze``).
    Rate: once per fork server.

A fork inherits the server's heap. Frozen, those objects are never walked again by a
collection in any process forked from it (a campaign worker, a run's video or plot process), so
their collections cost only what the process made itself, and the inherited pages are not written
to by the collector (they stay shared with the server). The server's own exit skips them too.
"""

import gc

import bench.sim.run  # noqa: F401 - every module a case needs

gc.collect()  # nothing unreachable is frozen
gc.freeze()
