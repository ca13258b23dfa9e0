"""Worker processes for the thread runner: each worker thread computes in a process of its own.

The thread runner's workers share one interpreter, so one GIL. MuJoCo, torch and the compiled
kernels release it for each call, and a call returns to wait for the other thread's Python
(up to the 5 ms switch interval): on the default run the two workers kept ~1.65 of 2 cores
busy through the retarget, render and metrics steps (2026-11-27). Here each worker thread hands
its batches to a process of its own and waits on a pipe, so the workers never share a GIL.

The processes are forked from a *zygote*: a fresh interpreter this module starts once per
driver process, which imports the steps' modules and builds their models (`tasks.stages.warm`)
while Prefect's server boots, then forks one process per worker for each run. Each forked
process starts warm (copy-on-write) and costs milliseconds. They are not forked from the
driver itself: a process that has created an EGL context hangs in its forked child's first EGL
call, and a driver (or a test session) may have rendered before. The zygote never renders.

A run's `Context` and `Pipeline` reach the zygote pickled, so their step functions must be
importable there (the driver's `sys.path`, working directory and environment go with them).
Where they are not, or the zygote fails, the worker threads compute as before. A worker keeps
one renderer open for the run's render steps (`render.record.kept_renderer`: the same
pictures, without building the scene and its GL context per sequence). A call goes to
the worker that computed the same sequences' previous step (whose in-memory results and memos
it reuses), waiting for it unless a free worker is wanted by no other waiting call (`_Pool`).
A process that dies (a crash, the OOM killer) fails the batch it held ("task crashed"); with
every worker dead the threads compute in-thread, `run.workers` at a time. A run with the VLM critic computes in the threads: its request budget caps the whole
run, and one client in one process counts it.

Pickles travel only over socket pairs this process creates and hands to its own children (no
listening socket, no file), so nothing else can feed one to a worker. No Prefect here.
"""

from __future__ import annotations

import atexit
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from embody.config import Config
from embody.tasks.execute import run_batch, run_shared
from embody.tasks.pipeline import Context, Pipeline, Step

__all__ = ["WorkerLost", "batch", "cpu_seconds", "prewarm", "process_cpu_seconds", "shared",
           "task_threads", "usable", "worker_pool"]

#: How long the driver waits for a worker's CPU report when a run closes its pool (s).
_CLOSE_WAIT_S = 10.0


class WorkerLost(RuntimeError):
    """A worker process exited while it held a batch."""


# --- the zygote ---------------------------------------------------------------------------


def _environment(env: dict[str, str], cwd: str, path: list[str]) -> None:
    os.environ.clear()
    os.environ.update(env)
    try:
        os.chdir(cwd)
    except OSError:
        pass
    sys.path[:] = path


def _warm(ctx: Context, pipeline: Pipeline) -> None:
    from embody.tasks.stages import warm
    try:
        warm(ctx, pipeline)
    except Exception:  # a bad model is each sequence's error, reported by its step
        pass


