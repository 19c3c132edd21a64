"""The map learns from the fleet: record accepted frames with a real service, merge them into
a new version, and measure what the merged map answers.

    python -m bench.experiences [--config default] [--work DIR] [--nordland-places 600]
        [--json docs/experiments/experiences/default.json] [--smoke]

Every step is what an operator runs: ``hmpf-index build`` of the map, a real ``hmpf-serve``
with recording on (``HMPF_EXPERIENCE_LOG``) driven in sequence mode by
:class:`hmpf.client.Client` (one vehicle, frames in order, one a second), the service
stopped, ``hmpf-index add --experiences LOG`` publishing the merged version, and
:func:`hmpf.evaluation.evaluate.evaluate_index` (what ``hmpf-eval --index`` runs: the
service's own path per query) on the bare and the merged versions.

Runs (Gardens Point frames are aligned across traverses; a frame's place is right within
+-2 frames, as everywhere in hmpf):

* ``gp``: map = day_left; the fleet drives day_right; test = night_right, single frame and
  sequence mode, bare map against merged map (paired sign test on the same queries). Each
  fleet pass is driven once per recording threshold (the service recording at it: its lock
  lead-ins depend on it), and each merge is also made with every frame at its recorded place
  (``--no-interpolate-places``, ``as_recorded``) and without the lead frames
  (``--no-place-leads``, ``without_leads``), each paired against the merge: what placing a
  frame between its time neighbours, and what recording a lock's lead-in, do.
* ``gp_halves``: map = day_left; the fleet drives the first half of night_right, merged;
  the second half is the test; and the reverse.
* ``nordland``: a stated proxy. Map = summer, the first ``--nordland-places`` frames; the
  fleet drives winter's even frames, the test is winter's odd frames.
* ``poison``: the ``gp`` log poisoned on purpose before the merge, two ways: 5 % of its
  records moved to a wrong place (50 frames away), and wrong copies (the same frames, 50
  frames away) added until they are 5 % of the log: how many the merge's gates keep out, and
  the recall of each poisoned merge against the clean one (paired sign tests).
* ``placement``: the ``gp`` pass's records merged at their true places instead of the
  places the service answered, with the gates and with them open, paired against the merge
  at the answered places: what the recorder's placement costs (its records are right within
  +-2 frames, but a night query's own error adds to theirs).
* ``cost``: index bytes per experience, the resident memory of a reader, the hierarchy's
  time per query with 1, 2 and 4 experiences per place (the extra experiences beyond the
  recorded pass are other traverses' frames merged with the gates open), and the merge's
  throughput (frames per second, extraction included).
* ``scenarios``: the place scoring alone. Frames merged at their true places with the gates
  open (a perfect recorder), the test frames on the bare and the merged version: day_left
  map + all of day_right (night_right tested); day_left map + one half of night_right (the
  other half tested, both ways: a night pass over half the route must not attract the other
  half's night frames); day_right map + all of day_left (night_right tested: images farther
  from the queries' view must cost nothing).
* ``gp_reverse`` (not in the default runs): the ``gp`` pass with the traverses' roles
  swapped: map = day_right; the fleet drives day_left; test = night_right (a pass the
  placing of frames between their time neighbours was not found on).
* ``gp_join``: the defence of lead-ins against a vehicle joining the route from off the map:
  map = day_left; one drive of ``JOIN_FRAMES`` Nordland frames (another country), day_right
  0-99, ``JOIN_FRAMES`` more Nordland frames, day_right 100-199, recorded at each threshold
  and merged: how many lead frames were recorded and merged, and how many merged frames are
  wrong (a Nordland frame merged is wrong wherever it goes).
* ``merge_speed``: the merge's throughput with the features the service recorded with each
  frame (setting ``experience_features``, on by default) against the same log with them
  stripped (every frame extracted again): map = day_left, the fleet drives day_right
  (recording at the lowest threshold), both logs merged with the same gates into copies of
  the map, one after the other, each timed whole (``hmpf-index add``) and through its gates
  (the report's ``frames_per_s``: reading, extraction or not, localisation and gates;
  publishing excluded).

What the merge added is audited against the ground truth: an experience is wrong when its
frame's true place is more than 2 frames from the place it was merged into.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from bench.harness import ROOT, add_json, parser, write_record
from hmpf.client import Client
from hmpf.config import load_config
from hmpf.datasets import dataset_root, list_images
from hmpf.evaluation.data import frame_ground_truth
from hmpf.evaluation.evaluate import evaluate_index
from hmpf.evaluation.metrics import paired_test
from hmpf.experience_log import ExperienceLog, read_log
from hmpf.features import FeatureCache, file_digest
from hmpf.imageio import load_image
from hmpf.index.reader import IndexReader

BIN = Path(sys.executable).parent
TOLERANCE = 2
POISON_SHARE = 0.05
POISON_SHIFT = 50
#: Off-map frames before each half of the ``gp_join`` drive.
JOIN_FRAMES = 8


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--config", default="default", help="preset or YAML of the map")
    ap.add_argument("--work", type=Path, default=ROOT / "results" / "experiences")
    ap.add_argument("--nordland-places", type=int, default=600)
    ap.add_argument(
        "--runs", default="gp,gp_halves,gp_join,nordland,poison,placement,cost,scenarios"
    )
    ap.add_argument(
        "--thresholds",
        default="0.99,0.9",
        help="p_correct thresholds to record at (the first is the default's, 0.99); each "
        "fleet pass is driven once per threshold, recording at it",
    )
    ap.add_argument(
        "--keep-maps",
        action="store_true",
        help="reuse the bare maps a previous run built in --work",
    )
    add_json(ap, default=ROOT / "docs" / "experiments" / "experiences" / "default.json")
    ap.smoke(nordland_places=120)
    args = ap.parse_args()
    runs = set(args.runs.split(","))
    ts = [float(t) for t in args.thresholds.split(",")]
    _fresh(args.work, args.keep_maps)
    gp = dataset_root() / "gardens_point"
    out: dict[str, Any] = {}
    map_dl = build_map(args.work / "gp_map", gp / "day_left", args.config, args.keep_maps)
    if runs & {"gp", "poison", "placement", "cost"}:
        out["gp"] = gp_pass(map_dl, gp, ts)
    if "gp_halves" in runs:
        out["gp_halves"] = halves(map_dl, list_images(gp / "night_right"), ts)
    if "nordland" in runs:
        out["nordland"] = nordland(args.work, args.config, args.nordland_places, ts, args.keep_maps)
    if "poison" in runs:
        out["poison"] = poison(map_dl, out["gp"], list_images(gp / "night_right"), min(ts))
    if "placement" in runs:
        out["placement"] = placement(map_dl, out["gp"], list_images(gp / "night_right"), ts)
    if "cost" in runs:
        out["cost"] = cost(map_dl, out["gp"], gp, list_images(gp / "night_right"), min(ts))
    if "gp_reverse" in runs:
        map_dr = build_map(args.work / "gp_dr_map", gp / "day_right", args.config, args.keep_maps)
        out["gp_reverse"] = gp_pass(map_dr, gp, ts, fleet_traverse="day_left")
    if "gp_join" in runs:
        out["gp_join"] = joining(map_dl, gp, ts)
    if "merge_speed" in runs:
        out["merge_speed"] = merge_speed(map_dl, list_images(gp / "day_right"), min(ts))
    if "scenarios" in runs:
        out["scenarios"] = scenarios(map_dl, gp, args.work, args.config, args.keep_maps)
    config = load_config(args.config)
    write_record(args.json, summary(out), args, preset=args.config, config=config)
    print(json.dumps(summary(out), indent=1))
    return 0


# -- the operator's steps ----------------------------------------------------------------------


def _fresh(work: Path, keep_maps: bool) -> None:
    """An empty ``work`` folder, or with ``keep_maps`` only its bare maps (``*_map``) kept."""
    work.mkdir(parents=True, exist_ok=True)
    for p in work.iterdir():
        if keep_maps and (p.name.endswith("_map") or p.name.endswith("_map-images")):
            continue
        shutil.rmtree(p) if p.is_dir() else p.unlink()


def build_map(index: Path, images: Path | list[Path], config: str, keep: bool = False) -> Path:
    """``hmpf-index build`` of ``images`` (a folder, or files copied into one); with ``keep``
    a map already built there is reused."""
    if keep and (index / "CURRENT").exists():
        return index
    if isinstance(images, list):
        folder = index.parent / f"{index.name}-images"
        folder.mkdir(parents=True, exist_ok=True)
        for p in images:
            shutil.copy(p, folder / p.name)
        images = folder
    run(
        [str(BIN / "hmpf-index"), "build", "--config", config, "--images", str(images)]
        + ["--index", str(index), "--quiet"]
    )
    return index


def run(cmd: list[str]) -> str:
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return done.stdout


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def drive(
    index: Path, frames: list[Path], log: Path, threshold: float, vehicle: str = "bench-car"
) -> dict:
    """A real ``hmpf-serve`` on ``index`` with recording on (at ``threshold``), ``frames``
    sent in order in sequence mode (one a second of capture time), then stopped (SIGTERM:
    the log flushed).

    Returns each frame's answer (place index or -1, accepted, p_correct) and the time."""
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("HMPF_")}
    if "HMPF_DATASETS" in os.environ:
        env["HMPF_DATASETS"] = os.environ["HMPF_DATASETS"]
    env.update(
        HMPF_AUTH="false",
        HMPF_LOG_LEVEL="warning",
        HMPF_EXPERIENCE_LOG=str(log),
        HMPF_EXPERIENCE_MIN_P_CORRECT=str(threshold),
    )
    out = log.parent / f"{log.name}.serve.log"
    proc = subprocess.Popen(
        [str(BIN / "hmpf-serve"), "--index", str(index), "--port", str(port)],
        env=env,
        stdout=out.open("wb"),
        stderr=subprocess.STDOUT,
    )
    answers: list[tuple[int, bool, float | None]] = []
    try:
        with Client(f"http://127.0.0.1:{port}", timeout=60, retries=0) as client:
            _wait_ready(client, proc, out)
            t0 = time.perf_counter()
            for i, path in enumerate(frames):
                a = client.localize(path.read_bytes(), vehicle_id=vehicle, timestamp=float(i))
                m = a.match
                if m is None:
                    answers.append((-1, False, None))
                else:
                    answers.append((m.reference_id, bool(m.accepted), m.p_correct))
            seconds = time.perf_counter() - t0
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
    return {"answers": answers, "seconds": seconds}


