"""Write ``docker/container-test.sh``'s run as a JSON record (``RECORD=path``).

    python3 docker/record.py OUT ANSWER_JSON key=value ... -- "step=seconds" ...

Runs with the host's ``python3`` and its standard library only (the script's other helper
runs the same way): the steps' seconds, the image sizes, whether the service image holds
torch, the answer's match, the served config (``index.json`` beside the answer: ``GET
/v1/index``) and the provenance (date, commit, machine, load average).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)
    except OSError:
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _cpu() -> tuple[str, list[str]]:
    """The first CPU's model name and its flags (``/proc/cpuinfo``)."""
    fields: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    model = fields.get("model name") or platform.processor() or "unknown"
    return model, fields.get("flags", "").split()


def main(argv: list[str]) -> int:
    out, answer_path, rest = argv[0], argv[1], argv[2:]
    split = rest.index("--")
    fields = dict(a.split("=", 1) for a in rest[:split])
    steps = {name: int(s) for name, s in (a.rsplit("=", 1) for a in rest[split + 1 :])}
    match = json.loads(Path(answer_path).read_text())["match"]
    index_path = Path(answer_path).with_name("index.json")  # GET /v1/index, when fetched
    config = json.loads(index_path.read_text())["config"] if index_path.exists() else {}
    root = Path(__file__).resolve().parent.parent
    cpu, flags = _cpu()
    record = {
        # the indexer job's HMPF_CONFIG, which the script leaves at "default"
        "preset": config.get("name", "default"),
        "config": config or None,  # the resolved config the service loaded
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "commit": _git(root, "rev-parse", "HEAD"),
        "code_changed_since_commit": (_git(root, "diff", "--name-only", "HEAD") or "").split(),
        "machine": f"{cpu}, {os.cpu_count()} cores",
        "cpu_flags": flags,  # bench/pages.py names the vector extensions from them
        "machine_details": {"cores": os.cpu_count(), "load_1min": os.getloadavg()[0]},
        "base_image_kept": fields["base_kept"] == "yes",
        "steps_s": steps,
        "total_s": int(fields["total"]),
        "images_mb": {k: int(fields[f"{k}_mb"]) for k in ("indexer", "service", "base")},
        "service_has_torch": fields["torch"] == "yes",
        "answer": {k: match.get(k) for k in ("name", "reference_id", "score", "p_correct")}
        | {"accepted": match.get("accepted")},
    }
    Path(out).write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
