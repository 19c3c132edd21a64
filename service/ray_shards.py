"""Region shards on Ray Serve: one deployment per shard, and a router with ``hmpf-serve``'s API.

    hmpf-serve shards --shards maps/city-shards [--replicas 2] [--replicas-of shard-01=3]
                      [--host H] [--port P] [--settings FILE] [--keys-file FILE]
                      [--address ray://...]

* :class:`Shard` (one deployment per shard, ``--replicas`` replicas each): opens the shard's
  index version and answers score requests (:func:`hmpf.sharded.score_request`), local
  features and thumbnails. Its version is its ``user_config`` (``{"version": NAME}``, or
  ``{}``: the folder's ``CURRENT``): redeploying a shard with another one makes Ray Serve
  call :meth:`Shard.reconfigure` on every running replica (no restart), and new replicas
  start on it.
* :class:`Router` (the ingress, ``--router-replicas``): the very app of ``hmpf-serve``
  (:func:`service.app.create_app`: same routes, answers and errors) over a
  :class:`~service.shards.ShardedEngine` whose reader scatters to the shard deployments
  (:class:`RayShards`). A shard call that fails because its replica died is sent again (to
  another replica): scoring is read-only. A shard answering from another version than the
  router loaded is a 503 ``shard_changed`` (the router reloads the map in the background;
  clients retry a 503), so an answer never mixes versions.

Ray is imported only here (the ``ray`` extra: ``pip install hmpf[ray]``).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from hmpf.cli.common import run
from hmpf.errors import HmpfError
from hmpf.index import layout
from hmpf.index.reader import IndexReader
from hmpf.sharded import ShardedReader, describe_shard, score_request
from hmpf.shards import ShardChanged, ShardScores, ShardUnavailable, read_shard_map
from service.app import create_app
from service.errors import ApiError
from service.reloader import reload_index
from service.settings import Settings, load_settings
from service.shards import ShardedEngine

__all__ = ["RayShards", "Router", "Shard", "build_app", "main"]

log = logging.getLogger("hmpf.service")
PROG = "hmpf-serve shards"
#: Tries of a shard call whose replica died (each to whichever replica Ray picks).
SHARD_TRIES = 4

serve: Any
try:  # the ray extra
    from ray import serve
except ImportError:  # pragma: no cover - checked by main()
    serve = None


def _require_ray() -> Any:
    if serve is None:
        raise HmpfError("Ray Serve is not installed: pip install 'hmpf[ray]'")
    return serve


# -- the shard deployment ------------------------------------------------------------------------
class Shard:
    """One shard's replica: its index version, opened read-only (see the module docstring)."""

    def __init__(self, folder: str, name: str) -> None:
        self.root = Path(folder) / name
        self.wanted: str | None = None
        self.reader = IndexReader(self.root, verify="stamp")

    def reconfigure(self, config: Mapping[str, Any]) -> None:
        """Open ``config["version"]`` (absent: the folder's ``CURRENT``) unless loaded."""
        wanted = config.get("version") if config else None
        self.wanted = str(wanted) if wanted else None
        name = self.wanted or layout.current_version(self.root)
        if name == self.reader.version:
            return
        old, self.reader = self.reader, IndexReader(self.root, name, verify="stamp")
        log.info("shard %s: version %s -> %s", self.root.name, old.version, self.reader.version)
        old.close()

    def describe(self) -> dict[str, Any]:
        out = describe_shard(self.reader)
        out["replica"] = _replica_id()
        return out

    def score(
        self, features: Mapping[str, Any], requests: Sequence[tuple[str, np.ndarray | None]]
    ) -> ShardScores:
        return score_request(self.reader, features, requests)

    def local_features(self, mid: str, local: np.ndarray) -> list[Any]:
        return self.reader.local_features(mid, local)

    def thumbnail(self, local: int) -> bytes | None:
        return self.reader.thumbnail(local)


def _replica_id() -> str:
    try:
        return str(serve.get_replica_context().replica_id.unique_id)
    except Exception:  # not in a replica (tests calling the class directly)
        return ""


