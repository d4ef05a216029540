"""plant=franka: a Franka arm (FR3, Panda) driven through libfranka with franky, one joint velocity command per
control period, time from the robot's clock, behind a safety layer of ours (docs/franka.md)."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any

import numpy as np

from pinnmpc.plant.base import PlantError
from pinnmpc.plant.franka_safety import SafetyLayer
from pinnmpc.plant.franka_sim import SimServer, free_loopback
from pinnmpc.plant.settings import FrankaPlantSettings
from pinnmpc.systems.base import System

LATE_TICKS = 2  # a command sent this many 1 ms ticks past plant.command_at counts as late


def state_at(
    target: float, before: tuple[float, np.ndarray] | None, after: tuple[float, np.ndarray], nq: int
) -> np.ndarray:
    """The state at robot time target from the reads around it: v linear between them (the later read's alone
    without an earlier one), q back from the later read by the trapezoid of v. A loop that reads its state a tick
    late would otherwise see the arm a tick's travel further on, and plan and estimate from it (docs/franka.md)."""
    t1, x1 = after
    q1, v1 = x1[:nq], x1[nq:]
    v = v1
    if before is not None and before[0] < target:
        t0, v0 = before[0], before[1][nq:]
        v = v1 + (t1 - target) / (t1 - t0) * (v0 - v1)
    return np.concatenate([q1 - (t1 - target) * 0.5 * (v + v1), v])


