"""A Franka arm as collect's recorder: each control period through libfranka, its fine samples the robot's state
read at `fine` equal sub-times of the period (robot time; its 1 kHz ticks, interpolated where a read missed one), with
the joint velocity command the robot reported at each (`commands`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pinnmpc.plant.franka import FrankaPlant
from pinnmpc.robot_data.collect import FineRecorder


@dataclass
class FrankaRecorder(FineRecorder):
    """The FineRecorder of a robot: start() moves the arm, step() runs one period and keeps its fine states."""

    plant: FrankaPlant  # type: ignore[assignment]

    @property
    def tau(self) -> float:
        """The control period (the robot's plant runs whole periods)."""
        return self.plant.tau

    @property
    def last_command(self) -> np.ndarray | None:
        """The robot's: the last command sent, as its safety layer made it."""
        return self.plant.last_command

    def start(self, x0: np.ndarray) -> np.ndarray:
        """A new episode: the arm moved to x0's joint angles at rest; returns the measured start state."""
        x = self.plant.start(np.asarray(x0, dtype=np.float64))
        self.states, self.commands, self.sent = [x], [self.plant.commanded], []
        return x

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One control period through the robot; its fine states are the stream's at the period's sub-times."""
        x = self.plant.step(x0, u)
        self.sent.append(np.array(self.plant.last_command))  # as the safety layer made it
        begin = self.plant.period_began
        samples = self.plant.fine_samples()
        del self.plant.fine[:-1]  # the period's last state begins the next one's samples
        times = begin + self.tau * np.arange(1, self.fine + 1) / self.fine
        self.states.extend(self.resample(samples["t"], samples["x"], times, x))
        self.commands.extend(self.resample(samples["t"], samples["command"], times, self.plant.commanded))
        self.step_times.append(self.plant.step_times[-1])
        return x

    @staticmethod
    def resample(t: np.ndarray, stream: np.ndarray, times: np.ndarray, end: np.ndarray) -> np.ndarray:
        """A stream read on the robot's clock at `times` by linear interpolation (its 1 ms ticks; the sub-times fall
        on them for periods a multiple of fine ms); with fewer than two reads, the last value."""
        if t.size < 2:
            return np.repeat(np.asarray(end)[None, :], len(times), axis=0)
        return np.stack([np.interp(times, t, stream[:, i]) for i in range(stream.shape[1])], axis=1)