# -- the router's backend ------------------------------------------------------------------------
def _dead_replica_errors() -> tuple[type[BaseException], ...]:
    import ray.exceptions as rx  # the ray extra, present wherever a router runs

    names = ("ActorDiedError", "ActorUnavailableError", "RayActorError")
    return tuple(getattr(rx, n) for n in names if hasattr(rx, n))


class RayShards:
    """A :class:`~hmpf.sharded.ShardBackend` over the shard deployments' handles (index =
    shard). Called on the router's query threads (blocking calls, never on its event loop)."""

    def __init__(self, handles: Sequence[Any]) -> None:
        self.handles = list(handles)
        self.dead = _dead_replica_errors()
        #: shard calls sent again after a replica died
        self.retried = 0

    def _call(self, s: int, method: str, *args: Any) -> Any:
        for attempt in range(SHARD_TRIES):
            try:
                return getattr(self.handles[s], method).remote(*args).result()
            except self.dead as exc:
                if attempt == SHARD_TRIES - 1:
                    raise ShardUnavailable(f"shard {s}: no replica answered ({exc})") from None
                self.retried += 1
                log.warning("shard %d: a replica died during %s; sent again", s, method)
                time.sleep(0.2 * (attempt + 1))
        raise AssertionError("unreachable")

    def describe(self, s: int) -> dict[str, Any]:
        out: dict[str, Any] = self._call(s, "describe")
        return out

    def scatter(
        self, features: Mapping[str, Any], calls: Sequence[tuple[int, Any]]
    ) -> list[ShardScores]:
        # Sent together, then collected: the shards score at once.
        pending = [self.handles[s].score.remote(features, req) for s, req in calls]
        out = []
        for (s, req), resp in zip(calls, pending, strict=True):
            try:
                out.append(resp.result())
            except self.dead:
                self.retried += 1
                log.warning("shard %d: a replica died during a score request; sent again", s)
                out.append(self._call(s, "score", features, req))
        return out

    def local_features(self, s: int, mid: str, local: np.ndarray) -> list[Any]:
        out: list[Any] = self._call(s, "local_features", mid, local)
        return out

    def thumbnail(self, s: int, local: int) -> bytes | None:
        out: bytes | None = self._call(s, "thumbnail", local)
        return out

    def close(self) -> None:
        """Nothing to close: the deployments outlive a router's map."""


# -- the router ----------------------------------------------------------------------------------
class Router:
    """The ingress: ``hmpf-serve``'s app over the shard deployments."""

    async def __init__(  # type: ignore[misc]  # Ray Serve awaits an async constructor
        self, folder: str, settings: Mapping[str, Any], *handles: Any
    ) -> None:
        self.folder = Path(folder)
        overrides = dict(settings)
        file = overrides.pop("settings_file", None)
        self.settings = load_settings(file, **{**overrides, "index": self.folder})
        self.backend = RayShards(handles)
        shard_map, _ = read_shard_map(self.folder)
        first = shard_map.names[0]

        def open_reader() -> ShardedReader:
            extractor = IndexReader(self.folder / first, verify="stamp")
            try:
                return ShardedReader(self.folder, self.backend, extractor)
            except BaseException:
                extractor.close()
                raise

        s = self.settings
        self.engine = ShardedEngine(
            self.folder,
            open_reader,
            workers=s.worker_count,
            queue=s.queue,
            threads_per_worker=s.thread_count,
            accept_threshold=s.accept_threshold,
        )
        # Loaded here, off the event loop (it waits for the shards' answers), so that the
        # app's lifespan finds it ready.
        await asyncio.get_running_loop().run_in_executor(None, self.engine.load)

    def __serve_build_asgi_app__(self) -> Any:
        return build_app(self.settings, self.engine)


def build_app(settings: Settings, engine: ShardedEngine) -> FastAPI:
    """``hmpf-serve``'s app over a sharded engine, with the answer to a shard that changed
    version under a query (503 ``shard_changed``, and a reload of the map)."""
    app = create_app(settings, engine=engine)
    reloading: list[asyncio.Task[Any]] = []

    async def shard_unavailable(request: Request, exc: Exception) -> JSONResponse:
        if isinstance(exc, ShardChanged) and (not reloading or reloading[-1].done()):
            reloading.append(asyncio.create_task(reload_index(engine, app.state.metrics, "watch")))
        code = getattr(exc, "code", ShardUnavailable.code)
        after = {"Retry-After": str(max(1, int(settings.retry_after_s)))}
        return ApiError(503, code, str(exc), after).response()

    app.add_exception_handler(ShardUnavailable, shard_unavailable)
    return app