class FrankaPlant:
    """The robot as a plant: step(x, u) sends u (made safe) as an asynchronous joint velocity motion that replaces
    the last, waits until the robot's clock is one period past the state the command answers, and returns the
    measured state. close() stops the arm, recovers from errors and stops an embedded server, however a run ends."""

    def __init__(self, system: System, tau: float, settings: FrankaPlantSettings, run_dir: Path | None = None) -> None:
        """Start franky-sim when plant.simulator asks for it, connect with franky; nothing moves yet."""
        import franky

        settings.make_consistent()
        self.franky = franky
        self.tau, self.settings, self.nq = float(tau), settings, system.nq
        self.step_times: list[float] = []
        self.stick_slip_steps = 0
        self.errors: list[str] = []
        self.fine: list[tuple[float, np.ndarray, np.ndarray]] = []  # (t, x, command) of every state read in a period
        self.commanded = np.zeros(self.nq)  # the joint velocity command the robot reported with the last state read
        self.server: SimServer | None = None
        self.robot: Any = None
        self.command_acceleration: np.ndarray | None = None  # how fast franky ramps each joint's command, rad/s^2
        self.last_command: np.ndarray | None = None  # the last command sent, as the safety layer made it
        self.closed = False
        self.rest = False  # whether the arm ended at rest (close() says)
        self.host = settings.host
        gains = settings.servo_gain or list(system.servo_gain)
        if settings.command_at > self.tau + 1e-9:
            raise ValueError(
                f"plant.command_at={settings.command_at} s; expected 0 to the control period {self.tau} s (the "
                "period: each command goes out as the next period begins)"
            )
        self.safety = SafetyLayer(system, tau, settings)
        self.period_start = 0.0  # robot time of the state the next command answers, s
        self.measured_at = 0.0  # robot time that state was read at (within a tick after it)
        self.period_began = 0.0  # robot time the last period run began at, s
        self.late = 0  # commands that came after their period had ended
        self.carried_back = 0  # states read a tick or more past their time, carried back to it (state_at)
        self.sent = 0  # commands sent since the arm was last brought to rest
        self.robot_periods: list[float] = []  # robot time between measurements, s
        self.send_offsets: list[float] = []  # robot time from each command's state to its sending, s
        try:
            host = settings.host
            if settings.simulator != "none":
                host = self._start_server(host, gains, run_dir)
            self.host = host
            realtime = franky.RealtimeConfig.Enforce if settings.realtime_kernel else franky.RealtimeConfig.Ignore
            self.robot = franky.Robot(host, realtime_config=realtime)
            self.robot.relative_dynamics_factor = settings.relative_dynamics_factor
            reported = np.asarray(self.robot.joint_velocity_limit.max, dtype=float)[: self.nq]
            if settings.velocity_limit is not None and np.any(np.asarray(settings.velocity_limit) > reported + 1e-9):
                raise PlantError(
                    f"plant.velocity_limit={list(settings.velocity_limit)}: above the robot's joint velocity limits "
                    f"{reported.tolist()} rad/s (franky's); expected each at most the robot's"
                )
            self.safety.cap_velocity(reported)
            limit = np.asarray(self.robot.joint_acceleration_limit.max, dtype=float)[: self.nq]
            self.command_acceleration = limit * settings.relative_dynamics_factor  # rad/s^2: franky's ramp
            if self.robot.has_errors:
                self.errors.append(f"at connect: {self.robot.state.current_errors}")
                self.robot.recover_from_errors()
        except BaseException:
            self.close()
            raise

    def _start_server(self, host: str | None, gains: list[float], run_dir: Path | None, tries: int = 3) -> str:
        """franky-sim on `host`, or on the first free loopback address; a server that exits before serving on a
        free address (another run took it between the check and the bind) is started again on the next one."""
        start_q = np.asarray(self.settings.initial_q or np.mean(self.safety.limits, axis=0), dtype=float)
        log_path = None if run_dir is None else Path(run_dir) / "franky_sim.log"
        for attempt in range(tries):
            address = host or free_loopback()
            self.server = SimServer(address, gains, start_q, log_path)
            try:
                self.server.wait_ready(self.settings.start_timeout)
                return address
            except RuntimeError:
                self.server.stop()
                if host or attempt == tries - 1 or not self.server.exited_early:
                    raise
        raise RuntimeError(f"plant=franka: franky-sim did not start in {tries} tries")  # tries >= 1 returns above

    @property
    def delay_periods(self) -> int:
        """1 where each command goes out a whole period after its state (plant.command_at = tau): the closed loop
        then plans from the predicted start of the period the command runs in; 0 otherwise."""
        return int(self.settings.command_at >= self.tau - 1e-9)

    def now(self) -> float:
        """The robot's clock, s."""
        return float(self.robot.state.time.to_sec())

    def measure(self) -> tuple[float, np.ndarray]:
        """The robot's time and state (q, dq) read together; the command it reports receiving (libfranka's dq_d:
        franky's ramp to each command, libfranka's filter) kept in self.commanded."""
        s = self.robot.state
        self.commanded = np.asarray(s.dq_d, dtype=float)
        return float(s.time.to_sec()), np.concatenate([np.asarray(s.q, dtype=float), np.asarray(s.dq, dtype=float)])

    def start(self, x0: np.ndarray) -> np.ndarray:
        """Move the arm to x0's joint angles at rest (a jerk-limited joint motion), then return the measured state:
        the closed loop starts from where the robot is, not from where the model says."""
        q0 = np.asarray(x0, dtype=float)[: self.nq]
        self.safety.check_target(q0)
        if self.settings.move_to_start:
            self.stop_arm()
            for _ in range(2):  # the second move takes out what the first left while the arm settled
                motion = self.franky.JointMotion(
                    self.franky.JointState(q0.tolist()), relative_dynamics_factor=self.settings.start_dynamics_factor
                )
                self._guarded(lambda m=motion: self._move_and_join(m, "move to the start"), "move to the start")
            self.at_rest(self.settings.start_settle_time, self.settings.start_settle_speed)
        self.sent = 0
        t, x = self.measure()
        self.fine = []
        self._keep(t, x)
        off = float(np.abs(x[: self.nq] - q0).max())
        if self.settings.move_to_start and off > self.settings.start_tolerance:
            raise PlantError(
                f"plant=franka: the arm stopped {off:.3g} rad from the reference's start (plant.start_tolerance="
                f"{self.settings.start_tolerance})"
            )
        self.period_start, self.measured_at = t, t
        return x

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Send u for the period that began at the last measurement, wait one period of robot time, measure."""
        wall = time.perf_counter()
        t_send, x_now = self.measure()
        self._keep(t_send, x_now)
        if not self.sent:  # the arm at rest waits for its first command: its period begins when it goes out
            self.period_start = self.measured_at = t_send
            if self.delay_periods:  # a period late: the servo holds the arm at rest until then (the input logged)
                self._send(np.zeros(self.nq))
        self.period_began = self.period_start
        elapsed = t_send - self.period_start
        if elapsed > self.settings.watchdog_periods * self.tau:
            self.safety.events["watchdog_stops"] += 1
            self.stop_arm()
            raise PlantError(
                f"watchdog: the command came {elapsed * 1e3:.1f} ms of robot time after its state, past "
                f"plant.watchdog_periods={self.settings.watchdog_periods} periods of {self.tau * 1e3:.0f} ms; the arm "
                "was stopped"
            )
        if self.settings.command_at > 0:  # a fixed dead time: wait on the robot's clock
            t_send, x_now = self._wait_until(self.period_start + self.settings.command_at)
        command = self.safety.command(np.asarray(u, dtype=float), x_now)  # made safe for the state it meets
        self.send_offsets.append(t_send - self.period_start)
        due = self.settings.command_at + LATE_TICKS * 1e-3 if self.settings.command_at > 0 else self.tau
        if t_send - self.period_start > due:
            self.late += 1  # past plant.command_at by more than the state stream's ticks, or past its period
        self._send(command)
        self.sent += 1
        target = self.period_start + self.tau
        # a command sent as the next period begins: that period's state is the one read just before it went out
        t, x = (t_send, x_now) if self.delay_periods else self._wait_until(target)
        self.robot_periods.append(t - self.measured_at)
        self.period_start, self.measured_at = target, t  # periods on the robot's clock, one tau apart
        self.step_times.append(time.perf_counter() - wall)
        return x

    def _send(self, command: np.ndarray) -> None:
        """A joint velocity command as an asynchronous motion replacing the last, held plant.hold_periods at most."""
        hold = self.franky.Duration(int(round(self.settings.hold_periods * self.tau * 1e3)))
        motion = self.franky.JointVelocityMotion(command.tolist(), duration=hold)
        self._guarded(lambda: self.robot.move(motion, asynchronous=True), "send a command")
        self.last_command = np.array(command, dtype=np.float64)

    def _keep(self, t: float, x: np.ndarray) -> None:
        """A state read on the robot's clock, kept for the fine samples (plant.record_fine) when it is new."""
        if self.settings.record_fine and (not self.fine or t > self.fine[-1][0]):
            self.fine.append((t, x, self.commanded))

    def _wait_until(self, target: float) -> tuple[float, np.ndarray]:
        """Poll the robot's clock until it reaches target: the time read and the state at target (a state read a
        tick or more later carried back to it, state_at); motion errors are recorded and end the run."""
        deadline = time.monotonic() + self.settings.stall_timeout
        before = None
        while True:
            t, x = self.measure()
            self._keep(t, x)
            if t >= target - 5e-4:  # the state stream's 1 ms tick
                if t <= target + 5e-4:
                    return t, x
                self.carried_back += 1
                return t, state_at(target, before, (t, x), self.nq)
            before = (t, x)
            self._guarded(self.robot.poll_motion, "wait for the period's end")
            if time.monotonic() > deadline:
                self.stop_arm()
                raise PlantError(
                    f"plant=franka: the robot's clock stood still for plant.stall_timeout="
                    f"{self.settings.stall_timeout} s of wall time (connection lost?)"
                )
            time.sleep(self.settings.poll_s)

    def _guarded(self, call: Any, what: str) -> Any:
        """Run a franky call; a libfranka error is recorded, recovered from, and ends the run as a plant failure."""
        try:
            return call()
        except self.franky.Exception as e:
            message = f"{what}: {type(e).__name__}: {e}"
            self.errors.append(message)
            self._recover()
            raise PlantError(f"libfranka: {message}") from None

    def _recover(self) -> None:
        """libfranka's automatic error recovery, recorded when it fails."""
        with contextlib.suppress(Exception):
            if self.robot is not None and self.robot.has_errors and not self.robot.recover_from_errors():
                self.errors.append("automatic error recovery failed")

    def _move_and_join(self, motion: Any, what: str) -> None:
        """A motion run to its end, waited for only while the robot's clock runs: a robot (or server) that stops
        answering mid-motion ends the run as a plant failure after plant.stall_timeout, not in a wait forever."""
        self.robot.move(motion, asynchronous=True)
        last, since = self.now(), time.monotonic()
        while not self.robot.join_motion(timeout=self.settings.poll_s * 20):
            t = self.now()
            if t > last:
                last, since = t, time.monotonic()
            elif time.monotonic() - since > self.settings.stall_timeout:
                why = f"{what}: the robot's clock stood still for plant.stall_timeout={self.settings.stall_timeout} s"
                self.errors.append(why)
                raise PlantError(f"plant=franka: {why} of wall time mid-motion (connection lost?)")

    def stop_arm(self) -> None:
        """A joint velocity stop motion, waited for, then error recovery: the arm at rest."""
        if self.robot is None:
            return
        try:
            self._move_and_join(self.franky.JointVelocityStopMotion(), "stop motion")
        except self.franky.Exception as e:
            self.errors.append(f"stop motion: {type(e).__name__}: {e}")
            self._recover()
            with contextlib.suppress(self.franky.Exception, PlantError):
                self._move_and_join(self.franky.JointVelocityStopMotion(), "stop motion")
        self._recover()

    def at_rest(self, settle: float = 1.0, speed: float | None = None) -> bool:
        """Whether every joint speed falls below `speed` (plant.rest_speed) within `settle` s of robot time."""
        speed = self.settings.rest_speed if speed is None else speed
        try:
            t, x = self.measure()
            end, deadline = t + settle, time.monotonic() + self.settings.stall_timeout
            while np.abs(x[self.nq :]).max() > speed:
                if t >= end or time.monotonic() > deadline:
                    return False
                time.sleep(self.settings.poll_s)
                t, x = self.measure()
        except Exception:
            return False
        return True

    def close(self) -> None:
        """Stop the arm and the embedded server; safe to call twice and from a signal's unwinding."""
        if self.closed:
            return
        self.closed = True
        try:
            if self.robot is not None:
                with contextlib.suppress(PlantError):  # recorded in self.errors; the server still goes below
                    self.stop_arm()
                self.rest = self.at_rest()
        finally:
            self.robot = None  # franky's destructor closes the connection before the server goes
            if self.server is not None:
                self.server.stop()

    def report(self) -> dict[str, Any]:
        """What the run's metrics.json says of the robot: its address, errors, the safety layer's actions, timing."""
        periods = np.asarray(self.robot_periods)
        return {
            "host": self.host,
            "simulator": self.settings.simulator,
            "server_pid": None if self.server is None else self.server.pid,
            "errors": list(self.errors),
            "safety": dict(self.safety.events),
            "late_commands": int(self.late),
            "states_carried_back": int(self.carried_back),
            "command_offset_s": {
                "median": float(np.median(self.send_offsets)) if self.send_offsets else float("nan"),
                "max": float(max(self.send_offsets)) if self.send_offsets else float("nan"),
            },
            "robot_period_s": {
                "median": float(np.median(periods)) if periods.size else float("nan"),
                "max": float(periods.max()) if periods.size else float("nan"),
            },
            "at_rest": self.rest,
        }

    def fine_samples(self) -> dict[str, np.ndarray]:
        """The states read while periods ran (plant.record_fine): t (n,), x (n, nx) and the command the robot
        reported with each (n, nq), on the robot's clock."""
        if not self.fine:
            return {"t": np.zeros(0), "x": np.zeros((0, 2 * self.nq)), "command": np.zeros((0, self.nq))}
        t, x, command = zip(*self.fine)
        return {"t": np.asarray(t), "x": np.stack(x), "command": np.stack(command)}