def _zygote_main(fd: int) -> None:
    """The zygote's loop: ``("warm", state)`` builds what a run will need; ``("fork", n,
    state)`` followed by `n` socket descriptors forks one worker per descriptor and answers
    their pids (or an error). `state` is the pickled (env, cwd, sys.path, ctx, pipeline)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # workers are reaped as they exit
    import torch
    torch.set_num_threads(1)  # one intra-op thread per worker (`flows.threads`)
    conn = Connection(fd)
    sock = socket.socket(fileno=os.dup(fd))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            break
        try:
            env, cwd, path, payload = msg[-1]
            _environment(env, cwd, path)
            ctx, pipeline = pickle.loads(payload)
        except Exception as exc:
            ctx = pipeline = None
            error = f"{type(exc).__name__}: {exc}"
        if msg[0] == "warm":
            if pipeline is not None:
                _warm(ctx, pipeline)
            continue
        fds = socket.recv_fds(sock, 1, msg[1])[1]
        if pipeline is None:
            for f in fds:
                os.close(f)
            conn.send(("error", error))
            continue
        _warm(ctx, pipeline)
        pids, me = [], os.getpid()
        for k, f in enumerate(fds):
            pid = os.fork()
            if pid == 0:
                code = 1
                try:
                    conn.close()
                    sock.close()
                    for other in fds[k + 1:]:
                        os.close(other)
                    _serve(f, ctx, pipeline, me)
                    code = 0
                finally:
                    os._exit(code)
            os.close(f)
            pids.append(pid)
        conn.send(("forked", pids))
    os._exit(0)


def _die_with_parent(parent: int) -> None:
    """SIGKILL this process when the zygote (its parent, single-threaded) exits: a driver that
    is killed closes the zygote's pipe, the zygote exits, and its workers stop at once instead
    of after their batch (Linux; elsewhere they stop on their pipe's EOF)."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the zygote exited before the call
            os._exit(1)
    except (OSError, AttributeError):
        pass


def _serve(fd: int, ctx: Context, pipeline: Pipeline, parent: int) -> None:
    """A worker's loop: ``(kind, step, records, shared)`` → ``("ok", result)``; None ends it,
    answered with the process's CPU seconds."""
    _die_with_parent(parent)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # the steps wait for their own children
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api="blas")
    steps: dict[str, Step] = {s.name: s for s in (pipeline.source, *pipeline.steps)}
    conn = Connection(fd)
    with ExitStack() as stack:
        if "render" in steps:  # one renderer for the run's sequences (`render.record`)
            from embody.render.record import kept_renderer
            stack.enter_context(kept_renderer())
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return
            if msg is None:
                t = os.times()
                conn.send(("bye", t.user + t.system + t.children_user + t.children_system))
                return
            kind, name, records, shared_keys = msg
            try:
                step = steps[name]
                out = (run_batch(step, ctx, records, shared_keys) if kind == "batch"
                       else run_shared(step, ctx, shared_keys))
                reply = ("ok", out)
            except BaseException as exc:  # noqa: BLE001 - the driver's task reports it
                reply = ("error", f"{type(exc).__name__}: {exc}")
            conn.send(reply)


@dataclass
class _Zygote:
    proc: subprocess.Popen
    conn: Connection
    sock: socket.socket
    lock: threading.Lock = field(default_factory=threading.Lock)

    @classmethod
    def start(cls) -> "_Zygote":
        ours, theirs = socket.socketpair()
        code = (f"import sys; sys.path[:] = {sys.path!r}; "
                f"from embody.tasks.workers import _zygote_main; _zygote_main({theirs.fileno()})")
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        # what `embody.render.gl` sets: mujoco then imports its EGL module (whose display is
        # made by the first context, in a worker) instead of GLFW's (~0.2 s of imports)
        env.setdefault("MUJOCO_GL", "egl")
        try:
            proc = subprocess.Popen([sys.executable, "-c", code], pass_fds=[theirs.fileno()],
                                    stdin=subprocess.DEVNULL, env=env)
        finally:
            theirs.close()
        return cls(proc, Connection(os.dup(ours.fileno())), ours)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        self.conn.close()
        self.sock.close()
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


_ZYGOTE: _Zygote | None = None
_ZYGOTE_LOCK = threading.Lock()


def _zygote() -> _Zygote:
    global _ZYGOTE
    with _ZYGOTE_LOCK:
        if _ZYGOTE is None or not _ZYGOTE.alive():
            if _ZYGOTE is None:
                atexit.register(lambda: _ZYGOTE is not None and _ZYGOTE.stop())
            _ZYGOTE = _Zygote.start()
        return _ZYGOTE


def _state(ctx: Context, pipeline: Pipeline) -> tuple[dict[str, str], str, list[str], bytes]:
    return dict(os.environ), os.getcwd(), list(sys.path), pickle.dumps((ctx, pipeline))


def usable(cfg: Config) -> bool:
    """Whether a run's worker threads compute in worker processes: several workers of the
    thread runner, `run.worker_processes` on, `os.fork` (POSIX), and no VLM critic (its request
    budget caps the whole run: one client in one process counts it)."""
    run = cfg.run
    vlm = run.critic and cfg.critic.kind == "vlm"
    return (run.worker_processes and run.runner == "threads" and run.workers > 1
            and hasattr(os, "fork") and not vlm)


