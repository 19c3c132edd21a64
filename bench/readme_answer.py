"""The README's example answers, produced by running what a new user runs.

    python -m bench.readme_answer [--index index/default] [--out results/readme_answer.json]

Builds the default preset's index over Gardens Point day_right (as ``make run``, unless
``--index`` already holds a version), serves it in-process (the real app, no
``hmpf-calibrate`` step: the bundled preset's shipped confidence model decides) and asks:

* the README's curl frame, night_right ``Image050.jpg``, single frame;
* a vehicle driving night_right ``Image020`` .. ``Image049`` in order (sequence mode), whose
  last answer is the README's sequence example; and the share of the 30 frames accepted
  single frame and in sequence mode, with how many were right (+-2 frames).

Prints both answers (long lists cut to their first entry and ``"..."``) and writes them with
the figures. ``tests/service/test_readme_answers.py`` checks the README's examples against a real
answer's fields.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from bench.harness import ROOT, add_json, parser, write_record
from hmpf.config import load_config
from hmpf.datasets import dataset_root
from indexer.build import BuildOptions, build
from service.app import create_app
from service.settings import load_settings

FRAME = "Image050.jpg"
DRIVE = range(20, 50)
TOLERANCE = 2


def abridged(x: Any, depth: int = 0) -> Any:
    """Lists cut to their first entry and "..." (the README's style), recursively."""
    if isinstance(x, dict):
        return {k: abridged(v, depth + 1) for k, v in x.items()}
    if isinstance(x, list):
        return [abridged(x[0], depth + 1), "..."] if len(x) > 1 else [abridged(v) for v in x]
    if isinstance(x, float):
        return round(x, 4)
    return x


def frame_number(name: str) -> int:
    m = re.search(r"(\d+)", name)
    assert m is not None
    return int(m.group(1))


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--index", default=str(ROOT / "index" / "default"))
    add_json(ap, "--out", default=str(ROOT / "results" / "readme_answer.json"), help="JSON report")
    args = ap.parse_args()
    data = dataset_root() / "gardens_point"
    index = Path(args.index)
    if not (index / "CURRENT").is_file():
        build(
            load_config("default"),
            data / "day_right",
            index,
            options=BuildOptions(progress=False),
        )
    settings = load_settings(index=str(index), auth=False, workers=1)
    night = data / "night_right"
    out: dict[str, Any] = {}
    with TestClient(create_app(settings)) as client:

        def post(name: str, **fields: Any) -> dict[str, Any]:
            path = night / name
            r = client.post(
                "/v1/localize",
                files={"image": (name, path.read_bytes(), "image/jpeg")},
                data=fields,
            )
            r.raise_for_status()
            return dict(r.json())

        single = post(FRAME)
        out["single"] = single
        track, rows = None, []
        for i, n in enumerate(DRIVE):
            fields: dict[str, Any] = {"vehicle_id": "car-17", "timestamp": i / 10}
            if track is not None:
                fields["track"] = track
            body = post(f"Image{n:03d}.jpg", **fields)
            track = body["sequence"]["track"]
            s, m = body["single"], body["match"]
            rows.append(
                {
                    "frame": n,
                    "single_right": abs(frame_number(s["name"]) - n) <= TOLERANCE,
                    "single_accepted": s["accepted"],
                    "single_p": s["p_correct"],
                    "sequence_right": abs(frame_number(m["name"]) - n) <= TOLERANCE,
                    "sequence_accepted": m["accepted"],
                    "sequence_p": m["p_correct"],
                }
            )
        body["sequence"]["track"] = body["sequence"]["track"][:16] + "..."
        out["sequence"] = body
        out["drive"] = rows
        info = client.get("/v1/index").json()
    n = len(rows)
    figures = {
        "preset": "default",
        "config_digest": load_config("default").digest(),
        "index_version": info["version"],
        "frames": n,
        "single_right": sum(r["single_right"] for r in rows),
        "single_accepted": sum(r["single_accepted"] for r in rows),
        "single_accepted_right": sum(r["single_accepted"] and r["single_right"] for r in rows),
        "sequence_right": sum(r["sequence_right"] for r in rows),
        "sequence_accepted": sum(r["sequence_accepted"] for r in rows),
        "sequence_accepted_right": sum(
            r["sequence_accepted"] and r["sequence_right"] for r in rows
        ),
    }
    out["figures"] = figures
    target = write_record(args.out, out, args, preset="default")
    print(json.dumps(abridged(single), indent=1))
    print(json.dumps(abridged(out["sequence"]), indent=1))
    print(json.dumps(figures, indent=1))
    print(f"wrote {target}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
