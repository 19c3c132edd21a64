"""``hmpf-serve``: serve an index over HTTP, and manage API keys.

    hmpf-serve [--index DIR] [--host H] [--port P] [--settings FILE] [--workers N]
               [--keys-file KEYS.yaml]                 (no subcommand: serve)
    hmpf-serve keys add --file KEYS.yaml --name car-17 [--role vehicle|admin]
    hmpf-serve keys list --file KEYS.yaml
    hmpf-serve shards --shards DIR [--replicas N] ...  (a sharded map on Ray Serve)
    hmpf-serve replicas {haproxy,run,reload} ...       (replicas behind HAProxy)
    hmpf-serve --version

Every serving flag can also come from the environment (``HMPF_INDEX``, ``HMPF_PORT``, ...) or
from a settings file; flags win. Exit codes: 0 ok, 2 bad settings, index or keys file, 130
interrupted (Ctrl-C, after a graceful shutdown).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from hmpf.cli.common import add_version, run
from service.replicas import main as replicas_main

# The service (FastAPI, numpy, OpenCV, the index reader) and Ray Serve load inside the commands
# that need them, so that --help, --version and `keys` start fast and need no extra.
if TYPE_CHECKING:
    from fastapi import FastAPI

    from service.settings import Settings

__all__ = ["build_parser", "main"]

PROG = "hmpf-serve"
#: Exit status when the app could not start inside uvicorn (uvicorn's own code for it).
_STARTUP_FAILURE = 3


def build_parser() -> argparse.ArgumentParser:
    """The command line: serving flags at the top level, ``keys`` as a subcommand."""
    ap = argparse.ArgumentParser(
        prog=PROG,
        usage=f"{PROG} [-h] [--version] [--index DIR] [--host H] [--port P] [--settings FILE]\n"
        f"{' ' * 18}[--workers N] [--keys-file FILE]\n"
        f"       {PROG} keys {{add,list}} ...",
        description="Serve an hmpf index over HTTP (the default), or manage API keys.",
        epilog="Serving flags may also come from HMPF_* variables or a settings file.",
    )
    add_version(ap)
    ap.add_argument("--index", type=Path, metavar="DIR", help="index folder (HMPF_INDEX)")
    ap.add_argument("--host", metavar="H", help="bind address (default 127.0.0.1)")
    ap.add_argument("--port", type=int, metavar="P", help="port (default 8000; 0 = any free port)")
    ap.add_argument(
        "--settings", type=Path, metavar="FILE", help="YAML settings file (HMPF_SETTINGS_FILE)"
    )
    ap.add_argument(
        "--workers", type=int, metavar="N", help="queries computed at once (default: cores)"
    )
    ap.add_argument("--keys-file", type=Path, metavar="FILE", help="API keys file (HMPF_KEYS_FILE)")
    commands = ap.add_subparsers(
        dest="command", metavar="COMMAND", title="commands (none: serve the index)"
    )
    keys = commands.add_parser("keys", help="manage API keys", description="Manage API keys.")
    key_commands = keys.add_subparsers(dest="keys_command", required=True)
    add = key_commands.add_parser("add", help="create a key; prints it once, stores only its hash")
    add.add_argument("--file", type=Path, required=True)
    add.add_argument("--name", required=True)
    add.add_argument("--role", default="vehicle", choices=["vehicle", "admin"])
    listing = key_commands.add_parser("list", help="names and roles in a keys file")
    listing.add_argument("--file", type=Path, required=True)
    commands.add_parser(
        "shards",
        add_help=False,
        help="serve a sharded map (hmpf-index shard) on Ray Serve; see hmpf-serve shards --help",
    )
    commands.add_parser(
        "replicas",
        add_help=False,
        help="replicas of one index behind HAProxy: its configuration, a local set, a reload "
        "of every replica; see hmpf-serve replicas --help",
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["shards"]:
        # imported here: Ray Serve is an optional extra, needed by this command only
        from service.ray_shards import main as shards_main

        return shards_main(argv[1:])
    if argv[:1] == ["replicas"]:
        return replicas_main(argv[1:])
    args = build_parser().parse_args(argv)
    if args.command == "keys":
        return run(f"{PROG} keys", lambda: _keys(args))
    return run(PROG, lambda: _serve(args))


def _serve(args: argparse.Namespace) -> int:
    from service.app import create_app
    from service.settings import load_settings

    settings = load_settings(
        args.settings,
        index=args.index,
        host=args.host,
        port=args.port,
        workers=args.workers,
        keys_file=args.keys_file,
    )
    logging.basicConfig(
        level=settings.log_level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # CPU-feature probing
    app = create_app(settings)
    app.state.engine.load()  # fail here, with exit code 2, rather than inside uvicorn
    return _run_server(app, settings)


def _run_server(app: FastAPI, settings: Settings) -> int:
    """Serve until stopped: 0 after SIGTERM, 3 when the app did not start (as uvicorn).

    Raises:
        KeyboardInterrupt: after Ctrl-C and the graceful shutdown it starts (uvicorn itself
            would return as after SIGTERM), so that the command exits 130.
    """
    import uvicorn  # serving only: building the app (tests, --help) needs no server

    from service.server import uvicorn_config

    class Server(uvicorn.Server):
        interrupted = False

        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            self.interrupted = self.interrupted or sig == signal.SIGINT
            super().handle_exit(sig, frame)

    server = Server(uvicorn_config(app, settings))
    server.run()
    if server.interrupted:
        raise KeyboardInterrupt
    return 0 if server.started else _STARTUP_FAILURE


def _keys(args: argparse.Namespace) -> int:
    from service.auth import KeyStore, add_key

    if args.keys_command == "add":
        print(add_key(args.file, args.name, args.role))
    else:
        for k in KeyStore.load(args.file).keys:
            print(f"{k.name}\t{k.role}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
