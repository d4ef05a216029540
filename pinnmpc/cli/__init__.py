"""Run a CLI body so that bad input ends in one clear line and a non-zero exit, not a traceback; guard its run dir
(one live run per dir, nothing the run did not create is ever deleted) and turn SIGTERM/SIGINT into a clean stop."""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import os
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from hydra.experimental.callback import Callback
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from pinnmpc.cli.args import CONF as CONF  # re-exported: the entry points take all of their CLI from here
from pinnmpc.cli.args import EXIT_BAD_INPUT as EXIT_BAD_INPUT
from pinnmpc.cli.args import check_choices as check_choices
from pinnmpc.cli.args import config_dir_args as config_dir_args
from pinnmpc.cli.jobs import JobFailedError as JobFailedError
from pinnmpc.cli.jobs import end_job as end_job
from pinnmpc.cli.jobs import exit_stopped as exit_stopped
from pinnmpc.cli.jobs import in_multirun
from pinnmpc.util.io import append_log as append_log  # re-exported for the tasks
from pinnmpc.util.io import atomic_write
from pinnmpc.util.signals import StopSignal as StopSignal  # re-exported for the tasks

T = TypeVar("T")

USER_ERRORS = (ValueError, FileNotFoundError, KeyError, OmegaConfBaseException)  # bad input, not a bug of ours
RUN_FAILURES = (FloatingPointError, OSError)  # a run that started and went wrong (a NaN training loss, a disk full)
EXIT_RUN_FAILED = 1  # exit code for a run that started and failed
# a run stopped by a signal exits with 128 + the signal number (130 SIGINT, 143 SIGTERM), as a shell reports it
LOCK_NAME = ".pinnmpc.lock"  # in a run dir while a run holds it: the PID of that run
BOOKKEEPING = (".hydra", LOCK_NAME)  # what Hydra and the guard put in every run dir, besides the job's log
STARTED = time.time()  # before Hydra writes into the run dir: files older than this are not this process's
ROOT = Path(__file__).resolve().parents[2]


def verbose() -> bool:
    """Tracebacks on request, as Hydra users expect."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1" or os.environ.get("PINNMPC_VERBOSE") == "1"


def fail(prog: str, message: str, code: int = EXIT_BAD_INPUT) -> None:
    """The one line a user sees for bad input, and the exit."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    sys.exit(code)


# ---------------------------------------------------------------------------------------------- run dir guard


@dataclass
class RunDirState:
    """What a run dir held before Hydra wrote into it, so a failed run removes exactly what it added."""

    path: Path
    job: str  # Hydra's job name: the job's own log is <job>.log
    existed: bool
    created_top: Path | None = None  # the top-most folder this process made for the run dir
    before: set[str] = field(default_factory=set)  # entry names present before the run
    hydra_files: dict[str, bytes] | None = None  # .hydra/* as it was (Hydra overwrites it); None: no .hydra
    lock_fd: int | None = None
    late: bool = False  # guarded after Hydra wrote into it (no RunDirGuard in the config): no record of before
    helper: bool = False  # a DDP process of rank > 0: rank 0 holds the dir; this one neither locks nor deletes


_STATE: dict[Path, RunDirState] = {}  # run dirs this process guards


def absolute(path: str | Path) -> Path:
    """The key of a run dir: absolute and normalised the way Hydra makes runtime.output_dir."""
    return Path(os.path.abspath(str(path)))


