"""``hmpf-replay``: play a folder of frames against a running service, as a vehicle would.

    hmpf-replay ../shared/datasets/gardens_point/night_right --url http://127.0.0.1:8000 \\
        --vehicle-id car-17 --start 40 --limit 30 --fps 2 --json drive.json

Frames are sent one at a time in file order (natural sort; ``--start``, ``--limit``,
``--every K`` to play only every K-th frame, as a vehicle K times faster than the mapping
run) to ``POST /v1/localize`` in sequence mode: with the ``vehicle_id`` and the ``track``
token of the previous answer; with ``--fps`` also a capture ``timestamp`` per frame, the
sending paced to that rate. One line per answer (frame, single-frame match, sequence
estimate, its mass, locked, the track's status, round-trip time), then a summary;
``--json FILE`` writes every answer. The API key comes from ``--key`` or ``HMPF_API_KEY``.

Exit codes: 0 every frame answered, 1 some frames answered with an error, 2 the service
cannot be reached or refuses the key (one line, no traceback), 130 Ctrl-C.
Standard library only (urllib), so it runs wherever hmpf is installed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.error import HTTPError, URLError
from urllib.parse import urlencode
from urllib.request import Request, urlopen

from hmpf.cli.common import add_version, run
from hmpf.errors import HmpfError

__all__ = ["Reply", "Vehicle", "build_parser", "main", "replay", "select_frames"]

PROG = "hmpf-replay"
_TYPES = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png", ".webp": "image/webp"}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Play a folder of frames against a running hmpf service, as a vehicle "
        "in sequence mode, and print each answer.",
    )
    add_version(ap)
    ap.add_argument("folder", type=Path, help="the frames, played in file order")
    ap.add_argument("--url", default="http://127.0.0.1:8000", help="the service's base URL")
    ap.add_argument(
        "--key", help="API key (default: HMPF_API_KEY); one that starts with - as --key=KEY"
    )
    ap.add_argument("--vehicle-id", default="replay", help="the vehicle's id (default: replay)")
    ap.add_argument("--start", type=int, default=0, metavar="N", help="first frame (0-based)")
    ap.add_argument("--limit", type=int, metavar="N", help="frames to send at most")
    ap.add_argument(
        "--every", type=int, default=1, metavar="K", help="send every K-th frame (a faster vehicle)"
    )
    ap.add_argument(
        "--fps", type=float, help="frames per second: pace the sending, send a timestamp per frame"
    )
    ap.add_argument("--track", help="start from this track token (a previous run's last)")
    ap.add_argument("--timeout", type=float, default=60.0, metavar="S", help="per request")
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every answer to FILE")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run(PROG, lambda: _run(args), interrupted="interrupted")


def _run(args: argparse.Namespace) -> int:
    if args.every < 1 or args.start < 0 or (args.limit is not None and args.limit < 1):
        raise HmpfError("--every and --limit must be >= 1, --start >= 0")
    if args.fps is not None and not args.fps > 0:
        raise HmpfError("--fps must be > 0")
    frames = select_frames(args.folder, args.start, args.limit, args.every)
    key = args.key or os.environ.get("HMPF_API_KEY")
    vehicle = Vehicle(args.url, key, args.vehicle_id, args.timeout, track=args.track)
    replies = replay(vehicle, frames, fps=args.fps, on_reply=lambda r: print(r.line(), flush=True))
    print(summary(replies))
    if args.json:
        args.json.write_text(json.dumps([r.record() for r in replies], indent=1) + "\n")
    return 0 if all(r.ok for r in replies) else 1


def select_frames(
    folder: Path, start: int, limit: int | None, every: int
) -> list[tuple[int, Path]]:
    """The frames to play, as (position in the folder, path): file order from ``start``,
    every ``every``-th, ``limit`` at most.

    Raises:
        HmpfError: the folder does not exist, holds no image, or none is selected.
    """
    from hmpf.datasets import list_images

    paths = list_images(folder)
    picked = list(range(len(paths)))[start::every][:limit]
    if not picked:
        raise HmpfError(f"no frame selected in {str(folder)!r} (start {start}, every {every})")
    return [(i, paths[i]) for i in picked]


@dataclass
class Reply:
    """One frame's answer (``body``) or error (``status`` >= 400, ``error``)."""

    frame: int
    path: Path
    status: int
    body: dict[str, Any]
    ms: float
    timestamp: float | None = None

    @property
    def ok(self) -> bool:
        return self.status == 200

    @property
    def error(self) -> dict[str, Any]:
        err: dict[str, Any] = self.body.get("error") or {}
        return err

    @property
    def sequence(self) -> dict[str, Any]:
        seq: dict[str, Any] = self.body.get("sequence") or {}
        return seq

    def line(self) -> str:
        """``frame name  single REF  sequence REF  mass M  locked|-  status  ms``."""
        head = f"{self.frame:5d} {self.path.name}"
        if not self.ok:
            return (
                f"{head}  error {self.status} {self.error.get('code')}: {self.error.get('message')}"
            )
        seq = self.sequence
        est = seq.get("match") or {}
        return (
            f"{head}  single {_ref(self.body.get('single'))}  sequence {_ref(est)}"
            f"  mass {seq.get('mass', 0.0):.2f}  {'locked' if seq.get('locked') else '-     '}"
            f"  {seq.get('status', '?')}{_reason(seq)}  {self.ms:.0f} ms"
        )

    def record(self) -> dict[str, Any]:
        """The frame and its whole answer, for ``--json``."""
        return {
            "frame": self.frame,
            "file": self.path.name,
            "timestamp": self.timestamp,
            "status": self.status,
            "ms": self.ms,
            "answer": self.body,
        }


def _ref(match: dict[str, Any] | None) -> str:
    return "   -" if not match else f"{match['reference_id']:4d}"


def _reason(seq: dict[str, Any]) -> str:
    return f" ({seq['reset_reason']})" if seq.get("reset_reason") else ""


@dataclass
class Vehicle:
    """A client in sequence mode: posts frames and carries the track token between them."""

    url: str
    key: str | None
    vehicle_id: str
    timeout: float = 60.0
    track: str | None = None
    _opener: Any = field(default=None, init=False, repr=False)

    def send(self, frame: int, path: Path, timestamp: float | None = None) -> Reply:
        """Post one frame; keep the answer's track for the next.

        Raises:
            HmpfError: the service cannot be reached, or refuses the key (401 / 403).
        """
        fields: dict[str, Any] = {}
        if timestamp is not None:
            fields["timestamp"] = repr(timestamp)
        headers = {
            "Content-Type": _TYPES.get(path.suffix.lower(), "application/octet-stream"),
            "X-Vehicle-Id": self.vehicle_id,  # the vehicle and its track never in the URL
        }
        if self.track:
            headers["X-Track"] = self.track
        if self.key:
            headers["X-API-Key"] = self.key
        query = f"?{urlencode(fields)}" if fields else ""
        target = f"{self.url.rstrip('/')}/v1/localize{query}"
        t = time.perf_counter()
        status, body = self._post(target, path.read_bytes(), headers)
        reply = Reply(frame, path, status, body, (time.perf_counter() - t) * 1e3, timestamp)
        if status in (401, 403):
            raise HmpfError(
                f"{self.url} refused the API key ({status} {reply.error.get('code')}): "
                "give a vehicle key with --key or HMPF_API_KEY"
            )
        if reply.ok and reply.sequence.get("track"):
            self.track = reply.sequence["track"]
        elif reply.error.get("code") == "invalid_track":
            self.track = None  # the service says start again
        return reply

    def _post(self, url: str, data: bytes, headers: dict[str, str]) -> tuple[int, dict[str, Any]]:
        request = Request(url, data=data, headers=headers, method="POST")
        try:
            with urlopen(request, timeout=self.timeout) as resp:
                return int(resp.status), _json(resp.read())
        except HTTPError as exc:
            with exc:
                return int(exc.code), _json(exc.read())
        except (URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise HmpfError(f"cannot reach the service at {self.url}: {reason}") from None


def _json(data: bytes) -> dict[str, Any]:
    try:
        body = json.loads(data)
    except ValueError:
        body = None
    if not isinstance(body, dict):
        return {"error": {"code": "not_json", "message": data[:200].decode(errors="replace")}}
    return body


def replay(
    vehicle: Vehicle,
    frames: Iterable[tuple[int, Path]],
    *,
    fps: float | None = None,
    first: int = 0,
    on_reply: Callable[[Reply], None] | None = None,
) -> list[Reply]:
    """Send ``frames`` (number, path) in order as one vehicle's frames.

    Args:
        vehicle: the client (its track is carried on, and left at the last one).
        frames: the frames, e.g. from :func:`select_frames`.
        fps: pace the sending to this rate and send ``n / fps`` as the ``n``-th frame's
            timestamp (``n`` counted from ``first``); None: as fast as answered, no
            timestamps.
        first: frames sent before (a drive continued: its timestamps go on).
        on_reply: called with each reply as it comes.
    """
    replies = []
    start = time.monotonic()
    for n, (number, path) in enumerate(frames, start=first):
        timestamp = None
        if fps is not None:
            timestamp = n / fps
            time.sleep(max(0.0, start + (n - first) / fps - time.monotonic()))
        reply = vehicle.send(number, path, timestamp)
        replies.append(reply)
        if on_reply is not None:
            on_reply(reply)
    return replies


def summary(replies: list[Reply]) -> str:
    """Frames answered, locked, resets and round-trip times of a replay."""
    ok = [r for r in replies if r.ok]
    locked = sum(1 for r in ok if r.sequence.get("locked"))
    resets = sum(1 for r in ok if r.sequence.get("status") == "reset")
    ms = sorted(r.ms for r in ok)
    timing = f", {ms[len(ms) // 2]:.0f} ms median, {ms[-1]:.0f} ms max" if ms else ""
    return (
        f"{len(replies)} frames: {len(ok)} answered, {len(replies) - len(ok)} errors, "
        f"{locked} locked, {resets} resets{timing}"
    )


if __name__ == "__main__":
    sys.exit(main())
