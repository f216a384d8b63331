"""One training run chained across time-limited jobs: the same command, run again, continues the run in its
own folder until it is done.

    python -m src.run.chain outputs/reproduce/unseen_shapes_ts --minutes 230 -- +exp=unseen_shapes sampling=ts trainer=gpu
    python -m src.run.chain outputs/reproduce/unseen_shapes_ts --submit --minutes 240 --slurm slurm_partition=gpu -- ...

Each call runs ``python -m src.train <overrides> hydra.run.dir=RUN_DIR ckpt_path=last`` (the folder's
``last.ckpt`` once it holds one; a run stopped before its first is set aside and started again), records itself in
``RUN_DIR/chain.json`` (the overrides; per call its start, the steps it reached and how it ended). A folder
started with other overrides is refused. Exit status: 0 once the run is done (a later call says so and runs
nothing), :data:`RESUMABLE` (75) when it stopped at a time limit with its progress in ``last.ckpt`` (run the
same command again), else ``src.train``'s own.

Time limits. ``--minutes M`` sends the training SIGTERM after M minutes: it writes ``last.ckpt`` at the end of
the current step and exits. A signal sent to the whole process group (Ctrl+C, ``timeout``, SLURM at a job's
time limit) reaches the training itself; the chain waits for it to stop. ``--submit`` submits the call as a
SLURM job through submitit (``--cluster local``: a local process with the same mechanics): SLURM sends the job
SIGUSR2 ``slurm_signal_delay_s`` before its time limit, the chain stops the training as above and submitit
requeues the job, which continues the run, until it is done or ``--requeues`` time limits have passed.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from src.run.resume import own_last_checkpoint
from src.utils.errors import ConfigError, exit_code_of
from src.utils.files import write_text_atomic

RESUMABLE = 75  # sysexits' EX_TEMPFAIL: stopped at a time limit, progress saved; run the same command again
RECORD = "chain.json"
AGAIN = "run the same command again to continue"
OWN_KEYS = ("hydra.run.dir", "ckpt_path")  # set by the chain, never by its overrides
SUBMIT_DEFAULTS: dict[str, Any] = {"gpus_per_node": 1, "tasks_per_node": 1, "cpus_per_task": 9,
                                   "slurm_signal_delay_s": 180}


def _start(command: list[str]) -> subprocess.Popen:
    """The training process, with SIGUSR2 blocked (inherited across exec): SLURM's signal before a job's time limit,
    whose default action would kill it, is the chain's to act on; one arriving meanwhile reaches the chain after."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR2})
    try:
        return subprocess.Popen(command)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


