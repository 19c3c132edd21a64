"""Sequence mode of :mod:`hmpf.evaluation`: query traverses driven as vehicles.

A route's queries, in order, are one vehicle's drive; the :class:`~hmpf.sequence.SequenceFilter`
answers each frame from the hierarchy's evidence of that frame and of the frames before it
(online, no look-ahead). Besides the whole traverse driven once at the mapping run's speed,
:func:`sequence_report` drives it in the ways a fleet does:

* **starts**: many drives from random places of the route, to count the frames needed to
  lock on and recall as a function of the frames seen (the history);
* **jumps**: spliced drives (a stretch of the route, then a distant stretch), to count the
  frames needed to re-lock after a relocation;
* **speeds**: every k-th frame (k times faster than the mapping run) and every frame twice
  (half as fast);
* **dropped frames**: a share of the frames left out at random, the gap known to the filter.

:func:`off_map_report` drives a vehicle that *leaves* the map (a stretch of the route, then
frames from a place the map does not hold, then the route again, :func:`leave_drives`): the
share of the frames away that the filter puts off the map, the in-map frames it wrongly puts
there, and the frames it needs to come back after re-entering.

Every frame counts, the first frames of a drive included. A drive *locks* at the first frame
from which its estimate is right for ``hold`` frames in a row (or to the end of the drive).

:func:`tune_sequence` chooses the filter's settings on a training part (a small grid) and
the lock threshold (``lock_mass``) for a target precision of the accepted (locked) answers.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from hmpf.confidence import absolute_evidence
from hmpf.evaluation.metrics import paired_test
from hmpf.hierarchy import HierarchyResult
from hmpf.sequence import (
    Estimate,
    Evidence,
    FilterParams,
    MotionSketch,
    RouteMap,
    SequenceFilter,
    sketch_method,
)

if TYPE_CHECKING:
    from hmpf.confidence import ReferenceProfile
    from hmpf.methods import Method

__all__ = [
    "SPEEDS",
    "Drive",
    "DriveResult",
    "drive",
    "evidences_of",
    "format_off_map_report",
    "format_sequence_report",
    "leave_drives",
    "lock_frames",
    "motion_sketches",
    "sketch_results",
    "off_map_report",
    "lock_threshold",
    "relock_frames",
    "sequence_report",
    "sequence_settings",
    "speed_drive",
    "training_drives",
    "tune_sequence",
]

#: Speed ratios (vehicle / mapping run) the report drives at.
SPEEDS = (0.5, 1.0, 2.0, 3.0, 4.0)
#: Frames in a row an estimate must be right to count as locked.
HOLD = 5


@dataclass(frozen=True)
class Drive:
    """One simulated drive: query indices in order and the frames elapsed before each.

    Attributes:
        frames: (T,) query index shown at each step.
        steps: (T,) frames elapsed since the previous step (1: the next frame; >1: frames
            were dropped; 0: the vehicle sent the same instant again).
        splice: the step at which the drive jumps to a distant stretch (None: no jump); for
            a drive that leaves the map, the step at which it is back on the map.
        away: for a drive that leaves the map, its steps off the map, ``(first, end)``
            (None: it never leaves).
    """

    frames: np.ndarray
    steps: np.ndarray
    splice: int | None = None
    away: tuple[int, int] | None = None

    @classmethod
    def along(cls, frames: Sequence[int] | np.ndarray, splice: int | None = None) -> Drive:
        f = np.asarray(frames, dtype=np.int64)
        return cls(f, np.ones(len(f), dtype=np.int64), splice)


@dataclass(frozen=True)
class DriveResult:
    """The estimates of one drive against the ground truth."""

    drive: Drive
    estimates: list[Estimate]
    correct: np.ndarray  # (T,) the estimate is right
    locked: np.ndarray  # (T,) the estimate is locked (accepted)


def evidences_of(
    results: Sequence[HierarchyResult],
    n: int,
    proposals: int,
    profile: ReferenceProfile | None = None,
) -> list[Evidence]:
    """Each query's :class:`Evidence` from its hierarchy result (``n`` references), with
    its absolute evidence when a ``profile`` of the map's references is given
    (:func:`absolute_evidence`; without one: NaN, the off hypothesis learns nothing) and
    the result's motion sketch, if it carries one (:func:`sketch_results`)."""
    return [
        Evidence.from_result(r, n, proposals=proposals, absolute=absolute_evidence(r, profile))
        for r in results
    ]


