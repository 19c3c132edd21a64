"""Service settings (environment, file, flags; unknown names are errors) and API key files."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from hmpf.errors import ConfigError
from service.auth import KeyStore, add_key, hash_key
from service.cli import main as serve_main
from service.settings import load_settings


def test_precedence_flags_env_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    f = tmp_path / "hmpf.yaml"
    f.write_text("index: /srv/idx\nport: 9001\nworkers: 3\nauth: false\nqueue: 4\n")
    s = load_settings(f)
    assert (s.index, s.port, s.workers, s.queue, s.auth) == (Path("/srv/idx"), 9001, 3, 4, False)
    monkeypatch.setenv("HMPF_PORT", "9002")
    monkeypatch.setenv("HMPF_SETTINGS_FILE", str(f))
    assert load_settings().port == 9002  # env over file (file named by the environment)
    assert load_settings(port=9003).port == 9003  # flags over env
    assert load_settings(port=None).port == 9002  # unset flags do not count


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("prot: 80\n", "unknown setting 'prot' (did you mean 'port'?)"),
        ("port: high\n", "port"),
        ("- a\n- b\n", "mapping"),
        ("port: [\n", "invalid YAML"),
    ],
)
def test_bad_settings_file(tmp_path: Path, text: str, needle: str) -> None:
    f = tmp_path / "s.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=None) as err:
        load_settings(f, auth=False)
    assert needle in str(err.value)


def test_unknown_environment_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HMPF_WORKRES", "2")
    with pytest.raises(ConfigError, match="HMPF_WORKRES.*did you mean 'workers'"):
        load_settings(auth=False)
    monkeypatch.delenv("HMPF_WORKRES")
    monkeypatch.setenv("HMPF_CACHE_DIR", "/tmp/x")  # the core's own variables are fine
    monkeypatch.setenv("HMPF_CNN_RUNTIME", "torch")
    assert load_settings(auth=False).port == 8000


def test_auth_needs_keys_file_or_explicit_off(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="HMPF_AUTH=false"):
        load_settings()
    s = load_settings(keys_file=tmp_path / "k.yaml")
    assert s.auth is True
    with pytest.raises(ConfigError, match="max_upload_bytes"):
        load_settings(auth=False, max_upload_bytes=10)


def test_threads_do_not_oversubscribe(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("os.cpu_count", lambda: 8)
    assert load_settings(auth=False).worker_count == 8
    s = load_settings(auth=False, workers=2)
    assert (s.worker_count, s.thread_count) == (2, 4)
    assert load_settings(auth=False, workers=16).thread_count == 1
    assert load_settings(auth=False, workers=2, threads_per_worker=3).thread_count == 3


def test_keys_file_roundtrip_and_checks(tmp_path: Path) -> None:
    path = tmp_path / "keys.yaml"
    car = add_key(path, "car-17", "vehicle")
    ops = add_key(path, "ops", "admin")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    text = path.read_text()
    assert car not in text and ops not in text and hash_key(car) in text
    store = KeyStore.load(path)
    assert store.check(car).name == "car-17" and store.check(ops).role == "admin"
    assert store.check(None) is None and store.check("") is None
    assert store.check(car[:-1]) is None and store.check(car + "x") is None
    assert store.check(car).allows("vehicle") and not store.check(car).allows("admin")
    assert store.check(ops).allows("vehicle") and store.check(ops).allows("admin")
    with pytest.raises(ConfigError, match="exists already"):
        add_key(path, "car-17", "vehicle")
    with pytest.raises(ConfigError, match="role"):
        add_key(path, "x", "root")


def test_a_key_never_reads_as_an_option(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A random key starting with ``-`` (one in 64) would be taken for an option by a command
    line (``hmpf-replay --key -X...``): such a draw is replaced by the next one."""
    import secrets

    draws = iter(["-first", "--second", "third"])
    monkeypatch.setattr(secrets, "token_urlsafe", lambda n: next(draws))
    key = add_key(tmp_path / "keys.yaml", "car", "vehicle")
    assert key == "third"
    assert KeyStore.load(tmp_path / "keys.yaml").check("third").name == "car"


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("keys: [{name: a, role: vehicle}]\n", "name, role and sha256"),
        ("keys: [{name: a, role: boss, sha256: " + "0" * 64 + "}]\n", "role 'boss'"),
        ("keys: [{name: a, role: admin, sha256: abc}]\n", "64 lower-case hex"),
        ("users: []\n", "one key, 'keys'"),
    ],
)
def test_bad_keys_file(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "keys.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        KeyStore.load(path)
    assert needle in str(err.value)


def test_keys_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "keys.yaml"
    assert serve_main(["keys", "add", "--file", str(path), "--name", "bus-3"]) == 0
    key = capsys.readouterr().out.strip()
    assert len(key) >= 40 and KeyStore.load(path).check(key).name == "bus-3"
    assert serve_main(["keys", "add", "--file", str(path), "--name", "ops", "--role", "admin"]) == 0
    capsys.readouterr()
    assert serve_main(["keys", "list", "--file", str(path)]) == 0
    assert capsys.readouterr().out.splitlines() == ["bus-3\tvehicle", "ops\tadmin"]
    assert serve_main(["keys", "add", "--file", str(path), "--name", "bus-3"]) == 2
    assert "exists already" in capsys.readouterr().err


def test_serve_cli_fails_cleanly(tmp_path: Path, capsys, monkeypatch) -> None:
    assert serve_main(["--index", str(tmp_path)]) == 2  # auth on, no keys file
    assert "HMPF_AUTH=false" in capsys.readouterr().err
    monkeypatch.setenv("HMPF_AUTH", "false")
    rc = serve_main(["--index", str(tmp_path / "none")])
    err = capsys.readouterr().err
    assert rc == 2 and "hmpf-serve: error:" in err and "none" in err and "Traceback" not in err


def test_serve_cli_help_lists_the_keys_command_and_version_exits_0(capsys) -> None:
    with pytest.raises(SystemExit) as done:
        serve_main(["--help"])
    out = capsys.readouterr().out
    assert done.value.code == 0
    assert "keys" in out and "--index" in out and "--port" in out
    with pytest.raises(SystemExit) as done:
        serve_main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith("hmpf-serve (hmpf ")
    # the old form of the keys command still works, and so does the serving form's parser
    with pytest.raises(SystemExit) as done:
        serve_main(["keys", "--help"])
    assert done.value.code == 0 and "add" in capsys.readouterr().out


def test_thread_limit_reaches_faiss() -> None:
    """FAISS's OpenMP pool is capped at the worker's threads like the BLAS pools."""
    import faiss

    from service.app import _limit_threads

    before = faiss.omp_get_max_threads()
    try:
        _limit_threads(1)
        assert faiss.omp_get_max_threads() == 1
        _limit_threads(2)
        assert faiss.omp_get_max_threads() == 2
    finally:
        faiss.omp_set_num_threads(before)


def test_approx_k_reaches_the_reader(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``approx_k`` (environment or flag) is what the engine's reader re-scores."""
    from hmpf.config import parse_config
    from indexer.build import BuildOptions, build
    from service.engine import Engine
    from tests.conftest import SERVICE_CONFIG, write_synthetic_images

    refs = write_synthetic_images(tmp_path / "refs", 4)
    build(
        parse_config(SERVICE_CONFIG),
        refs,
        tmp_path / "index",
        options=BuildOptions(workers=1, progress=False),
    )
    monkeypatch.setenv("HMPF_APPROX_K", "1024")
    s = load_settings(auth=False, index=tmp_path / "index")
    assert s.approx_k == 1024
    for want, k in ((1024, s.approx_k), (256, None)):
        engine = Engine(s.index, workers=1, queue=1, threads_per_worker=1, approx_k=k)
        try:
            assert engine.load().reader.approx_k == want
        finally:
            engine.close()
    with pytest.raises(ConfigError):
        load_settings(auth=False, approx_k=0)


def test_faiss_params_reach_the_reader(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``faiss_params`` (environment as JSON, or file) is set on the version's FAISS indexes
    on top of its stored parameters; a method or parameter the version cannot take stops
    the start with a clear error (exit 2, no traceback) and leaves nothing open."""
    from hmpf.config import parse_config
    from hmpf.index.ann import faiss_module
    from hmpf.index.layout import IndexBuildError
    from indexer.build import BuildOptions, build
    from service.engine import Engine
    from tests.conftest import SERVICE_CONFIG, write_synthetic_images

    refs = write_synthetic_images(tmp_path / "refs", 12)
    opts = BuildOptions(workers=1, progress=False, faiss={"*": "PCA8:2,SQfp16,k2"})
    build(parse_config(SERVICE_CONFIG), refs, tmp_path / "index", options=opts)
    monkeypatch.setenv("HMPF_FAISS_PARAMS", '{"*": "k_factor_rf=5", "gist": "k_factor_rf=3"}')
    s = load_settings(auth=False, index=tmp_path / "index")
    assert s.faiss_params == {"*": "k_factor_rf=5", "gist": "k_factor_rf=3"}
    faiss = faiss_module()
    engine = Engine(s.index, workers=1, queue=1, threads_per_worker=1, faiss_params=s.faiss_params)
    try:
        reader = engine.load().reader
        for mid, want in (("hog", 5.0), ("gist", 3.0)):
            refine = faiss.downcast_index(faiss.downcast_index(reader.faiss_index(mid)).index)
            assert refine.k_factor == want
    finally:
        engine.close()
    from hmpf.index.reader import IndexReader

    closed: list[Path] = []
    close = IndexReader.close

    def counted(reader: IndexReader) -> None:
        closed.append(reader.path)
        close(reader)

    monkeypatch.setattr(IndexReader, "close", counted)
    for bad, error in (
        ({"sad": "k_factor_rf=2"}, ConfigError),
        ({"*": "nprobe=x"}, IndexBuildError),
    ):
        engine = Engine(s.index, workers=1, queue=1, threads_per_worker=1, faiss_params=bad)
        try:
            with pytest.raises(error):
                engine.load()
            assert not engine.ready and len(closed) == 1  # the reader it opened, closed
            closed.clear()
        finally:
            engine.close()
    monkeypatch.setenv("HMPF_FAISS_PARAMS", '{"*": "k_factor_front=2"}')
    monkeypatch.setenv("HMPF_AUTH", "false")

    def serving(*_: object) -> int:  # a failure, not a server that never returns
        raise AssertionError("hmpf-serve started with parameters its index cannot take")

    monkeypatch.setattr("service.cli._run_server", serving)
    rc = serve_main(["--index", str(tmp_path / "index")])
    err = capsys.readouterr().err
    assert rc == 2 and "k_factor_front" in err and "a scan in front" in err
    assert "Traceback" not in err
    # A new version the parameters do not fit (an exact tier 1 has no "gist" to set): the
    # reload fails and the loaded version stays.
    engine = Engine(s.index, workers=1, queue=1, threads_per_worker=1, faiss_params=s.faiss_params)
    try:
        assert engine.load().version == "v0001"
        build(
            parse_config(SERVICE_CONFIG),
            refs,
            tmp_path / "index",
            options=BuildOptions(workers=1, progress=False),
        )
        with pytest.raises(ConfigError, match="'gist' not an approximate"):
            engine.load()
        assert engine.current.version == "v0001"
    finally:
        engine.close()
    monkeypatch.setenv("HMPF_FAISS_PARAMS", '["k_factor_rf=2"]')
    with pytest.raises(ConfigError, match="faiss_params"):
        load_settings(auth=False, index=tmp_path / "index")
