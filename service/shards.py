"""The service over a sharded map: the same app, with an engine whose version is every shard.

:class:`ShardedEngine` is an :class:`~service.engine.Engine` whose loaded version
(:func:`open_sharded`) reads the whole map through a :class:`~hmpf.sharded.ShardedReader`:
the routes, their answers and errors are ``hmpf-serve``'s own (:func:`service.app.create_app`
with this engine), and each query's scores are scattered to the shards. How the shards are
reached is the reader factory's business: in this process (:class:`~hmpf.sharded.LocalShards`)
or on Ray Serve (:mod:`service.ray_shards`).

A reload (``POST /v1/index/reload``) opens the map anew: the shards' versions as they are now.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from hmpf.sharded import ShardedReader
from service.engine import Engine, Loaded

__all__ = ["ShardedEngine", "open_sharded"]

log = logging.getLogger("hmpf.service")


def open_sharded(reader: ShardedReader, threshold: float | None) -> Loaded:
    """A :class:`~service.engine.Loaded` over the whole sharded map (``reader``): the same
    acceptance, profile, sequence filter and positions an unsharded version of the same
    places has (its files were verified by the shards themselves)."""
    return Loaded.over(reader, threshold, "full")


class ShardedEngine(Engine):
    """An :class:`~service.engine.Engine` over a shard folder; ``open_reader`` opens the
    whole map (called at start and on each reload)."""

    def __init__(
        self,
        folder: Path,
        open_reader: Callable[[], ShardedReader],
        *,
        workers: int,
        queue: int,
        threads_per_worker: int,
        accept_threshold: float | None = None,
    ) -> None:
        super().__init__(
            folder,
            workers=workers,
            queue=queue,
            threads_per_worker=threads_per_worker,
            accept_threshold=accept_threshold,
        )
        self.open_reader = open_reader

    def _open(self) -> Loaded:
        """The map as every shard is now (a sharded map is verified by its shards: nothing
        runs in the background, no fallback is kept)."""
        return open_sharded(self.open_reader(), self.accept_threshold)

    def _log_loaded(self, loaded: Loaded) -> None:
        log.info(
            "sharded map %s loaded (%d places; %s)", self.root, loaded.reader.n, loaded.version
        )