def _wait_ready(client: Any, proc: subprocess.Popen, out: Path) -> None:
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"hmpf-serve exited {proc.returncode}:\n{out.read_text()[-3000:]}")
        try:
            client.index()
            return
        except Exception:  # not up yet: any transport error or 503 while it loads
            time.sleep(0.3)
    raise SystemExit("hmpf-serve did not become ready in 300 s")


def merge(index: Path, logs: list[Path], *extra: str) -> dict[str, Any]:
    """``hmpf-index add --experiences`` (timed); the new version's counts and the merge's
    report (the manifest's ``experiences`` entry)."""
    t0 = time.perf_counter()
    text = run(
        [str(BIN / "hmpf-index"), "add", "--index", str(index), "--quiet"]
        + ["--experiences", *map(str, logs), *extra]
    )
    seconds = time.perf_counter() - t0
    with IndexReader(index) as reader:
        version = reader.version
        places = reader.manifest.get("places", {})
        report = reader.manifest.get("experiences", {})
    return {
        "version": version,
        "seconds": seconds,
        "places": places,
        "report": report,
        "output": text[-2000:],
    }


def evaluate(index: Path, queries: list[Path], gt: np.ndarray, version: str | None = None) -> dict:
    """Single-frame and sequence recall@1 of ``queries`` on a version (places)."""
    with IndexReader(index, version) as reader:
        # The queries' features are cached per fitted state (the bare and merged versions of
        # one map share it), in the bench's own folder: what the reader's methods computed.
        cache = FeatureCache(index.parent / "query-cache")
        rep = evaluate_index(
            reader, queries, gt, f"frames +-{TOLERANCE}", cache=cache, sequence=True
        )
        names = {n: i for i, n in enumerate(reader.refs.names[: reader.n])}
    matches = [names.get(m, -1) if m else -1 for m in rep["hierarchy"]["matches"]]
    correct = np.array([m >= 0 and gt[q, m] for q, m in enumerate(matches)])
    return {
        "single": float(rep["hierarchy"]["combined_recall_at_1"]),
        "sequence": float(rep["sequence"]["recall_at_1"]),
        "correct": correct,
        "seq_correct": np.array(rep["sequence"]["full_drive"]["correct"], bool),
        "hierarchy_ms": float(rep["timing_ms"]["hierarchy_per_query"]),
        "version": rep["index"]["version"],
    }


