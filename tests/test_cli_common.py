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
