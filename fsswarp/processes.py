"""Worker processes that run functions while the command goes on (figures, carvings' meshes).

Spawned, never forked: a child gets no copy of the parent's CUDA or OpenCL state. Every process
starts when the pool is made, so that its imports are done before the first job comes,
leaves Ctrl-C to the command (no traceback from a child), and ends without the interpreter's teardown.
"""

from __future__ import annotations

import os


def worker_count(variable: str, default: int) -> int:
    """The integer 0..64 in the environment variable ``variable`` (0: no processes), else
    ``default``; InputError naming the variable where it holds anything else."""
    from .errors import InputError

    value = os.environ.get(variable, "").strip()
    if value:
        if not (value.isdigit() and int(value) <= 64):
            raise InputError("must be an integer from 0 to 64", field=variable, value=value)
        return int(value)
    return default


class WorkerProcesses:
    """``workers`` spawned processes (a ``concurrent.futures.ProcessPoolExecutor``), each of
    which runs ``initializer(*initargs)`` first, if given. Keep ``initargs`` small: once they
    pass a pipe's buffer (64 KiB), each process's start waits until the process has read them,
    after its start-up imports (the command's script, the modules their unpickling needs; a
    truth mesh there held the demo's loop 14 s on a GPU host). Raises OSError where processes
    cannot start (e.g. no /dev/shm for the pool's semaphores in some containers).

    A process that dies (killed, out of memory) breaks the pool: it is closed, ``lost()`` is
    called once, and from then on :meth:`submit` and :meth:`outcome` give None, for the caller
    to do its jobs itself."""

    def __init__(self, workers: int, initializer=None, *initargs, lost=lambda: None):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers, self.lost, self.broken = workers, lost, False
        self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_start, initargs=(initializer, initargs))
        try:
            for _ in range(workers):  # each submit with no idle process starts one
                self.submit(int)
        except BaseException:
            self.close()
            raise

    def submit(self, function, *args, **kwargs):
        """``function(*args, **kwargs)`` in a process: a Future, or None where the pool is broken.
        SIGINT is blocked in this thread meanwhile: a process that the submit starts inherits the
        mask, so a Ctrl-C that comes before its initializer ignores SIGINT reaches the command alone."""
        import signal
        from concurrent.futures.process import BrokenProcessPool

        if self.broken:
            return None
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return self.pool.submit(function, *args, **kwargs)
        except BrokenProcessPool:
            self._break()
            return None
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)

    def outcome(self, future):
        """``future.result()`` of a :meth:`submit` (raising what the job raised), or None where a
        process died before it was done."""
        from concurrent.futures.process import BrokenProcessPool

        try:
            return future.result()
        except BrokenProcessPool:
            self._break()
            return None

    def _break(self) -> None:
        """The pool is broken: close it and call ``lost``, once."""
        if not self.broken:
            self.broken = True
            self.close()
            self.lost()

    def close(self) -> None:
        """Stop the processes (a job being run is finished first; jobs not started are dropped)."""
        self.pool.shutdown(wait=True, cancel_futures=True)


def _start(initializer, initargs) -> None:
    """Set up a worker process: Ctrl-C is the command's to handle, its end skips the
    interpreter's teardown (:func:`exit_now` with status 0, once its jobs are done and its results
    sent: freeing the imported modules one by one took 0.2 s (carvings' meshes) to 0.35 s
    (figures), which the command's end waited for); then ``initializer``, if any."""
    import atexit
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    atexit.register(exit_now, 0)
    if initializer is not None:
        initializer(*initargs)


def exit_now(status: int) -> None:
    """End this process with ``status`` at once: stdout and stderr flushed, no exit handler run
    and no teardown of the interpreter (its modules freed one by one)."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
