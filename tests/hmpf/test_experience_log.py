"""The experience log (:mod:`hmpf.experience_log`) on real files: framing, a torn tail cut at
every byte of the last record, a damaged record in the middle, rotation and the size bound,
prune by vehicle and by age beside a live writer, a write that fails part-way (a real file
size limit), and a writer process killed with SIGKILL while it appends.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from hmpf.cli.experiences import main as experiences_main
from hmpf.errors import HmpfError
from hmpf.experience_log import (
    MAGIC,
    ExperienceLog,
    ExperienceLogError,
    LogStats,
    Record,
    encode_frame,
    log_id,
    prune,
    read_log,
)

ROOT = Path(__file__).resolve().parents[2]


def image(seq: int, size: int = 200) -> bytes:
    """Deterministic bytes standing for frame ``seq``'s image."""
    out = b""
    while len(out) < size:
        out += hashlib.sha256(f"{seq}:{len(out)}".encode()).digest()
    return out[:size]


def fields(i: int, vehicle: str = "car-1", **over: Any) -> dict[str, Any]:
    f: dict[str, Any] = {
        "content_type": "image/jpeg",
        "place": i % 7,
        "place_name": f"Image{i % 7:03d}.jpg",
        "index_version": "v0001",
        "p_correct": 0.995,
        "vehicle": vehicle,
        "timestamp": 1000.0 + i,
        "mode": "sequence",
    }
    f.update(over)
    return f


def write(path: Path, n: int, size: int = 200, **kw: Any) -> list[Record]:
    with ExperienceLog(path, **kw) as log:
        return [log.append(image(log.next_seq, size), **fields(i)) for i in range(n)]


def read(path: Path) -> tuple[list[Record], LogStats]:
    stats = LogStats()
    return list(read_log(path, stats=stats)), stats


def segments(path: Path) -> list[Path]:
    return sorted(path.glob("*.seg"))


def test_records_round_trip_and_the_log_keeps_its_id(tmp_path: Path) -> None:
    log = tmp_path / "log"
    written = write(log, 5)
    got, stats = read(log)
    assert got == written
    assert (stats.records, stats.damaged, stats.torn, stats.segments) == (5, 0, 0, 1)
    assert [r.seq for r in got] == [0, 1, 2, 3, 4]
    assert got[3].place_name == "Image003.jpg" and got[3].image == image(3)
    assert len({r.log for r in got}) == 1 and got[0].log == log_id(log)
    header = json.loads((log / "log.json").read_text())
    assert header["format"] == "hmpf-experience-log" and header["id"] == got[0].log
    # A new writer keeps the id, never writes into an old segment, and goes on counting.
    more = write(log, 2)
    assert [r.seq for r in more] == [5, 6] and {r.log for r in more} == {got[0].log}
    assert len(segments(log)) == 2
    assert [r.seq for r in read(log)[0]] == list(range(7))
    assert (log.stat().st_mode & 0o777) == 0o700
    assert all((s.stat().st_mode & 0o777) == 0o600 for s in segments(log))


def test_features_ride_after_the_image_and_older_records_have_none(tmp_path: Path) -> None:
    log = tmp_path / "log"
    packed = image(99, 77)
    with ExperienceLog(log) as w:
        plain = w.append(image(0), **fields(0))
        rich = w.append(image(1), **fields(1), features=packed)
        with pytest.raises(ValueError, match="features"):
            w.append(image(2), **fields(2), features=b"")
    got, stats = read(log)
    assert got == [plain, rich] and stats.damaged == 0
    assert got[0].features is None and got[0].image == image(0)
    assert got[1].features == packed and got[1].image == image(1)
    # the header says how many of the payload's bytes are features; a length that cannot be
    # (more than the payload) makes the frame no record (skipped, never an image cut wrong)
    data = segments(log)[0].read_bytes()
    head = json.dumps(rich.header(), separators=(",", ":")).encode()
    assert b'"features_bytes":77' in head and head in data
    bad = head.replace(b'"features_bytes":77', b'"features_bytes":9999')
    with ExperienceLog(tmp_path / "bad") as w:
        w.append(image(0), **fields(0))
    seg = segments(tmp_path / "bad")[0]
    seg.write_bytes(seg.read_bytes() + encode_frame(json.loads(bad), rich.payload()))
    assert [r.seq for r in read(tmp_path / "bad")[0]] == [0]


