"""Child processes that end with their parent.

Every process the product starts (localization and fit workers, the render process, the worker pools of
`benchmark generate`, `evaluate`/`tune` and the benchmarks) calls `die_with_parent` first, so that killing
the parent, by any signal, SIGKILL included, leaves nothing running on the robot's computer.
"""

from __future__ import annotations

import ctypes
import os
import signal

PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Linux: this (child) process gets SIGKILL when its parent dies, even by SIGKILL (no orphans).

    Also a process pool's `initializer`. Elsewhere (no prctl) it does nothing.

    The "parent" is the thread that started the process, not the parent process (prctl(2)): the child is
    killed when that thread ends. Start such processes from a thread that lives as long as they must (the
    main thread, the daemon's setup thread), never from a thread made for one piece of work."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL))
    except (OSError, AttributeError):
        pass
    if os.getppid() == 1:  # the parent died before the call took effect
        os._exit(1)
