"""The flow driver splits a batch at the run's tail, so no worker idles while another works
through a whole batch step after step (flows/dataset.py, `_Driver._split`)."""

from __future__ import annotations

from embody.flows.dataset import _Driver
from embody.tasks.stages import default_pipeline


def _records(ids: list[str], failed: tuple[str, ...] = ()) -> list[dict]:
    return [{"id": i, "status": "failed" if i in failed else "ok", "keys": {}, "metrics": {},
             "computed": [], "error": None, "failed_step": None} for i in ids]


def _driver(batches: list[list[dict]], workers: int = 2) -> _Driver:
    driver = _Driver(default_pipeline(), ctx=None, manifest=None, progress=None,
                     max_inflight=2 * workers, workers=workers)
    driver.batches = batches
    driver.next_batch = driver.inflight = len(batches)
    return driver


def test_the_last_batch_is_halved_when_a_worker_would_idle():
    batch = _records(["a", "b", "c", "d", "e"], failed=("b",))
    driver = _driver([batch])
    half = driver._split(0, 1, batch)
    assert [r["id"] for r in half] == ["d", "e"]
    # the failed record stays with the first half, which keeps batch 0's slot
    assert [r["id"] for r in driver.batches[0]] == ["b", "a", "c"]
    assert driver.batches[1] is half and driver.next_batch == 2 and driver.inflight == 2


def test_a_lagging_batch_is_split_even_with_workers_busy():
    batch = _records(["a", "b", "c", "d"])
    driver = _driver([batch, _records(["e", "f"])])
    driver.outstanding = 1  # the other worker is busy
    driver.step_of[1] = 3  # batch 1 is past step 2 already
    half = driver._split(0, 2, batch)
    assert [r["id"] for r in half] == ["c", "d"] and driver.inflight == 3
    assert driver.step_of == {0: 2, 1: 3, 2: 2}


def test_no_split_before_every_batch_started_or_when_workers_are_busy():
    batch = _records(["a", "b", "c", "d"])
    driver = _driver([batch, _records(["e"])])
    driver.step_of[1] = 1  # batch 1 at the same step: nothing lags
    driver.next_batch = 1  # batch 1 not started yet
    assert driver._split(0, 1, batch) is None
    driver.next_batch = 2
    driver.outstanding = 1  # another task runs: this one takes the second worker
    assert driver._split(0, 1, batch) is None
    driver.outstanding = 0
    driver.ready.append((1, 0, driver.batches[1]))  # about to be submitted
    assert driver._split(0, 1, batch) is None
    assert len(driver.batches) == 2


def test_one_sequence_or_one_worker_is_never_split():
    single = _records(["a", "b"], failed=("b",))
    assert _driver([single])._split(0, 1, single) is None
    batch = _records(["a", "b", "c"])
    assert _driver([batch], workers=1)._split(0, 1, batch) is None


def test_no_split_past_the_flow_runs_task_run_bound():
    batch = _records(["a", "b", "c", "d"])
    driver = _driver([batch])
    driver.planned = driver.budget = len(driver.steps)  # every task run left is spoken for
    assert driver._split(0, 1, batch) is None and len(driver.batches) == 1
    driver.budget += len(driver.steps) - 1  # room for the second half's remaining steps
    assert driver._split(0, 1, batch) is not None and len(driver.batches) == 2
