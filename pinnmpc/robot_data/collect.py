"""Collecting a robot log: the simulated robot run in episodes for a given robot time, recorded `fine` times per period.

Episodes cycle through closed loops of the shipped controller on random-<seed> and driven-<seed> references and
input excitation (random steps held over whole periods around a weak stabilising feedback). The robot is stepped as
a plant of period tau / fine with the input held over the control period, so the fine samples and the control-rate
ones lie on one zero-hold trajectory; the controller sees the control rate only.
run_collect is the job `python -m pinnmpc.collect` runs: refuse a run dir that holds a log already (logs are
append-only), check the settings, collect with the .npz rewritten at each episode's end (a killed run keeps its
finished episodes, its meta saying cut_short), then write the whole log.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from pinnmpc.plant.base import Plant, PlantError
from pinnmpc.plant.build import make_plant
from pinnmpc.plant.settings import plant_settings, robot_name
from pinnmpc.robot_data.logs import RobotLog, log_files, write_log
from pinnmpc.robot_data.settings import validate_collect
from pinnmpc.simulation.loop import run_loop
from pinnmpc.simulation.settings import within_plant_limits
from pinnmpc.simulation.setup import build_controller, system_reference
from pinnmpc.systems.base import System
from pinnmpc.systems.settings import job_system
from pinnmpc.util.signals import StopSignal

log = logging.getLogger(__name__)

KINDS = ("random", "driven", "excitation")  # episode kinds: references of the system's built-ins, or excitation


@dataclass
class FineRecorder:
    """A plant of one control period made of `fine` steps of a plant of period tau / fine, every state kept."""

    plant: Plant
    fine: int
    states: list[np.ndarray] = field(default_factory=list)
    commands: list[np.ndarray] = field(default_factory=list)  # a robot's reported command at each state (or none)
    sent: list[np.ndarray] = field(default_factory=list)  # a robot's commands as its safety layer sent them (or none)
    step_times: list[float] = field(default_factory=list)
    stick_slip_steps: int = 0

    @property
    def tau(self) -> float:
        """The control period."""
        return self.plant.tau * self.fine

    @property
    def delay_periods(self) -> int:
        """The robot's: periods it holds each input late (the closed loop plans ahead of them)."""
        return int(getattr(self.plant, "delay_periods", 0))

    def start(self, x0: np.ndarray) -> np.ndarray:
        """A new episode from x0 (the start state, as a robot's recorder returns the measured one)."""
        self.states = [np.asarray(x0, dtype=np.float64)]
        return self.states[0]

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One control period, the input held; raises PlantError as the plant does."""
        begin, x = time.perf_counter(), np.asarray(x0, dtype=np.float64)
        for _ in range(self.fine):
            x = self.plant.step(x, u)
            self.states.append(x)
        self.step_times.append(time.perf_counter() - begin)
        return x


@dataclass
class Episode:
    """One episode as simulated: fine states ((periods * fine + 1), nx) and the inputs held (periods, nu)."""

    kind: str
    name: str
    x_fine: np.ndarray
    u: np.ndarray
    status: str
    command_fine: np.ndarray | None = None  # the command a robot reported at each fine state; None: not reported


def fine_plant(system: System, plant_cfg: DictConfig, fine: int, robots: Any) -> FineRecorder:
    """The robot as a plant of period tau / fine, MuJoCo's RK4 step kept (substeps / fine per fine period)."""
    cfg = OmegaConf.create(OmegaConf.to_container(plant_cfg, resolve=True))
    if cfg.get("kind") == "franka":  # a robot: whole periods, the fine samples from its 1 kHz state stream
        from pinnmpc.robot_data.franka_recorder import FrankaRecorder

        cfg.record_fine = True
        return FrankaRecorder(make_plant(system, cfg, system.tau, robots), fine)  # type: ignore[return-value]
    if cfg.get("kind") == "mujoco":
        cfg.substeps = max(1, -(-int(cfg.substeps) // fine))
    return FineRecorder(make_plant(system, cfg, system.tau / fine, robots), fine)


def inside_until(x: np.ndarray, low: np.ndarray, high: np.ndarray) -> int:
    """How many leading states lie inside [low, high] (all of them: len(x))."""
    out = np.flatnonzero(((x < low) | (x > high)).any(axis=1))
    return int(out[0]) if out.size else len(x)


def excitation_episode(
    system: System, recorder: FineRecorder, steps: int, settings: DictConfig, rng: np.random.Generator, box: Any
) -> Episode:
    """Random input steps held 1..hold periods on top of a weak feedback to random targets in the middle `fraction`
    of the joint range (gravity of the model compensated on torque arms), no step pushing a joint on beyond `speed`
    of its velocity bound (servos: commands clipped there); on a robot that ramps its commands (plant=franka) no
    command moves further from the last than the ramp covers in half a period; stops where the state leaves `box`."""
    n, tau = system.nq, system.tau
    limits = system.joint_limits or type(system.state_box)(system.state_box.low[:n], system.state_box.high[:n])
    lo, hi = np.asarray(limits.low), np.asarray(limits.high)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * float(settings.fraction)
    ulo, uhi = np.asarray(system.input_box.low), np.asarray(system.input_box.high)
    w, zeta, amp = float(settings.bandwidth), float(settings.damping), float(settings.amplitude)
    vmax = float(settings.speed) * np.minimum(-np.asarray(system.state_box.low[n:]), system.state_box.high[n:])
    hold_max, every = int(settings.hold), max(1, round(float(settings.target_every) / tau))
    x = np.concatenate((mid + half * rng.uniform(-1, 1, n), np.zeros(n)))
    x = recorder.start(x)  # a robot answers with where it is
    us, target, offset, left, status = [], x[:n], np.zeros(n), 0, "ok"
    ramp = getattr(recorder.plant, "command_acceleration", None)
    step_max = None if ramp is None else 0.5 * tau * np.asarray(ramp)  # the servo follows within half a period
    low, high = np.asarray(box.low), np.asarray(box.high)
    for k in range(steps):
        if k % every == 0:
            target = mid + half * rng.uniform(-1, 1, n)
        if left == 0:
            offset, left = amp * (uhi - ulo) / 2 * rng.uniform(-1, 1, n), int(rng.integers(1, hold_max + 1))
        left -= 1
        q, v = x[:n], x[n:]
        push = np.where((np.abs(v) > vmax) & (v * offset > 0), 0.0, offset)  # no push past the speed limit
        if system.actuation == "velocity_servo":
            u = np.clip(w * (target - q) + push, -vmax, vmax)
        else:
            m, g, _ = system.dynamics_terms(torch.from_numpy(q[None]), torch.zeros(1, n, dtype=torch.float64))
            u = g[0].numpy() + m[0].numpy() @ (w * w * (target - q) - 2 * zeta * w * v) + push  # h(v=0) = g
        if step_max is not None:
            last = us[-1] if us else np.zeros(n)  # the arm starts at rest
            u = np.clip(u, last - step_max, last + step_max)
        u = np.clip(u, ulo, uhi)
        try:
            x = recorder.step(x, u)
        except PlantError as e:
            status = f"plant_failure: {e}"
            break
        us.append(u)
        if inside_until(x[None], low, high) == 0:
            status = "left the state box"
            break
    return Episode("excitation", "excitation", np.array(recorder.states[: len(us) * recorder.fine + 1]),
                   applied(as_sent(recorder, np.array(us).reshape(-1, n)), recorder.plant), status,
                   reported(recorder, len(us) * recorder.fine + 1))  # fmt: skip


def as_sent(recorder: FineRecorder, commands: np.ndarray) -> np.ndarray:
    """The commands as the robot's safety layer sent them (clipped to its velocity limits, slowed before its joint
    limits), where it reports them; else the commands given."""
    return np.array(recorder.sent[: len(commands)]).reshape(commands.shape) if recorder.sent else commands


def reported(recorder: FineRecorder, samples: int) -> np.ndarray | None:
    """The commands the robot reported at the episode's first `samples` fine states (None where it reports none)."""
    return np.array(recorder.commands[:samples]) if recorder.commands else None


def applied(commands: np.ndarray, plant: Any) -> np.ndarray:
    """The inputs held over each period: the commands, or on a plant that sends each a period late (plant.command_at
    = tau) the one before (the first period's: zero, the arm at rest), so every logged step is a held input."""
    if not getattr(plant, "delay_periods", 0) or not len(commands):
        return commands
    return np.concatenate((np.zeros_like(commands[:1]), commands[:-1]))


def closed_loop_episode(
    kind: str,
    seed: int,
    steps: int,
    cfg: DictConfig,
    system: System,
    controller: Any,
    recorder: FineRecorder,
    reference: Callable[[str], Any],
    stop: Callable[[], bool] | None,
) -> Episode:
    """The controller tracking `<kind>-<seed>` from the reference's first state, at most `steps` periods."""
    ref = reference(f"{kind}-{seed}")
    x0 = recorder.start(ref.x[0])  # a robot answers with where it is
    run = run_loop(controller, recorder, ref, x0=x0, max_steps=steps, noise_sigma=float(cfg.noise_sigma), seed=seed,
                   progress=False, stop=stop)  # fmt: skip
    periods = len(run.x) - 1  # a failed step's input has no state after it
    return Episode(kind, ref.name, np.array(recorder.states[: periods * recorder.fine + 1]),
                   applied(as_sent(recorder, run.u[:periods]), recorder.plant), run.status,
                   reported(recorder, periods * recorder.fine + 1))  # fmt: skip


def collect(
    cfg: DictConfig,
    system: System,
    controller: Any,
    reference: Callable[[str], Any],
    *,
    stop: Callable[[], bool] | None = None,
    meta: dict[str, Any] | None = None,
    checkpoint: Callable[[RobotLog], None] | None = None,
) -> RobotLog | None:
    """Episodes until cfg.robot_time seconds of held input are logged (cut where a state leaves the state box);
    states logged with Gaussian noise of cfg.noise_sigma. checkpoint gets the log so far at each episode's end (its
    meta marked cut short), so a killed run keeps its finished episodes; None: stopped before any episode ended."""
    recorder = fine_plant(system, cfg.plant, int(cfg.fine), cfg.system.get("robots"))
    ramp = getattr(recorder.plant, "command_acceleration", None)
    if ramp is not None:  # identify leaves out the intervals where the servo still ramps towards a command
        meta = {**(meta or {}), "command_acceleration": [float(a) for a in ramp],
                "command_at": float(recorder.plant.settings.command_at)}  # fmt: skip
    try:  # a robot (plant=franka) stops its arm and its server however the collect ends
        return _collect(cfg, system, controller, reference, recorder, stop, meta, checkpoint)
    finally:
        if hasattr(recorder.plant, "close"):
            recorder.plant.close()


def _collect(
    cfg: DictConfig,
    system: System,
    controller: Any,
    reference: Callable[[str], Any],
    recorder: FineRecorder,
    stop: Callable[[], bool] | None,
    meta: dict[str, Any] | None,
    checkpoint: Callable[[RobotLog], None] | None,
) -> RobotLog | None:
    """collect's episodes on a built recorder."""
    fine, tau, sigma = int(cfg.fine), system.tau, float(cfg.noise_sigma)
    total = int(round(float(cfg.robot_time) / tau))
    noise = np.random.default_rng(int(cfg.seed) + 1)
    box = system.state_box
    low, high = np.asarray(box.low), np.asarray(box.high)
    kinds, episodes, done, number = list(cfg.episodes.kinds), [], 0, 0
    bar = tqdm(total=total * tau, desc="robot time", unit="s", disable=not cfg.progress, file=sys.stderr)
    while done < total and not (stop is not None and stop()):
        kind, seed = kinds[number % len(kinds)], int(cfg.seed) * 1000 + number
        steps = total - done
        if kind == "excitation":
            steps = min(steps, max(1, round(float(cfg.excitation.duration) / tau)))
            ep = excitation_episode(system, recorder, steps, cfg.excitation, np.random.default_rng(seed), box)
        else:
            ep = closed_loop_episode(kind, seed, steps, cfg, system, controller, recorder, reference, stop)
        number += 1
        keep = inside_until(ep.x_fine, low, high)  # whole periods up to the first state outside the box
        periods = min(len(ep.u), (keep - 1) // fine if keep else 0)
        if ep.status != "ok" or periods < len(ep.u):
            log.warning("episode %d (%s) %s after %d of %d periods", number - 1, ep.name, ep.status, periods, steps)
        if periods < 1:
            if not episodes and number >= 3 * len(kinds):
                raise RuntimeError(f"no episode logged a period in {number} tries; the robot leaves the state box")
            continue
        x_fine = ep.x_fine[: periods * fine + 1]
        measured = x_fine + sigma * noise.standard_normal(x_fine.shape) if sigma > 0 else x_fine
        commands = None if ep.command_fine is None else ep.command_fine[: periods * fine + 1]
        episodes.append((number - 1, measured, ep.u[:periods], commands))
        done += periods
        bar.update(periods * tau)
        if checkpoint is not None and done < total:
            cut = cut_short("the collect did not finish (killed?)", done * tau, total * tau)
            checkpoint(assemble(episodes, system, fine, sigma, {**(meta or {}), "cut_short": cut}))
    bar.close()
    if not episodes:
        return None
    cut = None if done >= total else cut_short("stopped", done * tau, total * tau)
    return assemble(episodes, system, fine, sigma, {**(meta or {}), "cut_short": cut})


def cut_short(why: str, logged_s: float, asked_s: float) -> str:
    """The meta's cut_short of a log that holds less than was asked for: why, and how much it holds."""
    return f"{why}: {logged_s:.6g} of {asked_s:.6g} s of robot time logged"


def assemble(
    episodes: list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]],
    system: System,
    fine: int,
    sigma: float,
    meta: dict[str, Any],
) -> RobotLog:
    """One log from the episodes (fine states as measured, inputs): episode after episode in time (one tau apart)
    and the control-rate samples taken from the fine ones; an episode's last sample repeats the input before it. The
    commands a robot reported at the fine samples go in where every episode has them."""
    tau, h = system.tau, system.tau / fine
    t, x, u, ep, tf, xf, ef, t0 = [], [], [], [], [], [], [], 0.0
    for number, measured, inputs, _ in episodes:
        m = len(measured)
        times = t0 + h * np.arange(m)
        times[::fine] = t0 + tau * np.arange(len(inputs) + 1)
        tf.append(times), xf.append(measured), ef.append(np.full(m, number))
        t.append(times[::fine]), x.append(measured[::fine]), ep.append(np.full(len(inputs) + 1, number))
        u.append(np.vstack((inputs, inputs[-1:])))
        t0 = times[-1] + tau
    cat = np.concatenate
    robot_time = sum(len(e[2]) for e in episodes) * tau
    meta = {
        **meta,
        "system": system.name,
        "tau": tau,
        "state_names": list(system.state_names),
        "input_names": list(system.input_names),
        "fine": fine,
        "noise_sigma": sigma,
        "robot_time_s": robot_time,
    }
    reported = [e[3] for e in episodes]
    commands = cat(reported) if all(c is not None for c in reported) else None
    return RobotLog(cat(t), cat(x), cat(u), cat(ep), cat(tf), cat(xf), cat(ef), meta, command_fine=commands)


def refuse_existing(stem: Path, out: str) -> None:
    """Logs are append-only: a collect never replaces one, so a run dir that holds a log of this stem is refused
    before anything runs."""
    found = [p for p in log_files(stem) if p.exists()]
    if found:
        raise ValueError(
            f"out={out}: {found[0]} already holds a log (a collect never replaces one); expected a run dir without "
            "it: another hydra.run.dir= or out="
        )


def run_collect(cfg: DictConfig, run_dir: Path, stop: StopSignal | None = None) -> dict[str, Any]:
    """Check the settings, build the robot first (a bad robot fails before the controller loads), collect, write."""
    start = time.perf_counter()
    system = job_system(cfg, validate_collect)
    within_plant_limits(cfg, system)
    refuse_existing(run_dir / str(cfg.out), str(cfg.out))
    if cfg.plant.get("kind") == "franka":  # a robot's settings alone: it is connected (or started) once, to collect
        plant_settings(OmegaConf.to_container(cfg.plant, resolve=True)).make_consistent()
    else:
        fine_plant(system, cfg.plant, int(cfg.fine), cfg.system.get("robots"))  # refuses an unknown or bad robot
    controller, _, tau = build_controller(cfg, system)
    if abs(tau - system.tau) > 1e-12 * system.tau:
        raise ValueError(f"the controller's tau={tau} differs from system.tau={system.tau}; expected one period")

    def reference(name: str) -> Any:
        """A built-in reference of the system by name."""
        return system_reference(OmegaConf.merge(cfg, {"reference": {"name": name, "path": None}}), system, tau)

    plant = OmegaConf.to_container(cfg.plant, resolve=True)
    robots = OmegaConf.to_container(cfg.system.robots, resolve=True) if cfg.system.get("robots") else {}
    meta = {
        "robot": robot_name(cfg.plant),
        "robot_effects": robots.get(cfg.plant.get("robot")) if cfg.plant.get("robot") else None,
        "seed": int(cfg.seed),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "command": " ".join(["python -m pinnmpc.collect", *sys.argv[1:]]),
        "sources": {"plant": plant, "controller": cfg.controller.get("kind", "pinn"), "checkpoint": cfg.checkpoint,
                    "episodes": list(cfg.episodes.kinds), "excitation": OmegaConf.to_container(cfg.excitation)},
    }  # fmt: skip
    stem, written = run_dir / str(cfg.out), False

    def keep(lg: RobotLog) -> None:
        """The log so far, over this run's own .npz (the first one created new, never replacing another's)."""
        nonlocal written
        try:
            write_log(stem, lg, csv=False, new=not written)
        except FileExistsError:
            raise ValueError(
                f"out={cfg.out}: {log_files(stem)[0]} appeared while collecting; expected it new"
            ) from None
        written = True

    log = collect(cfg, system, controller, reference, stop=None if stop is None else (lambda: stop.requested),
                  meta=meta, checkpoint=keep)  # fmt: skip
    stopped, asked = stop is not None and stop.requested, float(cfg.robot_time)
    result = {"robot_time_s": 0.0, "episodes": 0, "samples": 0, "fine_samples": 0, "files": [], "interrupted": stopped,
              "cut_short": "stopped before the first episode ended: nothing logged"}  # fmt: skip
    if log is not None:
        if stopped and log.meta["cut_short"]:
            log.meta["cut_short"] = cut_short(f"interrupted by {stop.name}", log.meta["robot_time_s"], asked)
        files = write_log(stem, log, new=not written)
        result.update(robot_time_s=log.meta["robot_time_s"], episodes=len(log.episodes), samples=len(log.t),
                      fine_samples=len(log.t_fine), files=[str(f) for f in files],
                      cut_short=log.meta["cut_short"])  # fmt: skip
    return {**result, "wall_s": time.perf_counter() - start}
