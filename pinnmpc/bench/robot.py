"""Section 7: a robot that is not the model (plant=mujoco plant.robot=<name>). The nominal classical NMPC, the
classical NMPC on a model identified from the robot's logs, the shipped network and the network fine-tuned on those
logs, each in one closed loop per reference on the same robot and protocol; the references should be ones the logs
did not hold."""

from __future__ import annotations

import logging
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from pinnmpc.bench.classical import classical_cfg, classical_solvers
from pinnmpc.bench.common import bench_reference, controller_cfg, make_plant, on_the_model, timing_cfg
from pinnmpc.bench.loops import loop_row
from pinnmpc.bench.paired import paired_ocp
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant.settings import robot_name
from pinnmpc.surrogate.checkpoint import Surrogate, load_surrogate
from pinnmpc.surrogate.delayed_command import controller_flow
from pinnmpc.systems.base import System
from pinnmpc.systems.previous_input import takes_previous_input
from pinnmpc.systems.registry import load_system
from pinnmpc.util.tables import fmt, md_table

log = logging.getLogger(__name__)


def estimator(cfg: DictConfig) -> dict[str, Any]:
    """Every row's offset-free estimator: the PINN controller's (robot.offset_free) or none."""
    return {"disturbance": cfg.controller.disturbance} if cfg.robot.offset_free else {"disturbance": {"gain": 0.0}}


def robot_controllers(
    cfg: DictConfig, system: System, networks: dict[str, Surrogate]
) -> list[tuple[str, str, Any, Any]]:
    """(key, label, controller, training box) of every row: the classical NMPC on the nominal and (robot.identified)
    the identified model, the shipped and (robot.adapted) the fine-tuned network; all with the same OCP."""
    from pinnmpc.controller.classical.nmpc import build_casadi_nmpc

    r, shared = cfg.robot, estimator(cfg)  # the shipped and (robot.adapted) fine-tuned networks: `networks`
    classical = OmegaConf.merge(classical_cfg(cfg, classical_solvers(cfg)[0]), shared)
    pinn = OmegaConf.merge(controller_cfg(cfg), shared)
    models = {"nominal": system}
    if r.identified is not None:
        fitted = load_system(str(r.identified))
        if tuple(fitted.state_names) != tuple(system.state_names):
            raise ValueError(f"robot.identified={r.identified} is another arm: states {fitted.state_names}")
        models["identified"] = fitted
    rows = []
    variants = classical_at_best(cfg, classical) if r.get("classical_variants") else [("", "", {})]
    for name, model in models.items():
        for suffix, tail, changes in variants:
            settings = OmegaConf.merge(classical, changes)
            label = f"classical NMPC, {name} model{tail}"
            rows.append((f"casadi_{name}{suffix}", label, build_casadi_nmpc(settings, model), None))
    labels = {"pinn_shipped": "PINN-MPC, shipped network", "pinn_adapted": "PINN-MPC, fine-tuned network"}
    for key, net in networks.items():
        rows.append((key, labels[key], build_nmpc(pinn, net, system), net.domain))
    return rows


def classical_at_best(cfg: DictConfig, classical: DictConfig) -> list[tuple[str, str, dict[str, Any]]]:
    """(key suffix, label tail, changes) of the classical NMPC at its best engineers' settings on a robot: the arm's
    default, its other mode (converged or real-time, sqpmethod only) and each with the estimator switched the other
    way (robot.offset_free's default off: on with the network controller's; on: off)."""
    modes = [("", "", {})]
    if classical.solver == "sqpmethod":
        fast = bool(classical.get("rti", False))
        modes.append(("_converged", ", converged", {"rti": False}) if fast else ("_rti", ", real-time", {"rti": True}))
    on = float(classical.disturbance.gain) > 0
    other = {"disturbance": {"gain": 0.0}} if on else {"disturbance": cfg.controller.disturbance}
    tail = ", no estimator" if on else ", offset-free"
    return [*modes, *((f"{k}_{'noest' if on else 'est'}", t + tail, {**c, **other}) for k, t, c in modes)]


def best_classical(rows: dict[str, dict[str, Any]], refs: list[str], angles: list[str]) -> dict[str, str]:
    """Per reference, the classical row with the smallest worst joint-angle MAE among those that ran ok."""
    out = {}
    for ref in refs:
        mine = {k: r for k, r in rows.items() if k.startswith("casadi_") and r["reference"] == ref}
        ok = {k: r for k, r in mine.items() if r["status"] == "ok"} or mine
        out[ref] = min(ok, key=lambda k: worst_angle_mae(ok[k], angles)).split("@")[0]
    return out


