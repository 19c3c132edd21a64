"""bench/cnn_batch.py's timing helper: every run size covers every image, the first round is
not counted, and the figure is per image."""

from __future__ import annotations

from typing import Any

import numpy as np

from bench import cnn_batch


class Recording:
    """A session that records the batch sizes it is run on."""

    def __init__(self) -> None:
        self.batches: list[int] = []

    def run(self, layers: list[str], feeds: dict[str, Any]) -> list[Any]:
        self.batches.append(len(feeds[cnn_batch.INPUT]))
        return [np.zeros(1) for _ in layers]


def test_per_image_ms_runs_each_size_over_every_image() -> None:
    session = Recording()
    x = np.zeros((8, 3, 4, 4), np.float32)
    ms = cnn_batch.per_image_ms(session, ["head"], x, [1, 4, 8], rounds=3)
    assert sorted(ms) == [1, 4, 8] and all(v >= 0 for v in ms.values())
    one_round = [1] * 8 + [4] * 2 + [8]
    assert session.batches == one_round * 3  # interleaved, three rounds (the first: warm-up)
