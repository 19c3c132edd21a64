"""The sequence filter's motion cue: chosen on the training parts, measured on the test parts.

    python -m bench.motion_cue [--config default] [--nordland-frames 800]
        [--grid motion|evidence|still|slow] [--out docs/experiments/sequence/motion_cue.json]

The filter explains a stretch of frames that all resemble one reference by a vehicle that
stopped there; a vehicle that drives on through look-alike places then falls behind. The
motion cue (:attr:`hmpf.sequence.FilterParams.stop_factor`) compares each frame with the
previous one (:class:`hmpf.sequence.MotionSketch` of tier 1's first global method): a frame
that differs by ``moved`` map steps or more makes the stopped hypotheses ``stop_factor``
times as likely.

The routes and their parts are ``bench/shipped_acceptance.py``'s (Gardens Point's three
protocols, Nordland summer -> winter, its first ``--nordland-frames`` frames; alternating
stretches of 20 frames). The filter runs as ``hmpf-eval --sequence`` runs it (the preset's
settings, the off-map state reading the part's own reference profile).

* **Chosen on the training parts**: ``stop_factor`` x ``moved`` over :data:`GRID`, scored by
  the mean sequence recall@1 of the training parts' traverses driven at the mapping run's
  speed and at half of it (every frame twice: a vehicle slower than the mapping run), every
  route alike; ties go to the preset (no cue).
* **Measured on the test parts** (held out) and on Gardens Point's whole traverses (which
  hold the training frames: not held out): the chosen setting against the preset, recall@1
  at speeds 1, 0.5 and 2, paired frame by frame (exact sign test), and the filter's own
  figures (:func:`~hmpf.evaluation.sequence.sequence_report`: re-lock after a jump, 25 %
  dropped frames).

``--grid evidence`` chooses the weights of a frame's evidence (:data:`EVIDENCE_GRID`) and
``--grid still`` the weight of a frame that did not move (:data:`STILL_GRID`) and ``--grid
slow`` the half-speed hypotheses' weight after two whole steps in a row (:data:`SLOW_GRID`)
the same way, their score also counting re-locks after a jump. It reports; it changes no
default. The acceptance models are not refitted here: the lock rule's accepted share
(posterior mass >= ``lock_mass``) is reported beside the recall.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from bench.harness import ROOT, add_json, parser, provenance, write_record
from bench.shipped_acceptance import NORDLAND_FRAMES, ROUTES, TOLERANCE, Route
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root
from hmpf.evaluation.acceptance import sequence_answers
from hmpf.evaluation.calibrate import paired_test
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.sequence import (
    evidences_of,
    motion_sketches,
    relock_frames,
    sequence_report,
    sketch_results,
    speed_drive,
)
from hmpf.evaluation.study import ScoreBank
from hmpf.features import FeatureCache
from hmpf.runtime import default_cache_dir
from hmpf.sequence import FilterParams, RouteMap, SequenceFilter

#: The grid over the preset's filter settings (``stop_factor`` 1: no cue, the preset).
GRID: dict[str, tuple[float, ...]] = {
    "stop_factor": (1.0, 0.3, 0.1, 0.03),
    "moved": (0.3, 0.5, 0.8),
}
#: ``--grid evidence``: how much one frame's evidence weighs, the Combined score's bonus at
#: the final candidates (min-max normalised per frame, so even a frame that tells nothing
#: gives its best candidate the whole bonus) and the tier-1 z-score's weight.
#: Lower weights trust the motion model more: a drive through look-alike frames stays on
#: course, but a vehicle that jumped (frames lost, a wrong start) is found again later, so
#: this grid's score also counts the share of jumps re-locked within 10 frames
#: (:data:`RELOCK_WITHIN`) on the training parts, weighed like one speed.
EVIDENCE_GRID: dict[str, tuple[float, ...]] = {
    "combined_weight": (0.5, 1.0, 1.5, 2.0),
    "evidence_weight": (0.15, 0.25),
}
#: ``--grid still``: how much a frame that did not move weighs (its sketch within ``moved``
#: of the previous frame's): it shows what the previous frame showed. Scored like
#: ``--grid evidence`` (a weight of the evidence: the re-lock counts).
STILL_GRID: dict[str, tuple[float, ...]] = {"still_weight": (1.0, 0.5, 0.25, 0.1, 0.0)}
#: ``--grid slow``: the likelihood of the half-speed hypotheses when a frame and the one
#: before it each moved ``fast_moved`` map steps or more (a vehicle at the mapping run's pace
#: is not at half of it; a half-speed drive that sends each place twice never moves a whole
#: step twice running). Scored like ``--grid evidence``.
SLOW_GRID: dict[str, tuple[float, ...]] = {
    "slow_factor": (1.0, 0.5, 0.2, 0.1),
    "fast_moved": (0.8, 1.0),
}
GRIDS = {"motion": GRID, "evidence": EVIDENCE_GRID, "still": STILL_GRID, "slow": SLOW_GRID}
#: Frames within which a jump must be re-locked (``--grid evidence``'s score).
RELOCK_WITHIN = 10
#: Jumps per training part (``--grid evidence``'s score).
JUMPS = 100
#: Each grid's record when ``--out`` is not given.
OUTS = {
    "motion": "docs/experiments/sequence/motion_cue.json",
    "evidence": "docs/experiments/sequence/evidence_weights.json",
    "still": "docs/experiments/sequence/still_weight.json",
    "slow": "docs/experiments/sequence/slow_factor.json",
}
#: Speed ratios of the drives (vehicle / mapping run).
SPEEDS = (1.0, 0.5, 2.0)
#: Speeds the choice is scored on.
TRAIN_SPEEDS = (1.0, 0.5)


class Part:
    """One traverse (a route's training or test part, or a whole protocol): its hierarchy
    results, ground truth, routes, reference profile and every query's motion sketch."""

    def __init__(self, bank: ScoreBank, config: HierarchyConfig) -> None:
        self.results = bank.results(config)
        self.gt = np.asarray(bank.gt, bool)
        self.routes = RouteMap.from_metadata(bank.n_db)
        self.profile = bank.profile(config)
        db = {m: f[0] for m, f in bank.features.items()}
        qs = {m: f[1] for m, f in bank.features.items()}
        # The sketches depend on the map and the frames only; a filter that weighs no motion
        # reads none of them.
        sketches = motion_sketches(bank.methods, config.tiers[0].methods, db, qs, self.routes)
        sketch_results(self.results, sketches)

    def correct(self, params: FilterParams, ratio: float) -> np.ndarray:
        """Per frame of the drive at ``ratio`` (one offset), whether the estimate is right."""
        d = speed_drive(len(self.results), ratio)
        return sequence_answers(
            self.results, self.gt, self.routes, params, [d], self.profile
        ).correct

    def relocked(self, params: FilterParams, jumps: int = JUMPS) -> float:
        """The share of ``jumps`` drives with a jump (:func:`relock_frames`; the same drives
        for every setting) whose estimate is right again, and stays so, within
        :data:`RELOCK_WITHIN` frames of the jump."""
        evs = evidences_of(self.results, self.routes.n, params.proposals, self.profile)
        filt = SequenceFilter(self.routes, params)
        frames, _ = relock_frames(filt, evs, self.gt, jumps, np.random.default_rng(0))
        return float(np.mean([f is not None and f <= RELOCK_WITHIN for f in frames]))

    def locked(self, params: FilterParams) -> dict[str, float]:
        """The drive at the mapping run's speed: the share of its estimates that are locked
        (posterior mass >= ``lock_mass``: the lock rule) and their precision."""
        run = sequence_answers(self.results, self.gt, self.routes, params, None, self.profile)
        locked = run.score >= params.lock_mass
        precision = float(run.correct[locked].mean()) if locked.any() else float("nan")
        return {"share": float(locked.mean()), "precision": precision}

    def report(self, params: FilterParams) -> dict[str, Any]:
        rep = sequence_report(self.results, self.gt, self.routes, params, profile=self.profile)
        return {
            "recall_at_1": rep["recall_at_1"],
            "recall_by_speed": rep["recall_by_speed"],
            "dropped_recall_at_1": rep["dropped"]["recall_at_1"],
            "relock_within_10": rep["lock_after_jump"].get("within_10"),
            "lock_after_start_within_10": rep["lock_after_start"].get("within_10"),
            "accepted_lock": rep["accepted"],
        }


def compare(part: Part, chosen: FilterParams, preset: FilterParams) -> dict[str, Any]:
    """The chosen setting against the preset on one traverse, per speed, paired."""
    out: dict[str, Any] = {}
    for ratio in SPEEDS:
        a, b = part.correct(chosen, ratio), part.correct(preset, ratio)
        out[f"{ratio:g}"] = {"cue": float(a.mean()), "preset": float(b.mean()), **paired_test(a, b)}
    out["locked"] = {"cue": part.locked(chosen), "preset": part.locked(preset)}
    return out


def choose(
    train: dict[str, Part],
    preset: FilterParams,
    grid: dict[str, tuple[float, ...]] = GRID,
    relock: bool = False,
) -> tuple[FilterParams, list[dict]]:
    """The grid scored on the training parts (mean recall@1 over routes and
    :data:`TRAIN_SPEEDS`, with ``relock`` also the share of jumps re-locked,
    :meth:`Part.relocked`); ties: the preset's setting, then the earlier grid point."""
    rows = []
    for values in itertools.product(*grid.values()):
        setting = dict(zip(grid, values, strict=True))
        params = preset.with_(**setting)
        rec = {
            name: {f"{r:g}": float(p.correct(params, r).mean()) for r in TRAIN_SPEEDS}
            | ({"relock": p.relocked(params)} if relock else {})
            for name, p in train.items()
        }
        score = float(np.mean([v for per in rec.values() for v in per.values()]))
        rows.append({**setting, "recall": rec, "score": score})
        print(f"  {setting}: score {score:.4f}", flush=True)
    best = max(
        rows,
        key=lambda r: (round(r["score"], 12), all(r[k] == getattr(preset, k) for k in grid)),
    )
    return preset.with_(**{k: best[k] for k in grid}), rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--config", default="default", help="the bundled preset")
    ap.add_argument(
        "--nordland-frames", type=int, default=NORDLAND_FRAMES, help="Nordland's first frames"
    )
    ap.add_argument("--routes", default=",".join(ROUTES), help="comma-separated")
    ap.add_argument(
        "--grid",
        choices=sorted(GRIDS),
        default="motion",
        help="motion: the motion cue against a preset without it; evidence: the weights of "
        "a frame's evidence against the preset's; still: the weight of a frame that did not "
        "move against the preset's; slow: the half-speed hypotheses' weight after two whole "
        "steps in a row against the preset's",
    )
    add_json(ap, "--out", default=None, help="the record (default: the grid's own, OUTS)")
    ap.smoke(nordland_frames=100, routes="gp_dl_nr")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    config = load_config(args.config)
    prov = provenance(args.config, config, args)
    preset = config.sequence_params()
    grid = GRIDS[args.grid]
    out = args.out or str(ROOT / OUTS[args.grid])
    if args.grid == "motion" and preset.motion:
        raise SystemExit(f"{args.config}: its filter already weighs motion; compare another")
    cache = FeatureCache(default_cache_dir())
    names = args.routes.split(",")
    train: dict[str, Part] = {}
    test: dict[str, Part] = {}
    for name in names:
        limit = args.nordland_frames or None if name == "nordland_s_w" else None
        route = Route(name, config, cache, 0, limit)
        train[name] = Part(route.train.rows(np.arange(route.n_train)), config)
        test[name] = Part(route.test.rows(np.arange(route.n_test)), config)
        print(f"{name}: parts ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    root = dataset_root()
    wholes = {}
    for name in names:
        if name in GARDENS_POINT_PROTOCOLS:
            ref, qry = GARDENS_POINT_PROTOCOLS[name]
            data = EvalData.frames(root / ref, root / qry, TOLERANCE)
            wholes[name] = Part(ScoreBank.build(config, data, cache=cache), config)
    print(f"whole traverses ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    relock = args.grid in ("evidence", "still", "slow")
    chosen, rows = choose(train, preset, grid, relock)
    picked = {k: getattr(chosen, k) for k in grid}
    print(f"chosen: {picked}", flush=True)
    report: dict[str, Any] = {
        "grid": {k: list(v) for k, v in grid.items()},
        "train_speeds": list(TRAIN_SPEEDS),
        "score_relock_within": RELOCK_WITHIN if relock else None,
        "rows": rows,
        "chosen": picked,
        "preset_setting": {k: getattr(preset, k) for k in grid},
        "test_parts": {n: compare(p, chosen, preset) for n, p in test.items()},
        "whole": {
            n: {
                **compare(p, chosen, preset),
                "cue_report": p.report(chosen),
                "preset_report": p.report(preset),
            }
            for n, p in wholes.items()
        },
        "nordland_frames": args.nordland_frames,
    }
    report["wall_s"] = time.perf_counter() - t0
    print_report(report)
    write_record(out, report, prov=prov)
    return 0


def print_report(report: dict[str, Any]) -> None:
    c = ", ".join(f"{k} {v:g}" for k, v in report["chosen"].items())
    print(f"\nchosen on the training parts: {c}")
    for key, title in (("test_parts", "test parts (held out)"), ("whole", "whole traverses")):
        print(f"\n{title}: recall@1 cue / preset (wins / losses, p)")
        for name, per in report[key].items():
            cells = [
                f"x{r}: {per[r]['cue']:.3f} / {per[r]['preset']:.3f} "
                f"({per[r]['wins']}/{per[r]['losses']}, p {per[r]['p']:.2g})"
                for r in (f"{s:g}" for s in SPEEDS)
            ]
            print(f"  {name:14s} " + "; ".join(cells))


if __name__ == "__main__":
    raise SystemExit(main())