def test_bad_fields_and_folders_are_refused(tmp_path: Path) -> None:
    with ExperienceLog(tmp_path / "log") as log:
        for bad, needle in (
            ({"place": -1}, "place"),
            ({"p_correct": 1.5}, "p_correct"),
            ({"mode": "guess"}, "mode"),
            ({"timestamp": float("nan")}, "finite"),
        ):
            with pytest.raises(ValueError, match=needle):
                log.append(b"x", **fields(0, **bad))
        # A second writer on the same log is refused while the first holds it.
        with pytest.raises(ExperienceLogError, match="another process is writing"):
            ExperienceLog(tmp_path / "log")
    ExperienceLog(tmp_path / "log").close()  # released on close
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    with pytest.raises(ExperienceLogError, match="not empty"):
        ExperienceLog(tmp_path / "other")
    with pytest.raises(ExperienceLogError, match="not an experience log"):
        read_log(tmp_path / "other")
    with pytest.raises(HmpfError, match="no such experience log"):
        read_log(tmp_path / "missing")
    with pytest.raises(ExperienceLogError, match="half of max_bytes"):
        ExperienceLog(tmp_path / "x", max_bytes=1000, segment_bytes=600)


def test_a_torn_tail_cut_at_every_byte_is_skipped(tmp_path: Path) -> None:
    log = tmp_path / "log"
    written = write(log, 3)
    (seg,) = segments(log)
    data = seg.read_bytes()
    last = data.rindex(MAGIC)  # the last record's frame starts here (its image holds no magic)
    assert last > 0
    for cut in range(last, len(data)):
        seg.write_bytes(data[:cut])
        got, stats = read(log)
        assert got == written[:2], cut
        assert stats.torn == (cut > last) and stats.damaged == 0, cut
        assert stats.skipped_bytes == cut - last
    # A writer after the cut goes on in a new segment; the torn tail stays where it was.
    more = write(log, 1)
    assert more[0].seq == 2
    got, stats = read(log)
    assert got == [*written[:2], *more] and stats.torn == 1


@pytest.mark.parametrize("where", ["payload", "magic", "length", "header"])
def test_a_damaged_record_in_the_middle_is_skipped_and_counted(tmp_path: Path, where) -> None:
    log = tmp_path / "log"
    written = write(log, 5)
    (seg,) = segments(log)
    data = bytearray(seg.read_bytes())
    starts = [i for i in range(len(data)) if data.startswith(MAGIC, i)]
    assert len(starts) == 5
    at = {"payload": starts[2] - 5, "magic": starts[1], "length": starts[1] + 7}.get(
        where, starts[1] + 20
    )
    data[at] ^= 0xFF
    seg.write_bytes(bytes(data))
    got, stats = read(log)
    assert got == [written[0], *written[2:]]
    assert (stats.damaged, stats.torn, stats.records) == (1, 0, 4)


def test_rotation_and_the_bound_drop_the_oldest_first(tmp_path: Path) -> None:
    log = tmp_path / "log"
    kw = {"segment_bytes": 3000, "max_bytes": 10_000, "sync_every": 4}
    with ExperienceLog(log, **kw) as w:
        for i in range(40):
            w.append(image(i, 900), **fields(i))
            on_disk = sum(s.stat().st_size for s in segments(log))
            assert on_disk <= 10_000 and on_disk == w.total_bytes
            assert all(s.stat().st_size <= 3000 for s in segments(log))
        dropped = w.dropped
    got, stats = read(log)
    seqs = [r.seq for r in got]
    assert seqs == list(range(40 - len(seqs), 40)), "the newest records, in order"
    assert dropped == 40 - len(seqs) > 0
    assert stats.damaged == stats.torn == 0 and len(segments(log)) >= 3
    assert all(r.image == image(r.seq, 900) for r in got)


