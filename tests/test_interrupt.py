"""Ctrl-C in the middle of a run: exit code 130, one line, no traceback, and
nothing written, neither the model nor a staging folder beside it, and no
worker left behind (issue 29)."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(
    not Path("/proc/self/stat").exists(), reason="reads processes from /proc (Linux)"
)

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


def _running_in_group(pgid: int) -> list[int]:
    """Processes of group ``pgid`` still running (zombies left to an init
    that does not reap them, as in some containers, do not count)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # it has just exited
        state, pgrp = fields[0], int(fields[2])
        if pgrp == pgid and state not in ("Z", "X"):
            found.append(int(stat.parent.name))
    return found


def _default_sigint() -> None:
    """In the child before it starts: SIGINT at its default, as a terminal's
    shell starts a foreground job. A runner started in the background of a
    non-interactive shell ignores SIGINT, and an ignored signal stays ignored
    across exec (Python then installs no KeyboardInterrupt handler)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _lines(stream, out: queue.Queue) -> None:
    for line in stream:
        out.put(line)
    out.put(None)


@pytest.mark.slow
@pytest.mark.parametrize(
    "when",
    [
        "cameras, map:",  # the per-image stages start (2 workers)
        "Creating SIFT CPU feature extractor",  # the tie points' features
    ],
)
def test_ctrl_c_mid_run_leaves_nothing(tmp_path, when):
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "obliq_colmap", "register",
            "--image_path", str(SAMPLE / "images"),
            "--cadastre_path", str(SAMPLE / "cadastre.geojson"),
            "--input_path", str(SAMPLE / "priors"),
            "--output_path", str(out),
            "--num_workers", "2",
            "--no_progress",
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own process group, as a shell job
        preexec_fn=_default_sigint,
    )  # fmt: skip
    try:
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=_lines, args=(proc.stderr, lines), daemon=True).start()
        seen, deadline = [], time.monotonic() + 120
        while time.monotonic() < deadline:
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            if line is None:
                break
            seen.append(line)
            if when in line:
                break
        assert seen and when in seen[-1], "".join(seen[-20:])
        time.sleep(1.0)  # well inside the stage
        os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C: the whole group
        assert proc.wait(timeout=60) == 130
        rest = []
        while (line := lines.get(timeout=10)) is not None:
            rest.append(line)
    finally:
        if proc.poll() is None:  # a failed check: leave nothing running
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
    tail = "".join(rest)
    assert "interrupted" in tail
    assert "Traceback" not in tail, tail
    assert [p.name for p in tmp_path.iterdir()] == []  # no model, no staging
    deadline = time.monotonic() + 10  # multiprocessing's helpers exit on EOF
    while _running_in_group(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _running_in_group(proc.pid) == []  # no worker outlives the run
