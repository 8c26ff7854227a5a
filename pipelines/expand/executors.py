"""Running expansion tasks in this process, in a local process pool, or on Ray; the same bytes each way.

Every task writes its own ShardWriter part and returns a small report, so the coordinator never holds
pixels; the commit sorts rows by key, so completion order does not matter. The progress bar counts relit
images: per camera in this process, per finished subject elsewhere.
"""

from __future__ import annotations

from collections.abc import Sequence

from relightanyone.errors import DependencyError
from relightanyone.pipelines.expand.task import run_expand_task

EXECUTORS = ("local", "ray")
WORKER_PRELOAD = (
    "torch",
    "relightanyone.pipelines.expand.task",
    "relightanyone.pipelines.expand.render",
    "relightanyone.pipelines.expand.avatar",
    "relightanyone.model.fit.fitter",
    "relightanyone.format.shards",
)


def run_expand_tasks(
    writer,
    settings,
    tasks: Sequence,
    images_per_view: int,
    workers: int = 1,
    executor: str = "local",
    progress: bool = True,
) -> list[dict]:
    """Run :func:`~relightanyone.pipelines.expand.task.run_expand_task` for every task; reports in task order.

    ``executor="local"`` runs in this process when ``workers == 1`` (or one task), else in a
    ``ProcessPoolExecutor`` of fresh ``forkserver`` workers. ``executor="ray"`` calls
    ``ray.init(num_cpus=workers)`` unless Ray is already initialised (then the running cluster is used).
    """
    from tqdm import tqdm

    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; expected one of {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    total = sum(len(t.source_keys) for t in tasks) * images_per_view
    bar = tqdm(total=total, desc=f"expand {settings.output.name}", unit="image", disable=not progress)
    results: dict[str, dict] = {}
    try:
        if executor == "ray":
            results = _run_ray(writer, settings, tasks, workers, bar, images_per_view)
        elif workers == 1 or len(tasks) <= 1:
            for task in tasks:
                results[task.name] = run_expand_task(writer, settings, task, bar.update)
        else:
            results = _run_pool(writer, settings, tasks, workers, bar, images_per_view)
    finally:
        bar.close()
    return [results[t.name] for t in tasks]


def _run_pool(writer, settings, tasks, workers, bar, images_per_view) -> dict:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(WORKER_PRELOAD))
    results = {}
    with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=context) as pool:
        # Subjects that need a fit take longest: start them first so no worker idles at the end.
        ordered = sorted(tasks, key=lambda t: (t.known, -len(t.source_keys)))
        futures = {pool.submit(run_expand_task, writer, settings, task): task for task in ordered}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                task = futures[future]
                results[task.name] = future.result()
                bar.update(len(task.source_keys) * images_per_view)
    return results


def _run_ray(writer, settings, tasks, workers, bar, images_per_view) -> dict:
    try:
        import ray
    except ImportError:
        raise DependencyError("the ray executor needs Ray: pip install 'relightanyone[ray]'") from None

    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    gpus = 1 if settings.device.startswith("cuda") else 0
    remote = ray.remote(num_cpus=1, num_gpus=gpus)(run_expand_task)
    writer_ref, settings_ref = ray.put(writer), ray.put(settings)
    refs = {remote.remote(writer_ref, settings_ref, task): task for task in tasks}
    results = {}
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        for ref in done:
            task = refs[ref]
            results[task.name] = ray.get(ref)
            bar.update(len(task.source_keys) * images_per_view)
    return results
