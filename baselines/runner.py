"""Run a registration method over many pairs on the CPU: worker processes, per-pair
timeouts, a progress bar, and no pair ever dropped.

:func:`run_pairs` returns one :class:`~baselines.result.RegistrationResult` per input pair, in
input order (each pair through :meth:`~baselines.base.Registrator.register_result`, so with its inlier
fit at the default threshold). A pair whose registration times out, raises, kills its worker process
(e.g. a segfault in native code), has bad clouds or returns a transform that is not a finite proper
rigid 4x4 is recorded with the identity as its estimate, ``failed=True`` and a one-line ``reason``
(``timed_out=True`` for a timeout).

Processes. Each worker is a fresh interpreter (``spawn`` by default: forking a parent that
already runs TBB/OpenMP/torch thread pools can deadlock). A worker receives the pickled
registrator once, then pairs one at a time over a pipe. A pair that exceeds ``timeout_s``
has its worker killed and replaced, so a stuck native call (Go-ICP's branch and bound has
no time limit of its own) cannot stall the run. Worker start-up (imports, unpickling) does
not count towards a pair's time; ``seconds`` is the registration time measured in the
worker (or the time until the kill, for timeouts).

Threads. Open3D 0.20 parallelises with TBB, which ignores ``OMP_NUM_THREADS`` but sizes its
pool from the process's CPU affinity. Each worker is therefore pinned to its own share of
the CPUs this process may use (``threads_per_worker`` of them, round-robin when there are
more workers than CPUs), and ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` /
``OPENBLAS_NUM_THREADS`` (and torch's intra-op threads, if torch is loaded) are set to the
same number, so ``workers × threads`` never exceeds the CPUs.

``workers=0`` runs in this process, one pair after the other, without pinning; there a
timeout cannot interrupt a call, so a pair that took longer than ``timeout_s`` is marked
failed after it returns (same result semantics, no protection against hangs).
"""

from __future__ import annotations

import math
import multiprocessing
import os
import pickle
import time
import traceback
from collections.abc import Sequence
from multiprocessing.connection import wait
from typing import Any

from baselines.base import Registrator
from baselines.result import RegistrationResult, one_line

__all__ = ["run_pairs", "usable_cpus"]

_THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")
_STARTUP_TIMEOUT_S = 300.0


def usable_cpus() -> list[int]:
    """CPU ids this process may run on."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return list(range(os.cpu_count() or 1))


def _register_one(registrator: Registrator, src: Any, ref: Any, timeout_s: float | None) -> RegistrationResult:
    """:meth:`~baselines.base.Registrator.register_result`, a pair with bad clouds recorded as failed too."""
    start = time.perf_counter()
    try:
        return registrator.register_result(src, ref, timeout_s=timeout_s)
    except Exception as exc:  # noqa: BLE001 - every failure is recorded, never raised
        return RegistrationResult.failure(one_line(exc), time.perf_counter() - start)


# --------------------------------------------------------------------------------------
# Worker side
# --------------------------------------------------------------------------------------


def _limit_threads(cpus: list[int] | None, threads: int) -> None:
    for var in _THREAD_ENV:
        os.environ[var] = str(threads)
    if cpus:
        try:
            os.sched_setaffinity(0, cpus)
        except (AttributeError, OSError):  # pragma: no cover - not Linux / not permitted
            pass


def _worker_main(conn, cpus: list[int] | None, threads: int, timeout_s: float | None) -> None:
    """Worker loop: limit threads, unpickle the registrator, then serve pairs until None."""
    _limit_threads(cpus, threads)
    try:
        registrator = pickle.loads(conn.recv_bytes())
        registrator.setup()
        import sys

        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(threads)
    except BaseException as exc:  # noqa: BLE001 - report anything to the parent
        try:
            exc_bytes = pickle.dumps(exc)
        except Exception:  # noqa: BLE001 - unpicklable exception: send the text only
            exc_bytes = None
        conn.send(("startup_error", one_line(exc), traceback.format_exc(), exc_bytes))
        return
    conn.send(("ready",))
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        if task is None:
            return
        conn.send(("done", _register_one(registrator, *task, timeout_s)))


# --------------------------------------------------------------------------------------
# Parent side
# --------------------------------------------------------------------------------------


class _Slot:
    """One worker process and what it is doing."""

    def __init__(self, ctx, payload: bytes, cpus: list[int] | None, threads: int, timeout_s: float | None) -> None:
        self.ctx, self.payload, self.cpus, self.threads, self.timeout_s = ctx, payload, cpus, threads, timeout_s
        self.proc = None
        self.conn = None
        self.ready = False
        self.task: int | None = None
        self.started = 0.0
        self.deadline = math.inf

    def start(self) -> None:
        parent, child = self.ctx.Pipe(duplex=True)
        proc = self.ctx.Process(target=_worker_main, args=(child, self.cpus, self.threads, self.timeout_s), daemon=True)
        try:
            proc.start()
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
        self.proc = proc
        self.conn = parent
        self.conn.send_bytes(self.payload)
        self.ready = False
        self.task = None
        self.started = time.monotonic()
        self.deadline = self.started + _STARTUP_TIMEOUT_S

    def assign(self, index: int, src: Any, ref: Any) -> bool:
        """Send a pair; False if the (idle) worker has died meanwhile (it is then reset)."""
        try:
            self.conn.send((src, ref))
        except (BrokenPipeError, ConnectionResetError, EOFError, OSError):
            self.kill()
            return False
        self.task = index
        self.started = time.monotonic()
        self.deadline = math.inf if self.timeout_s is None else self.started + self.timeout_s
        return True

    def kill(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.kill()
        if self.proc is not None:
            self.proc.join(timeout=5)
        if self.conn is not None:
            self.conn.close()
        self.proc, self.conn, self.ready, self.task = None, None, False, None

    def request_stop(self) -> None:
        """Ask an idle worker to exit (it finishes on its own; see :meth:`stop`)."""
        if self.conn is not None and self.proc is not None and self.task is None and self.proc.is_alive():
            try:
                self.conn.send(None)
            except (OSError, BrokenPipeError):
                pass

    def stop(self, grace_s: float = 2.0) -> None:
        """Wait up to ``grace_s`` for a requested exit, then kill."""
        if self.proc is not None and self.task is None:
            self.proc.join(timeout=grace_s)
        self.kill()

    def exit_description(self) -> str:
        if self.proc is None:
            return "worker process ended"
        self.proc.join(timeout=1)
        code = self.proc.exitcode
        if code is None:
            return "worker process stopped answering"
        if code < 0:
            import signal

            try:
                sig = signal.Signals(-code).name
            except ValueError:
                sig = f"signal {-code}"
            return f"worker process died ({sig})"
        return f"worker process exited with code {code}"


def _raise_startup_error(desc: str, line: str, trace: str, exc_bytes: bytes | None) -> None:
    """Re-raise a worker's set-up failure: user errors as themselves, others with the trace."""
    from src.utils.errors import UserError

    exc = None
    if exc_bytes is not None:
        try:
            exc = pickle.loads(exc_bytes)
        except Exception:  # noqa: BLE001 - fall back to the text
            exc = None
    if isinstance(exc, UserError):
        raise exc
    raise RuntimeError(f"{desc}: worker could not start: {line}\n{trace}")