def test_prune_by_vehicle_beside_a_live_writer(tmp_path: Path) -> None:
    log = tmp_path / "log"
    kw = {"segment_bytes": 2000, "max_bytes": 1 << 20}
    w = ExperienceLog(log, **kw)
    try:
        for i in range(31):  # the last one (car-a) in the segment being written
            w.append(image(i), **fields(i, vehicle="car-a" if i % 3 == 0 else "car-b"))
        live = segments(log)[-1]
        live_before = live.read_bytes()
        report = prune(log, vehicle="car-a")
        assert report.pending > 0 and report.removed + report.pending == 11
        assert report.rewritten > 0 and not report.dry_run
        assert live.read_bytes() == live_before, "the segment being written is not touched"
        # The writer goes on, rotating, while the log has been pruned under it.
        for i in range(31, 40):
            w.append(image(i), **fields(i, vehicle="car-b"))
    finally:
        w.close()
    left = [r for r in read(log)[0] if r.vehicle == "car-a"]
    assert len(left) == report.pending
    again = prune(log, vehicle="car-a")  # no writer now: every segment
    assert (again.removed, again.pending) == (report.pending, 0)
    got, stats = read(log)
    assert [r.seq for r in got] == [i for i in range(40) if i > 30 or i % 3 != 0]
    assert {r.vehicle for r in got} == {"car-b"} and stats.damaged == stats.torn == 0
    assert all(r.image == image(r.seq) for r in got)


def test_prune_by_age_dry_run_and_the_latest_seq_survives(tmp_path: Path) -> None:
    log = tmp_path / "log"
    with ExperienceLog(log, segment_bytes=1500, max_bytes=1 << 20) as w:
        for i in range(12):
            w.append(image(i), **fields(i), received=10_000.0 + 100 * i)
    before = {s.name: s.read_bytes() for s in segments(log)}
    dry = prune(log, older_than_s=350, now=10_000.0 + 1100, dry_run=True)  # before 10_750
    assert dry.removed == 8 and dry.kept == 4 and dry.dry_run
    assert {s.name: s.read_bytes() for s in segments(log)} == before
    report = prune(log, older_than_s=350, now=10_000.0 + 1100)
    assert (report.removed, report.kept) == (8, 4) and report.deleted > 0
    assert [r.seq for r in read(log)[0]] == [8, 9, 10, 11]
    # Everything removed: the log remembers its latest seq, a new writer goes on after it.
    assert prune(log, vehicle="car-1").removed == 4
    assert read(log)[0] == [] and segments(log)
    assert [r.seq for r in write(log, 2)] == [12, 13]
    with pytest.raises(ValueError, match="say what to prune"):
        prune(log)


def test_prune_in_a_loop_while_a_writer_thread_appends(tmp_path: Path) -> None:
    """The lock protocol under contention: a writer rotating and bounding in one thread,
    prune of one vehicle again and again in this one; nothing damaged, nothing of the other
    vehicle lost."""
    log = tmp_path / "log"
    w = ExperienceLog(log, segment_bytes=2500, max_bytes=1 << 20, sync_every=3)
    done = threading.Event()
    errors: list[BaseException] = []

    def append() -> None:
        try:
            for i in range(200):
                w.append(image(i), **fields(i, vehicle="car-x" if i % 2 else "car-y"))
        except BaseException as exc:  # reported below
            errors.append(exc)
        finally:
            done.set()

    t = threading.Thread(target=append)
    t.start()
    while not done.is_set():
        prune(log, vehicle="car-x")
        stats = LogStats()
        list(read_log(log, stats=stats))
        assert stats.damaged == 0
    t.join()
    w.close()
    assert not errors
    prune(log, vehicle="car-x")
    got, stats = read(log)
    assert [r.seq for r in got] == list(range(0, 200, 2))
    assert stats.damaged == stats.torn == 0


#: A writer that appends deterministic records until it is killed or hits its file limit.
WRITER = textwrap.dedent(
    """
    import hashlib, resource, signal, sys
    sys.path.insert(0, sys.argv[2])
    from hmpf.experience_log import ExperienceLog
    from tests.hmpf.test_experience_log import fields, image
    limit = int(sys.argv[3])
    if limit:  # a real write failure part-way, as a full disk gives
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    log = ExperienceLog(sys.argv[1], segment_bytes=1 << 20, max_bytes=1 << 24, sync_every=5)
    failures = 0
    while failures < 3:
        seq = log.next_seq
        try:
            log.append(image(seq, 300 + seq * 97 % 5000), **fields(seq))
        except OSError:
            failures += 1
    print(log.next_seq, flush=True)
    """
)


def _writer(log: Path, limit: int = 0) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", WRITER, str(log), str(ROOT), str(limit)],
        stdout=subprocess.PIPE,
        text=True,
    )