def bench_robot(cfg: DictConfig, system: System, shipped: Surrogate) -> dict[str, Any]:
    """Every controller of robot_controllers on every reference of robot.references, on the robot; then the
    shipped network on the nominal model as the plant (what fine-tuning should come back to)."""
    kind = cfg.plant.get("kind", "scipy")
    if kind != "franka" and (kind != "mujoco" or cfg.plant.get("robot") is None):
        raise ValueError(
            f"robot.enabled=true with plant.kind={kind}, plant.robot={cfg.plant.get('robot')}; expected "
            "plant=mujoco plant.robot=<name> or plant=franka (a robot that is not the model)"
        )
    if cfg.robot.logs:  # refused before the closed loops, not after them
        from pinnmpc.robot_data.logs import read_logs

        read_logs([str(p) for p in cfg.robot.logs], system)
    refs = [bench_reference(cfg, system, system.tau, str(name)) for name in cfg.robot.references]
    networks = {"pinn_shipped": shipped}  # each network loaded once: its rows and its one-step RMSE
    if cfg.robot.adapted is not None:
        networks["pinn_adapted"] = load_surrogate(str(cfg.robot.adapted), state_names=system.state_names)
    rows: dict[str, dict[str, Any]] = {}
    built = robot_controllers(cfg, system, networks)
    for key, label, controller, box in built:
        for ref in refs:
            row = loop_row(cfg, system, controller, box, system.tau, ref)
            rows[f"{key}@{ref.name}"] = {**row, "label": label, "controller": key, "reference": ref.name}
            log.info("robot: %s on %s done in %.1f s", label, ref.name, row["wall_s"])
    nominal = on_the_model(cfg)
    paired = []
    nets = {key: c for key, _, c, _ in built if key in networks}
    if cfg.robot.paired_ocp and len(nets) > 1:  # the fine-tuned network's OCP against the shipped one's, interleaved
        plant = lambda: make_plant(timing_cfg(cfg), system, system.tau)  # noqa: E731
        for ref in refs:
            paired.append(paired_ocp(nets, plant, ref, cfg.closed_loop.max_steps))
            log.info("robot: paired OCP times on %s done", ref.name)
    pinn = build_nmpc(OmegaConf.merge(controller_cfg(cfg), estimator(cfg)), shipped, system)
    for ref in refs:
        row = loop_row(nominal, system, pinn, shipped.domain, system.tau, ref)
        label = "PINN-MPC, shipped network, nominal plant"
        rows[f"pinn_shipped_nominal@{ref.name}"] = {**row, "label": label, "controller": "pinn_shipped_nominal"}
        rows[f"pinn_shipped_nominal@{ref.name}"]["reference"] = ref.name
    one_step = {}
    if cfg.robot.logs:
        fitted = cfg.robot.identified
        models = {} if fitted is None else {"casadi_identified": load_system(str(fitted))}
        one_step = held_out_rmse(system, networks, [str(p) for p in cfg.robot.logs], models, int(cfg.robot.rk4_steps))
    return {
        "one_step_rmse": one_step,
        "logs": [str(p) for p in cfg.robot.logs or []],
        "robot": str(robot_name(cfg.plant)),
        "references": [ref.name for ref in refs],
        "offset_free": bool(cfg.robot.offset_free),
        "adapted": None if cfg.robot.adapted is None else str(cfg.robot.adapted),
        "identified": None if cfg.robot.identified is None else str(cfg.robot.identified),
        "rows": rows,
        "best_classical": best_classical(rows, [ref.name for ref in refs], list(system.state_names[: system.nq])),
        "paired_ocp": paired,
    }


def held_out_rmse(
    system: System,
    networks: dict[str, Surrogate],
    logs: list[str],
    models: dict[str, System] | None = None,
    rk4_steps: int = 50,
) -> dict[str, dict[str, float]]:
    """Each network's (and each model's, by RK4 at rk4_steps per period) one-step RMSE per state on every one-period
    transition of the given logs (logs the fine-tuning did not see: another collect run): how well it predicts the
    robot, the model monitor's figure offline."""
    from pinnmpc.plant.integrators import rk4_fixed
    from pinnmpc.robot_data.episodes import transitions
    from pinnmpc.robot_data.logs import read_logs

    t, x0, both, x1 = transitions(read_logs(logs, system), system.tau, previous_input=True)  # (u, u_prev)
    at_tau = (t[:, 0] - system.tau).abs() <= 1e-9 * system.tau
    x0, both, x1 = x0[at_tau], both[at_tau], x1[at_tau]
    u = both[:, : len(system.input_names)]
    flows = {k: controller_flow(net) for k, net in networks.items()}  # each as its controller predicts
    steps = {  # a network given the previous input (or split at a command delay) gets it too
        k: (lambda a, b, n=net: n.step(a, both)) if takes_previous_input(net) else net.step for k, net in flows.items()
    }
    for key, model in (models or {}).items():
        steps[key] = lambda a, b, m=model: rk4_fixed(m.rhs, a, b, system.tau / rk4_steps, rk4_steps)
    out = {}
    for key, step in steps.items():
        with torch.no_grad():
            err = step(x0, u) - x1
        out[key] = {n: float(v) for n, v in zip(system.state_names, err.square().mean(dim=0).sqrt())}
    out["transitions"] = {"count": float(len(x0))}
    return out


