"""Latin-hypercube collocation and data points, redrawn on schedule, and a fixed validation set."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import lightning as L
import torch
from scipy.stats import qmc
from torch import Tensor
from torch.utils.data import DataLoader

from pinnmpc.plant.integrators import n_steps, rk4_fixed, rk4_step
from pinnmpc.systems.base import System
from pinnmpc.systems.previous_input import WithPreviousInput, arm_system
from pinnmpc.systems.sampling import random_pairs
from pinnmpc.training.settings import DataSettings

Scorer = Callable[[Tensor, Tensor, Tensor], Tensor]  # (t, x0, u) -> residual per point, as PINNModule provides
MIN_ROBOT_TRANSITIONS = 2000  # logged transitions below which a fine-tuning fits noise, not the robot
MIN_ROBOT_VALIDATION = 50  # held-out one-period transitions below which the validation RMSE says little


def lhs_box(n: int, low: Sequence[float], high: Sequence[float], seed: int) -> Tensor:
    """n Latin-hypercube points in the box, float64, reproducible by seed."""
    sampler = qmc.LatinHypercube(d=len(low), seed=seed)
    return torch.from_numpy(qmc.scale(sampler.random(n), list(low), list(high)))


def collocation_box(system: System, t_high: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Bounds of the (t, x0, u) points the physics loss sees, t in [0, t_high]."""
    return (0.0, *system.state_box.low, *system.input_box.low), (t_high, *system.state_box.high, *system.input_box.high)


def reference_flow(system: System, x0: Tensor, u: Tensor, tau: float, h: float) -> Tensor:
    """Accurate x(tau) by fine fixed-step RK4, vectorised over the batch."""
    with torch.no_grad():
        return rk4_step(system.fast_rhs, x0.double(), u.double(), tau, h)


def flow_scale(
    system: System, t_max: float, n: int, h: float, quantile: float, seed: int, prior: Any = None
) -> list[float]:
    """Typical size of x(t_max) - x0 per state (or of what a prior misses), so every network output is O(1)."""
    x0, u = random_pairs(system, n, seed)
    start = x0 if prior is None else prior(torch.full_like(x0[:, :1], t_max), x0, u)[0]
    delta = (reference_flow(system, x0, u, t_max, h) - start).abs()
    if not torch.isfinite(delta).all():
        raise ValueError(
            f"model.auto_scale.h={h}: RK4 at this step diverges on {system.name}'s flow (stiff); expected a smaller "
            "step, e.g. 1e-3"
        )
    return torch.quantile(delta, quantile, dim=0).clamp_min(1e-6).tolist()