@dataclass
class Chain:
    """Calls of ``src.train`` continuing one run in ``run_dir``; callable (one call) and checkpointable by submitit."""

    run_dir: Path
    overrides: list[str]
    minutes: float | None = None
    trainer: tuple[str, ...] = (sys.executable, "-m", "src.train")

    def __post_init__(self) -> None:
        self.run_dir = Path(self.run_dir)
        self._process: subprocess.Popen | None = None
        self._waiter: threading.Thread | None = None  # reaps the training: the main thread stays free for signals
        self._started, self._from_step, self._recorded, self._started_at = 0.0, 0, False, ""
        for override in self.overrides:
            key = override.lstrip("+~").split("=", 1)[0]
            if key in OWN_KEYS or override in ("-m", "--multirun"):
                raise ConfigError(f"{override}: the chain sets hydra.run.dir and ckpt_path itself (one run, in "
                                  f"{self.run_dir}); leave them out of the overrides")

    def __getstate__(self) -> dict[str, Any]:  # submitit pickles the chain to requeue it: no process handle
        return {**self.__dict__, "_process": None, "_waiter": None}

    @property
    def last(self) -> Path:
        return own_last_checkpoint(self.run_dir)

    def command(self) -> list[str]:
        """The ``src.train`` command of the next call."""
        return [*self.trainer, *self.overrides, f"hydra.run.dir={self.run_dir}", "ckpt_path=last"]

    def record(self) -> dict[str, Any]:
        """``chain.json`` (a new record for a folder without one); refuses a folder of other overrides."""
        path = self.run_dir / RECORD
        if not path.is_file():
            return {"overrides": list(self.overrides), "done": False, "calls": []}
        record = json.loads(path.read_text())
        if record["overrides"] != list(self.overrides):
            raise ConfigError(f"{self.run_dir} holds a run of other overrides ({' '.join(record['overrides'])}); "
                              "continue it with those, or choose another folder")
        return record

    def steps(self) -> tuple[int, int | None]:
        """The step of ``last.ckpt`` (0 without one) and the run's ``trainer.max_steps`` (None if unknown)."""
        step = 0
        if self.last.is_file():
            import torch  # (only here: a first call starts the training, and takes signals, at once)

            step = int(torch.load(self.last, map_location="cpu", weights_only=False, mmap=True)["global_step"])
        config = self.run_dir / "config_resolved.yaml"
        max_steps = yaml.safe_load(config.read_text()).get("trainer", {}).get("max_steps") if config.is_file() else None
        return step, (int(max_steps) if isinstance(max_steps, int) and max_steps > 0 else None)

    def __call__(self) -> int:
        """One call: the training until it is done, stops at the time limit, or fails; its exit status."""
        record = self.record()
        if record["done"]:
            print(f"chain: {self.run_dir} is done ({len(record['calls'])} calls); nothing to run")
            return 0
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._from_step = self.steps()[0]
        command = self.command()
        print(f"chain: call {len(record['calls']) + 1} of {self.run_dir}, from step {self._from_step:,}: "
              f"{' '.join(command[1:])}", flush=True)
        previous = {s: signal.signal(s, self._note) for s in (signal.SIGTERM, signal.SIGINT)}
        self._started, self._recorded = time.monotonic(), False
        self._started_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
        self._process = _start(command)
        self._waiter = threading.Thread(target=self._process.wait, daemon=True)
        self._waiter.start()
        try:
            return self._wait(record)
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)

    def _note(self, signum: int, frame: Any) -> None:
        """A signal to the chain while the training runs: the training, in the same process group, stops on its own."""
        print(f"chain: {signal.Signals(signum).name} received; waiting for the training (signalled with its process "
              "group) to stop", file=sys.stderr, flush=True)

    def _exit_status(self, timeout: float | None = None) -> int | None:
        """The training's exit status, waiting at most ``timeout`` seconds (None: until it exits)."""
        assert self._process is not None and self._waiter is not None
        deadline = None if timeout is None else time.monotonic() + timeout
        while self._waiter.is_alive() and (deadline is None or time.monotonic() < deadline):
            self._waiter.join(1.0 if deadline is None else max(0.0, min(1.0, deadline - time.monotonic())))
        return self._process.returncode

    def _wait(self, record: dict[str, Any]) -> int:
        assert self._process is not None
        stopped_by = None
        code = self._exit_status(None if self.minutes is None else self.minutes * 60)
        if code is None:
            stopped_by = f"the time limit (--minutes {self.minutes:g})"
            self._process.send_signal(signal.SIGTERM)
            code = self._exit_status()
        return self._finish(record, code, stopped_by)

    def _finish(self, record: dict[str, Any], code: int, stopped_by: str | None, next_step: str = AGAIN) -> int:
        """Record the call that ended with ``code``; its exit status, with one line on how to go on."""
        step, max_steps = self.steps()
        interrupted = code in (128 + signal.SIGTERM, 128 + signal.SIGINT, -signal.SIGTERM, -signal.SIGINT)  # < 0: before its handlers
        record["calls"].append({"started": self._started_at,
                                "seconds": round(time.monotonic() - self._started, 1), "from_step": self._from_step,
                                "to_step": step, "max_steps": max_steps, "exit": code,
                                "stopped_by": stopped_by or ("a signal" if interrupted else None)})
        record["done"] = code == 0
        self._recorded = True
        write_text_atomic(self.run_dir / RECORD, json.dumps(record, indent=2) + "\n")
        of = f" of {max_steps:,}" if max_steps else ""
        if code == 0:
            print(f"chain: {self.run_dir} is done: step {step:,}{of} in {len(record['calls'])} calls")
            return 0
        if interrupted:
            print(f"chain: stopped at step {step:,}{of} by {stopped_by or 'a signal'}; {next_step}", file=sys.stderr)
            return RESUMABLE
        return code

    def checkpoint(self) -> Any:
        """submitit, at a job's time limit (SIGUSR2) or preemption: stop the training at the end of its step
        (``last.ckpt``), record the call, and requeue this chain."""
        import submitit

        if self._process is not None and not self._recorded:
            if self._process.returncode is None:
                self._process.send_signal(signal.SIGTERM)
            if self._finish(self.record(), self._exit_status(), "the job's time limit", "requeued") != RESUMABLE:
                return None  # done, or failed: nothing to requeue
        return submitit.helpers.DelayedSubmission(replace(self))