def deployment_app(
    folder: str | Path,
    *,
    replicas: int = 1,
    replicas_of: Mapping[str, int] | None = None,
    router_replicas: int = 1,
    versions: Mapping[str, str] | None = None,
    settings: Mapping[str, Any] | None = None,
) -> Any:
    """The Ray Serve application: one :class:`Shard` deployment per shard of ``folder``
    (``replicas`` each, ``replicas_of[name]`` for some; ``versions[name]``: a version other
    than ``CURRENT``), the :class:`Router` ingress over them."""
    rs = _require_ray()
    folder = Path(folder).resolve()
    shard_map, _ = read_shard_map(folder)
    replicas_of = dict(replicas_of or {})
    unknown = sorted(set(replicas_of) - set(shard_map.names))
    if unknown:
        raise HmpfError(f"no shard {unknown[0]!r} in {folder} (have {', '.join(shard_map.names)})")
    shard_cls = rs.deployment(Shard, max_ongoing_requests=16)
    handles = []
    for name in shard_map.names:
        config = {"version": (versions or {}).get(name)} if versions and name in versions else {}
        handles.append(
            shard_cls.options(
                name=name,
                num_replicas=int(replicas_of.get(name, replicas)),
                user_config=config,
                ray_actor_options={"num_cpus": 0},
            ).bind(str(folder), name)
        )
    router = rs.deployment(rs.ingress()(Router), name="router", max_ongoing_requests=64)
    return router.options(num_replicas=router_replicas, ray_actor_options={"num_cpus": 0}).bind(
        str(folder), dict(settings or {}), *handles
    )


# -- the command ----------------------------------------------------------------------------------
def _pairs(values: Sequence[str] | None) -> dict[str, int]:
    out = {}
    for v in values or []:
        name, _, n = v.partition("=")
        if not name or not n.isdigit() or int(n) < 1:
            raise HmpfError(f"--replicas-of {v!r}: give NAME=N with N >= 1")
        out[name] = int(n)
    return out


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Serve a sharded map (hmpf-index shard) on Ray Serve: one deployment per "
        "shard and a router with hmpf-serve's HTTP API.",
    )
    ap.add_argument("--shards", type=Path, required=True, metavar="DIR", help="shard folder")
    ap.add_argument("--replicas", type=int, default=1, metavar="N", help="replicas per shard")
    ap.add_argument(
        "--replicas-of",
        action="append",
        metavar="NAME=N",
        help="replicas of one shard, e.g. shard-01=3 (repeatable)",
    )
    ap.add_argument("--router-replicas", type=int, default=1, metavar="N")
    ap.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    ap.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    ap.add_argument("--settings", type=Path, metavar="FILE", help="hmpf-serve settings file")
    ap.add_argument("--keys-file", type=Path, metavar="FILE", help="API keys file")
    ap.add_argument("--workers", type=int, metavar="N", help="router queries at once")
    ap.add_argument(
        "--address", help="Ray cluster to join (default: start a local one on this machine)"
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run(PROG, lambda: _serve(args))


def _serve(args: argparse.Namespace) -> int:
    rs = _require_ray()
    import ray  # the ray extra (checked by _require_ray)

    if args.replicas < 1 or args.router_replicas < 1:
        raise HmpfError("--replicas and --router-replicas must be at least 1")
    settings: dict[str, Any] = {
        "settings_file": str(args.settings) if args.settings else None,
        "keys_file": args.keys_file,
        "workers": args.workers,
    }
    app = deployment_app(
        args.shards,
        replicas=args.replicas,
        replicas_of=_pairs(args.replicas_of),
        router_replicas=args.router_replicas,
        settings={k: v for k, v in settings.items() if v is not None},
    )
    ray.init(address=args.address, include_dashboard=False)
    rs.start(http_options={"host": args.host, "port": args.port})
    rs.run(app, name="hmpf", route_prefix="/", blocking=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
