"""One owner per run directory: ``RunLock`` holds ``<run>/.lock`` (pid, host, start time) while a training runs.

A second training on the same directory refuses with the owner's pid and host. Another activity takes its own file
(a campaign's work on the run — training, evaluating, writing its record — holds ``<run>/.campaign.lock``, so two
campaign processes never work on one run). A lock whose owner is gone — the same host and no live process with that
pid (a run killed with ``kill -9``) — is reported and taken over. A lock from another host cannot be checked from
here; it is refused, naming the file to delete if that run is gone. Under SLURM the lock also names the job
(``scheduler_job``), so that a later attempt of a killed cluster job can release what that attempt left.
"""

from __future__ import annotations

import json
import os
import socket
import time

LOCK_FILE = ".lock"
CAMPAIGN_LOCK_FILE = ".campaign.lock"


def scheduler_job() -> str | None:
    """The SLURM job this process runs in, as ``sacct`` and submitit name it (``<array job>_<task>`` for a task of a
    job array); None outside SLURM. A lock keeps it, so that a later attempt of a killed job, on another host, knows
    the lock is that attempt's (``campaigns.cluster.release_stale_locks``)."""
    array, task = os.environ.get("SLURM_ARRAY_JOB_ID"), os.environ.get("SLURM_ARRAY_TASK_ID")
    return f"{array}_{task}" if array and task else os.environ.get("SLURM_JOB_ID") or None


class RunLockedError(RuntimeError):
    """The run directory is owned by another live training."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    return True


class RunLock:
    """Context manager owning ``<directory>/<name>`` for this process; released on exit (also on errors).
    ``activity`` and ``remedy`` word the refusal: "<dir> is in use by another <activity> (...); <remedy>"."""

    def __init__(self, directory: str, name: str = LOCK_FILE, activity: str = "training",
                 remedy: str = "wait for it or pass another --out"):
        self.path = os.path.join(directory, name)
        self.activity, self.remedy = activity, remedy
        job = scheduler_job()
        self.owner = {"pid": os.getpid(), "host": socket.gethostname(), **({"job": job} if job else {})}

    def _create(self) -> bool:
        try:
            fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w") as f:
            json.dump({**self.owner, "started": time.strftime("%Y-%m-%dT%H:%M:%S")}, f)
        return True

    def _read(self) -> dict:
        try:
            with open(self.path) as f:
                return json.load(f)
        except (OSError, ValueError):
            return {}

    def acquire(self) -> "RunLock":
        for _ in range(3):  # a stale lock is removed and the creation retried; a racing owner wins fairly
            if self._create():
                return self
            held = self._read()
            pid, host = held.get("pid"), held.get("host")
            if host == self.owner["host"] and isinstance(pid, int) and pid != os.getpid() and _alive(pid):
                raise RunLockedError(f"{os.path.dirname(self.path)} is in use by another {self.activity} (pid "
                                     f"{pid} on {host}, since {held.get('started', '?')}); {self.remedy}")
            if host not in (None, self.owner["host"]):
                raise RunLockedError(f"{os.path.dirname(self.path)} is in use by a {self.activity} on host {host} "
                                     f"(pid {pid}); if that run is gone, delete {self.path}")
            print(f"[lock] taking over {self.path}: its owner (pid {pid} on {host}) is gone", flush=True)
            try:
                os.remove(self.path)
            except FileNotFoundError:
                pass
        raise RunLockedError(f"could not take {self.path}; another training keeps creating it")

    def release(self) -> None:
        if self._read().get("pid") == self.owner["pid"]:
            try:
                os.remove(self.path)
            except FileNotFoundError:
                pass

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


__all__ = ["CAMPAIGN_LOCK_FILE", "LOCK_FILE", "RunLock", "RunLockedError", "scheduler_job"]
