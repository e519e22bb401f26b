"""Run independent per-scene jobs: one small interface, several back ends.

Stages hand a top-level (picklable) function and a list of picklable job descriptions
to an executor; the executor runs them and reports progress as jobs done / total.
Jobs must be idempotent: each writes its own content-addressed output atomically, so a
retried or duplicated job rewrites the same result.

``local`` (default) runs jobs in this process when ``workers == 1`` and in a process
pool otherwise (spawned processes, so torch / bpy state is never forked). If a worker
process dies (segfault, OOM kill), the pool's unfinished jobs are re-run once in a fresh
pool; a second death raises :class:`WorkerLostError` naming the unfinished jobs.

``ray`` (optional extra: ``pip install 'cnnps[ray]'``) runs each job as a Ray task on
an existing cluster (``address: auto`` or ``ray://host:port``) or on a Ray runtime it
starts on this machine (``address`` unset or ``local``). Tasks declare the CPUs / GPUs
they need, and a task whose worker process dies (segfault, OOM kill, lost node) is
retried up to ``max_retries`` times; an exception raised by the job itself is not
retried and is raised here.

Usage in a stage (``params`` has ``executor`` and ``workers`` fields; ``executor`` is
the one the caller passed, or None)::

    with stage_executor(params, executor) as ex:     # made here and closed at the end when None
        threads = ex.threads_per_job(len(jobs))      # e.g. Blender's thread count
        jobs = [dataclasses.replace(j, threads=threads) for j in jobs]
        results = ex.map(render_one, jobs, "render", num_cpus=threads, num_gpus=1 if gpu else 0)
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import logging
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Callable, Iterator, Protocol, Sequence

from tqdm import tqdm

from cnnps.infra.errors import CnnpsError, ConfigError
from cnnps.infra.progress import progress_bar

RAY_INSTALL_HINT = "pip install 'cnnps[ray]'"


@dataclass(frozen=True)
class ExecutorParams:
    kind: str = "local"  # local | ray
    # local: worker processes (0 = one per core). ray with a runtime started here: the
    # CPUs it may use (0 = all cores). Ignored when connecting to an existing cluster.
    workers: int = 0
    address: str | None = None  # ray: None / "local" (start one here), "auto", "ray://host:port", "host:port"
    max_retries: int = 3  # ray: re-runs of a job whose worker process died
    cpus_per_job: int = 0  # ray: threads (and CPUs reserved) per job; 0 = share the cluster's CPUs

    def __post_init__(self):
        if self.kind not in ("local", "ray"):
            raise ConfigError(f"executor.kind must be 'local' or 'ray', got {self.kind!r}")
        if self.workers < 0:
            raise ConfigError(f"executor.workers must be >= 0, got {self.workers}")
        if self.max_retries < 0:
            raise ConfigError(f"executor.max_retries must be >= 0, got {self.max_retries}")
        if self.cpus_per_job < 0:
            raise ConfigError(f"executor.cpus_per_job must be >= 0, got {self.cpus_per_job}")
        if self.kind == "ray" and not ray_available():
            raise ConfigError(f"executor.kind 'ray' needs Ray, which is not installed: {RAY_INSTALL_HINT}")


class Executor(Protocol):
    def threads_per_job(self, n_jobs: int) -> int:
        """Threads one job may use (pass it to the job, e.g. Blender's ``threads``)."""

    def map(
        self,
        fn: Callable[[Any], Any],
        jobs: Sequence[Any],
        desc: str = "jobs",
        num_cpus: int | None = None,
        num_gpus: float = 0,
    ) -> list[Any]:
        """Run fn(job) for every job; return results in job order; raise the first failure.

        ``num_cpus`` / ``num_gpus`` are what one job needs (``num_cpus`` defaults to
        ``threads_per_job(len(jobs))``); back ends that schedule by resources use them.
        """

    def close(self) -> None:
        """Release what the executor started (process pools, a local Ray runtime)."""


class WorkerLostError(CnnpsError):
    """A job's worker process died (crash, out of memory, lost node) more often than retried."""


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


def ray_available() -> bool:
    try:
        return importlib.util.find_spec("ray") is not None
    except (ImportError, ValueError):
        return False


def _describe(job: Any, limit: int = 120) -> str:
    """A job in a few words: its ``scene_id`` (a dict key or an attribute) when it has
    one, else its repr, cut at ``limit`` characters."""
    sid = job.get("scene_id") if isinstance(job, dict) else getattr(job, "scene_id", None)
    if isinstance(sid, str) and sid:
        return f"scene {sid}"
    text = repr(job)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _note_job(exc: BaseException, desc: str, index: int, job: Any) -> BaseException:
    note = f"(in {desc} job {index}: {_describe(job)})"
    if note not in getattr(exc, "__notes__", ()):
        exc.add_note(note)
    return exc


def _broken_cause(exc: BaseException | None) -> str:
    """' (cause: ...)' when a broken pool says why (e.g. a result that failed to unpickle)."""
    cause = getattr(exc, "__cause__", None)
    lines = [line.strip() for line in str(cause or "").splitlines()]
    lines = [line for line in lines if line.strip("'\"")]  # not the quote lines around the traceback
    return f" (cause: {lines[-1]})" if lines else ""


class LocalExecutor:
    def __init__(self, workers: int = 0):
        self.workers = workers if workers > 0 else cores()

    def threads_per_job(self, n_jobs: int) -> int:
        """Threads each job may use so workers together do not oversubscribe the cores."""
        active = max(1, min(self.workers, n_jobs))
        return max(1, cores() // active)

    def map(self, fn, jobs, desc="jobs", num_cpus=None, num_gpus=0):
        jobs = list(jobs)
        if not jobs:
            return []
        if self.workers == 1 or len(jobs) == 1:
            results = []
            for i, job in enumerate(progress_bar(jobs, desc=desc, unit="job", leave=True)):
                try:
                    results.append(fn(job))
                except Exception as exc:
                    raise _note_job(exc, desc, i, job)
            return results
        results: list[Any] = [None] * len(jobs)
        todo = list(range(len(jobs)))
        with progress_bar(total=len(jobs), desc=desc, unit="job", leave=True) as bar:
            for attempt in range(2):
                todo, broken = self._run_pool(fn, jobs, todo, results, desc, bar)
                if not todo:
                    return results
                if attempt == 0:
                    tqdm.write(
                        f"cnnps: warning: a {desc} worker process died (out of memory or killed?)"
                        f"{_broken_cause(broken)}; re-running its {len(todo)} unfinished job(s) in a fresh pool",
                        file=sys.stderr,
                    )
        named = ", ".join(f"{i} ({_describe(jobs[i], 80)})" for i in todo[:3])
        more = f" and {len(todo) - 3} more" if len(todo) > 3 else ""
        raise WorkerLostError(
            f"{desc}: a worker process died twice (out of memory or killed?){_broken_cause(broken)} "
            f"with job(s) {named}{more} unfinished; try fewer workers (executor.workers)"
        ) from broken

    def _run_pool(self, fn, jobs, todo, results, desc, bar) -> tuple[list[int], BrokenProcessPool | None]:
        """Run jobs ``todo`` in a fresh spawned pool, filling ``results``.

        Returns the indices left unfinished because a worker process died (the pool is
        then broken: its other workers are stopped too) and the pool's error; a job's own
        exception is raised.
        """
        finished: set[int] = set()
        broken: BrokenProcessPool | None = None
        pool = ProcessPoolExecutor(max_workers=min(self.workers, len(todo)), mp_context=get_context("spawn"))
        try:
            futures: dict[Any, int] = {}
            try:
                for i in todo:
                    futures[pool.submit(fn, jobs[i])] = i
                for fut in as_completed(futures):
                    i = futures[fut]
                    try:
                        results[i] = fut.result()
                    except BrokenProcessPool as exc:
                        broken = exc
                        break
                    except Exception as exc:
                        raise _note_job(exc, desc, i, jobs[i])
                    finished.add(i)
                    bar.update(1)
            except BrokenProcessPool as exc:  # from submit: the pool broke while jobs were queued
                broken = exc
            # keep what other jobs finished before the pool broke
            for fut, i in futures.items():
                if i not in finished and fut.done() and not fut.cancelled() and fut.exception() is None:
                    results[i] = fut.result()
                    finished.add(i)
                    bar.update(1)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)  # do not start queued jobs after a failure
        return [i for i in todo if i not in finished], broken

    def close(self) -> None:
        pass


class RayExecutor:
    """Jobs as Ray tasks, on an existing cluster or a runtime started on this machine.

    ``address``: None or ``"local"`` starts a runtime here with ``num_cpus`` CPUs (None:
    all cores) unless this process is already connected to one; ``"auto"`` joins the
    cluster this machine belongs to (``ray start`` ran here); ``"ray://host:port"``
    connects through Ray Client; ``"host:port"`` is a head node's GCS address.
    """

    def __init__(
        self,
        address: str | None = None,
        num_cpus: int | None = None,
        max_retries: int = 3,
        cpus_per_job: int = 0,
        node_ip_address: str | None = None,
    ):
        if not ray_available():
            raise ConfigError(f"executor.kind 'ray' needs Ray, which is not installed: {RAY_INSTALL_HINT}")
        self.address = None if address in (None, "", "local") else address
        self.num_cpus = num_cpus
        self.max_retries = max_retries
        self.cpus_per_job = cpus_per_job
        self.node_ip_address = node_ip_address
        self._started = False  # this executor called ray.init (and so shuts it down)

    # -- connection ---------------------------------------------------------------------

    def _ray(self):
        import ray

        if ray.is_initialized():
            return ray
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        kwargs: dict[str, Any] = dict(
            log_to_driver=False,  # worker output goes to the session's logs, not over the progress bar
            logging_level=logging.WARNING,
        )
        if self.address is None:
            kwargs.update(num_cpus=self.num_cpus, include_dashboard=False)
            if self.node_ip_address:
                kwargs["_node_ip_address"] = self.node_ip_address
        where = self.address or "a local Ray runtime"
        try:
            ray.init(address=self.address, **kwargs)
        except (ConnectionError, TimeoutError, RuntimeError, ValueError) as exc:
            raise ConfigError(f"executor: cannot connect to {where}: {exc}") from exc
        self._started = True
        return ray

    def cluster_cpus(self) -> tuple[int, int]:
        """(total CPUs, CPUs of the largest node) of the connected cluster."""
        ray = self._ray()
        per_node = [int(n.get("Resources", {}).get("CPU", 0)) for n in ray.nodes() if n.get("Alive")]
        per_node = [c for c in per_node if c > 0] or [1]
        return sum(per_node), max(per_node)

    def threads_per_job(self, n_jobs: int) -> int:
        if self.cpus_per_job > 0:
            return self.cpus_per_job
        total, largest = self.cluster_cpus()
        return max(1, min(largest, total // max(1, n_jobs)))

    # -- running ------------------------------------------------------------------------

    def _check_feasible(self, desc: str, num_cpus: float, num_gpus: float) -> None:
        """A task no node can hold would wait forever: refuse it on a runtime started here
        (it cannot grow), warn on a cluster (a bigger node may still join)."""
        import ray

        _, largest = self.cluster_cpus()
        problems = []
        if num_cpus > largest:
            problems.append(f"jobs need {num_cpus} CPUs each but the largest Ray node has {largest}")
        if num_gpus and not ray.cluster_resources().get("GPU"):
            problems.append(f"jobs need {num_gpus} GPU each but the Ray cluster has no GPU")
        if not problems:
            return
        message = f"{desc}: " + "; ".join(problems)
        if self._started and self.address is None:
            raise ConfigError(message)
        tqdm.write(f"cnnps: warning: {message} (yet); jobs wait until such a node joins")

    def map(self, fn, jobs, desc="jobs", num_cpus=None, num_gpus=0):
        jobs = list(jobs)
        if not jobs:
            return []
        ray = self._ray()
        from ray.exceptions import RayError, RayTaskError

        if num_cpus is None:
            num_cpus = self.threads_per_job(len(jobs))
        self._check_feasible(desc, num_cpus, num_gpus)
        task = ray.remote(fn).options(
            num_cpus=num_cpus,
            num_gpus=num_gpus,
            max_retries=self.max_retries,
            retry_exceptions=False,  # only worker deaths are retried; a job's own error is final
            name=f"{desc}:{getattr(fn, '__name__', 'job')}",
        )
        refs = [task.remote(job) for job in jobs]
        index = {ref: i for i, ref in enumerate(refs)}
        results: list[Any] = [None] * len(jobs)
        pending = list(refs)
        try:
            with progress_bar(total=len(jobs), desc=desc, unit="job", leave=True) as bar:
                while pending:
                    done, pending = ray.wait(pending, num_returns=len(pending), timeout=0.5)
                    for ref in done:
                        i = index[ref]
                        try:
                            results[i] = ray.get(ref)
                        except RayTaskError as exc:
                            cause = exc.cause if isinstance(exc.cause, BaseException) else exc
                            raise _note_job(cause, desc, i, jobs[i]) from exc
                        except RayError as exc:
                            # WorkerCrashedError, OutOfMemoryError, NodeDiedError, ...: retries are spent
                            raise WorkerLostError(
                                f"{desc} job {i} ({_describe(jobs[i])}): its worker process died "
                                f"{self.max_retries + 1} time(s) ({type(exc).__name__}); "
                                f"see the Ray logs (/tmp/ray/session_latest/logs on the node)"
                            ) from exc
                        bar.update(1)
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=False)
            raise
        return results

    def close(self) -> None:
        if self._started:
            import ray

            ray.shutdown()
            self._started = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def get_executor(params: ExecutorParams | None = None) -> Executor:
    params = params or ExecutorParams()
    if params.kind == "local":
        return LocalExecutor(params.workers)
    if params.kind == "ray":
        return RayExecutor(
            address=params.address,
            num_cpus=params.workers or None,
            max_retries=params.max_retries,
            cpus_per_job=params.cpus_per_job,
        )
    raise ConfigError(f"executor.kind must be 'local' or 'ray', got {params.kind!r}")  # pragma: no cover


def make_executor(params: ExecutorParams | None = None, workers: int | None = None) -> Executor:
    """The executor a stage makes for itself: ``params`` (default: in this process, one
    worker) with ``workers`` replacing its ``workers`` when set."""
    ep = params or ExecutorParams(workers=1)
    if workers is not None:
        ep = dataclasses.replace(ep, workers=workers)
    return get_executor(ep)


@contextlib.contextmanager
def stage_executor(params: Any, executor: Executor | None = None) -> Iterator[Executor]:
    """The executor a stage runs its per-scene jobs on.

    ``executor`` when given (the caller owns it: left open); otherwise one made from the
    stage's ``params.executor`` and ``params.workers`` (:func:`make_executor`) and closed
    when the block ends, on error too.
    """
    if executor is not None:
        yield executor
        return
    own = make_executor(getattr(params, "executor", None), getattr(params, "workers", None))
    try:
        yield own
    finally:
        own.close()


def runs_in_process(executor: Executor, n_jobs: int) -> bool:
    """Whether ``executor.map`` runs ``n_jobs`` jobs in this process (the local executor
    with one worker, or a single job): the jobs' own progress bars may show then."""
    return isinstance(executor, LocalExecutor) and (executor.workers == 1 or n_jobs == 1)
