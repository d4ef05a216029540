"""Closed loops: the loop itself (controller, plant, reference in; a LoopResult out), its metrics, and a loop from a
config as `python -m pinnmpc.closed_loop` runs it."""

from pinnmpc.simulation.loop import LoopResult, run_loop

__all__ = ["LoopResult", "run_loop"]