def motion_sketches(
    methods: Mapping[str, Method],
    tier1: Sequence[str],
    references: Mapping[str, Any],
    queries: Mapping[str, Sequence[Any]],
    routes: RouteMap,
) -> list[np.ndarray] | None:
    """Each query's :class:`~hmpf.sequence.MotionSketch`, from tier 1's first global method
    (:func:`~hmpf.sequence.sketch_method`): its stacked ``references`` and ``queries``
    features by method id, as :class:`~hmpf.evaluation.data.Prepared` holds them. None
    when the method's features are not given or the map gives no sketch. Needed only for a
    filter that weighs motion (:attr:`FilterParams.motion`)."""
    mid = sketch_method(methods, tier1)
    if mid is None or mid not in references:
        return None
    sketch = MotionSketch.from_references(references[mid], routes)
    return None if sketch is None else [sketch(q) for q in queries[mid]]


def sketch_results(
    results: Sequence[HierarchyResult], sketches: Sequence[np.ndarray] | None
) -> None:
    """Give each result its query's motion sketch (``sketches`` None: nothing to give), which
    :meth:`~hmpf.sequence.Evidence.from_result` hands on to the filter."""
    if sketches is None:
        return
    for r, sketch in zip(results, sketches, strict=True):
        r.sketch = sketch


def drive(
    filt: SequenceFilter, evidences: Sequence[Evidence], d: Drive, gt: np.ndarray
) -> DriveResult:
    """Run one drive through the filter from its start."""
    state, estimates = filt.start(), []
    for q, step in zip(d.frames, d.steps, strict=True):
        state, est = filt.update(state, evidences[int(q)], int(step))
        estimates.append(est)
    refs = np.array([e.ref for e in estimates], dtype=np.int64)
    correct = np.array([r >= 0 and bool(gt[q, r]) for q, r in zip(d.frames, refs, strict=True)])
    locked = np.array([e.locked for e in estimates], dtype=bool)
    return DriveResult(d, estimates, correct, locked)


def lock_frames(correct: np.ndarray, start: int = 0, hold: int = HOLD) -> int | None:
    """Frames from ``start`` (1 = the first) until the estimate is right ``hold`` frames in a
    row (or to the end of the drive); None when it never is."""
    c = np.asarray(correct, dtype=bool)[start:]
    for i in range(len(c)):
        if c[i : i + hold].all():
            return i + 1
    return None


# -- the drives --------------------------------------------------------------------------------


def _speed_frames(nq: int, ratio: float, offset: int = 0) -> np.ndarray:
    if ratio >= 1:
        return np.arange(offset, nq, int(ratio))
    repeat = round(1 / ratio)
    return np.repeat(np.arange(offset, nq), repeat)


def speed_drive(nq: int, ratio: float, offset: int = 0) -> Drive:
    """The traverse at ``ratio`` times the mapping run's speed (each step one frame of the
    vehicle: at half speed it sends every place twice)."""
    return Drive.along(_speed_frames(nq, ratio, offset))


def training_drives(nq: int) -> list[Drive]:
    """A training part's traverse at speeds 1, 2 and 3, every offset (what the tuning and the
    confidence models learn from)."""
    return [speed_drive(nq, r, o) for r in (1.0, 2.0, 3.0) for o in range(int(r))]


