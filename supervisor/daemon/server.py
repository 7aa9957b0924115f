"""The control socket: a Unix stream socket, JSON lines, one thread per client (bounded), never TCP.

Each line is one request object (`{"cmd": "status"}`); each gets one reply line. A line that is
not JSON, not an object, longer than `MAX_LINE` bytes, or names an unknown command gets an error
reply; the connection and the daemon go on. The socket file is created with mode 0600 (0660 with
a group) under a umask that never leaves it wider, and removed on close.
"""

from __future__ import annotations

import grp
import json
import os
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

MAX_LINE = 64 * 1024  # bytes per request
MAX_CLIENTS = 8


class ControlServer:
    def __init__(self, path: str | Path, handler: Callable[[dict[str, Any]], dict[str, Any]], *,
                 group: str | None = None) -> None:
        self.path = Path(path)
        self.handler = handler
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.is_socket():
            self.path.unlink()  # a stale socket of a previous run
        elif self.path.exists():
            raise FileExistsError(f"{self.path} exists and is not a socket: refusing to replace it")
        mode = 0o660 if group else 0o600
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o177 if not group else 0o117)
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        if group:
            os.chown(self.path, -1, grp.getgrnam(group).gr_gid)
        os.chmod(self.path, mode)
        self._sock.listen(MAX_CLIENTS)
        self._clients = threading.BoundedSemaphore(MAX_CLIENTS)
        self._closed = False
        self._thread = threading.Thread(target=self._accept, name="control-socket", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            if not self._clients.acquire(blocking=False):
                self._reply(conn, {"ok": False, "error": f"too many clients (at most {MAX_CLIENTS})"})
                conn.close()
                continue
            threading.Thread(target=self._serve, args=(conn,), name="control-client", daemon=True).start()

    @staticmethod
    def _reply(conn: socket.socket, obj: dict[str, Any]) -> None:
        try:
            conn.sendall((json.dumps(obj, sort_keys=True, default=str) + "\n").encode())
        except OSError:
            pass

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        try:
            with conn:
                while not self._closed:
                    try:
                        chunk = conn.recv(65536)
                    except OSError:
                        return
                    if not chunk:
                        return
                    buf += chunk
                    while b"\n" in buf:
                        line, buf = buf.split(b"\n", 1)
                        self._reply(conn, self._answer(line))
                    if len(buf) > MAX_LINE:
                        self._reply(conn, {"ok": False, "error": f"request longer than {MAX_LINE} bytes"})
                        return  # the rest of an oversized line cannot be framed: close this client only
        finally:
            self._clients.release()

    def _answer(self, line: bytes) -> dict[str, Any]:
        if len(line) > MAX_LINE:
            return {"ok": False, "error": f"request longer than {MAX_LINE} bytes"}
        try:
            req = json.loads(line.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            return {"ok": False, "error": f"not a JSON request: {exc}"}
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            return {"ok": False, "error": 'a request is a JSON object with a "cmd" string'}
        return self.handler(req)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass
