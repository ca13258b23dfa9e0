"""The step context is walked by Prefect's worker threads while other threads key new steps."""

from __future__ import annotations

import threading

from prefect.utilities.collections import visit_collection

from embody.config import Config
from embody.tasks.pipeline import Context
from embody.tasks.stages import default_pipeline


def _steps():
    pipe = default_pipeline()
    return [pipe.source, *pipe.steps]


def test_keying_a_new_step_never_grows_a_memo_someone_is_iterating(tmp_path):
    ctx = Context(cfg=Config(), store_root=str(tmp_path), run="t")
    first, *rest = _steps()
    ctx.key(first, {})
    # what Prefect's visit_collection does to a task parameter in a worker thread, paused mid-walk
    walking = iter(ctx._configs.items())
    next(walking)
    for step in rest:  # the driver keys the next steps meanwhile
        ctx.key(step, {"source": "ab" * 32})
    assert list(walking) == []  # the old walk ends cleanly: no "changed size during iteration"
    assert set(ctx._configs) == {s.name for s in [first, *rest]}


def test_keys_are_unchanged_by_the_memo_and_stable_under_threads(tmp_path):
    steps = _steps()
    plain = {s.name: s.key(Config(), {"source": "cd" * 32}) for s in steps}
    ctx = Context(cfg=Config(), store_root=str(tmp_path), run="t")
    errors: list[BaseException] = []
    stop = threading.Event()

    def walk() -> None:
        while not stop.is_set():
            try:
                visit_collection(ctx, visit_fn=lambda x: x, return_data=False)
            except BaseException as exc:  # noqa: BLE001 - the failure under test
                errors.append(exc)
                return

    walker = threading.Thread(target=walk)
    walker.start()
    try:
        keys = {s.name: ctx.key(s, {"source": "cd" * 32}) for s in steps}
    finally:
        stop.set()
        walker.join()
    assert errors == []
    for name, key in keys.items():
        assert key == plain[name]


def test_prefect_resolving_the_context_survives_a_step_keyed_mid_walk(tmp_path):
    """Prefect's task engine walks parameters with `return_data=True`, reading each dataclass field
    twice; a step keyed in between (the driver, another worker) must not make it rebuild the
    context (`dataclasses.replace` refused the memo field: "Failed to resolve inputs")."""
    from embody.tasks.pipeline import Step

    ctx = Context(cfg=Config(), store_root=str(tmp_path), run="t")
    first, *_ = _steps()
    ctx.key(first, {})
    fresh = iter(range(10_000))

    def visit(expr):  # every visited value: another thread keys one more step meanwhile
        ctx.key(Step(f"s{next(fresh)}", "1", (), lambda c, i: None, lambda a, b: None), {})
        return expr

    assert visit_collection(ctx, visit_fn=visit, return_data=True) is ctx
    assert ctx.key(first, {}) == first.key(Config(), {})
