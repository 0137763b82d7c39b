"""The resident process of a ``fsswarp batch`` worker (``fsswarp.batch.Resident``;
docs/batch.md, "Resident processes"): ``python -m fsswarp.resident`` is the supervisor
(:func:`supervise`), which runs ``python -m fsswarp.resident --serve`` (:func:`serve`), the
process that runs the worker's jobs one after another as ``fsswarp`` commands in its one
interpreter.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys


def supervise() -> int:
    """``python -m fsswarp.resident``: run the resident process (``python -m fsswarp.resident
    --serve``, :func:`serve`, with this process's stdin and stdout) as the leader of a new
    process group and kill that group, its figure and mesh processes included, when it ends,
    when this process is terminated, or when this process's parent (the Ray actor) dies
    (Linux). Returns the resident's exit status, 128 + N if signal N killed it."""
    child = subprocess.Popen([sys.executable, "-m", "fsswarp.resident", "--serve"], start_new_session=True)

    def stop(signum=None, frame=None) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(child.pid, signal.SIGKILL)

    signal.signal(signal.SIGTERM, stop)
    if sys.platform.startswith("linux"):
        import ctypes

        set_parent_death_signal = 1  # PR_SET_PDEATHSIG: SIGTERM to this process when its parent dies
        ctypes.CDLL(None, use_errno=True).prctl(set_parent_death_signal, signal.SIGTERM)
        if os.getppid() == 1:  # the parent died before that
            stop()
    returncode = child.wait()
    stop()
    return 128 - returncode if returncode < 0 else returncode


def serve() -> int:
    """The resident process: for each JSON line on stdin, ``{"arguments": [...], "stderr":
    FILE}``, runs ``fsswarp ARGUMENTS`` here with its stderr appended to FILE and its stdout
    discarded, and answers ``{"returncode": N}`` on stdout. Ends at the end of stdin and after a
    job that failed other than by bad input (exit 2)."""
    import traceback

    from .batch import BAD_INPUT
    from .cli import main

    replies = os.fdopen(os.dup(1), "w")
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 1)
    for line in sys.stdin:
        request = json.loads(line)
        with open(request["stderr"], "a") as stderr:
            os.dup2(stderr.fileno(), 2)
        try:
            status = main(request["arguments"])
        except BaseException:  # an internal error: its traceback, as a process of its own would print
            traceback.print_exc()
            status = 1
        sys.stdout.flush()
        sys.stderr.flush()
        replies.write(json.dumps({"returncode": status}) + "\n")
        replies.flush()
        if status not in (0, BAD_INPUT):
            break
    return 0


if __name__ == "__main__":
    raise SystemExit(serve() if sys.argv[1:] == ["--serve"] else supervise())