class CollocationDataModule(L.LightningDataModule):
    """Full-batch training points (redrawn at `resample_epochs`) and one-step validation rollouts.

    Under DDP (N processes) every process makes the same global draw and keeps its rows rank::N, so the shards are
    disjoint, together they are the one-process draw, and each redraw is the same on every process; its batch then
    carries `share` = N x shard size / n_collocation, which makes the mean over the processes of each shard's
    weighted physics loss the mean over all points. The anchors are sharded the same way (`anchor_share`). The data
    points at t = 0 and the validation set are the same on every process.

    The keyword defaults are DataSettings' (pinnmpc/training/settings.py), the structured config behind
    conf/data/collocation.yaml; seed is the run's (the top-level `seed` of conf/train.yaml).
    """

    def __init__(
        self,
        system: System,
        tau: float,
        t_max: float,
        n_collocation: int = DataSettings.n_collocation,
        n_data: int = DataSettings.n_data,
        resample_every: int = DataSettings.resample_every,
        resample_epochs: Sequence[int] = (),  # DataSettings' empty list (a list field has no class default)
        n_val: int = DataSettings.n_val,
        val_h: float = DataSettings.val_h,
        seed: int = 0,
        adaptive_pool: int = DataSettings.adaptive_pool,
        adaptive_k: float = DataSettings.adaptive_k,
        adaptive_c: float = DataSettings.adaptive_c,
        t_high: float | None = DataSettings.t_high,
        n_anchor: int = DataSettings.n_anchor,
        anchor_h: float = DataSettings.anchor_h,
        logs: Sequence[str] = (),  # as resample_epochs
        n_robot: int = DataSettings.n_robot,
        val_episodes: float = DataSettings.val_episodes,
        robot_max_input_step: float | None = DataSettings.robot_max_input_step,
        physics: System | None = None,  # the model anchors and the model's validation flow integrate (None: system)
        robot_start: float | None = None,  # s into each period the robot's pairs start from (model.command_delay)
    ) -> None:
        super().__init__()
        if n_collocation < 1 or n_data < 0 or n_val < 1 or n_anchor < 0:
            raise ValueError(
                f"need n_collocation >= 1, n_data >= 0, n_val >= 1, n_anchor >= 0; "
                f"got {n_collocation}, {n_data}, {n_val}, {n_anchor}"
            )
        if not 0 < anchor_h < math.inf:
            raise ValueError(f"data.anchor_h={anchor_h}: expected a positive RK4 step in seconds")
        if adaptive_pool < 0 or adaptive_k < 0 or adaptive_c < 0 or (adaptive_pool and adaptive_pool < 2):
            raise ValueError(
                f"need adaptive_pool 0 (off) or >= 2, adaptive_k >= 0, adaptive_c >= 0; "
                f"got {adaptive_pool}, {adaptive_k}, {adaptive_c}"
            )
        if not 0 < tau <= t_max:
            raise ValueError(f"need 0 < tau <= t_max, got tau={tau}, t_max={t_max}")
        t_high = t_max if t_high is None else float(t_high)
        if not tau <= t_high <= t_max:
            raise ValueError(
                f"need tau ({tau}) <= t_high <= t_max ({t_max}) for the collocation times, got t_high={t_high}"
            )
        self.system, self.tau, self.t_max, self.t_high = system, float(tau), float(t_max), t_high
        self.physics = physics or system
        self.n_collocation, self.n_data = int(n_collocation), int(n_data)
        self.resample_every, self.resample_epochs = int(resample_every), {int(e) for e in resample_epochs}
        self.n_val, self.val_h, self.seed = int(n_val), float(val_h), int(seed)
        self.n_anchor, self.anchor_h = int(n_anchor), float(anchor_h)
        self.adaptive_pool, self.adaptive_k, self.adaptive_c = int(adaptive_pool), float(adaptive_k), float(adaptive_c)
        self.logs, self.n_robot, self.val_episodes = [str(p) for p in logs], int(n_robot), float(val_episodes)
        if self.n_robot < 0 or not 0 < self.val_episodes < 1:
            raise ValueError(
                f"need data.n_robot >= 0 (0: every logged transition) and 0 < data.val_episodes < 1; "
                f"got {n_robot}, {val_episodes}"
            )
        if robot_max_input_step is not None and not 0 < robot_max_input_step < math.inf:
            raise ValueError(f"data.robot_max_input_step={robot_max_input_step}; expected a positive number or null")
        self.robot_max_input_step = None if robot_max_input_step is None else float(robot_max_input_step)
        self.robot_start = None if robot_start is None else float(robot_start)
        self.robot: dict[str, Tensor] = {}  # the logs' training transitions (t, x0, u, dx), read once
        self.robot_meta: list[dict[str, Any]] = []  # each log's meta, for the network's provenance
        self.draws = 0
        self.batch: dict[str, Tensor] = {}
        self.val: dict[str, Tensor] = {}
        self._drawn_for_epoch = -1

    def shard(self) -> tuple[int, int]:
        """(rank, number of processes) of this process in the trainer's strategy; (0, 1) without a trainer."""
        if self.trainer is None:
            return 0, 1
        return int(self.trainer.global_rank), int(self.trainer.world_size)

    def _scorer(self) -> Scorer | None:
        """The training module's pointwise residual, once there is a trained model to ask (not for the first draw)."""
        if not self.adaptive_pool or self.draws == 0 or self.trainer is None:
            return None
        return getattr(self.trainer.lightning_module, "pointwise_residual", None)

    def _collocation(self, low: Sequence[float], high: Sequence[float], seed: int) -> Tensor:
        """LHS points, or with adaptive_pool the RAR-D draw (Wu et al. 2023) from a larger LHS pool.

        Density ~ r^k / mean(r^k) + c over the pool (r: squared residual of the current model), so points
        gather where the physics is still violated (small t; where a joint velocity crosses zero and friction
        switches) while c keeps the whole box covered.
        """
        scorer = self._scorer()
        if scorer is None:
            return lhs_box(self.n_collocation, low, high, seed)
        pool = lhs_box(self.adaptive_pool * self.n_collocation, low, high, seed)
        r = self._score(scorer, pool).pow(self.adaptive_k)
        weights = r / r.mean().clamp_min(torch.finfo(r.dtype).tiny) + self.adaptive_c
        generator = torch.Generator().manual_seed(seed)
        return pool[torch.multinomial(weights, self.n_collocation, replacement=False, generator=generator)]

    def _score(self, scorer: Scorer, pool: Tensor) -> Tensor:
        """The residual at every pool point (on the CPU); under DDP each process scores its rows rank::N and all
        gather them, so every process holds the same scores."""
        nx = self.system.state_box.dim
        rank, world = self.shard()
        if world == 1:
            return scorer(pool[:, :1], pool[:, 1 : 1 + nx], pool[:, 1 + nx :]).cpu()
        mine = pool[rank::world]
        r = scorer(mine[:, :1], mine[:, 1 : 1 + nx], mine[:, 1 + nx :])
        padded = r.new_zeros(-(-len(pool) // world))  # all_gather wants the same size on every process
        padded[: len(r)] = r
        gathered = self.trainer.strategy.all_gather(padded).cpu()  # (world, padded size)
        scores = torch.empty(len(pool), dtype=gathered.dtype)
        for k in range(world):
            scores[k::world] = gathered[k, : len(range(k, len(pool), world))]
        return scores

    def draw(self) -> None:
        """Draw a fresh set of collocation and data points; the k-th plain-LHS draw is fixed by (seed, k). Under
        DDP this process keeps its shard of the collocation points (rows rank::N of the same draw)."""
        s = self.system
        seed = self.seed + 7919 * self.draws
        low, high = collocation_box(s, self.t_high)
        pts = self._collocation(low, high, seed)
        pts, share = self._my_rows(pts, "n_collocation")
        nx = s.state_box.dim
        batch = {"t": pts[:, :1], "x0": pts[:, 1 : 1 + nx], "u": pts[:, 1 + nx :]}
        if share is not None:
            batch["share"] = share
        if self.n_data:
            data = lhs_box(self.n_data, low[1:], high[1:], seed + 1)
            batch.update(data_x0=data[:, :nx], data_u=data[:, nx:])
        if self.n_anchor:
            batch.update(self._anchors(low, high, seed + 2))
        if self.robot:
            batch.update(self._robot_rows(seed + 3))
        self.batch = batch
        self.draws += 1

    def _my_rows(self, pts: Tensor, setting: str) -> tuple[Tensor, Tensor | None]:
        """This process's rows rank::N of a global draw and their `share` weight (None without DDP)."""
        rank, world = self.shard()
        total = getattr(self, setting)
        if world > total:
            raise ValueError(f"data.{setting}={total}: expected at least one point per process ({world})")
        if world == 1:
            return pts, None
        mine = pts[rank::world].clone()  # a copy: the global draw is not kept
        return mine, torch.tensor(world * len(mine) / total, dtype=torch.float64)

    def _anchors(self, low: Sequence[float], high: Sequence[float], seed: int) -> dict[str, Tensor]:
        """LHS points (t, x0, u) with the accurate change x(t) - x0 by fine RK4 of the same ODE (every row to its
        own t): the anchor loss, a supervised term that needs no data beyond the model the residual uses. Under DDP
        each process integrates only its shard."""
        pts, share = self._my_rows(lhs_box(self.n_anchor, low, high, seed).double(), "n_anchor")
        nx = self.system.state_box.dim
        t, x0, u = pts[:, :1], pts[:, 1 : 1 + nx], pts[:, 1 + nx :]
        n = n_steps(self.t_high, self.anchor_h)
        with torch.no_grad():
            dx = rk4_fixed(self.physics.fast_rhs, x0, u, t / n, n) - x0
        out = {"anchor_t": t, "anchor_x0": x0, "anchor_u": u, "anchor_dx": dx}
        if share is not None:
            out["anchor_share"] = share
        return out

    def _robot_rows(self, seed: int) -> dict[str, Tensor]:
        """The robot-data loss's rows: every logged transition, or n_robot of them drawn afresh with each draw."""
        r = self.robot
        if self.n_robot and self.n_robot < len(r["t"]):
            rows = torch.randperm(len(r["t"]), generator=torch.Generator().manual_seed(seed))[: self.n_robot]
            r = {k: v[rows] for k, v in r.items()}
        return {f"robot_{k}": v for k, v in r.items()}

    def _read_logs(self) -> None:
        """The robot's logs: whole episodes held out for validation (the one-step error at tau on the robot), every
        pair of samples within one hold period of the others for the robot-data loss."""
        from pinnmpc.robot_data.episodes import check_enough, split_episodes, transitions
        from pinnmpc.robot_data.logs import read_logs

        prev = isinstance(self.system, WithPreviousInput)  # the network takes u_prev too: the logs give it
        # checked as a set: shared episodes would leak into validation
        logs = read_logs(self.logs, arm_system(self.system))
        parts = [split_episodes(log, self.val_episodes, self.seed) for log in logs]
        train, step, start = [p for p, _ in parts], self.robot_max_input_step, self.robot_start
        t, x0, u, xt = transitions(train, self.t_max, step, prev, start)
        fine = min(log.fine for log in logs)
        check_enough(
            len(t),
            MIN_ROBOT_TRANSITIONS,
            "data.logs",
            tau=self.tau,
            fine=fine,
            t_max=self.t_max,
            from_start=prev or start is not None,
        )
        self.robot = {"t": t, "x0": x0, "u": u, "dx": xt - x0}
        split = start is not None  # the controller's step: start s under u_prev, then the rest under u
        vt, vx0, vu, vx1 = transitions([val for _, val in parts], self.tau, step, prev or split)
        at_tau = (vt[:, 0] - self.tau).abs() <= 1e-9 * self.tau  # one control period: what the controller asks for
        check_enough(int(at_tau.sum()), MIN_ROBOT_VALIDATION, "the held-out episodes of data.logs", tau=self.tau)
        self.val = {"x0": vx0[at_tau], "u": vu[at_tau], "x1": vx1[at_tau]}
        if split:
            nu = vu.shape[1] // 2
            self.val["u"], self.val["u_prev"] = vu[at_tau, :nu], vu[at_tau, nu:]
            self.val["t_split"] = torch.full_like(vt[at_tau], start)
        self.robot_meta = [log.meta for log in logs]

    def setup(self, stage: str | None = None) -> None:
        """Initial draw and the held-out validation rollouts (computed once): the model's flow at tau, or with
        logs the robot's next states in held-out episodes."""
        if self.logs and not self.robot:
            self._read_logs()
        if not self.batch:
            self.draw()
        if not self.val:
            x0, u = random_pairs(self.system, self.n_val, self.seed + 104729)
            self.val = {"x0": x0, "u": u, "x1": reference_flow(self.physics, x0, u, self.tau, self.val_h)}

    def due(self, epoch: int) -> bool:
        """Whether the schedule asks for new points at this epoch."""
        if epoch == 0:
            return False
        return epoch in self.resample_epochs or (self.resample_every > 0 and epoch % self.resample_every == 0)

    def train_dataloader(self) -> DataLoader:
        """One full batch per epoch; redraws first when the schedule says so."""
        epoch = self.trainer.current_epoch if self.trainer is not None else 0
        if self.due(epoch) and epoch != self._drawn_for_epoch:
            self.draw()
            self._drawn_for_epoch = epoch
        return DataLoader([self.batch], batch_size=None)

    def val_dataloader(self) -> DataLoader:
        """The fixed held-out one-step rollouts, one batch."""
        return DataLoader([self.val], batch_size=None)

    def state_dict(self) -> dict:
        """Resume with the same draw counter, so a resumed run draws what the original would have."""
        return {"draws": self.draws}

    def load_state_dict(self, state: dict) -> None:
        """Restore the draw counter and redraw the points that were in use."""
        self.draws = max(0, int(state["draws"]) - 1)
        self.draw()
