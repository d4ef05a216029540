"""Sweeps: a failing job is one failed job. Each job of a multirun leaves its verdict in job_status.json, the other
jobs run to the end, and when the sweep ends one summary (sweep_summary.md/.json) names every failed job and why,
and the sweep exits non-zero if any failed."""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import traceback
from pathlib import Path
from typing import Any, NoReturn

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pinnmpc.util.io import atomic_write, save_json
from pinnmpc.util.tables import md_table

STATUS_FILE = "job_status.json"  # in each sweep job's dir: its verdict, exit code and why
SUMMARY = "sweep_summary"  # .md and .json in the sweep dir
EXIT_SWEEP_FAILED = 1  # a sweep with a failed job exits with this
log = logging.getLogger(__name__)


class JobFailedError(Exception):
    """A sweep job that failed and said so already: Hydra records it, the summary names it, the sweep goes on."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


def in_multirun() -> bool:
    """Whether this process runs a job of a Hydra multirun (-m)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def record(run_dir: Path | None, verdict: str, code: int, message: str) -> None:
    """Write a job's verdict into its dir (nothing where the dir is gone or unwritable: the summary says so)."""
    if run_dir is None or not Path(run_dir).is_dir():
        return
    with contextlib.suppress(OSError):
        save_json(Path(run_dir) / STATUS_FILE, {"verdict": verdict, "exit_code": code, "message": message})


def end_job(code: int, message: str, run_dir: Path | None) -> NoReturn:
    """A job that failed with exit code `code`: alone, the process exits; in a sweep its verdict is recorded and
    JobFailedError raised, so that Hydra ends this job and starts the next."""
    if in_multirun():
        record(run_dir, "failed", code, message)
        raise JobFailedError(code, message)
    sys.exit(code)


def exit_stopped(code: int, message: str, run_dir: Path | None) -> NoReturn:
    """A job stopped by a signal exits with `code` (128 + the signal). A signal means "stop", not "skip": in a
    sweep the job's verdict is recorded, the summary written for the jobs that ran (the later ones never start),
    and the whole sweep exits with that code."""
    if in_multirun() and run_dir is not None:
        record(run_dir, "interrupted", code, message)
        from hydra.core.hydra_config import HydraConfig

        sweep_dir = Path(HydraConfig.get().sweep.dir)
        with contextlib.suppress(OSError):
            s = write_summary(sweep_dir, interrupted=message)
            print(f"sweep: stopped at job {run_dir.name} ({message}): {s['ok']} of {s['jobs']} jobs ran to the end, "
                  f"the rest did not start; summary: {sweep_dir / f'{SUMMARY}.md'}", file=sys.stderr)  # fmt: skip
    sys.exit(code)


def _overrides(job_dir: Path) -> list[str]:
    """The job's own overrides as Hydra saved them."""
    f = job_dir / ".hydra" / "overrides.yaml"
    return [str(o) for o in OmegaConf.to_container(OmegaConf.load(f))] if f.is_file() else []  # type: ignore[union-attr]