def start_drives(
    nq: int, count: int, length: int, ratio: float, rng: np.random.Generator
) -> list[Drive]:
    """``count`` drives of ``length`` steps from random places, at a speed ratio."""
    span = int(np.ceil(length * max(ratio, 1.0)))
    if nq <= span:
        return [Drive.along(_speed_frames(nq, ratio)[:length])]
    starts = rng.choice(nq - span, size=min(count, nq - span), replace=False)
    return [Drive.along(_speed_frames(nq, ratio, int(s))[:length]) for s in np.sort(starts)]


def jump_drives(
    nq: int, count: int, before: int, after: int, min_gap: int, rng: np.random.Generator
) -> list[Drive]:
    """Spliced drives: ``before`` frames of one stretch, then ``after`` frames of a stretch at
    least ``min_gap`` frames away."""
    out: list[Drive] = []
    tries = 0
    while len(out) < count and tries < 50 * count:
        tries += 1
        a = int(rng.integers(0, nq - before))
        b = int(rng.integers(0, nq - after))
        if abs(b - a) < min_gap or abs(b - (a + before)) < min_gap:
            continue
        frames = np.concatenate([np.arange(a, a + before), np.arange(b, b + after)])
        out.append(Drive.along(frames, splice=before))
    return out


def relock_frames(
    filt: SequenceFilter,
    evs: Sequence[Evidence],
    gt: np.ndarray,
    count: int,
    rng: np.random.Generator,
) -> tuple[list[int | None], int]:
    """Frames to lock again after a jump (:func:`lock_frames` from the splice) on ``count``
    :func:`jump_drives` of the traverse (20 frames, then 30 of a stretch at least a fifth of
    it away, fewer on a short traverse), and how many frames each drive has after its jump."""
    nq = len(evs)
    before, after = min(20, nq // 4), min(30, nq // 3)
    runs = [
        drive(filt, evs, d, gt)
        for d in jump_drives(nq, count, before, after, max(10, nq // 5), rng)
    ]
    return [lock_frames(r.correct, r.drive.splice or 0) for r in runs], after


def leave_drives(
    nq: int,
    n_away: int,
    count: int,
    before: int,
    away: int,
    after: int,
    rng: np.random.Generator,
) -> list[Drive]:
    """Drives that leave the map and come back: ``before`` frames of the route, ``away``
    consecutive frames of a place the map does not hold, then ``after`` frames of the route
    from where the vehicle left it or further on (it drove a detour). The route's queries
    are frames ``0 .. nq - 1``, the frames away ``nq .. nq + n_away - 1`` (the caller
    stacks their evidence after the queries'). :attr:`Drive.away` is the stretch away,
    :attr:`Drive.splice` the step back on the map."""
    if before < 1 or away < 1 or after < 1 or nq < before + after or n_away < away:
        return []
    out: list[Drive] = []
    for _ in range(count):
        a = int(rng.integers(0, nq - before - after + 1))
        b = int(rng.integers(a + before, nq - after + 1))
        f = nq + int(rng.integers(0, n_away - away + 1))
        frames = np.concatenate(
            [np.arange(a, a + before), np.arange(f, f + away), np.arange(b, b + after)]
        )
        d = Drive.along(frames, splice=before + away)
        out.append(Drive(d.frames, d.steps, d.splice, (before, before + away)))
    return out


def dropped_drive(nq: int, share: float, rng: np.random.Generator) -> Drive:
    """The whole traverse with ``share`` of the frames left out (the gap known)."""
    keep = np.sort(np.flatnonzero(rng.random(nq) >= share))
    if not len(keep):
        keep = np.array([0])
    steps = np.diff(np.concatenate([[keep[0] - 1], keep]))
    return Drive(keep.astype(np.int64), steps.astype(np.int64))


# -- the report --------------------------------------------------------------------------------


def _precision_recall(runs: Sequence[DriveResult]) -> dict[str, float]:
    correct = np.concatenate([r.correct for r in runs])
    locked = np.concatenate([r.locked for r in runs])
    tp = int((correct & locked).sum())
    return {
        "accepted": float(locked.mean()) if len(locked) else 0.0,
        "precision": tp / int(locked.sum()) if locked.any() else 1.0,
        "recall": tp / len(correct) if len(correct) else 0.0,
    }


def _summary(values: Sequence[int | None], limit: int) -> dict[str, Any]:
    """Median / p95 of frames-to-lock (None: never, counted as the drive's length + 1)."""
    v = np.array([limit + 1 if x is None else x for x in values], dtype=np.float64)
    if not len(v):
        return {"n": 0}
    return {
        "n": len(v),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "within_10": float(np.mean(v <= 10)),
        "never": int(sum(x is None for x in values)),
    }


def sequence_report(
    results: Sequence[HierarchyResult],
    gt: np.ndarray,
    routes: RouteMap,
    params: FilterParams,
    *,
    seed: int = 0,
    starts: int = 40,
    start_length: int = 20,
    jumps: int = 100,
    dropped: float = 0.25,
    speeds: Sequence[float] = SPEEDS,
    profile: ReferenceProfile | None = None,
) -> dict[str, Any]:
    """Sequence-mode figures of one route's query traverse (``results`` in route order):
    the estimate's recall@1 beside the single-frame one, the accepted (locked) answers'
    share and precision, frames to lock after a start and after a jump, recall by speed
    ratio and by frames of history, and with dropped frames. Without a ``profile`` (no
    absolute evidence) the filter runs without the off hypothesis (``leave = 0``: it could
    not tell it, and its resting mass would cap every estimate's)."""
    gt = np.asarray(gt, dtype=bool)
    nq = len(results)
    if profile is None:
        params = params.with_(leave=0.0)
    filt = SequenceFilter(routes, params)
    evs = evidences_of(results, routes.n, params.proposals, profile)
    rng = np.random.default_rng(seed)
    single = np.array([r.match >= 0 and bool(gt[q, r.match]) for q, r in enumerate(results)])
    full = drive(filt, evs, Drive.along(np.arange(nq)), gt)
    by_speed = {}
    history: dict[str, list[float]] = {}
    for ratio in speeds:
        runs = [
            drive(filt, evs, speed_drive(nq, ratio, off), gt)
            for off in range(max(1, int(ratio)) if ratio >= 1 else 1)
        ]
        by_speed[f"{ratio:g}"] = float(np.mean(np.concatenate([r.correct for r in runs])))
        s_runs = [
            drive(filt, evs, d, gt) for d in start_drives(nq, starts, start_length, ratio, rng)
        ]
        curve = np.array([r.correct for r in s_runs if len(r.correct) == start_length])
        history[f"{ratio:g}"] = curve.mean(axis=0).tolist() if len(curve) else []
    start_runs = [drive(filt, evs, d, gt) for d in start_drives(nq, starts, start_length, 1.0, rng)]
    relocks, after = relock_frames(filt, evs, gt, jumps, rng)
    drop_run = drive(filt, evs, dropped_drive(nq, dropped, rng), gt)
    return {
        "params": asdict(params),
        "n_query": nq,
        "single_recall_at_1": float(single.mean()) if nq else 0.0,
        "recall_at_1": float(full.correct.mean()) if nq else 0.0,
        "vs_single": paired_test(full.correct, single),
        "accepted": _precision_recall([full]),
        "lock_after_start": _summary([lock_frames(r.correct) for r in start_runs], start_length),
        "lock_after_jump": _summary(relocks, after),
        "recall_by_speed": by_speed,
        "recall_by_history": history,
        "dropped": {"share": dropped, "recall_at_1": float(drop_run.correct.mean())},
        "full_drive": {
            "correct": full.correct.astype(int).tolist(),
            "locked": full.locked.astype(int).tolist(),
            "mass": [round(e.mass, 4) for e in full.estimates],
        },
    }


def _first(mask: np.ndarray, start: int) -> int | None:
    """Frames from ``start`` (1 = the first) until ``mask`` holds; None when it never does."""
    hit = np.flatnonzero(np.asarray(mask, dtype=bool)[start:])
    return int(hit[0]) + 1 if len(hit) else None


def _leave_figures(runs: Sequence[DriveResult], after: int) -> dict[str, Any]:
    """The figures of drives that leave the map (see :func:`off_map_report`)."""
    away, on, accepted = [], [], []
    detect, back, relock = [], [], []
    for r in runs:
        assert r.drive.away is not None and r.drive.splice is not None
        lo, hi = r.drive.away
        off = np.array([e.off_map >= 0.5 for e in r.estimates])
        inside = np.ones(len(off), dtype=bool)
        inside[lo:hi] = False
        away.append(off[lo:hi])
        on.append(off[inside])
        accepted.append(r.locked[lo:hi])
        detect.append(_first(off[:hi], lo))
        back.append(_first(~off, hi))
        relock.append(lock_frames(r.correct, hi))
    return {
        "away_off_map": float(np.mean(np.concatenate(away))) if runs else 0.0,
        "away_accepted": float(np.mean(np.concatenate(accepted))) if runs else 0.0,
        "on_map_off_map": float(np.mean(np.concatenate(on))) if runs else 0.0,
        "frames_to_detect": _summary(detect, hi - lo if runs else 0),
        "frames_back_on_map": _summary(back, after),
        "frames_to_relock": _summary(relock, after),
    }


def off_map_report(
    results: Sequence[HierarchyResult],
    away_results: Sequence[HierarchyResult],
    gt: np.ndarray,
    routes: RouteMap,
    params: FilterParams,
    profile: ReferenceProfile | None,
    *,
    seed: int = 0,
    count: int = 40,
    before: int = 20,
    away: int = 30,
    after: int = 30,
) -> dict[str, Any]:
    """Drives that leave the map and come back (:func:`leave_drives`): the route's queries
    (``results`` in route order, ground truth ``gt``) and frames of a place the map does not
    hold (``away_results``, in driving order, run on the same map), absolute evidence from
    ``profile``.

    Figures, with ``params`` and with the same drives through the filter without the off
    hypothesis (``leave = 0``, ``"without_off"``): ``away_off_map``, the share of the frames
    away whose ``off_map`` is >= 0.5; ``away_accepted``, the share of them whose estimate
    is locked (an answer accepted where there is none); ``on_map_off_map``, the share of the
    frames on the map put off it (``off_map`` >= 0.5); and, as :func:`sequence_report`'s
    frames-to-lock summaries, the frames from leaving until ``off_map`` >= 0.5
    (``frames_to_detect``), from re-entering until it is < 0.5 (``frames_back_on_map``) and
    until the estimate is right :data:`HOLD` frames in a row (``frames_to_relock``).
    """
    gt = np.asarray(gt, dtype=bool)
    nq, na = len(results), len(away_results)
    both = np.vstack([gt, np.zeros((na, gt.shape[1]), dtype=bool)])
    evs = evidences_of([*results, *away_results], routes.n, params.proposals, profile)
    rng = np.random.default_rng(seed)
    after = min(after, nq - before)
    drives = leave_drives(nq, na, count, before, away, after, rng)
    out: dict[str, Any] = {"n_drives": len(drives), "before": before, "away": away}
    out["after"] = after
    for key, p in (("with_off", params), ("without_off", params.with_(leave=0.0))):
        filt = SequenceFilter(routes, p)
        out[key] = _leave_figures([drive(filt, evs, d, both) for d in drives], after)
    absolute = np.array([e.absolute for e in evs])
    out["absolute"] = {
        "map": _quantiles(absolute[:nq]),
        "away": _quantiles(absolute[nq:]),
    }
    return out


def _quantiles(x: np.ndarray) -> dict[str, float]:
    """5 / 25 / 50 / 75 / 95 % quantiles of the finite values (empty: {})."""
    x = x[np.isfinite(x)]
    if not len(x):
        return {}
    q = np.percentile(x, [5, 25, 50, 75, 95])
    return {f"p{k}": round(float(v), 3) for k, v in zip((5, 25, 50, 75, 95), q, strict=True)}


def format_off_map_report(rep: dict[str, Any]) -> list[str]:
    """:func:`off_map_report` as text lines."""

    def frames(x: dict[str, Any]) -> str:
        if not x["n"]:
            return "no drives"
        return f"median {x['median']:.0f}, p95 {x['p95']:.0f}, never {x['never']}"

    lines = [
        f"leaving the map     {rep['n_drives']} drives: {rep['before']} frames on the map, "
        f"{rep['away']} away, {rep['after']} back"
    ]
    for key, name in (("with_off", "off hypothesis"), ("without_off", "without it")):
        r = rep[key]
        lines.append(
            f"  {name:<17} away put off the map {r['away_off_map']:.3f}, accepted "
            f"{r['away_accepted']:.3f}; on the map put off {r['on_map_off_map']:.3f}; "
            f"back on the map {frames(r['frames_back_on_map'])}; re-lock "
            f"{frames(r['frames_to_relock'])}"
        )
    return lines


def format_sequence_report(rep: dict[str, Any]) -> list[str]:
    """:func:`sequence_report` as text lines."""
    acc, drop = rep["accepted"], rep["dropped"]

    def lock(x: dict[str, Any]) -> str:
        if not x["n"]:
            return "no drives"
        return (
            f"median {x['median']:.0f} frames, p95 {x['p95']:.0f}, within 10: "
            f"{x['within_10']:.2f} ({x['n']} drives)"
        )

    speeds = "  ".join(f"x{k}: {v:.3f}" for k, v in rep["recall_by_speed"].items())
    return [
        f"sequence recall@1   {rep['recall_at_1']:.3f}   (single frame "
        f"{rep['single_recall_at_1']:.3f}; frames won/lost {rep['vs_single']['wins']}/"
        f"{rep['vs_single']['losses']}, sign test p = {rep['vs_single']['p']:.2g})",
        f"accepted (locked)   {acc['accepted']:.3f} of frames, precision "
        f"{acc['precision']:.3f}, recall {acc['recall']:.3f}",
        f"lock after start    {lock(rep['lock_after_start'])}",
        f"re-lock after jump  {lock(rep['lock_after_jump'])}",
        f"recall by speed     {speeds}",
        f"dropped frames ({drop['share']:.0%})  recall@1 {drop['recall_at_1']:.3f}",
    ]


# -- tuning on a training part -------------------------------------------------------------------

#: The grid :func:`tune_sequence` searches (over the defaults of :class:`FilterParams`).
TUNING_GRID: dict[str, Sequence[Any]] = {
    "evidence_weight": (0.1, 0.25),
    "combined_weight": (2.0, 4.0),
    "jump": (0.05, 0.1),
    "reset": (0.0, 0.5, 0.9),
}


def sequence_settings(params: FilterParams) -> dict[str, Any]:
    """The settings of ``params`` that differ from the defaults, for a config's
    ``sequence:`` (floats rounded to 6 digits)."""
    default = FilterParams()
    out: dict[str, Any] = {}
    for f in fields(FilterParams):
        value = getattr(params, f.name)
        if value != getattr(default, f.name):
            out[f.name] = round(value, 6) if isinstance(value, float) else value
    return out


def lock_threshold(mass: np.ndarray, correct: np.ndarray, precision: float) -> float:
    """The lowest posterior mass whose answers at or above it reach ``precision``."""
    order = np.argsort(-mass, kind="stable")
    c = correct[order].astype(np.float64)
    prec = np.cumsum(c) / np.arange(1, len(c) + 1)
    ok = np.flatnonzero(prec >= precision)
    if not len(ok):
        return 1.0
    return float(min(1.0, mass[order][ok[-1]]))


def tune_sequence(
    parts: Sequence[tuple[Sequence[HierarchyResult], np.ndarray, RouteMap]],
    *,
    base: FilterParams | None = None,
    grid: dict[str, Sequence[Any]] | None = None,
    target_precision: float = 0.99,
    seed: int = 0,
    progress: Callable[[dict[str, Any]], Any] | None = None,
) -> tuple[FilterParams, dict[str, Any]]:
    """Choose the filter's settings on training parts, then its lock threshold.

    Args:
        parts: per route, (hierarchy results in query order, ground truth, routes).

    Each setting of ``grid`` (over ``base``) drives each part's traverse at speeds 1, 2 and 3
    and 40 spliced drives. Its ``lock_mass`` is the lowest posterior mass whose answers reach
    ``target_precision`` on all its training drives pooled, and its score the mean of three
    shares, each averaged over the parts where it applies: recall@1 over the speed drives,
    recall@1 over every frame of the spliced drives (so a slow re-lock costs what it costs a
    vehicle) and the answers accepted at ``lock_mass`` (an answer a vehicle cannot rely on is
    worth less). Ties: the earlier grid point.
    """
    base = base or FilterParams()
    grid = grid or TUNING_GRID
    rng = np.random.default_rng(seed)
    prepared = []
    for results, gt, routes in parts:
        nq = len(results)
        before, after = min(20, nq // 4), min(30, nq // 3)
        drives = training_drives(nq)
        jumps = jump_drives(nq, 40, before, after, max(10, nq // 5), rng)
        prepared.append((results, np.asarray(gt, dtype=bool), routes, drives, jumps))
    rows = []
    evidence: dict[tuple[int, int], list[Evidence]] = {}
    best: tuple[float, FilterParams, float] | None = None
    for values in itertools.product(*grid.values()):
        setting = dict(zip(grid, values, strict=True))
        params = base.with_(**setting)
        # No absolute evidence here: the filter runs without the off hypothesis (its resting
        # mass would cap every estimate's); the settings returned keep the base's.
        inner = params.with_(leave=0.0)
        row: dict[str, Any] = {**setting, "recall": [], "jump_recall": [], "relock_10": []}
        runs: list[DriveResult] = []
        for i, (results, gt, routes, drives, jumps) in enumerate(prepared):
            key = (i, params.proposals)  # the evidence depends on the grid only through this
            if key not in evidence:
                evidence[key] = evidences_of(results, routes.n, params.proposals)
            evs = evidence[key]
            filt = SequenceFilter(routes, inner)
            s_runs = [drive(filt, evs, d, gt) for d in drives]
            j_runs = [drive(filt, evs, d, gt) for d in jumps]
            relock = [lock_frames(r.correct, r.drive.splice or 0) for r in j_runs]
            row["recall"].append(float(np.mean([r.correct.mean() for r in s_runs])))
            row["jump_recall"].append(
                float(np.mean([r.correct.mean() for r in j_runs])) if j_runs else 1.0
            )
            row["relock_10"].append(
                float(np.mean([x is not None and x <= 10 for x in relock])) if relock else 1.0
            )
            runs += s_runs + j_runs
        mass = np.concatenate([[e.mass for e in r.estimates] for r in runs])
        correct = np.concatenate([r.correct for r in runs])
        row["lock_mass"] = lock_threshold(mass, correct, target_precision)
        row["accepted"] = float(np.mean(mass >= row["lock_mass"]))
        row["score"] = (
            float(np.mean(row["recall"]) + np.mean(row["jump_recall"]) + row["accepted"]) / 3
        )
        rows.append(row)
        if progress is not None:
            progress(row)
        if best is None or row["score"] > best[0] + 1e-12:
            best = (row["score"], params, row["lock_mass"])
    assert best is not None
    _, params, lock = best
    chosen = params.with_(lock_mass=max(lock, 1e-6))
    return chosen, {"grid": rows, "lock_mass": lock, "target_precision": target_precision}
