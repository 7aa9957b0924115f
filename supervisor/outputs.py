"""Output locations: checked before any work, written through a staging sibling, replaced only when ours.

Every command that writes calls this module first, so a bad `-o` fails in a line before a
frame is rendered or localized:

- `check_location`: the nearest existing ancestor is a writable directory (not a file), the
  path is not under /proc, /sys or /dev, and an existing path is of the expected kind.
- `StagedOutput`: a directory output built in `.NAME.partial-XXXX` next to it and renamed into
  place on success (removed on failure), so a reader never sees half an output. Each output
  directory carries a marker (`MARKER`: the command and the files it wrote); an existing
  directory is replaced only when everything in it is listed there (or, for directories
  from before the marker, is a file the command writes), and refused otherwise, naming the
  first unexpected file. Nothing the project did not write is ever deleted.
- `prepare_incremental`: for outputs that grow across runs (a benchmark suite, an evaluation
  with its cache): the same checks, but files are added, each written atomically, never removed.
"""

from __future__ import annotations

import io
import json
import os
import secrets
import shutil
import sys
from collections.abc import Iterable
from pathlib import Path

from supervisor.errors import OutputError

MARKER = ".supervisor-output"
_SYSTEM_ROOTS = ("/proc", "/sys", "/dev")


def check_location(path: str | Path, *, directory: bool) -> Path:
    """The absolute output path, or OutputError if it cannot be created or replaced there."""
    p = Path(os.path.abspath(path))
    real = os.path.realpath(p)
    for root in _SYSTEM_ROOTS:
        if real == root or real.startswith(root + "/"):
            raise OutputError(path, f"is under {root}, which is not a place for output")
    ancestor = p.parent
    while not os.path.lexists(ancestor) and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(path, f"cannot be created: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise OutputError(path, f"cannot be created: directory {ancestor} is not writable")
    if os.path.lexists(p):
        if directory and not p.is_dir():
            raise OutputError(path, "exists and is not a directory (an output directory was expected)")
        if not directory and p.is_dir():
            raise OutputError(path, "is a directory; give a file name (for example DIR/model.npz)")
        if not directory and not p.is_file():
            raise OutputError(path, "exists and is not a regular file")
    return p


def _marker(path: Path) -> dict | None:
    f = path / MARKER
    if not f.is_file():
        return None
    try:
        info = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        info = None
    if not (isinstance(info, dict) and isinstance(info.get("command"), str)
            and isinstance(info.get("files"), list) and all(isinstance(x, str) for x in info["files"])):
        raise OutputError(f, "unreadable output marker; remove the directory yourself if it is not needed")
    return info


def check_replaceable(path: Path, command: str, known: Iterable[str] = ()) -> None:
    """OutputError unless every entry of the existing directory `path` is something `command` wrote."""
    entries = sorted(os.listdir(path))
    if not entries:
        return
    info = _marker(path)
    if info is not None and info["command"] != command:
        raise OutputError(path, f"holds the output of `supervisor {info['command']}`, not of `{command}`; "
                                "choose another output")
    ours = {MARKER, *known, *(info["files"] if info else ())}
    foreign = [e for e in entries if e not in ours]
    if foreign:
        raise OutputError(path / foreign[0], "was not written by supervisor; it is never deleted: choose another "
                                             "output or move it away")


def check_target(path: str | Path, command: str, *, replace: bool = True, known: Iterable[str] = (),
                 exists_hint: str = "use --force to replace it") -> Path:
    """All the checks `StagedOutput` makes, without creating anything (to fail before any work)."""
    p = check_location(path, directory=True)
    if p.exists():
        if not replace:
            raise OutputError(path, f"output already exists ({exists_hint})")
        check_replaceable(p, command, known)
    return p


def _write_marker(directory: Path, command: str, files: list[str]) -> None:
    tmp = directory / f"{MARKER}.tmp"
    tmp.write_text(json.dumps({"command": command, "files": sorted(files)}, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, directory / MARKER)


def record_file(directory: Path, name: str) -> None:
    """Add `name` to the marker of an output directory (a file written into it later, e.g. model.npz)."""
    info = _marker(directory)
    if info is not None and name not in info["files"]:
        _write_marker(directory, info["command"], [*info["files"], name])


def _fresh_sibling(final: Path, kind: str) -> Path:
    """A new empty directory `.NAME.KIND-XXXXXXXX` beside `final`, with the umask's mode (mkdtemp's
    0700 would become the output's mode after the rename)."""
    for _ in range(100):
        candidate = final.parent / f".{final.name}.{kind}-{secrets.token_hex(4)}"
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            continue
    raise OutputError(final, f"cannot create a {kind} directory beside it")


class StagedOutput:
    """A directory output, checked on construction, built in `path`, moved to `final` on `commit()`.

    As a context manager it commits on success and removes the staging directory on any exception."""

    def __init__(self, final: str | Path, command: str, *, replace: bool = True, known: Iterable[str] = (),
                 exists_hint: str = "use --force to replace it") -> None:
        self.command = command
        self.known = tuple(known)
        self.final = check_target(final, command, replace=replace, known=self.known, exists_hint=exists_hint)
        self.final.parent.mkdir(parents=True, exist_ok=True)
        self.path = _fresh_sibling(self.final, "partial")
        self._done = False

    def commit(self) -> Path:
        """Write the marker and move the staged directory into place (replacing an earlier output of ours)."""
        if self._done:
            raise RuntimeError("output already committed or aborted")
        _write_marker(self.path, self.command, [e for e in os.listdir(self.path) if e != MARKER])
        trash = None
        if os.path.lexists(self.final):
            check_replaceable(self.final, self.command, self.known)  # again: files may have appeared since
            trash = _fresh_sibling(self.final, "replaced")
            os.replace(self.final, trash / "old")
        try:
            os.replace(self.path, self.final)
        except OSError:
            if trash is not None:
                os.replace(trash / "old", self.final)
                trash.rmdir()
            raise
        self._done = True
        if trash is not None:
            try:
                shutil.rmtree(trash)
            except OSError as exc:
                print(f"warning: could not remove the replaced output {trash}: {exc}", file=sys.stderr)
        return self.final

    def abort(self) -> None:
        if not self._done:
            shutil.rmtree(self.path, ignore_errors=True)
            self._done = True

    def __enter__(self) -> StagedOutput:
        return self

    def __exit__(self, exc_type, *_: object) -> None:
        if exc_type is None and not self._done:
            self.commit()
        else:
            self.abort()


def prepare_incremental(path: str | Path, command: str, known: Iterable[str] = ()) -> Path:
    """Check (and create) a directory that `command` adds files to across runs; files in it are only
    ever added or replaced one by one, atomically, by their writers."""
    p = check_location(path, directory=True)
    if p.exists() and os.listdir(p):
        info = _marker(p)
        if info is None:
            check_replaceable(p, command, known)  # a directory from before the marker: only our files
        elif info["command"] != command:
            raise OutputError(p, f"holds the output of `supervisor {info['command']}`, not of `{command}`; "
                                 "choose another output")
    p.mkdir(parents=True, exist_ok=True)
    if _marker(p) is None:
        _write_marker(p, command, [])
    return p


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file in the same directory, on disk before it is renamed.

    The file gets the mode a plain `open(path, "w")` would give it: an existing file's own mode, a new
    file the umask's (mkstemp's 0600 would make a rewritten README or a calibration private to whoever
    wrote it last)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        keep = os.stat(path).st_mode & 0o777  # not set-id or sticky bits
    except FileNotFoundError:
        keep = None
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the kernel applies the umask
            break
        except FileExistsError:
            continue
    else:
        raise OutputError(path, "cannot create a temporary file beside it")
    try:
        with os.fdopen(fd, "wb") as fh:
            if keep is not None:
                os.fchmod(fh.fileno(), keep)
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_figure(path: Path, fig, dpi: int = 110) -> None:
    """A matplotlib figure as a PNG at `path`, written through `write_atomic` (the caller closes the figure)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    write_atomic(path, buf.getvalue())
