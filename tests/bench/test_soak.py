"""bench/soak.py's judgement of resident memory: the floor of the last minutes against the
first minute, on synthetic samples shaped like a real run (reload peaks while the old version
is held for its background check)."""

from __future__ import annotations

from bench.soak import Log, summary


def samples(floor_step: float) -> list[tuple[float, float, int]]:
    """Every 5 s for 10 minutes: a warm level of 800 MiB, a second version held for 100 s
    after each reload at 2, 4, 6 and 8 minutes; the level between reloads rises by
    ``floor_step`` MiB per reload (a leak) or not."""
    out = []
    for i in range(121):
        t = 5.0 * i
        reloads = [r for r in (120, 240, 360, 480) if r <= t]
        level = 800.0 + floor_step * len(reloads)
        held = sum(1 for r in reloads if r <= t < r + 100)
        out.append((t, level + 380.0 * held, 26))
    return out


def test_reload_peaks_are_not_a_leak_and_a_rising_floor_is() -> None:
    log = Log()
    log.add("vehicle", 200, 100.0)
    calm = summary(log, samples(0.0), 600.0, True, 1)["rss_mib"]
    assert calm["floor_growth"] == 0.0
    assert calm["growth_first_to_last_minute"] > 150  # the old median rule failed this run
    assert calm["peak"] == 800.0 + 380.0
    leak = summary(log, samples(60.0), 600.0, True, 1)["rss_mib"]
    assert leak["floor_growth"] >= 180.0  # three reloads inside the 4-minute window's floor
    assert (
        summary(log, samples(0.0), 600.0, True, 1, floor_minutes=1.0)["rss_mib"]["floor_minutes"]
        == 1.0
    )