def _progress_bar(total: int, enabled: bool, desc: str):
    from tqdm.auto import tqdm

    return tqdm(total=total, disable=not enabled, desc=desc, unit="pair", dynamic_ncols=True)


def run_pairs(
    registrator: Registrator,
    pairs: Sequence[tuple[Any, Any]],
    workers: int | None = None,
    timeout_s: float | None = None,
    progress: bool = True,
    *,
    threads_per_worker: int | None = None,
    mp_context: str = "spawn",
) -> list[RegistrationResult]:
    """Register every ``(src, ref)`` pair; return one RegistrationResult per pair, in input order.

    Args:
        registrator: any :class:`~baselines.base.Registrator` (must be picklable for workers > 0).
        pairs: sequence of ``(src (N, 3), ref (M, 3))``.
        workers: worker processes (default: one per usable CPU, at most one per pair);
            0 runs in this process (timeouts then only flag slow pairs after the fact).
        timeout_s: per-pair wall-clock limit in seconds (None: no limit).
        progress: show a tqdm progress bar.
        threads_per_worker: CPUs (and native threads) per worker; default
            ``max(1, usable CPUs // workers)``.
        mp_context: multiprocessing start method (``"spawn"``, ``"forkserver"``, ``"fork"``).
    """
    if not isinstance(registrator, Registrator):
        raise TypeError(f"registrator must be a baselines Registrator, got {type(registrator).__name__}")
    if timeout_s is not None and not timeout_s > 0:
        raise ValueError(f"timeout_s must be > 0 or None, got {timeout_s!r}")
    pairs = list(pairs)
    n = len(pairs)
    cpus = usable_cpus()
    if workers is None:
        workers = len(cpus)
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    workers = min(workers, n)
    if n == 0:
        return []
    desc = getattr(registrator, "name", type(registrator).__name__)
    if workers == 0:
        return _run_serial(registrator, pairs, timeout_s, progress, desc)

    threads = threads_per_worker or max(1, len(cpus) // workers)
    cpu_sets = [sorted({cpus[(w * threads + k) % len(cpus)] for k in range(threads)}) for w in range(workers)]
    try:
        payload = pickle.dumps(registrator)
    except Exception as exc:  # noqa: BLE001 - explain what is needed
        raise TypeError(
            f"{desc}: the registrator must be picklable to run in worker processes "
            f"(keep native handles out of its attributes, or pass workers=0): {one_line(exc)}"
        ) from exc
    ctx = multiprocessing.get_context(mp_context)
    slots = [_Slot(ctx, payload, cpu_set, threads, timeout_s) for cpu_set in cpu_sets]
    return _run_parallel(slots, pairs, timeout_s, progress, desc)


class _Results:
    """The results in input order as they arrive, with the progress bar and its count of failed pairs."""

    def __init__(self, total: int, progress: bool, desc: str) -> None:
        self.items: list[RegistrationResult | None] = [None] * total
        self.bar = _progress_bar(total, progress, desc)
        self.failed = 0

    def record(self, index: int, result: RegistrationResult) -> None:
        self.items[index] = result
        self.failed += result.failed
        self.bar.update(1)
        if self.failed:
            self.bar.set_postfix(failed=self.failed, refresh=False)

    @property
    def complete(self) -> bool:
        return all(r is not None for r in self.items)


def _dispatch(slots: list[_Slot], todo: list[int], pairs: list[tuple[Any, Any]]) -> None:
    """Hand the next pairs to idle, ready workers (restarting ended ones while pairs remain)."""
    for slot in slots:
        if slot.conn is None and todo:
            slot.start()
        if slot.ready and slot.task is None and todo:
            index = todo.pop()
            if not slot.assign(index, *pairs[index]):
                todo.append(index)  # the worker died while idle: retry on a fresh one


def _collect(live: list[_Slot], results: _Results, desc: str) -> None:
    """Read what the busy or starting workers sent, waiting at most until the nearest deadline (and 1 s)."""
    wait_s = max(0.0, min(s.deadline for s in live) - time.monotonic())
    ready_conns = wait([s.conn for s in live], timeout=min(wait_s, 1.0))
    for slot in live:
        if slot.conn not in ready_conns:
            continue
        try:
            msg = slot.conn.recv()
        except (EOFError, OSError):
            reason = slot.exit_description()
            if slot.task is None:
                raise RuntimeError(
                    f"{desc}: {reason} while starting; if run_pairs is called from a script, "
                    "guard the script's entry point with `if __name__ == '__main__':` "
                    "(worker processes are started with multiprocessing's 'spawn')"
                ) from None
            results.record(slot.task, RegistrationResult.failure(reason, time.monotonic() - slot.started))
            slot.kill()
            continue
        kind = msg[0]
        if kind == "ready":
            slot.ready = True
            slot.deadline = math.inf
        elif kind == "startup_error":
            _raise_startup_error(desc, *msg[1:])
        else:  # "done"
            results.record(slot.task, msg[1])
            slot.task, slot.deadline = None, math.inf  # idle: no deadline until its next pair


def _time_out(slots: list[_Slot], results: _Results, timeout_s: float | None, desc: str) -> None:
    """Kill the workers past their deadline, their pair recorded as timed out."""
    now = time.monotonic()
    for slot in slots:
        if slot.conn is None or now < slot.deadline:
            continue
        if slot.task is None:
            raise RuntimeError(f"{desc}: worker did not start within {_STARTUP_TIMEOUT_S:g} s")
        reason = f"timed out after {timeout_s:g} s (worker killed)"
        results.record(slot.task, RegistrationResult.failure(reason, now - slot.started, timed_out=True))
        slot.kill()


def _run_parallel(slots: list[_Slot], pairs: list[tuple[Any, Any]], timeout_s: float | None, progress: bool,
                  desc: str) -> list[RegistrationResult]:
    """Every pair through the worker ``slots``: dispatch, collect, time out, until each has its result."""
    results = _Results(len(pairs), progress, desc)
    todo = list(range(len(pairs) - 1, -1, -1))  # a stack: pop() yields 0, 1, 2, ...
    try:
        for slot in slots:
            slot.start()
        while not results.complete:
            _dispatch(slots, todo, pairs)
            live = [s for s in slots if s.conn is not None and (not s.ready or s.task is not None)]
            if not live:  # pragma: no cover - defensive: nothing running yet results missing
                raise RuntimeError("runner stalled: no worker is running and pairs remain")
            _collect(live, results, desc)
            _time_out(slots, results, timeout_s, desc)
    finally:
        for slot in slots:  # let all workers exit in parallel, then reap them
            slot.request_stop()
        for slot in slots:
            slot.stop()
        results.bar.close()
    return results.items  # type: ignore[return-value]


def _run_serial(
    registrator: Registrator, pairs: list[tuple[Any, Any]], timeout_s: float | None, progress: bool, desc: str
) -> list[RegistrationResult]:
    registrator.setup()
    results = []
    with _progress_bar(len(pairs), progress, desc) as bar:
        for src, ref in pairs:
            results.append(_register_one(registrator, src, ref, timeout_s))
            bar.update(1)
    return results
