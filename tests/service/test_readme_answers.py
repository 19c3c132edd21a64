"""The user guide's example answers have the fields of a real answer, and say what a user gets.

The examples (``docs/user-guide.md``, "Answers" and "Sequence mode"; they were the README's
before it became the short guide) are printed by ``bench/readme_answer.py`` (the default preset over
Gardens Point day_right, no calibration step); here a real index and service (the small
service index of the other tests, with the default preset's shipped policy rules applied by
the same code) answer a frame single and in sequence mode, and every field of each
example must be a field of the real answer and the other way round (lists: their first
entry; ``"..."`` stands for the rest).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import load_settings
from tests.service_helpers import ROOT

EXAMPLES = ROOT / "docs" / "user-guide.md"


def examples() -> dict[str, dict[str, Any]]:
    """The user guide's JSON blocks that follow a line naming an answer: ``An answer (...)``
    (single frame) and ``An answer in sequence mode``."""
    text = EXAMPLES.read_text()
    out = {}
    leads = (("single", "An answer (`POST /v1/localize`)"), ("sequence", "An answer in sequence"))
    for key, lead in leads:
        at = text.index(lead)
        block = re.search(r"```json\n(.*?)\n```", text[at:], re.S)
        assert block is not None, f"no JSON block after {lead!r}"
        out[key] = json.loads(block.group(1))
    return out


#: Keys whose entries are method ids (the example's hierarchy is not the test index's).
BY_METHOD = ("scores", "extract_per_method")


def shape(x: Any, path: str = "") -> set[str]:
    """Every key path in ``x`` (lists: their first entry; "..." ignored; the entries of
    :data:`BY_METHOD` not)."""
    keys: set[str] = set()
    if isinstance(x, dict):
        for k, v in x.items():
            if k == "...":
                continue
            keys.add(f"{path}.{k}")
            if k not in BY_METHOD:
                keys |= shape(v, f"{path}.{k}")
    elif isinstance(x, list) and x and x[0] != "...":
        keys |= shape(x[0], f"{path}[]")
    return keys


@pytest.fixture(scope="module")
def answers(service_index: Path, gardens_point: Path) -> dict[str, dict[str, Any]]:
    night = sorted((gardens_point / "night_right").iterdir())
    settings = load_settings(index=str(service_index), auth=False, workers=1)
    with TestClient(create_app(settings)) as c:

        def post(i: int, **data: Any) -> dict[str, Any]:
            f = night[i]
            r = c.post("/v1/localize", files={"image": (f.name, f.read_bytes())}, data=data)
            assert r.status_code == 200, r.text
            return dict(r.json())

        single = post(5)
        seq = post(5, vehicle_id="car-17", timestamp=0.0)
        seq = post(6, vehicle_id="car-17", timestamp=0.1, track=seq["sequence"]["track"])
    return {"single": single, "sequence": seq}


@pytest.mark.parametrize("kind", ["single", "sequence"])
def test_readme_example_has_the_fields_of_a_real_answer(answers, kind: str) -> None:
    example, real = examples()[kind], answers[kind]
    # Fields a real answer omits when empty (a prior, per-method timing of a cached method)
    # are allowed in the example only where the real answer has them too.
    assert shape(example) <= shape(real), sorted(shape(example) - shape(real))
    top = {k for k in real if real[k] is not None}
    assert top <= set(example), sorted(top - set(example))
    m = example["match"]
    assert set(m) == set(real["match"]), "the example's match shows every field"
    assert isinstance(m["accepted"], bool) and m["accepted_by"] in ("p_correct", "quality", "lock")
    if kind == "sequence":
        assert set(example["sequence"]) == set(real["sequence"])


def test_readme_says_what_the_default_preset_answers_out_of_the_box() -> None:
    """The examples are the default preset's (a shipped model: p_correct is a number)."""
    for kind, ex in examples().items():
        assert ex["match"]["accepted_by"] == "p_correct", kind
        assert 0.0 <= ex["match"]["p_correct"] <= 1.0, kind


def test_readme_points_to_the_examples() -> None:
    """The README (the short guide) sends the reader to the page holding the examples."""
    assert "](docs/user-guide.md#answers)" in (ROOT / "README.md").read_text()