def audit(log: Path, truth: dict[str, int]) -> dict[str, Any]:
    """The log's records against the ground truth: ``truth`` maps a frame's sha256 to its
    true place; wrong = more than ``TOLERANCE`` frames from the recorded place (a frame not
    in ``truth`` is wrong). Lead frames (a lock's lead-in, placed by the merge) are counted
    apart (``leads``), not audited: their recorded place is their own unsure answer."""
    everything = list(read_log(log))
    records = [r for r in everything if r.mode != "lead"]
    wrong = [
        r
        for r in records
        if abs(truth.get(hashlib.sha256(r.image).hexdigest(), -(10**9)) - r.place) > TOLERANCE
    ]
    p = [r.p_correct for r in records]
    return {
        "recorded": len(records),
        "wrong": len(wrong),
        "p_correct_min": min(p) if p else None,
        "leads": len(everything) - len(records),
    }


def merged_rows(
    index: Path, truth: dict[str, int], leads: set[str] | None = None
) -> dict[str, Any]:
    """What the current version holds beyond its places: count, and wrong experiences; with
    ``leads`` (the sha256 of a log's lead frames), how many of them and how many wrong."""
    with IndexReader(index) as reader:
        place = reader.refs.meta.get("place")
        if place is None:
            rows = np.zeros(0, dtype=np.int64)
        else:
            rows = np.flatnonzero(~np.isnan(place))
        bad = {
            int(i)
            for i in rows
            if abs(truth.get(reader.refs.sha256[i], -(10**9)) - int(place[i])) > TOLERANCE
        }
        lead_rows = [int(i) for i in rows if reader.refs.sha256[i] in (leads or set())]
    out = {"experiences": int(len(rows)), "wrong": len(bad)}
    if leads is not None:
        out["leads"] = len(lead_rows)
        out["leads_wrong"] = sum(i in bad for i in lead_rows)
    return out


def lead_digests(log: Path) -> set[str]:
    """The sha256 of the log's lead frames."""
    return {hashlib.sha256(r.image).hexdigest() for r in read_log(log) if r.mode == "lead"}


