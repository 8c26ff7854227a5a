"""Executors for ingest tasks: in-process, a local process pool, or Ray. Same task function, same bytes.

A task is one subject (:class:`~relightanyone.ingest.runner.SubjectTask`); it writes its own part of the
:class:`~relightanyone.format.shards.ShardWriter` and returns a small
:class:`~relightanyone.ingest.runner.TaskResult`, so the coordinator never holds pixels and its memory
does not grow with the number of subjects. The commit that follows sorts rows by key, which makes the
dataset independent of the order in which tasks finish.
"""

from __future__ import annotations

from collections.abc import Sequence

EXECUTORS = ("local", "ray")
WORKER_PRELOAD = (
    "relightanyone.ingest.subject_task",
    "relightanyone.ingest.decode",
    "relightanyone.ingest.steps",
    "relightanyone.align.colour",
    "relightanyone.align.geometry",
    "relightanyone.format.codecs",
    "relightanyone.format.shards",
    "cv2",
    "trimesh",
)


def _bar(total: int, progress: bool, desc: str):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="view")


def run_tasks(
    writer, settings, tasks: Sequence, workers: int = 1, executor: str = "local", progress: bool = True
):
    """Run ``run_subject_task(writer, settings, task)`` for every task; returns the results in task order.

    ``executor="local"``: in this process when ``workers == 1``, else a ``ProcessPoolExecutor`` of
    ``workers`` processes started by a ``forkserver`` (fresh interpreters, like ``spawn``: tasks and their
    arguments are pickled, no state is inherited from the caller; the server imports the heavy modules
    once and every worker forks from it). ``executor="ray"``: ``ray.init(num_cpus=workers)``
    when Ray is not yet initialised (a running cluster is used as it is). The progress bar counts views.
    """
    from .subject_task import run_subject_task

    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; expected one of {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    bar = _bar(sum(len(t.plan.views) for t in tasks), progress, f"ingest {settings.dataset}")
    results = {}
    try:
        if executor == "ray":
            results = _run_ray(writer, settings, tasks, workers, bar)
        elif workers == 1 or len(tasks) <= 1:
            for task in tasks:
                results[task.task] = run_subject_task(writer, settings, task)
                if bar is not None:
                    bar.update(len(task.plan.views))
        else:
            results = _run_pool(writer, settings, tasks, workers, bar)
    finally:
        if bar is not None:
            bar.close()
    return [results[t.task] for t in tasks]


def _run_pool(writer, settings, tasks, workers, bar) -> dict:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    from .subject_task import run_subject_task

    results = {}
    context = multiprocessing.get_context("forkserver")
    # Workers fork from a clean server process that imported the heavy modules once, instead of each
    # spawned worker importing them again; nothing is inherited from this (possibly threaded) process.
    context.set_forkserver_preload(list(WORKER_PRELOAD))
    with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=context) as pool:
        # Largest subjects first, so a long one does not start last and leave the other workers idle.
        ordered = sorted(tasks, key=lambda t: -len(t.plan.views))
        futures = {pool.submit(run_subject_task, writer, settings, task): task for task in ordered}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                task = futures[future]
                results[task.task] = future.result()
                if bar is not None:
                    bar.update(len(task.plan.views))
    return results


def _run_ray(writer, settings, tasks, workers, bar) -> dict:
    try:
        import ray
    except ImportError:
        raise RuntimeError("the ray executor needs Ray: pip install 'relightanyone[ray]'") from None
    from .subject_task import run_subject_task

    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    remote = ray.remote(num_cpus=1)(run_subject_task)
    writer_ref, settings_ref = ray.put(writer), ray.put(settings)
    refs = {remote.remote(writer_ref, settings_ref, task): task for task in tasks}
    results = {}
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        for ref in done:
            task = refs[ref]
            results[task.task] = ray.get(ref)
            if bar is not None:
                bar.update(len(task.plan.views))
    return results