def submit(chain: Chain, options: dict[str, Any], cluster: str, requeues: int) -> Any:
    """Submit ``chain`` as a job (submitit, logs in ``RUN_DIR/.submitit``) requeued at each time limit; the job."""
    import submitit

    if chain.minutes is None:
        raise ConfigError("--submit needs --minutes (the job's time limit)")
    chain = replace(chain, run_dir=chain.run_dir.resolve())  # the job may start in another folder
    executor = submitit.AutoExecutor(folder=chain.run_dir / ".submitit", cluster=cluster,
                                     **{f"{name}_max_num_timeout": requeues for name in ("slurm", "local")})
    executor.update_parameters(**{**SUBMIT_DEFAULTS, "timeout_min": math.ceil(chain.minutes), **options})
    job = executor.submit(replace(chain, minutes=None))
    print(f"chain: submitted job {job.job_id} ({cluster}), requeued at its time limit until {chain.run_dir} is done "
          f"(at most {requeues} times); logs in {chain.run_dir / '.submitit'}; progress in {chain.run_dir / RECORD}")
    return job


def _option(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise ConfigError(f"--slurm {text}: expected KEY=VALUE, e.g. slurm_partition=gpu or mem_gb=64")
    return key, yaml.safe_load(value)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m src.run.chain", description=__doc__.split("\n\n")[0],
                                     usage="python -m src.run.chain RUN_DIR [options] -- <src.train overrides>")
    parser.add_argument("run_dir", type=Path, help="the run's folder (hydra.run.dir); the same folder continues it")
    parser.add_argument("--minutes", type=float, default=None,
                        help="stop the training after this many minutes (with --submit: the job's time limit)")
    parser.add_argument("--submit", action="store_true", help="submit as a job through submitit, requeued until done")
    parser.add_argument("--cluster", default="slurm", choices=("slurm", "local"), help="submitit's executor (default slurm)")
    parser.add_argument("--slurm", action="append", default=[], metavar="KEY=VALUE",
                        help="a submitit parameter, e.g. slurm_partition=gpu, cpus_per_task=9, mem_gb=64 (repeatable)")
    parser.add_argument("--requeues", type=int, default=100, help="--submit: time limits to requeue after (default 100)")
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])
    args.overrides = argv[split + 1:]
    status = [0]

    def action() -> None:
        if args.minutes is not None and not (math.isfinite(args.minutes) and args.minutes > 0):
            raise ConfigError(f"--minutes must be a positive number, got {args.minutes}")
        chain = Chain(args.run_dir, list(args.overrides), args.minutes)
        if args.submit:
            chain.record()  # a folder of other overrides is refused before anything is submitted
            submit(chain, dict(_option(o) for o in args.slurm), args.cluster, args.requeues)
        else:
            status[0] = chain()

    return exit_code_of(action) or status[0]


if __name__ == "__main__":
    sys.exit(main())
