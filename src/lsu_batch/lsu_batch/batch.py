"""The driver of `lsu batch`: one Ray Core task per bag, progress, summary, and the gallery written once.

Ray (PyPI ``ray``) schedules the tasks: with no address it starts a private local Ray on this machine (its
own temporary folder and token, OS-chosen ports, no dashboard, ``num_cpus`` = the workers), with an
address it joins that cluster and runs the same tasks there. Ray starts its workers as fresh processes
(exec'd by its raylet, never forked from this one), each runs `lsu_batch.task.process_bag` on paths and
writes its own files; only small result dicts come back. A task takes one CPU; at most ``2 x workers``
tasks wait in Ray at a time, so a million bags never sit in the driver's or Ray's memory at once.

Resuming: a bag whose folder holds the done marker with the steps asked is skipped; folders half-written by
a killed run (``<out>/.partial``) are removed at the start; the output folder is locked (``<out>/.lock``)
while a batch runs, so two batches never write into one folder.

The face stage: tasks write ``signature.bin``; the driver enrols every finished bag's signature in the
gallery (SQLite: one writer) after the tasks, skipping those the gallery holds already (keyed by the
bag's output folder, stored as the entry's ``mesh_file``), so a rerun or a resumed run enrols each scan once.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

from .bags import find_bags, output_names
from .task import DONE_FILE, PARTIAL_DIR, STEPS, BagJob, done_steps

__all__ = ["BatchSummary", "run_batch", "local_ray", "enroll_finished", "SUMMARY_FILE"]

SUMMARY_FILE = "summary.json"
OBJECT_STORE_BYTES = 100 << 20  # tasks move paths and small dicts only (Ray's minimum is 75 MB)
IN_FLIGHT_PER_WORKER = 2        # tasks handed to Ray per worker: the next one waits there, not here


@dataclass
class BatchSummary:
    """What a batch did (also written as ``<out>/summary.json``)."""

    out_dir: str
    steps: list[str]
    bags: int = 0
    done: list[dict[str, Any]] = field(default_factory=list)      # BagResult dicts of the bags done now
    skipped: list[str] = field(default_factory=list)              # names finished by an earlier run
    failed: list[dict[str, Any]] = field(default_factory=list)    # BagResult dicts with the reason
    enrolled: int = 0            # signatures added to the gallery now
    gallery: str = ""
    gallery_note: str = ""
    wall_s: float = 0.0          # the whole batch, Ray's start included
    tasks_wall_s: float = 0.0    # from the first task handed to Ray to the last result
    cpu_s: float = 0.0           # the tasks' CPU (their processes) + this driver's
    snaps: int = 0
    address: str = ""            # the cluster ("local": started by the batch)
    workers: int = 0

    @property
    def ok(self) -> bool:
        return not self.failed

    def table(self) -> str:
        """The end-of-run table: counts, times, then every failed bag with its reason."""
        rate = len(self.done) / self.tasks_wall_s if self.tasks_wall_s > 0 else 0.0
        snap_rate = self.snaps / self.tasks_wall_s if self.tasks_wall_s > 0 else 0.0
        rows = [("bags", str(self.bags)), ("done", str(len(self.done))),
                ("skipped (done before)", str(len(self.skipped))), ("failed", str(len(self.failed))),
                ("snaps", f"{self.snaps} ({snap_rate:.0f} snaps/s, {rate:.2f} bags/s)"),
                ("wall time", f"{self.wall_s:.1f} s ({self.tasks_wall_s:.1f} s of tasks)"),
                ("CPU time", f"{self.cpu_s:.1f} s"),
                ("workers", f"{self.workers} on {self.address}")]
        if "face" in self.steps:
            rows.append(("gallery", f"{self.enrolled} enrolled in {self.gallery}" +
                         (f" ({self.gallery_note})" if self.gallery_note else "")))
        width = max(len(k) for k, _ in rows)
        lines = [f"{k:<{width}}  {v}" for k, v in rows]
        for bag in self.failed:
            lines.append(f"FAILED {bag['name']} ({bag['bag']}): {bag['reason']}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "ok": self.ok}


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".lock", "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.seek(0)
            raise RuntimeError(f"another lsu batch writes to {out} (pid {handle.read().strip() or '?'}); wait for it "
                               f"or give another --out") from None
        handle.truncate(0)
        handle.write(str(os.getpid()))
        handle.flush()
        yield


@contextlib.contextmanager
def local_ray(workers: int) -> Iterator[str]:
    """A private Ray on this machine for the ``with`` block (module doc); yields its address.

    Token authentication with a token of its own (in its temporary folder) unless the environment chose
    ``RAY_AUTH_MODE``/a token; ``ray.shutdown`` and the folder removed on the way out.
    """
    temp = tempfile.mkdtemp(prefix="lsu-ray-")  # short: Ray's socket paths live under it
    saved = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN_PATH")}
    if not os.environ.get("RAY_AUTH_MODE") and not os.environ.get("RAY_AUTH_TOKEN"):
        import secrets

        token = Path(temp) / "auth_token"
        token.write_text(secrets.token_hex(32))
        token.chmod(0o600)
        os.environ["RAY_AUTH_MODE"], os.environ["RAY_AUTH_TOKEN_PATH"] = "token", str(token)
    import ray
    from ray._raylet import AuthenticationTokenLoader, Config  # type: ignore[attr-defined]  # Cython; its .pyi omits them

    # Ray reads the mode and the token once and caches them (at import): read them again, as ray.init does
    # when it turns token mode on itself
    Config.initialize("")
    AuthenticationTokenLoader.instance().reset_cache()
    try:
        context = ray.init(address="local", num_cpus=workers, object_store_memory=OBJECT_STORE_BYTES,
                           include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False,
                           _temp_dir=temp)
        try:
            yield str(context.address_info.get("gcs_address", "local"))
        finally:
            ray.shutdown()
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        shutil.rmtree(temp, ignore_errors=True)


@contextlib.contextmanager
def _ray(address: str | None, workers: int | None) -> Iterator[tuple[str, int]]:
    """Ray for the batch: the one this process has already (tests), a cluster's, or a private local one;
    yields (address, task slots)."""
    import ray

    if ray.is_initialized():
        yield "existing", int(workers or ray.cluster_resources().get("CPU", 1))
        return
    if address:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
        try:
            yield address, int(workers or ray.cluster_resources().get("CPU", 1))
        finally:
            ray.shutdown()
        return
    count = workers or os.cpu_count() or 1
    with local_ray(count) as local:
        yield f"local ({local})", count


def _progress(total: int, stream: IO[str] | None | bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, unit="bag", file=stream if not isinstance(stream, bool) and stream else sys.stderr,
                disable=stream is False or total == 0,
                dynamic_ncols=True, smoothing=0.1)


def run_batch(inputs: Sequence[str | Path], out_dir: str | Path, steps: Sequence[str] = STEPS,
              address: str | None = None, workers: int | None = None, gallery: str | Path | None = None,
              launch: str = "replay", launch_args: Sequence[tuple[str, str]] = (),
              progress: IO[str] | None | bool = None) -> BatchSummary:
    """Reprocess every bag of ``inputs`` into ``out_dir`` (module doc); returns the summary (also written).

    ``workers``: tasks at a time (a local Ray gets that many CPUs; default: one per core, or the cluster's
    CPUs); ``gallery``: the face gallery (default ``<out_dir>/gallery.db``); ``progress``: the stream of the
    progress bar (False: none).

    Raises:
        FileNotFoundError: an input does not exist, or no bag was found.
        RuntimeError: another batch writes to ``out_dir``.
    """
    t0, c0 = time.monotonic(), time.process_time()
    out = Path(out_dir).expanduser().resolve()
    bags = find_bags(inputs, skip=[out])
    if not bags:
        raise FileNotFoundError(f"no bags found in {', '.join(map(str, inputs))} (a bag is a folder with "
                                f"metadata.yaml, or an .mcap/.db3 file)")
    names = output_names(bags)
    summary = BatchSummary(out_dir=str(out), steps=list(steps), bags=len(bags))
    with _locked(out):
        shutil.rmtree(out / PARTIAL_DIR, ignore_errors=True)  # what a killed run left half-written
        todo = []
        for bag in bags:
            have = done_steps(out / names[bag])
            if have is not None and set(steps) <= set(have):
                summary.skipped.append(names[bag])
            else:
                todo.append(BagJob(str(bag), str(out), names[bag], tuple(steps), launch, tuple(launch_args)))
        if todo:
            _run_tasks(todo, summary, address, workers, progress)
        with contextlib.suppress(OSError):
            (out / PARTIAL_DIR).rmdir()  # empty unless a task of a killed run is still writing
        summary.cpu_s += time.process_time() - c0
        if "face" in steps:
            enroll_finished(out, [names[b] for b in bags], Path(gallery) if gallery else out / "gallery.db", summary)
        summary.wall_s = time.monotonic() - t0
        _write_summary(out, summary)
    return summary


def _run_tasks(todo: list[BagJob], summary: BatchSummary, address: str | None, workers: int | None,
               progress: IO[str] | None | bool) -> None:
    import ray

    from .task import process_bag

    with _ray(address, workers) as (where, slots):
        summary.address, summary.workers = where, slots
        task = ray.remote(num_cpus=1, max_retries=1)(process_bag)  # a retry only when the worker process died
        bar = _progress(len(todo), None if progress is True else progress)
        pending: dict[Any, BagJob] = {}
        queue = list(reversed(todo))
        t0 = time.monotonic()
        try:
            while queue or pending:
                while queue and len(pending) < IN_FLIGHT_PER_WORKER * slots:
                    job = queue.pop()
                    pending[task.remote(job)] = job
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    job = pending.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # noqa: BLE001 - the worker died (crash, out of memory): reported
                        result = {"name": job.name, "bag": job.bag, "status": "failed", "snaps": 0, "cpu_s": 0.0,
                                  "reason": f"the task's worker failed: {exc.__class__.__name__}: "
                                            f"{str(exc).splitlines()[0] if str(exc) else ''}"}
                    (summary.done if result["status"] == "done" else summary.failed).append(result)
                    summary.snaps += int(result.get("snaps", 0)) if result["status"] == "done" else 0
                    summary.cpu_s += float(result.get("cpu_s", 0.0))
                    elapsed = max(time.monotonic() - t0, 1e-9)
                    bar.set_postfix_str(f"{summary.snaps / elapsed:.0f} snaps/s, {len(summary.failed)} failed",
                                        refresh=False)
                    bar.update(1)
        finally:
            bar.close()
            for ref in pending:  # Ctrl-C: what is still queued is not started
                ray.cancel(ref, force=False)
        summary.tasks_wall_s = time.monotonic() - t0


def enroll_finished(out: Path, names: list[str], gallery_file: Path, summary: BatchSummary) -> None:
    """Every finished bag's signature into the gallery, once (module doc); one writer: this process."""
    from lsu_faces.gallery import Gallery, GalleryError
    from lsu_faces.signature import Signature, SignatureError

    summary.gallery = str(gallery_file)
    try:
        gallery = Gallery(gallery_file)
        known = {entry.mesh_file for entry in gallery.list()}
        for name in names:
            folder = out / name
            mesh = folder / "mesh.ply" if (folder / "mesh.ply").is_file() else folder
            if done_steps(folder) is None or not (folder / "signature.bin").is_file() or str(mesh) in known:
                continue
            result = json.loads((folder / "result.json").read_text())
            gallery.enroll(result.get("scan_id") or name, Signature.from_bytes((folder / "signature.bin").read_bytes()),
                           mesh_file=str(mesh))
            summary.enrolled += 1
        faces = sum((out / n / "signature.bin").is_file() for n in names if (out / n / DONE_FILE).is_file())
        summary.gallery_note = f"{faces} of {len(names)} bags are faces"
    except (GalleryError, SignatureError, OSError, ValueError) as exc:
        summary.gallery_note = f"gallery not written: {exc}"
        summary.failed.append({"name": "(gallery)", "bag": str(gallery_file), "status": "failed",
                               "reason": f"the face gallery was not written: {exc}"})


def _write_summary(out: Path, summary: BatchSummary) -> None:
    tmp = out / f".{SUMMARY_FILE}.{os.getpid()}"
    tmp.write_text(json.dumps(summary.to_dict(), indent=1) + "\n")
    tmp.replace(out / SUMMARY_FILE)
