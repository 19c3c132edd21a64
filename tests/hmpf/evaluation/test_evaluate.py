from pathlib import Path

import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.datasets import frame_ground_truth, list_images
from hmpf.errors import ImageError
from hmpf.evaluation.evaluate import EvalData, evaluate, pr_curve, recall_at_n
from hmpf.features import FeatureCache, extract_images, file_digest
from hmpf.methods import create_method


def test_recall_at_n_ties_and_missing_ground_truth():
    scores = np.array([[0.1, 0.9, 0.5, 0.9], [0.3, 0.2, 0.1, 0.0]])
    gt = np.array([[0, 0, 0, 1], [0, 0, 0, 0]], bool)
    # Query 0: the tie at 0.9 goes to index 1 first, so its match (3) ranks second.
    assert recall_at_n(scores, gt, (1, 2, 4)) == {1: 0.0, 2: 0.5, 4: 0.5}
    # Distances: lower is better.
    assert recall_at_n(-scores, gt, (1, 2), higher_is_better=False) == {1: 0.0, 2: 0.5}


def test_pr_curve_hand_computed():
    correct = np.array([True, True, False, True])
    quality = np.array([3.0, 0.2, 1.0, np.nan])
    pr = pr_curve(correct, quality)
    # theta = 0: TP 2, FP 1 -> P 2/3, R 2/4; theta = 0.5: TP 1, FP 1 -> P 1/2, R 1/4;
    # theta = 1 .. 2.5: TP 1, FP 0 -> P 1, R 1/4; theta >= 3: nothing predicted -> P NaN.
    assert pr["precision"][0] == pytest.approx(2 / 3)
    assert pr["precision"][1] == pytest.approx(0.5)
    assert pr["precision"][2:6] == [1.0] * 4
    assert pr["precision"][6] is None
    assert pr["recall"][:7] == pytest.approx([0.5, 0.25, 0.25, 0.25, 0.25, 0.25, 0.0])
    # AUC: reversed curve R = [0, .25 x5, .5], P = [1 x5, .5, 2/3]:
    # 0.25 * 1 + 0.25 * (0.5 + 2/3) / 2 = 0.3958333
    assert pr["auc"] == pytest.approx(0.25 + 0.25 * (0.5 + 2 / 3) / 2)
    assert pr["max_f1"] == pytest.approx(4 / 7)
    assert pr["recall_at_100_precision"] == pytest.approx(0.25)


def test_pr_curve_all_wrong():
    pr = pr_curve(np.array([False, False]), np.array([5.0, 6.0]))
    assert pr["recall_at_100_precision"] == 0.0
    assert pr["max_f1"] == 0.0


def test_cache_reuses_and_invalidates(tmp_path: Path, image_folder):
    folder = image_folder("refs", 4)
    paths = list_images(folder)
    cache = FeatureCache(tmp_path / "cache")
    hog = {"hog": create_method("hog")}
    first = extract_images(paths, hog, cache=cache, workers=1)
    assert first.cached == {"hog": 0}
    second = extract_images(paths, hog, cache=cache, workers=1)
    assert second.cached == {"hog": 4}
    np.testing.assert_array_equal(np.stack(first.features["hog"]), np.stack(second.features["hog"]))
    # The extraction time stored with the entry comes back with it.
    np.testing.assert_array_equal(first.ms["hog"], second.ms["hog"])
    # A different method config is a different cache key.
    other = extract_images(
        paths, {"hog": create_method("hog", {"cell_size": 50})}, cache=cache, workers=1
    )
    assert other.cached == {"hog": 0}
    assert other.features["hog"][0].shape != first.features["hog"][0].shape
    # Changing an image's content invalidates that image only.
    paths[0].write_bytes(paths[1].read_bytes())
    third = extract_images(paths, hog, cache=cache, workers=1)
    assert third.cached == {"hog": 4}  # image 0 now has image 1's content, which is cached
    np.testing.assert_array_equal(third.features["hog"][0], first.features["hog"][1])
    # A corrupt entry is recomputed, not trusted.
    digest = file_digest(paths[2])
    entry = tmp_path / "cache" / hog["hog"].cache_key() / digest[:2] / f"{digest}.npz"
    entry.write_bytes(b"garbage")
    fourth = extract_images(paths, hog, cache=cache, workers=1)
    assert fourth.cached == {"hog": 3}
    np.testing.assert_array_equal(fourth.features["hog"][2], first.features["hog"][2])