def holder(run_dir: Path) -> int | None:
    """PID of the live run holding run_dir, or None (no lock file, or a stale one of a dead run)."""
    lock = run_dir / LOCK_NAME
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:  # someone holds it: a live run
        text = os.read(fd, 64).decode(errors="replace").strip()
        return int(text) if text.isdigit() else -1
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def acquire(run_dir: Path) -> int:
    """Hold run_dir for this process: a lock file with our PID under an exclusive flock, which the kernel drops
    when the process dies, so a killed run's lock is stale and taken over. RuntimeError when a live run holds it."""
    lock = run_dir / LOCK_NAME
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            pid = holder(run_dir)
            if pid is None:  # released between the two looks: try again
                continue
            raise RuntimeError(
                f"run dir {run_dir} is in use by another live run (PID {pid}, lock {lock}); "
                "wait for it to end or choose another hydra.run.dir"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # the holder removed the file as we opened it: lock the new one
            os.close(fd)
            continue
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        return fd


def release(run_dir: Path) -> None:
    """Remove the lock file, then drop the lock (in that order, so nobody locks a file about to vanish)."""
    run_dir = absolute(run_dir)
    state = _STATE.get(run_dir)
    if state is None or state.lock_fd is None:
        return
    (run_dir / LOCK_NAME).unlink(missing_ok=True)
    os.close(state.lock_fd)
    state.lock_fd = None


def _release_all() -> None:
    """At exit: every lock this process holds."""
    for path in list(_STATE):
        release(path)


atexit.register(_release_all)


RANK_VARIABLES = ("RANK", "LOCAL_RANK", "NODE_RANK", "SLURM_PROCID")  # torchrun, Lightning's DDP children, srun


def launched_rank() -> int:
    """This process's rank as the launcher that started it says (Lightning re-runs the command for DDP ranks > 0
    with LOCAL_RANK set, torchrun sets RANK, srun SLURM_PROCID); 0 for a process started by hand."""
    ranks = [os.environ.get(name, "0") for name in RANK_VARIABLES]
    return max((int(r) for r in ranks if r.strip().isdigit()), default=0)


def guard(run_dir: Path, job: str) -> RunDirState:
    """Before Hydra writes into run_dir: check it can be a run dir, note what it holds, and lock it.
    Raises ValueError with a one-line message when it cannot, RuntimeError when a live run holds it.
    A DDP process of rank > 0 shares rank 0's run dir: it takes no lock and never removes anything."""
    run_dir = absolute(run_dir)
    if run_dir in _STATE:
        return _STATE[run_dir]
    if launched_rank() > 0:
        _STATE[run_dir] = RunDirState(run_dir, job, existed=True, helper=True)
        return _STATE[run_dir]
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"hydra.run.dir={run_dir} is a file; expected a directory (new or existing) for the outputs")
    state = RunDirState(run_dir, job, existed=run_dir.is_dir())
    if state.existed:
        state.before = {e.name for e in run_dir.iterdir()}
        hydra_dir = run_dir / ".hydra"
        if hydra_dir.is_dir():
            state.hydra_files = {f.name: f.read_bytes() for f in hydra_dir.iterdir() if f.is_file()}
    else:
        top = run_dir
        while not top.parent.exists():
            top = top.parent
        try:
            run_dir.mkdir(parents=True)
        except OSError as e:
            raise ValueError(
                f"hydra.run.dir={run_dir} cannot be created ({e.strerror}); expected a writable path"
            ) from None
        state.created_top = top
    if not os.access(run_dir, os.W_OK | os.X_OK):
        raise ValueError(f"hydra.run.dir={run_dir} is not writable; expected a directory this user can write to")
    try:
        state.lock_fd = acquire(run_dir)
    except OSError as e:
        raise ValueError(f"hydra.run.dir={run_dir}: cannot write the lock file ({e.strerror})") from None
    _STATE[run_dir] = state
    return state


class RunDirGuard(Callback):
    """Hydra callback (hydra.callbacks in conf/*.yaml): guards the run dir before Hydra writes .hydra/ into it."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Single runs: refuse a bad or busy run dir in one line, before anything is written."""
        prog = f"pinnmpc.{config.hydra.job.name}"
        try:
            guard(Path(str(config.hydra.run.dir)), str(config.hydra.job.name))
        except (ValueError, RuntimeError) as e:
            fail(prog, str(e))

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Sweep jobs (each in a new subdir): lock it too; single runs are already guarded."""
        path = absolute(config.hydra.runtime.output_dir)
        if path not in _STATE:
            guard(path, str(config.hydra.job.name))

    def on_job_end(self, config: DictConfig, **kwargs: Any) -> None:
        """A sweep worker runs many jobs: free each dir when its job ends."""
        release(absolute(config.hydra.runtime.output_dir))


def _remove(path: Path) -> None:
    """A file or a folder, whichever it is."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def discard_own_files(run_dir: Path | None) -> None:
    """After bad input: remove what this process added to run_dir (Hydra's .hydra/, the job's log, the lock) and
    the dir itself only if this process made it; never anything that was there before."""
    if run_dir is None or not run_dir.is_dir():
        return
    run_dir = absolute(run_dir)
    state = _STATE.get(run_dir)
    if state is not None and state.helper:
        return
    release(run_dir)
    if state is None or state.late:
        _discard_unguarded(run_dir)
        return
    own = {*BOOKKEEPING, f"{state.job}.log"}
    entries = list(run_dir.iterdir())
    if not state.existed:
        if all(e.name in own or (e.is_file() and e.suffix == ".log") for e in entries):
            top = state.created_top or run_dir
            shutil.rmtree(run_dir, ignore_errors=True)
            for parent in [run_dir, *run_dir.parents]:  # folders made for it, up to the top-most one, if empty
                if parent != run_dir and parent.is_dir() and not any(parent.iterdir()):
                    parent.rmdir()
                if parent == top:
                    break
        return
    for e in entries:
        if e.name in own and e.name not in state.before:
            _remove(e)
    hydra_dir = run_dir / ".hydra"
    if state.hydra_files is not None and hydra_dir.is_dir():  # Hydra rewrote the earlier run's record: put it back
        for f in hydra_dir.iterdir():
            if f.name not in state.hydra_files:
                _remove(f)
        for name, data in state.hydra_files.items():
            atomic_write(hydra_dir / name, lambda tmp, data=data: tmp.write_bytes(data))


def _discard_unguarded(run_dir: Path) -> None:
    """Without the guard's record (a config without RunDirGuard): only .hydra/ and logs written since this process
    started, and the dir when that leaves it empty."""
    entries = list(run_dir.iterdir())
    fresh = [e for e in entries if e.stat().st_mtime >= STARTED]
    if len(fresh) == len(entries) and all(e.name == ".hydra" or (e.is_file() and e.suffix == ".log") for e in entries):
        for e in entries:
            _remove(e)
        run_dir.rmdir()