def worst_angle_mae(row: dict[str, Any], angles: list[str]) -> float:
    """The worst joint angle's MAE of a row: one number per closed loop."""
    return max(row["mae"][n] for n in angles)


ONE_STEP_LABELS = {
    "casadi_identified": "identified model (RK4)",
    "pinn_shipped": "shipped network",
    "pinn_adapted": "fine-tuned network",
}


def md_robot(section: dict[str, Any], system: dict[str, Any]) -> str:
    """Section 7: worst joint-angle MAE per controller and reference, OCP median, and each against the nominal
    classical NMPC on the same reference."""
    angles = system["state_names"][: system["nq"]]
    rows = section["rows"]
    refs = section["references"]
    keys = list(dict.fromkeys(r["controller"] for r in rows.values()))
    head = ["controller", *(f"{ref} MAE [rad]" for ref in refs), "÷ nominal classical (worst)", "OCP median [ms]"]
    head += ["OCP p99 [ms]", "past the period", "samples past a limit", "status"]
    table = []
    for key in keys:
        mine = [rows[f"{key}@{ref}"] for ref in refs]
        maes = [worst_angle_mae(r, angles) for r in mine]
        base = [worst_angle_mae(rows[f"casadi_nominal@{ref}"], angles) for ref in refs]
        ratio = max(m / b for m, b in zip(maes, base))
        ocp = max(r["ocp_time_s"]["median"] for r in mine)
        p99 = max(r["ocp_time_s"].get("p99", float("nan")) for r in mine)
        past = sum(int(r.get("over_period", 0)) for r in mine)
        limits = sum(int(r.get("joint_limit_samples", 0)) for r in mine)
        bad = [r["status"] for r in mine if r["status"] != "ok"]
        status = "ok" if not bad else f"{len(bad)} not ok: {bad[0][:60]}"
        times = [fmt(1e3 * ocp), fmt(1e3 * p99)]
        table.append([mine[0]["label"], *(fmt(m) for m in maes), fmt(ratio), *times, str(past), str(limits), status])
    estimator = "with" if section["offset_free"] else "without"
    one_step, names = section.get("one_step_rmse") or {}, system["state_names"]
    nets = [k for k in ("casadi_identified", "pinn_shipped", "pinn_adapted") if k in one_step]
    rmse = (
        [
            "",
            f"One-step RMSE on {int(one_step['transitions']['count'])} held-out robot transitions "
            f"({', '.join(section['logs'])}):",
            "",
            md_table(["model", *names], [[ONE_STEP_LABELS[k], *(fmt(one_step[k][n]) for n in names)] for k in nets]),
        ]
        if nets
        else []
    )
    paired = md_paired(section.get("paired_ocp") or [])
    best = section.get("best_classical") or {}
    if best:
        label = {r["controller"]: r["label"] for r in rows.values()}
        paired = [
            "",
            "Best classical per reference (smallest worst joint-angle MAE of the classical rows): "
            + "; ".join(f"{r}: {label[k]}, {fmt(worst_angle_mae(rows[f'{k}@{r}'], angles))}" for r, k in best.items())
            + ".",
            *paired,
        ]
    return "\n".join(
        [
            f"## 7. On the robot `{section['robot']}` (a robot the model is not)",
            "",
            f"Worst joint-angle MAE per reference, every controller {estimator} the offset-free estimator; the last "
            "rows run the shipped network on the nominal model as the plant (where a fine-tuned network should come "
            "back to). Adapted network: "
            f"{section['adapted'] or '—'}; identified model: {section['identified'] or '—'}.",
            "",
            md_table(head, table),
            *paired,
            *rmse,
            "",
        ]
    )


def md_paired(paired: list[dict[str, Any]]) -> list[str]:
    """Lines of the interleaved OCP comparison (bench/paired.py): the fine-tuned network against the shipped one."""
    lines = []
    for p in paired:
        med = p["ocp_median_s"]
        status = "" if p["status"] == "ok" else f"; {p['status']}"
        lines.append(
            f"- {p['reference']}: {fmt(p['ratio_median']['pinn_adapted'])}x (OCP medians "
            f"{fmt(1e3 * med['pinn_adapted'])} / {fmt(1e3 * med['pinn_shipped'])} ms, {p['samples']} samples{status})"
        )
    if not lines:
        return []
    head = (
        "OCP time of the fine-tuned network's controller against the shipped one's, their samples interleaved in one "
        "process (median of the per-sample ratio; pinnmpc/bench/paired.py):"
    )
    return ["", head, "", *lines]
