"""The control socket's client (`supervisor ctl`): one JSON request, one JSON reply."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path
from typing import Any

from supervisor.errors import SupervisorError


def default_socket() -> Path:
    """`$RUNTIME_DIRECTORY/control.sock` (systemd's RuntimeDirectory=), else /run/panda-supervisor/."""
    rd = os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
    return Path(rd or "/run/panda-supervisor") / "control.sock"


class ControlError(SupervisorError):
    """The daemon cannot be reached, or its reply is not one."""


def request(path: str | Path, obj: dict[str, Any], timeout: float = 30.0) -> dict[str, Any]:
    """Send one request to the daemon at `path` and return its reply."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(timeout)
            s.connect(str(path))
            s.sendall((json.dumps(obj) + "\n").encode())
            buf = b""
            while b"\n" not in buf:
                chunk = s.recv(65536)
                if not chunk:
                    break
                buf += chunk
    except (FileNotFoundError, ConnectionRefusedError) as exc:
        raise ControlError(f"no supervisor daemon at {path} ({exc.strerror})") from exc
    except TimeoutError as exc:
        raise ControlError(f"the daemon at {path} did not answer within {timeout:.0f} s") from exc
    except OSError as exc:
        raise ControlError(f"control socket {path}: {exc}") from exc
    try:
        reply = json.loads(buf.split(b"\n", 1)[0])
    except json.JSONDecodeError as exc:
        raise ControlError(f"the daemon at {path} sent a reply that is not JSON: {exc}") from exc
    if not isinstance(reply, dict):
        raise ControlError(f"the daemon at {path} sent a reply that is not an object")
    return reply