def prewarm(ctx: Context, pipeline: Pipeline) -> bool:
    """Start the zygote (once per process) and have it build what `pipeline` needs, without
    waiting; False when the run computes in its threads (`usable`) or its context or pipeline
    does not pickle."""
    if not usable(ctx.cfg):
        return False
    try:
        state = _state(ctx, pipeline)
    except Exception:
        return False
    zygote = _zygote()
    with zygote.lock:
        try:
            zygote.conn.send(("warm", state))
        except OSError:
            return False
    return True


# --- the driver's side --------------------------------------------------------------------


@dataclass
class _Worker:
    pid: int
    conn: Connection
    lock: threading.Lock = field(default_factory=threading.Lock)
    dead: bool = False


class _Pool:
    """One run's worker processes. A call goes to the worker that computed the same sequences'
    previous step (its `tasks.recent` arrays and its memos hold them: the targets, the human
    tracks, the finger-clearance frames), waiting for it while it is busy, unless no waiting
    call wants a free worker, which then takes that call: no worker idles while a call waits.
    The run gives its pool a thread per batch in flight (`task_threads`), so calls wait here
    instead of in Prefect's queue, and a freed worker can choose among them. With every worker
    dead the calling thread computes itself."""

    def __init__(self, workers: list[_Worker]) -> None:
        self.workers = workers
        self._busy: set[int] = set()
        self._last: dict[str, int] = {}  # sequence id → pid of the worker that last had it
        self._cond = threading.Condition()
        self._waiting: list[int | None] = []  # the preferred worker of each waiting call

    def _preferred(self, ids: list[str]) -> int | None:
        """The live worker that last had most of `ids` (None: none of them yet)."""
        live = {w.pid for w in self.workers if not w.dead}
        votes: dict[int, int] = {}
        for i in ids:
            pid = self._last.get(i)
            if pid in live:
                votes[pid] = votes.get(pid, 0) + 1
        return max(votes, key=lambda pid: votes[pid]) if votes else None  # ties: the first

    def _pick(self, prefer: int | None) -> _Worker | None:
        """The free worker a call preferring `prefer` takes now, or None (it waits): its own
        one, else the first free one that no other waiting call prefers. Called with the
        call's own preference not in `_waiting`."""
        free = [w for w in self.workers if not w.dead and w.pid not in self._busy]
        for w in free:
            if w.pid == prefer:
                return w
        wanted = set(self._waiting)
        return next((w for w in free if w.pid not in wanted), None)

    def _take(self, ids: list[str]) -> _Worker | None:
        """A worker for a call on `ids` (see the class), marked busy; None when all are dead."""
        with self._cond:
            prefer = self._preferred(ids)
            while True:
                if all(w.dead for w in self.workers):
                    return None
                w = self._pick(prefer)
                if w is not None:
                    self._busy.add(w.pid)
                    return w
                self._waiting.append(prefer)
                try:
                    self._cond.wait()
                finally:
                    self._waiting.remove(prefer)
                if prefer is not None and not any(x.pid == prefer and not x.dead for x in self.workers):
                    prefer = None  # it died meanwhile

    def _give(self, w: _Worker, ids: list[str]) -> None:
        with self._cond:
            self._busy.discard(w.pid)
            self._last.update(dict.fromkeys(ids, w.pid))
            self._cond.notify_all()

    def call(self, kind: str, name: str, records: Any, shared_keys: dict[str, str],
             affinity: bool = True) -> tuple[bool, Any]:
        """(True, result) from a worker, or (False, None): compute in-thread. `affinity`
        False: the worker is not remembered for these sequences (`Step.affinity`)."""
        ids = [r["id"] for r in records] if records else []
        w = self._take(ids)
        if w is None:
            return False, None
        try:
            with w.lock:
                w.conn.send((kind, name, records, shared_keys))
                status, value = w.conn.recv()
        except (EOFError, OSError) as exc:
            w.dead = True
            raise WorkerLost(f"worker process {w.pid} exited while computing step "
                             f"{name!r} ({type(exc).__name__})") from None
        finally:
            self._give(w, ids if affinity else [])
        if status != "ok":
            raise RuntimeError(f"worker process {w.pid}: {value}")
        return True, value

    def close(self) -> float:
        """End the workers; returns the CPU seconds they report."""
        cpu = 0.0
        for w in self.workers:
            with w.lock:
                try:
                    if not w.dead:
                        w.conn.send(None)
                        if w.conn.poll(_CLOSE_WAIT_S):
                            cpu += float(w.conn.recv()[1])
                except (EOFError, OSError):
                    pass
                finally:
                    w.conn.close()
        return cpu


