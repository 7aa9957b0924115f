"""Killing a command that runs a worker pool ends its workers too (no orphans left rendering on the machine).

Each command is started in its own session, its pool workers found by parent pid, the command SIGKILLed
(no handler can run), then every worker must be gone. Whatever survives is killed by pid at the end.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUPERVISOR = str(Path(sys.executable).with_name("supervisor"))


def children(pid: int) -> set[int]:
    """The live processes whose parent is `pid` (from /proc)."""
    out = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) "
            if int(fields[1]) == pid and fields[0] != "Z":
                out.add(int(d.name))
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return state[state.rindex(")") + 2] != "Z"


@pytest.mark.parametrize("command", [
    pytest.param(lambda out: [SUPERVISOR, "benchmark", "generate", str(out), "--quick", "--jobs", "2"],
                 id="benchmark-generate"),
    pytest.param(lambda out: [sys.executable, str(ROOT / "benchmarks" / "dryrun_trials.py"), "--jobs", "2",
                              "--scenes", "box_foam", "--modes", "stop_and_go", "-o", str(out)],
                 id="dryrun-trials"),
])
def test_workers_end_with_a_killed_parent(tmp_path, command):
    proc = subprocess.Popen(command(tmp_path / "out"), cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and proc.poll() is None:
            workers = children(proc.pid)
            if len(workers) >= 2:
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert len(workers) >= 2, f"no pool after 90 s: {workers}"
        time.sleep(1.0)  # the workers are past their initializer and working
        workers = children(proc.pid)
        proc.kill()
        proc.wait(10)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and any(alive(w) for w in workers):
            time.sleep(0.1)
        assert not [w for w in workers if alive(w)], "workers outlived their killed parent"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        for w in workers:
            if alive(w):
                os.kill(w, signal.SIGKILL)
        proc.stderr.close()