def test_local_features_roundtrip_through_cache(tmp_path: Path, image_folder):
    paths = list_images(image_folder("refs", 2))
    cache = FeatureCache(tmp_path / "cache")
    kaze = {"kaze": create_method("kaze")}
    a = extract_images(paths, kaze, cache=cache, workers=1)
    b = extract_images(paths, kaze, cache=cache, workers=1)
    assert b.cached == {"kaze": 2}
    for fa, fb in zip(a.features["kaze"], b.features["kaze"], strict=True):
        assert len(fa) > 0
        np.testing.assert_array_equal(fa.descriptors, fb.descriptors)
        np.testing.assert_array_equal(fa.keypoints, fb.keypoints)


@pytest.mark.parametrize("workers", [1, 2])
def test_unreadable_image_is_named(tmp_path: Path, image_folder, workers: int):
    folder = image_folder("refs", 3)
    (folder / "img001.png").write_bytes(b"not a png")
    with pytest.raises(ImageError, match="img001.png"):
        extract_images(list_images(folder), {"sad": create_method("sad")}, workers=workers)


def test_evaluate_on_synthetic_identical_sets(tmp_path: Path, image_folder):
    # Query images identical to the references: every method and the hierarchy find them.
    refs = list_images(image_folder("refs", 8, seed=0))
    qrys = list_images(image_folder("qrys", 8, seed=0))
    cfg = parse_config(
        {
            "tiers": [{"methods": ["gist", "sad"], "k": 3}, {"methods": ["hog", "kaze"], "k": 1}],
        }
    )
    report = evaluate(
        cfg, EvalData(refs, qrys, frame_ground_truth(8, 8, 0), "frames +-0"), cache=None, workers=1
    )
    for mid in ("gist", "sad", "hog", "kaze"):
        assert report["methods"][mid]["recall_at"]["1"] == 1.0
    h = report["hierarchy"]
    assert h["combined_recall_at_1"] == 1.0
    assert h["flat_recall_at_1"] == 1.0
    assert h["matches"] == list(range(8))
    assert [t["recall"] for t in h["tiers"]] == [1.0, 1.0]
    assert set(report["timing_ms"]["extract_per_image"]) == {"gist", "sad", "hog", "kaze"}


def test_evaldata_frames_reads_two_aligned_traverses(gardens_point: Path):
    data = EvalData.frames(gardens_point / "day_left", gardens_point / "night_right", 3)
    assert data.reference == list_images(gardens_point / "day_left")
    assert data.query == list_images(gardens_point / "night_right")
    np.testing.assert_array_equal(data.gt, frame_ground_truth(200, 200, 3))
    assert data.ground_truth == "frames +-3"


def test_hmpf_eval_cli_help_version_and_ctrl_c(monkeypatch, capsys, tmp_path: Path, image_folder):
    from hmpf.cli import eval as cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    out = capsys.readouterr().out
    assert exc.value.code == 0 and "experiments" in out and "--config" in out
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("hmpf-eval (hmpf ")
    with pytest.raises(SystemExit) as exc:
        cli.main(["--config", "x.yaml", "--reference", str(tmp_path)])  # no --query
    assert exc.value.code == 2 and "--query is required" in capsys.readouterr().err

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    # The command imports these when it runs (so that --help stays light): patch their homes.
    monkeypatch.setattr("hmpf.evaluation.evaluate.evaluate", interrupted)
    config = parse_config({"tiers": [{"methods": ["sad"], "k": 1}]})
    monkeypatch.setattr("hmpf.config.load_config", lambda path: config)
    folder = str(image_folder("refs", 2))
    argv = ["--config", "x.yaml", "--reference", folder, "--query", folder, "--no-cache"]
    assert cli.main(argv) == 130
    assert capsys.readouterr().err == "hmpf-eval: interrupted\n"