# ---------------------------------------------------------------------------------------------- the body


def job_log(run_dir: Path, prog: str) -> Path:
    """The run dir's log file Hydra opened for this job (`<job name>.log`)."""
    from hydra.core.hydra_config import HydraConfig

    name = HydraConfig.get().job.name if HydraConfig.initialized() else prog.rsplit(".", 1)[-1]
    return run_dir / f"{name}.log"


def say(message: str, run_dir: Path | None, prog: str, err: bool = False) -> None:
    """Print a command's closing line and keep it in the run dir's log, so the log says how the run ended (a log
    that cannot be written raises OSError naming it)."""
    print(message, file=sys.stderr if err else sys.stdout)
    if run_dir is not None and run_dir.is_dir():
        path = job_log(run_dir, prog)
        try:
            append_log(path, message)
        except OSError as e:
            raise OSError(f"cannot write {path}: {e.strerror or e}") from None


def run_cli(body: Callable[[], T], prog: str, run_dir: Path | None = None) -> T:
    """Call body; a user error or failed run becomes `prog: error: message` on stderr and exit code 2 or 1;
    after bad input, what this process added to run_dir is removed (the dir too, if this process made it). In a
    sweep the job's dir is kept with its verdict (job_status.json) and JobFailedError ends this job alone."""
    try:
        if run_dir is not None and absolute(run_dir) not in _STATE and run_dir.is_dir():
            try:  # configs without the Hydra callback still get the lock
                guard(run_dir, prog.rsplit(".", 1)[-1]).late = True
            except RuntimeError as e:
                raise ValueError(str(e)) from None
        return body()
    except (*USER_ERRORS, *RUN_FAILURES) as e:
        bad_input, sweep = isinstance(e, USER_ERRORS), in_multirun()
        if bad_input and not sweep:
            discard_own_files(run_dir)
        if verbose():
            raise
        message = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        kept = run_dir if sweep or not bad_input else None  # after bad input the run dir is gone or not ours
        line = f"{prog}: error: {message} (HYDRA_FULL_ERROR=1 for a traceback)"
        with contextlib.suppress(OSError):  # the log is what failed: the line is on stderr all the same
            say(line, kept, prog, err=True)
        end_job(EXIT_BAD_INPUT if bad_input else EXIT_RUN_FAILED, message, kept)


def hydra_run_dir() -> Path:
    """The run dir Hydra made for this job (inside @hydra.main)."""
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir)


def run_job(body: Callable[[Path], T], prog: str, summary: Callable[[T, Path], str]) -> T:
    """An entry point's whole job: run body in Hydra's run dir under run_cli, then print and log its summary."""
    run_dir = hydra_run_dir()

    def whole() -> T:
        """The body and its closing line (a log that cannot be written is a failed run too)."""
        result = body(run_dir)
        say(summary(result, run_dir), run_dir, prog)
        return result

    return run_cli(whole, prog, run_dir)


# ---------------------------------------------------------------------------------------------- make clean


def shipped_files() -> set[Path]:
    """Real paths of the shipped checkpoints (pinnmpc/checkpoints, checkpoints/): clean never deletes these."""
    found: set[Path] = set()
    for folder in (ROOT / "pinnmpc" / "checkpoints", ROOT / "checkpoints"):
        if folder.is_dir():
            found |= {p.resolve() for p in folder.rglob("*") if p.is_file()}
    return found


def clean(paths: list[Path]) -> list[Path]:
    """Delete run outputs under paths, keeping run dirs a live run holds and every file a shipped checkpoint
    resolves to; returns what was kept."""
    keep_files, kept = shipped_files(), []
    for top in paths:
        if top.is_symlink() or top.is_file():
            if top.resolve() in keep_files:
                kept.append(top)
            else:
                top.unlink()
            continue
        if not top.is_dir():
            continue
        for folder, dirs, files in os.walk(top, topdown=True):
            here = Path(folder)
            if LOCK_NAME in files and holder(here) is not None:
                kept.append(here)
                dirs[:] = []
                continue
            for name in files + [d for d in dirs if (here / d).is_symlink()]:
                p = here / name
                if p.resolve() in keep_files:
                    kept.append(p)
                else:
                    p.unlink()
        for folder, _dirs, _files in sorted(os.walk(top), key=lambda w: -len(Path(w[0]).parts)):
            if Path(folder).is_dir() and not any(Path(folder).iterdir()):
                Path(folder).rmdir()
    return kept


def main(argv: list[str]) -> int:
    """`python -m pinnmpc.cli clean PATH...` (make clean)."""
    if len(argv) < 2 or argv[0] != "clean":
        print("usage: python -m pinnmpc.cli clean PATH...", file=sys.stderr)
        return EXIT_BAD_INPUT
    for p in clean([Path(a) for a in argv[1:]]):
        print(f"kept {p} (a live run holds it, or it is a shipped checkpoint)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