_POOLS: dict[str, _Pool] = {}
#: Per run session: at most `run.workers` batches compute in the threads at once (the run has
#: more threads than workers when its workers are processes, `task_threads`).
_IN_THREAD: dict[str, threading.Semaphore] = {}
_CPU = [0.0]


def task_threads(cfg: Config) -> int:
    """Threads of the run's task runner: one per batch the driver keeps in flight (2 ×
    workers) when the workers are processes (`usable`), so each batch's call waits in its
    pool for the worker that has its sequences (`_Pool`); else one per worker, each computing."""
    return 2 * cfg.run.workers if usable(cfg) else cfg.run.workers


def _fork(n: int, ctx: Context, pipeline: Pipeline) -> _Pool | None:
    try:
        state = _state(ctx, pipeline)
    except Exception:
        return None
    zygote = _zygote()
    pairs = [socket.socketpair() for _ in range(n)]
    try:
        with zygote.lock:
            zygote.conn.send(("fork", n, state))
            socket.send_fds(zygote.sock, [b"f"], [theirs.fileno() for _, theirs in pairs])
            status, value = zygote.conn.recv()
    except (EOFError, OSError):
        status, value = "error", "zygote lost"
    finally:
        for _, theirs in pairs:
            theirs.close()
    if status != "forked":
        for ours, _ in pairs:
            ours.close()
        return None
    workers = []
    for pid, (ours, _) in zip(value, pairs):
        workers.append(_Worker(pid, Connection(os.dup(ours.fileno()))))
        ours.close()
    return _Pool(workers)


@contextmanager
def worker_pool(ctx: Context, pipeline: Pipeline) -> Iterator[bool]:
    """Worker processes for the run of `ctx` (its session; one per `run.workers`) inside the
    block when the run can use them (`usable`); yields whether there are any (else the worker
    threads compute, as with one worker)."""
    pool = _fork(ctx.cfg.run.workers, ctx, pipeline) if usable(ctx.cfg) else None
    _IN_THREAD[ctx.session] = threading.Semaphore(max(1, ctx.cfg.run.workers))
    try:
        if pool is None:
            yield False
            return
        _POOLS[ctx.session] = pool
        try:
            yield True
        finally:
            del _POOLS[ctx.session]
            _CPU[0] += pool.close()
    finally:
        _IN_THREAD.pop(ctx.session, None)


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a running process so far (Linux's /proc; 0 elsewhere or
    when it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def cpu_seconds() -> float:
    """CPU seconds of this process's worker processes so far: those of ended runs (as they
    reported) plus the zygote's own."""
    z = _ZYGOTE
    return _CPU[0] + (process_cpu_seconds(z.proc.pid) if z is not None and z.alive() else 0.0)


def batch(step: Step, ctx: Context, records: list[dict[str, Any]],
          shared_keys: dict[str, str]) -> list[dict[str, Any]]:
    """`run_batch`, in this thread's worker process when the run has them."""
    pool = _POOLS.get(ctx.session)
    if pool is not None:
        done, out = pool.call("batch", step.name, records, shared_keys, step.affinity)
        if done:
            return out
    with _in_thread(ctx):
        return run_batch(step, ctx, records, shared_keys)


def shared(step: Step, ctx: Context, shared_keys: dict[str, str]) -> dict[str, Any]:
    """`run_shared`, in this thread's worker process when the run has them."""
    pool = _POOLS.get(ctx.session)
    if pool is not None:
        done, out = pool.call("shared", step.name, None, shared_keys)
        if done:
            return out
    with _in_thread(ctx):
        return run_shared(step, ctx, shared_keys)


def _in_thread(ctx: Context) -> Any:
    """The slot a thread computes in (at most `run.workers` at once in a run session)."""
    return _IN_THREAD.get(ctx.session) or nullcontext()
