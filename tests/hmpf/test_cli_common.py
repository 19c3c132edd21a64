"""hmpf.cli.common: what every command does on --version, errors, Ctrl-C and a closed pipe."""

from __future__ import annotations

import subprocess
import sys

import pytest

from hmpf.cli.common import EXIT_BROKEN_PIPE, EXIT_ERROR, EXIT_INTERRUPTED, run
from hmpf.errors import HmpfError


def test_run_maps_errors_and_ctrl_c(capsys: pytest.CaptureFixture[str]) -> None:
    def fail() -> int:
        raise HmpfError("no such index")

    def interrupt() -> int:
        raise KeyboardInterrupt

    assert run("hmpf-x", lambda: 0) == 0
    assert run("hmpf-x", fail) == EXIT_ERROR
    assert run("hmpf-x", interrupt, interrupted="stopped; nothing written") == EXIT_INTERRUPTED
    err = capsys.readouterr().err.splitlines()
    assert err == ["hmpf-x: error: no such index", "hmpf-x: stopped; nothing written"]


def test_closed_pipe_is_a_quiet_exit_not_a_traceback() -> None:
    """Like ``hmpf-index info --names | head -1``: the reader leaves after one line."""
    code = (
        "import sys\n"
        "from hmpf.cli.common import run\n"
        "def body():\n"
        "    for i in range(10**6):\n"
        "        print('reference', i)\n"
        "    return 0\n"
        "sys.exit(run('hmpf-x', body))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    assert proc.stdout.readline() == b"reference 0\n"
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == EXIT_BROKEN_PIPE
    assert "Traceback" not in err and "Exception ignored" not in err, err


@pytest.mark.parametrize(
    "module",
    [
        "hmpf.cli.eval",
        "hmpf.cli.calibrate",
        "hmpf.cli.experiments",
        "hmpf.cli.replay",
        "indexer.cli",
        "service.cli",
    ],
)
def test_command_modules_import_no_heavy_modules(module: str) -> None:
    """Ctrl-C while numpy/OpenCV/h5py/FAISS/torch/scipy load must also be one line and exit
    130, so every command loads them inside ``run``; --help and --version stay instant."""
    heavy = {"numpy", "cv2", "h5py", "faiss", "torch", "scipy"}
    code = f"import sys, {module}; print(sorted({heavy!r} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
