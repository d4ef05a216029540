"""Data from a robot: the log format (logs.py), its transitions and episodes in use (episodes.py), collecting
logs from a simulated robot (collect.py), fitting the model's physical coefficients to them (identify.py, the job in
identify_job.py) and that fitted model as a fine-tuning's physics (residual_model.py)."""

from pinnmpc.robot_data.episodes import (
    check_enough,
    select_episodes,
    split_episodes,
    transitions,
    transitions_per_second,
)
from pinnmpc.robot_data.logs import RobotLog, read_log, read_logs, write_log

__all__ = [
    "RobotLog",
    "check_enough",
    "read_log",
    "read_logs",
    "select_episodes",
    "split_episodes",
    "transitions",
    "transitions_per_second",
    "write_log",
]
