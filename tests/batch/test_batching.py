"""How the engine packs set tasks into Dask tasks, and what its embedded workers run with."""

from __future__ import annotations

import os

import pytest

from app.batch.engine import MAX_SETS_PER_TASK, TASKS_PER_WORKER, connect, sets_per_task


@pytest.mark.parametrize(("n_tasks", "n_workers", "expected"), [
    (0, 1, 1), (3, 2, 1), (16, 2, 2), (24, 1, 6), (24, 2, 3), (7000, 2, MAX_SETS_PER_TASK),
])
def test_sets_per_task_spreads_dask_cost_and_keeps_every_worker_busy(n_tasks, n_workers,
                                                                     expected):
    per_task = sets_per_task(n_tasks, n_workers)
    assert per_task == expected
    if per_task > 1:  # batching never leaves a worker with fewer than TASKS_PER_WORKER tasks
        assert n_tasks // per_task >= TASKS_PER_WORKER * n_workers


def test_sets_per_task_names_its_arguments():
    with pytest.raises(ValueError, match="^n_tasks, n_workers"):
        sets_per_task(4, 0)


def _worker_settings() -> tuple[str | None, bool]:
    import dask.config

    return os.environ.get("MALLOC_ARENA_MAX"), bool(dask.config.get(
        "distributed.worker.profile.enabled"))


@pytest.mark.slow
def test_embedded_workers_start_with_one_arena_and_no_profiler():
    with connect(None, 1, timeout_s=60) as client:
        settings = list(client.run(_worker_settings).values())
    assert settings == [("1", False)]
