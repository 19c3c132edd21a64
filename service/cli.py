"""``hmpf-serve``: serve an index over HTTP, and manage API keys.

    hmpf-serve --index DIR [--host H] [--port P] [--settings FILE] [--workers N]
    hmpf-serve keys add --file KEYS.yaml --name car-17 [--role vehicle|admin]
    hmpf-serve keys list --file KEYS.yaml

Every flag can also come from the environment (``HMPF_INDEX``, ``HMPF_PORT``, ...) or from a
settings file; flags win. Exit codes: 0 ok, 2 bad settings or index.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from hmpf.errors import HmpfError

__all__ = ["main"]


def _serve(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hmpf-serve", description="Serve an hmpf index over HTTP.")
    ap.add_argument("--index", type=Path, help="index folder (HMPF_INDEX)")
    ap.add_argument("--host", help="bind address (default 127.0.0.1)")
    ap.add_argument("--port", type=int, help="port (default 8000; 0 = any free port)")
    ap.add_argument("--settings", type=Path, help="YAML settings file (HMPF_SETTINGS_FILE)")
    ap.add_argument("--workers", type=int, help="queries computed at once (default: cores)")
    ap.add_argument("--keys-file", type=Path, help="API keys file (HMPF_KEYS_FILE)")
    args = ap.parse_args(argv)

    from service.settings import load_settings

    try:
        settings = load_settings(
            args.settings,
            index=args.index,
            host=args.host,
            port=args.port,
            workers=args.workers,
            keys_file=args.keys_file,
        )
        import uvicorn

        from service.app import create_app

        logging.basicConfig(
            level=settings.log_level.upper(),
            format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        )
        logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # CPU-feature probing
        app = create_app(settings)
        app.state.engine.load()  # fail here, with exit code 2, rather than inside uvicorn
    except HmpfError as exc:
        print(f"hmpf-serve: error: {exc}", file=sys.stderr)
        return 2
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=10,
    )
    return 0


def _keys(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hmpf-serve keys", description="Manage API keys.")
    sub = ap.add_subparsers(dest="cmd", required=True)
    add = sub.add_parser("add", help="create a key; prints it once, stores only its hash")
    add.add_argument("--file", type=Path, required=True)
    add.add_argument("--name", required=True)
    add.add_argument("--role", default="vehicle", choices=["vehicle", "admin"])
    ls = sub.add_parser("list", help="names and roles in a keys file")
    ls.add_argument("--file", type=Path, required=True)
    args = ap.parse_args(argv)

    from service.auth import KeyStore, add_key

    try:
        if args.cmd == "add":
            print(add_key(args.file, args.name, args.role))
        else:
            for k in KeyStore.load(args.file).keys:
                print(f"{k.name}\t{k.role}")
    except HmpfError as exc:
        print(f"hmpf-serve keys: error: {exc}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["keys"]:
        return _keys(argv[1:])
    return _serve(argv)


if __name__ == "__main__":
    sys.exit(main())