def truth_of(frames: list[Path], offset: int = 0) -> dict[str, int]:
    """sha256 of each aligned frame -> its true place (its position + ``offset``)."""
    return {file_digest(p): i + offset for i, p in enumerate(frames)}


# -- runs --------------------------------------------------------------------------------------


def _copy(index: Path, name: str) -> Path:
    dst = index.parent / name
    shutil.copytree(index, dst)
    return dst


def fleet_pass(
    base: Path,
    name: str,
    fleet: list[Path],
    truth: dict[str, int],
    test: list[Path],
    gt: np.ndarray,
    thresholds: list[float],
) -> dict[str, Any]:
    """One fleet pass: per threshold, ``fleet`` driven against (a copy of) ``base`` with
    recording on at that threshold, a copy of ``base`` merged with its log and ``test``
    evaluated on it, against the bare map (paired sign tests); and the same log merged with
    every frame at its recorded place (``as_recorded``) and without its lead frames
    (``without_leads``), each paired against the merge."""
    bare = evaluate(base, test, gt)
    out: dict[str, Any] = {"fleet_frames": len(fleet), "bare": _recall(bare), "merges": {}}
    places = [truth[digest(p)] for p in fleet]
    for t in sorted(thresholds, reverse=True):
        log = base.parent / f"{name}_{t:g}.log"
        drove = drive(_copy(base, f"{name}_served_{t:g}"), fleet, log, t)
        recorded = audit(log, truth)
        print(f"{name} at {t:g}: recorded {recorded}", flush=True)
        # the answers do not depend on the threshold: the lowest's drive is the one kept
        out["drive_s"] = drove["seconds"]
        out["answers"] = answer_shares(drove["answers"], places, thresholds)
        out["recorded"] = recorded
        leads = lead_digests(log)
        index = _copy(base, f"{name}_at_{t:g}")
        merged = merge(index, [log], "--min-p-correct", str(t))
        rows = merged_rows(index, truth, leads)
        print(f"{name} at {t:g}: merged in {merged['seconds']:.0f} s: {rows}", flush=True)
        after = evaluate(index, test, gt)
        run: dict[str, Any] = {
            "_correct": after["correct"],  # for the poisoning's paired tests (not recorded)
            "_seq_correct": after["seq_correct"],
            "_log": str(log),
            "recorded": recorded,
            "index": str(index),
            "merge": merged,
            "added": rows,
            "merged": _recall(after),
            "single_test": paired_test(after["correct"], bare["correct"]),
            "sequence_test": paired_test(after["seq_correct"], bare["seq_correct"]),
        }
        # the same log merged otherwise: wins are the default merge's
        for key, flag in (
            ("as_recorded", "--no-interpolate-places"),
            ("without_leads", "--no-place-leads"),
        ):
            _, kept_rows, kept = _merge_eval(
                _copy(base, f"{name}_at_{t:g}_{key}"),
                log,
                (flag, "--min-p-correct", str(t)),
                truth,
                test,
                gt,
                leads,
            )
            run[key] = {
                "added": kept_rows,
                "merged": _recall(kept),
                "single_test": paired_test(after["correct"], kept["correct"]),
                "sequence_test": paired_test(after["seq_correct"], kept["seq_correct"]),
            }
        out["merges"][f"{t:g}"] = run
        out["_log"] = str(log)  # the lowest threshold's (the poisoning's)
    return out


