"""``flyscan plan``'s run: a catalogue's candidates as tasks on Dask distributed.

Each part's mesh goes to the cluster once, as the result of a task that holds it (rather
than scattered: scattered data dies with its worker, a task's result is computed again); each candidate not already in the cache
(``planning.cache``) is one task (``planning.evaluate.evaluate``) whose key is its cache
key, so a task is never computed twice within a run either. Results are stored as they
arrive: a run stopped halfway, or one whose worker died, keeps every finished candidate, and
the next run computes only what is missing. A worker that dies mid-task has its tasks run
again elsewhere by the scheduler; the results are seeded, so they are the same.
Progress goes to the terminal (and the cluster's dashboard, when it has one).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from planning.cache import ResultCache, candidate_key
from planning.candidates import PRESET_NAMES, candidates
from planning.catalogue import read_catalogue
from planning.evaluate import PLAN_SEED, evaluate
from planning.report import write_outputs

__all__ = ["PlanRun", "plan_catalogue", "local_cluster"]


@dataclass
class PlanRun:
    """What a run did. ``tasks``: candidates in all; ``computed``: run as tasks now;
    ``cached``: taken from the cache; ``errors``: tasks that raised (not cached);
    ``summary``: the catalogue summary written (``planning.report.write_outputs``);
    ``compute_s``: from the first task submitted to the last result in (no start-up)."""

    tasks: int = 0
    computed: int = 0
    cached: int = 0
    errors: int = 0
    wall_s: float = 0.0
    compute_s: float = 0.0
    workers: int = 0
    summary: dict = field(default_factory=dict)


def local_cluster(workers: int | None = None, *, processes: bool = True):
    """A ``LocalCluster`` of `workers` single-threaded workers (default: one per core), its
    dashboard on a free port (the scheduler's web server starts even without a dashboard,
    on 8787 unless told: another cluster may hold it); the caller closes it.

    Before each worker process starts, its nanny writes the workers' variables
    (``distributed.nanny.pre-spawn-environ``: ``MALLOC_TRIM_THRESHOLD_=65536``,
    ``OMP_NUM_THREADS=1``, ...) into this process's environment, where every child started
    later inherits them: a ``flyscan serve`` started after a plan ran with glibc trimming its
    heap at every 64 KiB and lost frames under load. The cluster puts this process's
    environment back once its workers have started and again when it closes (a worker that
    dies is started again, and writes them again)."""
    import os

    from distributed import LocalCluster

    class EnvironmentKeepingCluster(LocalCluster):
        def close(self, timeout: float | None = None):
            try:
                return super().close(timeout)
            finally:
                _restore_environment(environment)

    n = int(workers) if workers else (os.cpu_count() or 1)
    if n < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    environment = dict(os.environ)
    try:
        return EnvironmentKeepingCluster(n_workers=n, threads_per_worker=1, processes=processes,
                                         dashboard_address="127.0.0.1:0", silence_logs=40)
    finally:
        _restore_environment(environment)


def _restore_environment(saved: dict[str, str]) -> None:
    """``os.environ`` as `saved`: variables added since removed, changed ones set back."""
    import os

    for name in set(os.environ) - set(saved):
        del os.environ[name]
    for name, value in saved.items():
        if os.environ.get(name) != value:
            os.environ[name] = value


def plan_catalogue(catalogue, out, *, units: str | None = None, client=None,
                   scheduler: str | None = None, workers: int | None = None,
                   turn_step_deg: float = 90.0, presets=PRESET_NAMES, resting: int = 3,
                   cache=None, tolerance_mm: float = 0.1, tolerance_deg: float = 0.1,
                   on_result=None, log=sys.stderr) -> PlanRun:
    """Plan every part of a catalogue folder and write the plans and the summary to `out`.

    Parameters
    ----------
    catalogue : path-like
        The folder (``planning.catalogue.read_catalogue``).
    out : path-like
        ``plans/<part>/plan.json``, ``catalogue.csv``, ``report.html`` and its pictures.
    units : str, optional
        Unit of the files the catalogue's manifest does not name.
    client : distributed.Client, optional
        Use it; else `scheduler` (an address, ``tcp://HOST:8786``); else a LocalCluster of
        `workers` started here and closed at the end.
    turn_step_deg, presets, resting
        The candidates (``planning.candidates.candidates``).
    cache : path-like, optional
        The result cache; default ``out/cache``.
    tolerance_mm, tolerance_deg : float
        The act tolerance the candidates' sigmas are ranked against.
    on_result : callable, optional
        ``on_result(done, total, client)`` after each computed task (tests kill a worker).
    log : file
        Progress lines.
    """
    t0 = time.perf_counter()
    out = Path(out)
    entries = read_catalogue(catalogue, units)
    store = ResultCache(Path(cache) if cache is not None else out / "cache")
    jobs = {}  # key -> (entry, candidate)
    per_part = {}
    for entry in entries:
        if entry.part is None:
            continue
        kept, left_out = candidates(entry.part, turn_step_deg=turn_step_deg, presets=presets,
                                    resting=resting)
        keys = [candidate_key(entry.mesh.digest, entry.units, c.key(), PLAN_SEED) for c in kept]
        per_part[entry.name] = {"candidates": list(zip(keys, kept)), "left_out": left_out}
        for key, c in zip(keys, kept):
            jobs[key] = (entry, c)
    results = {}
    for key in jobs:
        hit = store.get(key)
        if hit is not None:
            results[key] = hit
    run = PlanRun(tasks=len(jobs), cached=len(results))
    broken = sum(e.part is None for e in entries)
    print(f"plan: {len(entries)} parts ({broken} broken), {len(jobs)} candidates, "
          f"{len(results)} cached", file=log, flush=True)
    missing = [k for k in jobs if k not in results]
    if missing:
        _compute(missing, jobs, results, store, run, client=client, scheduler=scheduler,
                 workers=workers, on_result=on_result, log=log)
    run.summary = write_outputs(out, entries, per_part, results, tolerance_mm=tolerance_mm,
                                tolerance_deg=tolerance_deg)
    run.wall_s = time.perf_counter() - t0
    run.summary["run"] = {"tasks": run.tasks, "computed": run.computed, "cached": run.cached,
                          "errors": run.errors, "workers": run.workers,
                          "wall_s": round(run.wall_s, 2), "compute_s": round(run.compute_s, 2)}
    print(f"plan: {run.computed} computed, {run.cached} cached, {run.errors} failed to run, "
          f"{run.wall_s:.1f} s; {out / 'report.html'}", file=log, flush=True)
    return run


def _compute(missing, jobs, results, store, run, *, client, scheduler, workers, on_result,
             log) -> None:
    from distributed import Client, as_completed

    own_cluster = own_client = None
    try:
        if client is None:
            if scheduler:
                client = own_client = Client(scheduler)
            else:
                own_cluster = local_cluster(workers)
                client = own_client = Client(own_cluster)
        run.workers = len(client.scheduler_info(n_workers=-1)["workers"])
        link = getattr(client, "dashboard_link", None)
        print(f"plan: {len(missing)} tasks on {run.workers} workers"
              + (f"; dashboard {link}" if link else ""), file=log, flush=True)
        meshes = {}
        for key in missing:
            entry = jobs[key][0]
            if entry.name not in meshes:  # each part's mesh goes to the cluster once
                # as a task holding it, not scattered: scattered data lost with its worker
                # is gone, a task's result is computed again from the graph
                meshes[entry.name] = client.submit(_hold, entry.mesh, key=f"mesh-{key[:16]}",
                                                   pure=False)
        t0 = time.perf_counter()
        futures = {client.submit(evaluate, meshes[jobs[k][0].name], jobs[k][1], key=f"plan-{k}",
                                 pure=False): k for k in missing}
        for done, future in enumerate(as_completed(futures), 1):
            key = futures[future]
            entry, candidate = jobs[key]
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - reported per candidate, not cached
                run.errors += 1
                results[key] = {"status": "error", "reason": f"{type(exc).__name__}: {exc}"}
            else:
                store.put(key, result)
                results[key] = result
                run.computed += 1
            _progress(done, len(missing), time.perf_counter() - t0, entry.name, candidate,
                      results[key], log)
            if on_result is not None:
                on_result(done, len(missing), client)
        run.compute_s = time.perf_counter() - t0
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()


def _hold(mesh):
    """A part's mesh, as a task's result: it lives on a worker and goes to the others that
    need it (a worker's tasks of one part fetch it once)."""
    return mesh


def _progress(done, total, elapsed, part, candidate, result, log) -> None:
    pose = result.get("pose") or {}
    verdict = (("every axis fixed" if pose.get("observable") else
                "free: " + ", ".join(pose.get("free_axes") or ["sigma beyond tolerance"]))
               if result.get("status") == "done" else result.get("reason", "failed"))
    eta = elapsed / done * (total - done)
    print(f"[{done:>{len(str(total))}}/{total}] {elapsed:6.1f} s, eta {eta:5.0f} s  {part}: "
          f"{candidate.label}: {verdict[:70]}", file=log, flush=True)
