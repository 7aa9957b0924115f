"""Where the predictor's fits run: inline (simulated time), on a thread, or in a process (the real clock).

The loop asks for one fit per step (`submit`) and applies it when it is done (`take`); a fit never
arrives late without the loop noticing (its `prediction_timeout`). On the real clock the fits run in a
process of their own (`ProcessFits`): a free-width EMG fit takes 10-40 ms, most of it inside scipy's
MINPACK, which holds the GIL between its Python callbacks; on a thread beside a 4 ms tick the tick waits
for it (benchmarks/bench_fit_gil.py: p99 lateness 2-2.6 ms against 0.35 ms; in a real-clock dry-run one
72 ms tick while a fit ran). A process shares no GIL.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
from typing import Any

import numpy as np


def update_predictor(predictor, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None):
    """One predictor update; the step's pose uncertainty goes to the predictors that model it. An exception
    leaves with a note of where it was raised (file:line in function), which survives pickling out of the fit
    process and reaches the loop's `predictor_error` event."""
    try:
        if getattr(predictor, "needs_err", False):
            return predictor.update(xs, ns, err=err)
        return predictor.update(xs, ns)
    except Exception as exc:
        exc.add_note(raised_at(exc))
        raise


def raised_at(exc: BaseException) -> str:
    """`at FILE:LINE in FUNCTION` of the innermost frame of `exc`'s traceback (the package's path relative)."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return "at (no traceback)"
    f = frames[-1]
    path = f.filename
    for root in ("/supervisor/", "/sim/", "/drivers/"):
        if root in path:
            path = root[1:] + path.split(root, 1)[1]
            break
    return f"at {path}:{f.lineno} in {f.name}"


class InlineFits:
    """The predictor's fits where the loop asks for them (simulated time: deterministic)."""

    def __init__(self, predictor) -> None:
        self.predictor = predictor
        self._done: dict[int, tuple[object, BaseException | None]] = {}

    def submit(self, step: int, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> None:
        try:
            self._done[step] = (update_predictor(self.predictor, xs, ns, err), None)
        except Exception as exc:  # noqa: BLE001 - handed to the loop, which treats it as no valid model
            self._done[step] = (None, exc)

    def take(self, step: int):
        """(prediction, exception) once the fit for `step` is done, else None."""
        return self._done.pop(step, None)

    def close(self) -> None:
        """The run is over."""


class ThreadFits(InlineFits):
    """The predictor's fits on a thread of their own: off the tick, but sharing its GIL (see the module
    docstring; the real clock uses `ProcessFits`). Fits run in step order."""

    def __init__(self, predictor) -> None:
        super().__init__(predictor)
        import queue as _queue

        self._lock = threading.Lock()
        self._jobs: _queue.Queue = _queue.Queue()
        self._thread = threading.Thread(target=self._run, name="predictor", daemon=True)
        self._thread.start()

    def submit(self, step: int, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> None:
        self._jobs.put((step, xs, ns, err))

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            step, xs, ns, err = job
            try:
                out = (update_predictor(self.predictor, xs, ns, err), None)
            except Exception as exc:  # noqa: BLE001
                out = (None, exc)
            with self._lock:
                self._done[step] = out

    def take(self, step: int):
        with self._lock:
            return self._done.pop(step, None)

    def close(self) -> None:
        self._jobs.put(None)


def _picklable(exc: BaseException) -> BaseException:
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - whatever the exception holds, its text reaches the loop
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _fits_main(conn) -> None:
    """The fit process: ("predictor", run, predictor) starts a run, ("fit", run, step, xs, ns, err) asks for
    a fit, answered with (run, step, (prediction, exception)); None or a closed pipe ends it."""
    from supervisor.processes import die_with_parent

    die_with_parent()
    try:  # ordinary policy, whatever the spawning thread had (a real-time tick's would be inherited)
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass
    predictor, run = None, 0
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        if msg[0] == "predictor":
            _, run, predictor = msg
            continue
        _, job_run, step, xs, ns, err = msg
        if job_run != run or predictor is None:
            continue  # a job of an earlier run
        try:
            out: tuple[Any, BaseException | None] = (update_predictor(predictor, xs, ns, err), None)
        except Exception as exc:  # noqa: BLE001 - handed to the loop, which treats it as no valid model
            out = (None, _picklable(exc))
        try:
            conn.send((run, step, out))
        except (BrokenPipeError, OSError):
            return


class ProcessFits:
    """The predictor's fits in one long-lived process (spawned: it never forks a threaded parent), used by
    run after run: `start_run(predictor)` hands it the run's fresh predictor; results of an earlier run are
    dropped. A dead fit process raises in `submit`/`take`, which the loop turns into a fault (brake)."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_fits_main, args=(child,), name="predictor-fits", daemon=True)
        self._proc.start()
        child.close()
        self._run = 0
        self._done: dict[int, tuple[object, BaseException | None]] = {}
        self._closed = False

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def start_run(self, predictor) -> ProcessFits:
        """A new run with `predictor` (pickled to the process): what an earlier run left is dropped."""
        self._run += 1
        self._done.clear()
        self._conn.send(("predictor", self._run, predictor))
        return self

    def submit(self, step: int, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> None:
        self._conn.send(("fit", self._run, step, np.asarray(xs), np.asarray(ns), err))

    def take(self, step: int):
        """(prediction, exception) once the fit for `step` is done, else None (never waits)."""
        while self._conn.poll(0):
            run, done_step, out = self._conn.recv()
            if run == self._run:
                self._done[done_step] = out
        if step not in self._done and not self._proc.is_alive():
            raise RuntimeError(f"the fit process exited (code {self._proc.exitcode})")
        return self._done.pop(step, None)

    def close(self) -> None:
        """The run is over (the process stays for the next run; `shutdown` ends it)."""

    def shutdown(self, timeout: float = 0.25) -> None:
        """End the process: a short join, then terminate. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(1.0)
        self._conn.close()