def _intact_prefix(log: Path) -> list[Record]:
    got, stats = read(log)
    assert stats.damaged == 0
    assert [r.seq for r in got] == list(range(len(got))), "a prefix of what was written"
    assert all(r.image == image(r.seq, 300 + r.seq * 97 % 5000) for r in got)
    return got


def test_kill_9_of_a_writer_leaves_an_intact_prefix(tmp_path: Path) -> None:
    log = tmp_path / "log"
    total = 0
    for round_ in range(3):  # three kills at different moments, each writer going on
        start = sum(s.stat().st_size for s in segments(log))
        proc = _writer(log)
        deadline = time.monotonic() + 30
        while sum(s.stat().st_size for s in segments(log)) < start + 30_000:
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.002)
        time.sleep(0.003 * round_)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        got = _intact_prefix(log)
        assert len(got) > total
        total = len(got)
    assert read(log)[1].torn <= 3


def test_a_write_that_fails_part_way_is_taken_back(tmp_path: Path) -> None:
    """A file size limit (RLIMIT_FSIZE) fails a write after part of the frame got out, as a
    full disk does: the partial frame is truncated away, the writer goes on failing cleanly,
    and every record before stays intact."""
    log = tmp_path / "log"
    proc = _writer(log, limit=40_000)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0
    got = _intact_prefix(log)
    assert int(out) == len(got) > 0
    _, stats = read(log)
    assert stats.torn == 0 and stats.damaged == 0
    assert sum(s.stat().st_size for s in segments(log)) <= 40_000


def test_a_killed_prune_leaves_the_segment_whole(tmp_path: Path) -> None:
    """A prune killed after writing its new file but before the rename leaves a .tmp file:
    the segment is still the original, and the next writer or prune clears the .tmp."""
    log = tmp_path / "log"
    written = write(log, 4)
    (seg,) = segments(log)
    shutil.copy(seg, seg.with_name(seg.name + ".tmp"))
    with open(seg.with_name(seg.name + ".tmp"), "r+b") as f:
        f.truncate(100)
    assert read(log)[0] == written
    prune(log, vehicle="nobody")
    assert not list(log.glob("*.tmp"))
    assert os.listdir(log)


def test_the_command_lists_and_prunes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``hmpf-experiences list`` and ``prune`` on a log with two vehicles and a torn tail."""
    log = tmp_path / "log"
    with ExperienceLog(log, segment_bytes=1500, max_bytes=1 << 20) as w:
        for i in range(9):
            w.append(image(i), **fields(i, vehicle="car-a" if i % 3 else ""), received=86400.0 * i)
    last = segments(log)[-1]
    last.write_bytes(last.read_bytes()[:-5])  # the last record torn

    assert experiences_main(["list", str(log)]) == 0
    out = capsys.readouterr().out
    assert f"log {log_id(log)}" in out and "8 records" in out
    assert "torn tails: 1, damaged stretches: 0" in out
    assert re.search(r"^  \(none\) +3 +1970-01-01", out, re.M), out
    assert re.search(r"^  car-a +5 ", out, re.M), out
    assert re.search(r"^  v0001 +3 +Image003.jpg +1$", out, re.M), out
    assert experiences_main(["list", str(log), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["records"] == 8 and summary["torn"] == 1
    assert {k: v["records"] for k, v in summary["vehicles"].items()} == {"": 3, "car-a": 5}
    assert sum(p["records"] for p in summary["places"]) == 8

    assert experiences_main(["prune", str(log), "--vehicle", "car-a", "--dry-run"]) == 0
    assert "would remove 5 records of vehicle 'car-a'; 3 kept" in capsys.readouterr().out
    assert len(read(log)[0]) == 8
    assert experiences_main(["prune", str(log), "--older-than", "4.5"]) == 0  # all received in 1970
    assert "removed 8 records received more than 4.5 days ago; 0 kept" in capsys.readouterr().out
    assert read(log)[0] == []

    assert experiences_main(["list", str(tmp_path)]) == 2
    assert "hmpf-experiences: error:" in capsys.readouterr().err
    assert experiences_main(["prune", str(log), "--older-than", "-1"]) == 2
    assert "--older-than must be" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        experiences_main(["prune", str(log)])  # --vehicle or --older-than is required
