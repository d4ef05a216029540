"""franky-sim, the libfranka protocol served from MuJoCo, started on its own loopback address and stopped by its
process id: the embedded robot of plant=franka (`python -m pinnmpc.plant.franka_sim` is what the plant runs)."""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

COMMAND_PORT = 1337  # libfranka's fixed TCP port: one server per loopback address


def franky_missing() -> str:
    """Why franky or franky-sim cannot be used here ('' when both import): the one line a skipped test prints."""
    try:
        import franky  # noqa: F401
        import franky_sim  # noqa: F401
    except ImportError as e:
        return f"plant=franka needs franky-control and franky-sim (make install; Python 3.11 on Linux x86-64): {e}"
    return ""


def free_loopback(first: int = 2, last: int = 254) -> str:
    """The first 127.0.0.x (x >= 2) whose libfranka port is free: parallel runs each get one of their own."""
    for x in range(first, last + 1):
        host = f"127.0.0.{x}"
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, COMMAND_PORT))
            except OSError:
                continue
            return host
    raise RuntimeError(f"plant=franka: no free loopback address 127.0.0.{first}..{last} for franky-sim")


def _die_with_parent() -> None:
    """Linux: the server gets SIGTERM when the process that started it dies, even by SIGKILL."""
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class SimServer:
    """A franky-sim process on `host`: started, waited for until it serves, stopped by its pid however the run
    ends (stop() is idempotent; the server also dies with this process)."""

    def __init__(self, host: str, gains: Sequence[float], initial_q: Sequence[float], log_path: Path | None) -> None:
        """Start the server; its output goes to log_path (None: discarded)."""
        self.host = host
        cmd = [sys.executable, "-m", "pinnmpc.plant.franka_sim", "--hostname", host]
        cmd += ["--kv", *map(str, gains), "--initial-q", *map(str, initial_q)]
        self._log = open(log_path, "ab") if log_path is not None else subprocess.DEVNULL  # noqa: SIM115
        self.proc = subprocess.Popen(
            cmd, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent
        )
        self.pid = self.proc.pid
        self.exited_early = False  # whether it exited before serving (its address taken by another server)

    def wait_ready(self, timeout: float) -> None:
        """Block until the server accepts libfranka connections; a server that exits or never answers is stopped
        and named in one line."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                self.exited_early = True
                raise RuntimeError(
                    f"plant=franka: franky-sim on {self.host} exited with code {self.proc.returncode} before serving "
                    "(its log: franky_sim.log in the run dir)"
                )
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                s.settimeout(0.5)
                if s.connect_ex((self.host, COMMAND_PORT)) == 0:
                    return
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"plant=franka: franky-sim on {self.host} did not answer in plant.start_timeout={timeout} s")

    def stop(self, grace: float = 10.0) -> None:
        """SIGTERM by pid (the server ignores SIGINT), SIGKILL if it outlives the grace period; then reaped."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
                self.proc.wait()
        if self._log is not subprocess.DEVNULL:
            self._log.close()
            self._log = subprocess.DEVNULL


def main(argv: Sequence[str] | None = None) -> None:
    """Serve one FR3 from MuJoCo on --hostname with joint velocity gains --kv until SIGTERM."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--hostname", required=True, help="loopback address to serve on, e.g. 127.0.0.2")
    parser.add_argument("--kv", type=float, nargs=7, required=True, help="joint velocity gains, N m s/rad")
    parser.add_argument("--initial-q", type=float, nargs=7, required=True, help="start configuration, rad")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # unwinds the context managers: sockets closed
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    with MujocoSimulator() as sim:
        sim.add_robot(initial_q=tuple(args.initial_q), kv=tuple(args.kv))
        with SimulationServer(sim, hostname_candidates=[args.hostname]) as server:
            print(f"franky-sim serving on {args.hostname}", flush=True)
            server.run_forever()


if __name__ == "__main__":
    main()
