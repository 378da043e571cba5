"""The MLflow run of one job, kept by a separate process (``python -m spatialseg.tracking_worker``).

Importing MLflow and opening its store takes seconds that the job would otherwise wait
for before it reads its first event; in a process of its own it overlaps the segmentation,
which holds the interpreter lock too often for a thread to help (docs/performance.md).
:class:`spatialseg.tracking.LiveRun` starts it and sends it pickled requests on stdin; it
answers on stdout:

- ``("start", job)`` -> ``("started", run_id, uri)`` or ``("warning", text)``
- ``("metrics", points, stamp)`` -> nothing, or ``("warning", text)`` on a failure; the
  points carry ``stamp`` (ms), when the job measured them
- ``("outputs", folder)`` -> ``("hint", text or None)``
- ``("end", status, error or None)`` -> ``("ended", announce)``, then it exits

After a failure it stays idle (each later request answered as if tracking were off): one
warning per job, never a lost result. Ctrl-C and SIGTERM are the job's to handle, so this
process ignores them; if the job dies without an ``end``, its run ends KILLED.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import sys
from pathlib import Path
from typing import Any, BinaryIO

from spatialseg.tracking import (
    MAX_PARAM_CHARS,
    browse_hint,
    code_tags,
    experiment_id,
    first_line,
    log_metrics,
    log_outputs,
    log_params,
    store_client,
)

#: This process's niceness (the lowest priority): its seconds of MLflow import and logging
#: take the cores only when the job's segmentation leaves them idle, instead of slowing the
#: job's parallel kernels on a machine with few cores (docs/performance.md, session 52).
NICENESS = 19


class Worker:
    """The job's client and run, answering each request on ``out``."""

    def __init__(self, out: BinaryIO) -> None:
        self._out = out
        self._client: Any = None
        self._run_id = ""
        self.gone = False  # the job's end of the pipe closed: no one reads the answers

    def reply(self, *message: object) -> None:
        """Send one answer to the job; a job that died meanwhile (its pipe closed) leaves
        :attr:`gone` set, not an error that would end this process with the run open."""
        try:
            pickle.dump(message, self._out)
            self._out.flush()
        except OSError:
            self.gone = True

    def start(self, job: dict[str, Any]) -> None:
        """Create the run (a child of the sweep's parent, if any) with the job's start time,
        code version and config."""
        client = store_client(job["settings"], job["cwd"])
        tags = {"spatialseg.overrides": " ".join(job["overrides"])[:MAX_PARAM_CHARS]}
        tags.update(code_tags())
        if job["parent"] is not None:
            tags["mlflow.parentRunId"] = job["parent"]
        run = client.create_run(
            experiment_id(client, job["settings"]["experiment"]),
            start_time=job["start_time"],
            tags=tags,
            run_name=",".join(job["overrides"])[:250] or None,
        )
        self._client, self._run_id = client, run.info.run_id
        log_params(client, self._run_id, job["params"], job["config_yaml"])
        self.reply("started", self._run_id, str(client.tracking_uri))

    def handle(self, message: tuple) -> bool:
        """Serve one request; False once the run has ended."""
        kind, *args = message
        if kind == "start":
            self._guarded(self.start, *args)
        elif kind == "metrics" and self._client is not None:
            self._guarded(log_metrics, self._client, self._run_id, *args)
        elif kind == "outputs":
            sent = self._client is not None and self._guarded(
                log_outputs, self._client, self._run_id, Path(args[0])
            )
            uri = str(self._client.tracking_uri) if sent else ""
            self.reply("hint", browse_hint(uri, self._run_id) if sent else None)
        elif kind == "end":
            self.reply("ended", self._client is not None and self.end(*args))
            return False
        return True

    def end(self, status: str, error: str | None) -> bool:
        """End the run as ``status`` with ``error`` as its tag; whether it could."""
        try:
            if error is not None:
                self._client.set_tag(self._run_id, "error", error[:MAX_PARAM_CHARS])
            self._client.set_terminated(self._run_id, status)
        except Exception as exc:
            self._warn(exc)
            return False
        return True

    def abandon(self) -> None:
        """End an open run KILLED: the job went away without ending it."""
        if self._client is not None:
            self.end("KILLED", None)

    def _guarded(self, action: Any, *args: Any) -> bool:
        """Run ``action``; on an error warn once, end the run FAILED, go idle."""
        try:
            action(*args)
        except Exception as exc:
            self._warn(exc)
            if self._client is not None:
                with contextlib.suppress(Exception):  # the store is gone: the warning said so
                    self._client.set_terminated(self._run_id, "FAILED")
            self._client = None
            return False
        return True

    def _warn(self, exc: BaseException) -> None:
        """Pass the failure's first line to the job, which warns."""
        self.reply("warning", first_line(exc))


def serve(inp: BinaryIO, out: BinaryIO) -> None:
    """Answer requests until the run ends; a job gone without ending it leaves it KILLED."""
    worker = Worker(out)
    while True:
        try:
            message = pickle.load(inp)
        except EOFError:  # the job is gone, and its output with it
            break
        if not worker.handle(message):
            return
        if worker.gone:  # the job died while this process answered it
            break
    worker.abandon()  # answers to a job gone are dropped (reply), so this cannot raise OSError


def main() -> None:
    """Serve the job on stdin and stdout, at the lowest CPU priority and leaving its
    signals to it; exit at once after, without tearing MLflow's modules down (most of a
    second the job would wait for)."""
    if hasattr(os, "nice"):  # POSIX; elsewhere it keeps the job's priority
        os.nice(NICENESS)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    with contextlib.suppress(ImportError):  # else the run's start warns why
        import mlflow.tracking  # noqa: F401  (now: a worker started early imports it meanwhile)

    serve(sys.stdin.buffer, sys.stdout.buffer)
    os._exit(0)


if __name__ == "__main__":
    main()