def _merge_eval(
    index: Path,
    log: Path,
    args: tuple[str, ...],
    truth: dict[str, int],
    test: list[Path],
    gt: Any,
    leads: set[str] | None = None,
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """``log`` merged into ``index`` with ``args``: the merge, its audit against ``truth`` (and
    its ``leads``), and the ``test`` frames evaluated on it."""
    merged = merge(index, [log], *args)
    return merged, merged_rows(index, truth, leads), evaluate(index, test, gt)


def answer_shares(
    answers: list[tuple[int, bool, float | None]], places: list[int], thresholds: list[float]
) -> dict[str, Any]:
    """The drive's answers: accepted, and accepted at ``p_correct`` >= each threshold, with
    how many of them were right (within ``TOLERANCE`` of the frame's place)."""

    def count(keep: Any) -> dict[str, int]:
        sel = [(a, p) for a, p in zip(answers, places, strict=True) if keep(a)]
        return {"n": len(sel), "right": sum(abs(a[0] - p) <= TOLERANCE for a, p in sel)}

    return {
        "accepted": count(lambda a: a[1]),
        "p_correct_at_least": {
            f"{t:g}": count(lambda a, t=t: a[1] and a[2] is not None and a[2] >= t)
            for t in thresholds
        },
    }


def digest(path: Path) -> str:
    return file_digest(path)


def _recall(ev: dict[str, Any]) -> dict[str, Any]:
    out = {k: ev[k] for k in ("single", "sequence", "hierarchy_ms", "version")}
    print(f"  {out}", flush=True)
    return out


def gp_pass(
    base: Path, gp: Path, thresholds: list[float], fleet_traverse: str = "day_right"
) -> dict[str, Any]:
    """Map ``base`` (day_left), the fleet drives ``fleet_traverse``, night_right tested."""
    fleet, test = list_images(gp / fleet_traverse), list_images(gp / "night_right")
    gt = frame_ground_truth(len(test), _places(base), TOLERANCE)
    name = "gp" if fleet_traverse == "day_right" else f"gp_{fleet_traverse}"
    return fleet_pass(base, name, fleet, truth_of(fleet), test, gt, thresholds)


def _places(index: Path) -> int:
    with IndexReader(index) as reader:
        return reader.n


def halves(base: Path, night: list[Path], thresholds: list[float]) -> dict[str, Any]:
    """First half of night_right recorded and merged, second half tested; and the reverse.

    The test's recall is over the test half's frames (its ground truth on the whole map)."""
    h = len(night) // 2
    gt_all = frame_ground_truth(len(night), _places(base), TOLERANCE)
    truth = truth_of(night)
    return {
        name: fleet_pass(base, f"gp_{name}", fleet, truth, test, gt_all[sl], thresholds)
        for name, fleet, test, sl in (
            ("first_then_second", night[:h], night[h:], slice(h, None)),
            ("second_then_first", night[h:], night[:h], slice(0, h)),
        )
    }


def joining(base: Path, gp: Path, thresholds: list[float]) -> dict[str, Any]:
    """A vehicle that joins the route from off the map, twice (at its start and half way):
    ``JOIN_FRAMES`` Nordland frames before each half of day_right, recorded at each threshold
    and merged into a copy of ``base``; the lead frames recorded and merged, and the merged
    frames that are wrong (a Nordland frame is wrong at any place)."""
    day = list_images(gp / "day_right")
    away = list_images(dataset_root() / "nordland_64x32" / "summer")[1000:]
    h = len(day) // 2
    fleet = away[:JOIN_FRAMES] + day[:h] + away[JOIN_FRAMES : 2 * JOIN_FRAMES] + day[h:]
    truth = truth_of(day)
    foreign = {digest(p) for p in away[: 2 * JOIN_FRAMES]}
    out: dict[str, Any] = {"fleet_frames": len(fleet), "off_map_frames": len(foreign)}
    for t in sorted(thresholds, reverse=True):
        log = base.parent / f"gp_join_{t:g}.log"
        drive(_copy(base, f"gp_join_served_{t:g}"), fleet, log, t)
        leads = lead_digests(log)
        index = _copy(base, f"gp_join_at_{t:g}")
        merged = merge(index, [log], "--min-p-correct", str(t))
        with IndexReader(index) as reader:
            held = set(reader.refs.sha256[reader.n :])
        out[f"{t:g}"] = {
            "recorded": audit(log, truth),
            "off_map_leads": len(leads & foreign),
            "added": merged_rows(index, truth, leads),
            "off_map_merged": len(held & foreign),
            "leads_placed": merged["report"].get("leads_placed", 0),
            "gates": merged["report"].get("gates", {}),
        }
        print(f"gp_join at {t:g}: {out[f'{t:g}']}", flush=True)
    return out


def nordland(
    work: Path, config: str, places: int, thresholds: list[float], keep: bool = False
) -> dict[str, Any]:
    """Summer map of the first ``places`` frames; winter even frames driven, odd tested."""
    root = dataset_root() / "nordland_64x32"
    summer, winter = list_images(root / "summer")[:places], list_images(root / "winter")[:places]
    index = build_map(work / "nordland_map", summer, config, keep)
    gt = frame_ground_truth(places, places, TOLERANCE)[1::2]
    out = fleet_pass(
        index, "nordland", winter[0::2], truth_of(winter), winter[1::2], gt, thresholds
    )
    out["proxy"] = (
        f"summer map of the first {places} frames; winter even frames driven (recorded), "
        "winter odd frames tested"
    )
    return out


def poison(base: Path, gp: dict[str, Any], test: list[Path], threshold: float) -> dict[str, Any]:
    """The ``gp`` pass's log (recorded at ``threshold``) poisoned two ways, each merged into a
    copy of the bare map at that threshold with the gates and with every gate open
    (``--no-gates``: what poisoning costs when nothing keeps it out), against the clean merge
    at the same threshold (paired sign tests on the same queries):

    * ``moved``: ``POISON_SHARE`` of its records moved ``POISON_SHIFT`` places away (a wrong
      lock: the frames' own places lose them too);
    * ``added``: copies of as many records, ``POISON_SHIFT`` places away, added to the clean
      log so that they are ``POISON_SHARE`` of it (wrong experiences on top of the right
      ones: what the wrong ones alone cost)."""
    records = [r for r in read_log(gp["_log"]) if r.mode == "lead" or r.p_correct >= threshold]
    locked = [i for i, r in enumerate(records) if r.mode != "lead"]  # leads stay as recorded
    rng = np.random.default_rng(0)
    n_bad = max(1, round(POISON_SHARE * len(locked)))
    bad = {int(i) for i in rng.choice(locked, n_bad, replace=False)}
    with IndexReader(base) as reader:
        names, n_map = list(reader.place_names), reader.n
    n_added = max(1, round(POISON_SHARE * len(records) / (1.0 - POISON_SHARE)))
    added = sorted(int(i) for i in rng.choice(locked, n_added, replace=False))
    # (record, place it is written at, by the poisoner?)
    moved = [
        (r, (r.place + POISON_SHIFT) % n_map if i in bad else r.place, i in bad)
        for i, r in enumerate(records)
    ]
    extra = [(records[i], (records[i].place + POISON_SHIFT) % n_map, True) for i in added]
    truth = truth_of(list_images(dataset_root() / "gardens_point" / "day_right"))
    clean_run = gp["merges"][f"{threshold:g}"]
    clean = clean_run["merged"]
    gt = frame_ground_truth(len(test), n_map, TOLERANCE)
    out: dict[str, Any] = {
        "threshold": threshold,
        "records": len(records),
        "poisoned": n_bad,
        "added_wrong": n_added,
    }
    clean_rows = [(r, r.place, False) for r in records]
    for kind, rows in (("moved", moved), ("added", [*clean_rows, *extra])):
        log = base.parent / f"poisoned_{kind}.log"
        _write_log(log, rows, names)
        out[kind] = _gated_and_open(
            base, f"poison_{kind}", log, threshold, clean_run, truth, test, gt
        )
        for row in out[kind].values():
            row["vs_clean_merge"] = {k: row["merged"][k] - clean[k] for k in ("single", "sequence")}
    return out


def placement(
    base: Path, gp: dict[str, Any], test: list[Path], thresholds: list[float]
) -> dict[str, Any]:
    """Where the recorded merge falls short of a perfect recorder: the ``gp`` pass's records
    at or above each threshold merged at their *true* places (the frame's own position)
    instead of the places the service answered, with the gates and with every gate open,
    against the recorded merge at that threshold (paired). The recorded places are right
    (within ``TOLERANCE``) but carry the drive's own localisation error (day_right's frames
    answered one place early about half the time), which a night query's error adds to; the
    perfect recorder of the scenarios also has every frame, not only the accepted ones."""
    truth = truth_of(list_images(dataset_root() / "gardens_point" / "day_right"))
    with IndexReader(base) as reader:
        names, n_map = list(reader.place_names), reader.n
    gt = frame_ground_truth(len(test), n_map, TOLERANCE)
    out: dict[str, Any] = {}
    for t in sorted(thresholds, reverse=True):
        # that threshold's log; a lead frame at its true place as if recorded for its answer
        kept = [
            dataclasses.replace(r, mode="sequence", p_correct=max(r.p_correct, t))
            if r.mode == "lead"
            else r
            for r in read_log(gp["merges"][f"{t:g}"]["_log"])
        ]
        at_truth = [(r, truth[hashlib.sha256(r.image).hexdigest()], False) for r in kept]
        log = base.parent / f"placement_{t:g}.log"
        _write_log(log, at_truth, names)
        recorded = gp["merges"][f"{t:g}"]
        runs = _gated_and_open(base, f"placement_{t:g}", log, t, recorded, truth, test, gt)
        out[f"{t:g}"] = {"records": len(kept), "recorded_places": recorded["merged"], **runs}
    return out


def _gated_and_open(
    base: Path,
    name: str,
    log: Path,
    threshold: float,
    against: dict[str, Any],
    truth: dict[str, int],
    test: list[Path],
    gt: np.ndarray,
) -> dict[str, dict[str, Any]]:
    """``log`` merged into two copies of ``base`` (``<name>_gated``: the gates at
    ``threshold``; ``<name>_open``: ``--no-gates``), each audited against ``truth`` and its
    ``test`` frames (ground truth ``gt``) paired with the merge ``against`` (a
    :func:`fleet_pass` merge)."""
    out: dict[str, dict[str, Any]] = {}
    for gate, args in (("gated", ("--min-p-correct", str(threshold))), ("open", ("--no-gates",))):
        merged, counted, after = _merge_eval(
            _copy(base, f"{name}_{gate}"), log, args, truth, test, gt
        )
        print(f"{name} {gate}: {counted}", flush=True)
        out[gate] = {
            "merge": merged,
            "added": counted,
            "merged": _recall(after),
            "single_test": paired_test(after["correct"], against["_correct"]),
            "sequence_test": paired_test(after["seq_correct"], against["_seq_correct"]),
        }
    return out


def _write_log(log: Path, rows: list[tuple[Any, int, bool]], names: list[str]) -> None:
    """A log of ``(record, place, poisoner)`` rows: each record's image and fields at that
    place, its vehicle ``poisoner`` where the row says so (no features: the merge extracts
    them)."""
    with ExperienceLog(log) as writer:
        for r, place, bad in rows:
            writer.append(
                r.image,
                content_type=r.content_type,
                place=place,
                place_name=names[place],
                index_version=r.index_version,
                p_correct=r.p_correct,
                vehicle="poisoner" if bad else r.vehicle,
                timestamp=r.timestamp,
                mode=r.mode,
            )


def cost(
    base: Path, gp: dict[str, Any], gp_root: Path, test: list[Path], threshold: float
) -> dict[str, Any]:
    """Bytes and memory per experience, query time with 1, 2, 3, 4 images per place, merge
    throughput (the ``gp`` pass's merge at ``threshold``)."""
    at = gp["merges"][f"{threshold:g}"]
    with IndexReader(base) as reader:
        n_map, bare_bytes = reader.n, reader.manifest["summary"]["bytes_total"]
    with IndexReader(Path(at["index"])) as reader:
        extra = reader.n_rows - reader.n
        merged_bytes = reader.manifest["summary"]["bytes_total"]
    report = at["merge"]["report"]
    frames = at["recorded"]["recorded"] + at["recorded"]["leads"]  # the log's records
    out: dict[str, Any] = {
        "bytes_per_experience": (merged_bytes - bare_bytes) / extra if extra else None,
        "merge": {
            "frames": frames,
            "seconds": at["merge"]["seconds"],
            "frames_per_s": frames / at["merge"]["seconds"],
            "frames_extracted": report.get("frames_extracted"),
            "features_recorded": report.get("features_recorded", 0),
            "note": "the whole hmpf-index add --experiences run: reading the log, extracting "
            "the frames whose features it does not hold, localising every frame for the "
            "agreement gate, publishing",
        },
    }
    # 2, 3, 4 images per place: day_right, night_right and day_left's own frames merged one
    # after the other with the gates open (only the count matters here).
    versions = {1: base}
    index = _copy(base, "cost_many")
    for k, name in zip((2, 3, 4), ("day_right", "night_right", "day_left"), strict=True):
        frames = list_images(gp_root / name)[:n_map]
        log = truth_log(base, base.parent / f"cost_{name}.log", frames, range(len(frames)))
        merge(index, [log], "--no-gates")
        versions[k] = _copy(index, f"cost_{k}")
    out["query_ms_by_images_per_place"] = query_times(versions, test[:: max(1, len(test) // 40)])
    out["rss_mb"] = {str(k): _reader_rss(p) for k, p in versions.items()}
    return out


def query_times(versions: dict[int, Path], images: list[Path]) -> dict[str, Any]:
    """Per version, the median ms per query of extraction + hierarchy and of the hierarchy
    alone (what the service runs per frame, one thread), the versions taking turns on each
    image so that they share the machine's moments alike."""
    readers = {k: IndexReader(p) for k, p in versions.items()}
    samples: dict[int, dict[str, list[float]]] = {
        k: {"total": [], "hierarchy": []} for k in readers
    }
    # BLAS on one thread (the service caps its pools too; as OPENBLAS_NUM_THREADS=1 does):
    # on a loaded machine a BLAS pool of several threads stalls on one query's small
    # products, and those stalls, not the experiences, would be measured
    with threadpool_limits(1, user_api="blas"):
        _time_versions(readers, images, samples)
    for r in readers.values():
        r.close()
    med = {k: {m: float(np.median(v)) for m, v in s.items()} for k, s in samples.items()}
    return {
        "queries": len(images),
        "blas_threads": 1,
        "median_ms": {str(k): v for k, v in med.items()},
        "total_vs_one": {str(k): v["total"] / med[1]["total"] for k, v in med.items()},
    }


def _time_versions(
    readers: dict[int, IndexReader], images: list[Path], samples: dict[int, dict[str, list[float]]]
) -> None:
    for warm in (True, False):
        for path in images[:3] if warm else images:
            image = load_image(path)
            for k, r in readers.items():
                t0 = time.perf_counter()
                feats = r.extract_query(image)
                t1 = time.perf_counter()
                r.hierarchy().run(r.scorer(feats), r.n)
                t2 = time.perf_counter()
                if not warm:
                    samples[k]["total"].append((t2 - t0) * 1e3)
                    samples[k]["hierarchy"].append((t2 - t1) * 1e3)


def truth_log(index: Path, log: Path, frames: list[Path], places: Any) -> Path:
    """An experience log of ``frames`` recorded at their true ``places`` (what a perfect
    recorder would keep) by vehicle ``truth-<log's stem>``, as the service writes it, for
    ``hmpf-index add --experiences``."""
    with IndexReader(index) as reader:
        names = reader.place_names
    with ExperienceLog(log) as writer:
        for i, (p, place) in enumerate(zip(frames, places, strict=True)):
            writer.append(
                p.read_bytes(),
                content_type="image/jpeg",
                place=int(place),
                place_name=names[int(place)],
                index_version="v0001",
                p_correct=1.0,
                vehicle=f"truth-{log.stem}",
                timestamp=float(i),
                mode="sequence",
            )
    return log


def scenarios(base_dl: Path, gp: Path, work: Path, config: str, keep: bool) -> dict[str, Any]:
    """The place scoring alone: frames merged at their true places with the gates open (a
    perfect recorder), then the test frames on the bare and the merged version.

    * day_left map + all of day_right, night_right tested: every place gains an image
      closer to the queries' view;
    * day_left map + night_right's first half, the second half tested (and the reverse):
      the half the night pass covered must not attract the other half's night frames;
    * day_right map + all of day_left, night_right tested: every place gains an image
      farther from the queries' view, which should cost nothing.
    """
    night, day_right = list_images(gp / "night_right"), list_images(gp / "day_right")
    day_left = list_images(gp / "day_left")
    map_dr = build_map(work / "gp_dr_map", gp / "day_right", config, keep)
    n, h = len(night), len(night) // 2
    cases = [
        ("dl_plus_dr", base_dl, day_right, range(n), night, slice(None)),
        ("dl_plus_night_first", base_dl, night[:h], range(h), night[h:], slice(h, None)),
        ("dl_plus_night_second", base_dl, night[h:], range(h, n), night[:h], slice(0, h)),
        ("dr_plus_dl", map_dr, day_left, range(n), night, slice(None)),
    ]
    out: dict[str, Any] = {}
    for name, base, frames, places, test, sl in cases:
        gt = frame_ground_truth(n, _places(base), TOLERANCE)[sl]
        bare = evaluate(base, test, gt)
        index = _copy(base, f"scenario_{name}")
        log = truth_log(base, base.parent / f"scenario_{name}.log", frames, places)
        merged = merge(index, [log], "--no-gates")
        after = evaluate(index, test, gt)
        out[name] = {
            "map": base.name,
            "experiences": len(frames),
            "tested": len(test),
            "bare": _recall(bare),
            "merged": _recall(after),
            "merge": merged,
            "single_test": paired_test(after["correct"], bare["correct"]),
            "sequence_test": paired_test(after["seq_correct"], bare["seq_correct"]),
        }
        print(f"scenario {name}: {out[name]['bare']} -> {out[name]['merged']}", flush=True)
    return out


def _reader_rss(index: Path) -> float:
    """Resident memory (MB, ``VmRSS``) of a fresh process once it has opened the version,
    built its reference profile and answered one query (models loaded, files mapped)."""
    code = (
        "import sys, re, pathlib; from hmpf.index.reader import IndexReader; "
        "from hmpf.imageio import load_image; "
        "r = IndexReader(sys.argv[1]); r.reference_profile(); "
        "img = next(iter(sorted(pathlib.Path(sys.argv[2]).iterdir()))); "
        "r.hierarchy().run(r.scorer(r.extract_query(load_image(img))), r.n); "
        "s = pathlib.Path('/proc/self/status').read_text(); "
        "print(int(re.search(r'VmRSS:\\s+(\\d+)', s)[1]) / 1024)"
    )
    query_dir = dataset_root() / "gardens_point" / "night_right"
    return float(run([sys.executable, "-c", code, str(index), str(query_dir)]).strip())


def merge_speed(base: Path, fleet: list[Path], threshold: float) -> dict[str, Any]:
    """The merge's throughput with the recorded features and without them (see the module
    docstring): one drive, two logs, two merges."""
    log = base.parent / "speed.log"
    drive(_copy(base, "speed_served"), fleet, log, threshold)
    stripped = base.parent / "speed_stripped.log"
    records = list(read_log(log))
    with ExperienceLog(stripped) as writer:
        for r in records:
            writer.append(
                r.image,
                content_type=r.content_type,
                place=r.place,
                place_name=r.place_name,
                index_version=r.index_version,
                p_correct=r.p_correct,
                vehicle=r.vehicle,
                timestamp=r.timestamp,
                mode=r.mode,
                received=r.received,
            )
    out: dict[str, Any] = {
        "records": len(records),
        "with_features": sum(r.features is not None for r in records),
        "feature_bytes_per_record": float(
            np.median([len(r.features) for r in records if r.features is not None] or [0])
        ),
        "image_bytes_per_record": float(np.median([len(r.image) for r in records] or [0])),
    }
    for name, source in (("extracted", stripped), ("recorded", log)):
        index = _copy(base, f"speed_{name}")
        timed = merge(index, [source], "--min-p-correct", str(threshold))
        report = timed["report"]
        out[name] = {
            "wall_s": timed["seconds"],
            "gates_s": report.get("seconds"),
            "frames_per_s": report.get("frames_per_s"),
            "frames_extracted": report.get("frames_extracted"),
            "features_recorded": report.get("features_recorded"),
            "added": report.get("added"),
            "gates": report.get("gates"),
            "load_end": list(os.getloadavg()),
        }
        print(f"merge_speed {name}: {out[name]}", flush=True)
    out["ratio_frames_per_s"] = out["recorded"]["frames_per_s"] / out["extracted"]["frames_per_s"]
    return out


def summary(out: dict[str, Any]) -> dict[str, Any]:
    """The figures the goals name, for the console."""

    def strip(d: Any) -> Any:
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if not k.startswith("_") and k != "output"}
        return d

    return strip(out)


if __name__ == "__main__":
    sys.exit(main())