def _read(path: Path) -> dict[str, Any]:
    """A JSON file as a dict ({} where absent or unreadable)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _numbered(path: Path) -> tuple[int, str]:
    """Sort key: job dirs by number."""
    return (int(path.name), "") if path.name.isdigit() else (sys.maxsize, path.name)


def job_row(job_dir: Path, common: set[str]) -> dict[str, Any]:
    """One job's line of the summary: the overrides that set it apart (not those every job shares), verdict, exit
    code, why, and the headline numbers of its own metrics."""
    status = _read(job_dir / STATUS_FILE)
    verdict = status.get("verdict", "unknown")
    own = [o for o in _overrides(job_dir) if o not in common]
    row: dict[str, Any] = {"job": job_dir.name, "overrides": " ".join(own)}
    if verdict == "running":  # the job started and never ended: killed from outside (OOM, a scheduler)
        row.update(verdict="failed", exit_code=None, message="ended without a verdict (killed?)")
    else:
        row.update(verdict=verdict, exit_code=status.get("exit_code"), message=status.get("message", ""))
    closed = _read(job_dir / "metrics.json")
    if closed:
        row["status"] = closed.get("status") if closed.get("status") != row["message"] else "(as message)"
        mae = closed.get("mae") or {}
        angles = list(mae)[: len(mae) // 2]
        row["worst_angle_mae"] = max((mae[n] for n in angles), default=None)
    trained = _read(job_dir / "train_metrics.json")
    if trained:
        row["status"] = trained.get("status")
        row["best_val_rmse_position"] = trained.get("best_val_rmse_position")
    return row


def write_summary(sweep_dir: Path, interrupted: str | None = None) -> dict[str, Any]:
    """sweep_summary.json and .md in the sweep dir, from every job dir's verdict (interrupted: why the sweep
    stopped before its end, None: it ran every job)."""
    jobs = sorted((p for p in sweep_dir.iterdir() if p.is_dir() and (p / ".hydra").is_dir()), key=_numbered)
    sets = [set(_overrides(j)) for j in jobs]
    common = set.intersection(*sets) if len(sets) > 1 else set()
    rows = [job_row(j, common) for j in jobs]
    failed = [r for r in rows if r["verdict"] != "ok"]
    summary = {
        "sweep_dir": str(sweep_dir),
        "jobs": len(rows),
        "ok": len(rows) - len(failed),
        "failed": len(failed),
        "exit_code": EXIT_SWEEP_FAILED if failed else 0,
        "interrupted": interrupted,  # why the sweep stopped early (the jobs after the last row never started)
        "rows": rows,
    }
    save_json(sweep_dir / f"{SUMMARY}.json", summary)
    fields = list(dict.fromkeys(k for r in rows for k in r))
    table = md_table(fields, [["" if r.get(f) is None else str(r.get(f)) for f in fields] for r in rows])
    head = f"{summary['ok']} of {len(rows)} jobs ok, {len(failed)} failed"
    head += f"; the sweep stopped early: {interrupted}\n\n" if interrupted else "\n\n"
    atomic_write(sweep_dir / f"{SUMMARY}.md", lambda p: p.write_text(head + table + "\n"))
    return summary


def _sweeping(config: DictConfig) -> bool:
    """Whether a job's config is one of a multirun (hydra.mode is an enum there, a string where a user set it)."""
    return str(OmegaConf.select(config, "hydra.mode")).endswith("MULTIRUN")


class SweepSummary(Callback):
    """Hydra callback (conf/hydra/default.yaml): every sweep job's verdict on disk, a failed job no end to the sweep,
    one summary at its end and a non-zero exit when a job failed. Single runs are left alone."""

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Mark the job as running: a job killed from outside is then told apart from one that never started."""
        if _sweeping(config):
            record(Path(config.hydra.runtime.output_dir), "running", -1, "")

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """Record the verdict; a failed job's exception stays here (the launcher would end the sweep with it)."""
        if not _sweeping(config):
            return
        run_dir = Path(config.hydra.runtime.output_dir)
        if job_return.status == JobStatus.FAILED:
            e = job_return._return_value
            if isinstance(e, JobFailedError):
                code, message = e.code, e.message
            else:  # not one of ours: a bug, or an error no check caught; its traceback goes to the job's log
                code, message = EXIT_SWEEP_FAILED, f"{type(e).__name__}: {e}".splitlines()[0]
                text = "".join(traceback.format_exception(type(e), e, e.__traceback__))
                log.error("job %s failed: %s", config.hydra.job.num, text)
                job = f"pinnmpc.{config.hydra.job.name}"
                print(f"{job}: error: {message} (job {config.hydra.job.num})", file=sys.stderr)
            record(run_dir, "failed", code, message)
            job_return.status = JobStatus.COMPLETED
            job_return.return_value = None
        elif _read(run_dir / STATUS_FILE).get("verdict") in (None, "running"):
            record(run_dir, "ok", 0, "")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Write the summary, say which jobs failed, and exit non-zero if any did."""
        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        s = write_summary(sweep_dir)
        where = sweep_dir / f"{SUMMARY}.md"
        if not s["failed"]:
            print(f"sweep: all {s['jobs']} jobs ok; summary: {where}")
            return
        for r in s["rows"]:
            if r["verdict"] != "ok":
                print(f"sweep: job {r['job']} ({r['overrides']}) failed, exit {r['exit_code']}: {r['message']}",
                      file=sys.stderr)  # fmt: skip
        print(f"sweep: {s['failed']} of {s['jobs']} jobs failed; summary: {where}", file=sys.stderr)
        sys.exit(EXIT_SWEEP_FAILED)
