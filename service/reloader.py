"""Switching index versions: on ``POST /v1/index/reload`` and, with ``watch_current_s``, when
the index's ``CURRENT`` changes (every replica of a balanced service watches the same folder,
so a new version reaches all of them, not only the one a reload request happened to reach).

Both go through :func:`reload_index`: the engine loads the version ``CURRENT`` names (queries
in flight finish on the version they started on); a version that cannot be loaded leaves the
loaded one in service, is logged and counted (``hmpf_index_reload_failures_total``), and
``hmpf_index_behind`` stays 1 until this replica serves what ``CURRENT`` names. The watch
tries a failed version again only when ``CURRENT`` is written again (``hmpf-index use``), or
on ``POST /v1/index/reload``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from typing import Literal

from hmpf.errors import HmpfError
from hmpf.index import layout
from service.engine import Engine
from service.metrics import Metrics

__all__ = ["CurrentWatch", "current_version", "reload_index", "update_behind"]

log = logging.getLogger("hmpf.service")
Trigger = Literal["request", "watch"]


async def reload_index(engine: Engine, metrics: Metrics, trigger: Trigger) -> tuple[str, str]:
    """Load the version ``CURRENT`` names; returns (old version, new version).

    Raises:
        Exception: whatever the load raised (the loaded version stays; counted).
    """
    try:
        old, new = await engine.reload()
    except Exception:
        metrics.reload_failures.labels(trigger).inc()
        update_behind(engine, metrics)
        raise
    metrics.set_index(new)
    if old != new:
        metrics.reloads.labels(trigger).inc()
        log.info("index version %s -> %s (%s)", old, new, trigger)
    update_behind(engine, metrics)
    return old, new


def current_version(engine: Engine) -> str | None:
    """The version the index's ``CURRENT`` names now; None when it cannot be read."""
    try:
        return layout.current_version(engine.root)
    except (OSError, HmpfError):
        return None


def update_behind(engine: Engine, metrics: Metrics) -> bool:
    """Set ``hmpf_index_behind``: whether ``CURRENT`` names another version than the loaded
    one (or cannot be read). Returns it."""
    behind = not engine.ready or current_version(engine) != engine.current.version
    metrics.index_behind.set(int(behind))
    return behind


def _stamp(engine: Engine) -> tuple[str | None, int]:
    """What ``CURRENT`` names and when it was written (a rewrite of the same name counts)."""
    try:
        mtime = os.stat(engine.root / layout.CURRENT).st_mtime_ns
    except OSError:
        mtime = -1
    return current_version(engine), mtime


class CurrentWatch:
    """Polls ``CURRENT`` every ``interval`` seconds and reloads when it names another version
    than the loaded one (an asyncio task of the app, started and stopped by its lifespan)."""

    def __init__(self, engine: Engine, metrics: Metrics, interval: float) -> None:
        self.engine = engine
        self.metrics = metrics
        self.interval = interval
        self._task: asyncio.Task[None] | None = None
        #: CURRENT's (name, mtime) when a reload of it failed: not tried again until it changes.
        self._failed: tuple[str | None, int] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="hmpf-watch")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(self.interval)
            try:
                await self.poll(loop)
            except asyncio.CancelledError:
                raise
            except Exception:  # never let the watch die: the next poll tries again
                log.exception("watching %s/CURRENT failed", self.engine.root)

    async def poll(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """One look at ``CURRENT``: reload when it names a version other than the loaded one
        (and not the same write of it that failed before)."""
        loop = loop or asyncio.get_running_loop()
        stamp = await loop.run_in_executor(None, _stamp, self.engine)
        name = stamp[0]
        behind = name != self.engine.current.version
        self.metrics.index_behind.set(int(behind))
        if name is None or not behind or stamp == self._failed:
            return
        log.info(
            "index %s: CURRENT names %s, %s is loaded: reloading",
            self.engine.root,
            name,
            self.engine.current.version,
        )
        try:
            await reload_index(self.engine, self.metrics, "watch")
        except Exception as exc:
            self._failed = stamp
            log.error(
                "index %s: version %s cannot be loaded, version %s stays in service "
                "(hmpf_index_behind 1; tried again when CURRENT is written again): %s",
                self.engine.root,
                name,
                self.engine.current.version,
                exc,
            )
        else:
            self._failed = None
