"""Output locations (issue 14): checked before any work, staged and renamed, replaced only when ours.

Every writing command is given an output that is a file, lies under a file, or lies under /proc:
each must exit 2 with one line naming the output, before doing any work, and leave nothing behind.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from supervisor.cli import main
from supervisor.dataset.format import Dataset, DatasetWriter
from supervisor.errors import OutputError
from supervisor.geometry import make_T
from supervisor.outputs import MARKER, StagedOutput, check_location, prepare_incremental, write_atomic
from test_dataset_format import _write


def run(argv: list, capfd) -> tuple[int, str, str]:
    capfd.readouterr()
    rc = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return rc, out, err


def one_error(rc: int, err: str, *needles: str) -> str:
    assert rc == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return _write(tmp_path_factory.mktemp("tiny") / "ds")


BAD = {
    "file": ("a_file", "exists and is not a directory"),
    "under_file": ("a_file/out", "a_file is a file, not a directory"),
    "proc": ("/proc/self/out", "is under /proc"),
}


def _commands(tiny: Path, out: str) -> dict[str, list]:
    return {
        "localize": ["localize", tiny, "-o", out],
        "dataset generate": ["dataset", "generate", out, "--motion", "arc"],
        "dry-run": ["dry-run", "-o", out],
        "dry-run --replay": ["dry-run", "--replay", tiny, "-o", out],
        "demo": ["demo", "-o", out],
        "evaluate": ["evaluate", tiny.parent, "-o", out],
        "benchmark generate": ["benchmark", "generate", out, "--quick"],
    }


@pytest.mark.parametrize("bad", sorted(BAD))
@pytest.mark.parametrize("command", ["localize", "dataset generate", "dry-run", "dry-run --replay", "demo",
                                     "evaluate", "benchmark generate"])
def test_bad_output_location_fails_first(tmp_path, tiny, capfd, command, bad):
    (tmp_path / "a_file").write_text("keep me\n")
    rel, needle = BAD[bad]
    out = rel if rel.startswith("/") else str(tmp_path / rel)
    rc, stdout, err = run(_commands(tiny, out)[command], capfd)
    one_error(rc, err, needle, out)
    assert "localized" not in err and "generating" not in stdout and "dry-run:" not in stdout  # no work done
    assert listing(tmp_path) == ["a_file"] and (tmp_path / "a_file").read_text() == "keep me\n"


@pytest.mark.parametrize("bad", sorted(BAD))
def test_model_build_bad_output(tmp_path, tiny, capfd, bad):
    (tmp_path / "a_file").write_text("keep me\n")
    rel, needle = BAD[bad]
    out = rel if rel.startswith("/") else str(tmp_path / rel)
    if bad == "file":  # a file that is not a target model is never overwritten
        needle = "exists and is not a target model"
    rc, _, err = run(["model", "build", tiny, "-o", out], capfd)
    one_error(rc, err, needle)
    assert (tmp_path / "a_file").read_text() == "keep me\n"


def test_model_build_into_existing_directory_is_a_clear_error(tmp_path, tiny, capfd):
    rc, _, err = run(["model", "build", tiny, "-o", tmp_path], capfd)
    one_error(rc, err, str(tmp_path), "is a directory; give a file name")


def _as_nobody(fn) -> int:
    """Run `fn()` in a forked child as user and group 65534 (nobody), for tests that need an unprivileged user
    while the suite runs as root; its exit status: 0 when `fn` returned, 1 when it raised (anything else: killed
    after 30 s)."""
    import os
    import time

    pid = os.fork()
    if pid == 0:  # the child: drop privileges, run, report by exit status only
        code = 1
        try:
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            fn()
            code = 0
        finally:
            os._exit(code)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        time.sleep(0.02)
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    return -9


def test_unwritable_parent(tmp_path):
    import os
    import tempfile

    def refused() -> None:
        with pytest.raises(OutputError, match="is not writable"):
            check_location(ro / "out", directory=True)

    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            refused()
        finally:
            ro.chmod(0o700)
        return
    # root writes anywhere: the check runs as nobody, in a directory it may enter but not write (under /tmp, since
    # pytest's own tmp_path is private to root)
    top = Path(tempfile.mkdtemp(prefix="supervisor-ro-", dir="/tmp"))
    try:
        top.chmod(0o755)
        ro = top / "ro"
        ro.mkdir(mode=0o755)
        assert _as_nobody(refused) == 0
        assert _as_nobody(lambda: check_location(top / "elsewhere", directory=True)) == 1  # the child does fail
    finally:
        import shutil

        shutil.rmtree(top)


def test_force_never_deletes_a_foreign_directory(tmp_path, capfd):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("surgical notes\n")
    rc, _, err = run(["dataset", "generate", out, "--motion", "arc", "--force"], capfd)
    one_error(rc, err, str(out / "notes.txt"), "was not written by supervisor")
    assert listing(out) == ["notes.txt"] and listing(tmp_path) == ["mine"]


def test_force_on_a_plain_file_refuses_and_leaves_nothing(tmp_path, capfd):
    out = tmp_path / "plain"
    out.write_text("data\n")
    rc, _, err = run(["dataset", "generate", out, "--motion", "arc", "--force"], capfd)
    one_error(rc, err, str(out), "not a directory")
    assert listing(tmp_path) == ["plain"] and out.read_text() == "data\n"  # no .plain.old-PID


def test_overwrite_replaces_only_our_dataset(tmp_path):
    root = _write(tmp_path / "ds")
    info = json.loads((root / MARKER).read_text())
    assert info["command"] == "dataset generate" and set(info["files"]) == {"dataset.json", "frames.csv", "frames",
                                                                           "model"}
    _write_over = lambda: _write_into(DatasetWriter(root, overwrite=True))  # noqa: E731
    _write_over()
    assert Dataset.open(root).frames and listing(tmp_path) == ["ds"]  # nothing left beside it
    (root / "frames" / "extra.png").write_bytes(b"x")  # inside a listed directory: part of our output
    _write_over()
    (root / "notes.txt").write_text("n")
    with pytest.raises(OutputError, match=r"notes.txt: was not written by supervisor"):
        DatasetWriter(root, overwrite=True)
    assert (root / "notes.txt").read_text() == "n" and listing(tmp_path) == ["ds"]


def _write_into(w: DatasetWriter) -> Path:
    T = make_T(np.eye(3), [0.3, 0.0, 0.4])
    img = np.zeros((48, 64), np.uint8)
    for _ in range(2):
        w.add_model_image(img, 0.0, np.zeros(7), T, np.eye(4))
    w.add_frame(img, 0, 0, 0.0, 0.1, np.zeros(7), T, np.eye(4))
    from test_dataset_format import INTR

    return w.finish({"kind": "arc", "intrinsics": INTR.to_dict(), "T_flange_cam": np.eye(4).tolist(),
                     "motion": {"kind": "arc"}})


def test_staged_output_is_atomic_and_cleans_up(tmp_path):
    final = tmp_path / "run"
    with pytest.raises(RuntimeError):
        with StagedOutput(final, "dry-run") as s:
            (s.path / "events.jsonl").write_text("{}\n")
            assert not final.exists()
            raise RuntimeError("boom")
    assert listing(tmp_path) == []  # no partial output, no staging directory
    with StagedOutput(final, "dry-run") as s:
        (s.path / "summary.json").write_text("{}")
    assert listing(final) == [MARKER, "summary.json"]
    with StagedOutput(final, "dry-run") as s:  # a second run replaces the first
        (s.path / "summary.json").write_text("[]")
    assert (final / "summary.json").read_text() == "[]" and listing(tmp_path) == ["run"]
    with pytest.raises(OutputError, match=r"holds the output of `supervisor dry-run`, not of `localize`"):
        StagedOutput(final, "localize")


def test_legacy_output_without_marker_is_replaced_only_if_all_ours(tmp_path):
    old = tmp_path / "dry"
    old.mkdir()
    for name in ("summary.json", "events.jsonl", "timeline.png"):
        (old / name).write_text("old")
    with StagedOutput(old, "dry-run", known=("summary.json", "events.jsonl", "timeline.png")) as s:
        (s.path / "summary.json").write_text("new")
    assert listing(old) == [MARKER, "summary.json"]
    (tmp_path / "empty").mkdir()
    with StagedOutput(tmp_path / "empty", "dry-run"):
        pass


def test_files_appearing_during_the_run_are_never_deleted(tmp_path):
    final = tmp_path / "run"
    with StagedOutput(final, "dry-run") as s:
        (s.path / "a").write_text("1")
    s = StagedOutput(final, "dry-run")
    (final / "user.txt").write_text("mine")
    with pytest.raises(OutputError, match="user.txt: was not written by supervisor"):
        s.commit()
    s.abort()
    assert listing(final) == [MARKER, "a", "user.txt"] and listing(tmp_path) == ["run"]


def test_incremental_output(tmp_path):
    out = prepare_incremental(tmp_path / "ev", "evaluate", known=("cache",))
    assert listing(out) == [MARKER]
    (out / "cache").mkdir()
    (out / "notes.txt").write_text("kept")
    assert prepare_incremental(out, "evaluate") == out  # adds files, never deletes: others may stay
    with pytest.raises(OutputError, match="holds the output of `supervisor evaluate`"):
        prepare_incremental(out, "benchmark generate")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("x")
    with pytest.raises(OutputError, match="thesis.tex: was not written by supervisor"):
        prepare_incremental(foreign, "evaluate", known=("cache",))


def test_dry_run_azimuth_nan_names_the_flag_and_writes_nothing(tmp_path, capfd):
    out = tmp_path / "dr"
    with pytest.raises(SystemExit) as ei:
        main(["dry-run", "--azimuth", "nan", "-o", str(out)])
    assert ei.value.code == 2
    err = capfd.readouterr().err
    assert "argument --azimuth: must be a finite number, got 'nan'" in err
    assert listing(tmp_path) == []


@pytest.mark.parametrize("argv, flag", [
    (["dataset", "generate", "OUT", "--motion", "line", "--offset", "inf"], "--offset"),
    (["dataset", "generate", "OUT", "--motion", "arc", "--azimuth", "-inf"], "--azimuth"),
    (["demo", "-o", "OUT", "--azimuth", "nan"], "--azimuth"),
    (["dataset", "generate", "OUT", "--motion", "line", "--offset", "ten"], "--offset"),
])
def test_non_finite_flags_are_refused(tmp_path, capfd, argv, flag):
    with pytest.raises(SystemExit) as ei:
        main([str(tmp_path / "o") if a == "OUT" else a for a in argv])
    assert ei.value.code == 2
    err = capfd.readouterr().err
    assert f"argument {flag}:" in err and "Traceback" not in err
    assert listing(tmp_path) == []


def test_huge_line_offset_is_a_clear_error(tmp_path, capfd):
    rc, _, err = run(["dataset", "generate", tmp_path / "o", "--motion", "line", "--offset", "1e300"], capfd)
    one_error(rc, err, "offset: must be a finite angle within +-90 deg")
    assert listing(tmp_path) == []


def test_output_directory_gets_the_umask_mode_not_0700(tmp_path):
    import os
    import stat

    old = os.umask(0o022)
    try:
        with StagedOutput(tmp_path / "run", "dry-run") as s:
            (s.path / "a").write_text("1")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "run").stat().st_mode) == 0o755


def test_write_atomic_gives_new_files_the_umask_mode_and_keeps_an_existing_files_mode(tmp_path):
    """A rewritten README or calibration keeps who may read it; a new file gets what open() would give."""
    import os
    import stat

    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "new.yaml", b"a: 1\n")
        kept = tmp_path / "kept.csv"
        kept.write_bytes(b"old\n")
        kept.chmod(0o640)
        write_atomic(kept, b"new\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "new.yaml").stat().st_mode) == 0o644
    assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_bytes() == b"new\n"
    assert listing(tmp_path) == ["kept.csv", "new.yaml"]  # no temporary left beside them
