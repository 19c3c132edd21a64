from pathlib import Path

import pytest

import hmpf
from hmpf.config import build_methods, load_config, parse_config, preset_names
from hmpf.errors import ConfigError, UnknownMethodError

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
PRESETS = Path(hmpf.__file__).parent / "presets"


@pytest.mark.parametrize("name", preset_names())
def test_shipped_presets_validate(name: str):
    cfg = load_config(name)
    methods = build_methods(cfg)
    assert set(methods) == set(cfg.method_ids)
    assert len(cfg.tier_weights) == len(cfg.tiers)


def test_configs_folder_is_the_packaged_presets():
    """``configs/`` (browsing, documented paths) and the package data are one folder, and
    every YAML file in it is a preset named by its relative path."""
    assert CONFIGS.resolve() == PRESETS.resolve()
    names = sorted(str(p.relative_to(CONFIGS).with_suffix("")) for p in CONFIGS.rglob("*.yaml"))
    assert names == preset_names()
    assert {"default", "handcrafted", "calibration-pool", "calibrated/gp_dr_nr"} <= set(
        preset_names()
    )


def test_preset_by_name_equals_the_file_from_any_folder(tmp_path: Path, monkeypatch):
    by_path = load_config(CONFIGS / "calibrated" / "gp_dr_nr.yaml")
    monkeypatch.chdir(tmp_path)
    for name in ("calibrated/gp_dr_nr", "calibrated/gp_dr_nr.yaml"):
        assert load_config(name) == by_path
    assert load_config("handcrafted").digest() == load_config(CONFIGS / "handcrafted.yaml").digest()


def test_an_existing_file_wins_over_a_preset_of_that_name(tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("handcrafted").write_text("name: mine\ntiers: [{methods: [hog], k: 1}]\n")
    assert load_config("handcrafted").name == "mine"


def test_unknown_name_or_missing_path_lists_the_presets(tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="neither a file nor a preset; presets: .*handcrafted"):
        load_config("handcrafed")
    with pytest.raises(ConfigError, match="no such file; presets: .*calibrated/gp_dr_nr"):
        load_config("configs/handcrafted.yaml")
    with pytest.raises(ConfigError, match="not a file"):
        load_config(tmp_path)


def test_calibration_pool_default_is_a_preset(tmp_path: Path, monkeypatch):
    from hmpf.cli.calibrate import build_parser

    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(["--reference", "r", "--query", "q", "--out", "o"])
    assert load_config(args.pool) == load_config(CONFIGS / "calibration-pool.yaml")


def test_handcrafted_is_three_tiers_of_the_four_methods():
    cfg = load_config(CONFIGS / "handcrafted.yaml")
    assert len(cfg.tiers) == 3
    assert set(cfg.method_ids) == {"hog", "gist", "sad", "kaze"}
    assert cfg.tier_weights == (0.5, 0.75, 1.0)


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return p


def test_unknown_top_level_key_is_named(tmp_path: Path):
    p = _write(tmp_path, "tiers: [{methods: [hog], k: 1}]\ntiers_typo: 3\n")
    with pytest.raises(ConfigError, match="unknown key 'tiers_typo'"):
        load_config(p)


def test_unknown_tier_key_is_named(tmp_path: Path):
    p = _write(tmp_path, "tiers: [{methods: [hog], k: 1, kk: 2}]\n")
    with pytest.raises(ConfigError, match="tiers.0.kk"):
        load_config(p)


def test_unknown_method_parameter_is_named(tmp_path: Path):
    p = _write(tmp_path, "methods: {kaze: {max_keypoint: 5}}\ntiers: [{methods: [kaze], k: 1}]\n")
    with pytest.raises(ConfigError, match="max_keypoint"):
        load_config(p)


def test_unknown_method_lists_valid_names():
    with pytest.raises(UnknownMethodError, match="available methods: .*gist.*hog"):
        parse_config({"tiers": [{"methods": ["hogg"], "k": 1}]})


def test_invalid_values():
    with pytest.raises(ConfigError, match="k"):
        parse_config({"tiers": [{"methods": ["hog"], "k": 0}]})
    with pytest.raises(ConfigError, match="weights"):
        parse_config({"tiers": [{"methods": ["hog"], "k": 1}], "weights": [1, 2]})
    with pytest.raises(ConfigError, match="explicit weights"):
        parse_config({"tiers": [{"methods": ["hog"], "k": 5}] * 4})
    with pytest.raises(ConfigError, match="twice"):
        parse_config({"tiers": [{"methods": ["hog", "hog"], "k": 1}]})
    with pytest.raises(ConfigError, match="mode"):
        parse_config({"mode": "exact", "tiers": [{"methods": ["hog"], "k": 1}]})
    with pytest.raises(ConfigError, match="used by no tier"):
        parse_config({"methods": {"gist": {}}, "tiers": [{"methods": ["hog"], "k": 1}]})


def test_bad_yaml_and_missing_file(tmp_path: Path):
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config(_write(tmp_path, "tiers: [\n"))
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(_write(tmp_path, "- 1\n- 2\n"))


def test_method_alias_with_type_allows_two_settings_of_one_method():
    cfg = parse_config(
        {
            "methods": {"kaze_fast": {"type": "kaze", "max_keypoints": 100}},
            "tiers": [{"methods": ["kaze_fast"], "k": 5}, {"methods": ["kaze"], "k": 1}],
        }
    )
    m = build_methods(cfg)
    assert m["kaze_fast"].config.max_keypoints == 100
    assert m["kaze"].config.max_keypoints == 500
    assert m["kaze_fast"].cache_key() != m["kaze"].cache_key()


def test_digest_is_stable_and_sensitive():
    a = parse_config({"tiers": [{"methods": ["hog"], "k": 1}]})
    b = parse_config({"tiers": [{"methods": ["hog"], "k": 1}]})
    c = parse_config({"tiers": [{"methods": ["hog"], "k": 2}]})
    assert a.digest() == b.digest() != c.digest()


def test_tier_score_is_validated_and_max_keeps_the_old_digest():
    base = {"tiers": [{"methods": ["hog"], "k": 5}, {"methods": ["gist"], "k": 1}]}
    plain = parse_config(base)
    assert plain.tier_score == "max"
    assert parse_config({**base, "tier_score": "max"}).digest() == plain.digest()
    assert parse_config({**base, "tier_score": "mean"}).digest() != plain.digest()
    with pytest.raises(ConfigError, match="tier_score"):
        parse_config({**base, "tier_score": "median"})


def test_acceptance_is_validated_and_left_out_of_the_digest():
    base = {"tiers": [{"methods": ["hog"], "k": 1}]}
    plain = parse_config(base)
    with_acc = parse_config({**base, "acceptance": {"threshold": 2.2, "precision": 0.99}})
    assert plain.acceptance is None and with_acc.acceptance.threshold == 2.2
    assert plain.digest() == with_acc.digest()
    with pytest.raises(ConfigError, match="precision"):
        parse_config({**base, "acceptance": {"threshold": 2.2, "precision": 1.5}})
    with pytest.raises(ConfigError, match="thresh"):
        parse_config({**base, "acceptance": {"thresh": 2.2}})
