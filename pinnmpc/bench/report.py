"""bench.md: one markdown table per measurement, the paper's published numbers beside ours where the system has
them (the `paper` block), names and units from the system."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pinnmpc.bench.common import status_suffix
from pinnmpc.bench.floor import md_floor
from pinnmpc.bench.kinds import md_kinds
from pinnmpc.bench.loops import mode
from pinnmpc.bench.peers import md_peers
from pinnmpc.bench.robot import md_robot
from pinnmpc.util.tables import fmt, md_table

TRUE_MODEL_JACOBIANS = {"torch": "by autodiff through RK4 in torch", "compiled": "by CasADi AD, compiled C"}


def machine_line(m: dict[str, Any]) -> str:
    """One line naming the machine, so nobody compares timings from different boxes unknowingly."""
    return (
        f"Machine: {m['platform']}, {m['cpu']}, {m['cpu_count']} CPUs, Python {m['python']}, torch {m['torch']}, "
        f"numpy {m['numpy']}, scipy {m['scipy']}, torch threads {m['torch_threads']}, "
        f"1-min load average at start {m['load_average_1min']:.2f}."
    )


def units_line(system: dict[str, Any]) -> str:
    """The unit of every state, since MAE and RMSE columns carry the state's own unit."""
    return "Units: " + ", ".join(f"{n} [{u}]" for n, u in zip(system["state_names"], system["state_units"])) + "."


def md_step(step: dict[str, Any], paper: dict[str, Any] | None, names: Sequence[str]) -> str:
    """Section 1 tables: timing per batch size (with the paper's numbers where there are any), then accuracy."""
    out = [
        "## 1. One-step cost x_k -> x_k+1" + (" (Table 1 done right)" if paper else ""),
        "",
        f"tau = {step['tau_s']:g} s; Euler/RK4 step h = {step['h_s']:g} s; {step['repeats']} timed calls after "
        f"{step['warmup']} warm-up calls; batch 1 cycles through {step['n_states']} random states in the training box. "
        f"Ratio: median / RK45 median at the same batch size, this run. RK45 at batch > 1: "
        + (
            f"a per-sample loop of solve_ivp, {step['rk45_loop_repeats']} timed loops."
            if step["rk45_batch"] == "loop"
            else "skipped (solve_ivp has no batch)."
        ),
        "",
    ]
    headers = ["method", "median [s]", "mean [s]", "p95 [s]", "median per sample [s]", "/ RK45 median"]
    if paper:
        headers += ["paper mean [s]", "paper median [s]"]
    for b, rows in step["timing"].items():
        table = []
        for key, r in rows.items():
            meta = step["methods"][key]
            cells = [
                meta["label"],
                fmt(r["median_s"], ".3e"),
                fmt(r["mean_s"], ".3e"),
                fmt(r["p95_s"], ".3e"),
                fmt(r["per_sample_median_s"], ".3e"),
                fmt(r.get("ratio_to_rk45")),
            ]
            if paper:
                published = (paper["step_mean_s"], paper["step_median_s"]) if b == "1" else ({}, {})
                cells += [fmt(p.get(meta["paper"]), ".2e") for p in published]
            table.append(cells)
        out += [f"### batch {b}", "", md_table(headers, table), ""]
    acc = [[step["methods"][k]["label"], *(fmt(v[n], ".2e") for n in names)] for k, v in step["rmse"].items()]
    if "rmse_hold" in step:  # absent in reports of older runs
        acc.append(["no model: x(tau) = x0 (the size of one step)", *(fmt(step["rmse_hold"][n], ".2e") for n in names)])
    out += [
        f"### one-step RMSE vs fine RK4 (h = {step['ref_h_s']:g} s), {step['n_states']} random states",
        "",
        md_table(["method", *(f"RMSE {n}" for n in names)], acc),
        "",
    ]
    return "\n".join(out)


def md_closed_loop(
    cl: dict[str, Any],
    paper: dict[str, Any] | None,
    names: Sequence[str],
    plant: str,
    optimality: dict[str, Any] | None = None,
) -> str:
    """Section 2 table: tracking error, solve cost and optimality gap per controller, with the paper's row."""
    optimality = optimality or {}
    headers = [
        "controller",
        *(f"MAE {n}" for n in names),
        "OCP mean [s]",
        "OCP median [s]",
        "OCP p95 [s]",
        "OCP median / plant step median",
        "iterations mean",
        "optimality rel gap max",
        "fallbacks",
        "steps",
    ]
    rows = []
    for r in cl["rows"].values():
        rows.append(
            [
                r["label"] + status_suffix(r["status"]),
                *(fmt(r["mae"][n], ".2e") for n in names),
                fmt(r["ocp_time_s"]["mean"], ".2e"),
                fmt(r["ocp_time_s"]["median"], ".2e"),
                fmt(r["ocp_time_s"]["p95"], ".2e"),
                fmt(r["ratio_ocp_to_plant"]),
                fmt(r["iterations_mean"], ".1f"),
                _gap_cell(r, optimality),
                fmt(r["fallbacks"]),
                fmt(r["steps"]),
            ]
        )
    if paper and paper.get("closed_loop"):
        pc = paper["closed_loop"]
        rows.append(
            [
                str(pc.get("label", "paper")),
                *(fmt(pc["mae"].get(n), ".2e") for n in names),
                fmt(pc["ocp_mean_s"], ".2e"),
                *["—"] * 7,
            ]
        )
    return "\n".join(
        [
            "## 2. Closed loop",
            "",
            f"Reference: {cl['reference']}; horizon {cl['horizon']}; plant {plant}; MAE per state in its unit. "
            "The true-model rows run the same controller on an RK4 model of the physics (exact Jacobians, "
            + TRUE_MODEL_JACOBIANS.get(cl.get("true_model_backend", "torch"), "")
            + "). Optimality gap: section 3."
            + _left_out(paper),
            "",
            md_table(headers, rows),
            "",
        ]
    )


def _left_out(paper: dict[str, Any] | None) -> str:
    """Why the paper's closed-loop row is not in the table, where it was left out (another reference ran)."""
    why = (paper or {}).get("closed_loop_left_out")
    return f" The paper's row is left out: it was {why}." if why else ""


def md_other_references(cl: dict[str, Any], names: Sequence[str]) -> str:
    """Section 2 sub-table: the configured controller on the built-in references."""
    headers = [
        "reference",
        "solver",
        "steps",
        *(f"MAE {n}" for n in names),
        "OCP median [s]",
        "OCP p95 [s]",
        "OCP median / plant step median",
        "iterations mean",
        "fallbacks",
    ]
    plain = any("mae_without_disturbance" in r for r in cl["references"].values())
    if plain:
        headers[3:3] = [f"MAE {n} without offset-free" for n in names]
    rows = [
        [
            name + status_suffix(r["status"]),
            r["solver"] + mode(r),
            fmt(r["steps"]),
            *((fmt(r.get("mae_without_disturbance", {}).get(n), ".2e") for n in names) if plain else ()),
            *(fmt(r["mae"][n], ".2e") for n in names),
            fmt(r["ocp_time_s"]["median"], ".2e"),
            fmt(r["ocp_time_s"]["p95"], ".2e"),
            fmt(r["ratio_ocp_to_plant"]),
            fmt(r["iterations_mean"], ".1f"),
            fmt(r["fallbacks"]),
        ]
        for name, r in cl["references"].items()
    ]
    return "\n".join(["### Built-in references", "", md_table(headers, rows), ""])


def _gap_cell(row: dict[str, Any], optimality: dict[str, Any]) -> str:
    """The worst relative optimality gap of a PINN row's solver (section 3), or a dash when not examined."""
    op = optimality.get(row["solver"]) if row["model"] == "pinn" else None
    return "—" if op is None else fmt(op["rel_gap"]["max"], ".1e")


def md_optimality(per_solver: dict[str, dict[str, Any]]) -> str:
    """Section 3 table: the gap distribution of each solver to the L-BFGS-B reference."""
    rows = [_optimality_row(op) for op in per_solver.values()]
    op = next(iter(per_solver.values()))
    headers = [
        "solver",
        "OCPs",
        "rel gap median",
        "rel gap p95",
        "rel gap max",
        "abs gap max",
        "fraction optimal",
        "best start (count)",
        "L-BFGS-B iterations mean",
    ]
    return "\n".join(
        [
            "## 3. OCP optimality",
            "",
            "States visited by each solver's closed loop of section 2; each OCP re-solved on the same surrogate by "
            f"scipy L-BFGS-B (ftol {op['ftol']:g}, gtol {op['gtol']:g}, maxiter {op['maxiter']}, autograd gradient) "
            "from zeros, the solver's own solution and random starts. "
            "rel gap = (solver's cost - best cost) / best cost; "
            f"optimal: rel gap <= {op['rel_tol']:g} or abs gap <= {op['abs_tol']:g}.",
            "",
            md_table(headers, rows),
            "",
        ]
    )


def _optimality_row(op: dict[str, Any]) -> list[str]:
    """One solver's row of the optimality table."""
    g = op["rel_gap"]
    return [
        op["solver"],
        fmt(op["n_states"]),
        fmt(g["median"], ".2e"),
        fmt(g["p95"], ".2e"),
        fmt(g["max"], ".2e"),
        fmt(op["abs_gap_max"], ".2e"),
        fmt(op["fraction_within"]),
        ", ".join(f"{k} {v}" for k, v in op["best_start_counts"].items()),
        fmt(op["lbfgsb_iterations_mean"], ".1f"),
    ]


def md_scaling(sc: dict[str, Any]) -> str:
    """Section 4 tables: OCP time vs horizon and batch size, one-step cost vs batch size."""

    def ocp_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
        return [
            [
                fmt(r["horizon"]),
                fmt(r["batch"]),
                fmt(r["median_s"], ".2e"),
                fmt(r["p95_s"], ".2e"),
                fmt(r["per_problem_median_s"], ".2e"),
                fmt(r["problems_per_s"], ".3g"),
                fmt(r["iterations_mean"], ".1f"),
            ]
            for r in rows
        ]

    headers = ["H", "B", "median per solve [s]", "p95 [s]", "per problem [s]", "problems/s", "iterations mean"]
    st = sc["step"]
    columns = ("pinn_f64_median_s", "pinn_f64_per_sample_s", "rk4_torch_median_s", "rk4_torch_per_sample_s")
    step_rows = [
        [fmt(int(b)), *(fmt(v, ".2e") for v in values)]
        for b, *values in zip(st["batch_sizes"], *(st[c] for c in columns))
    ]
    return "\n".join(
        [
            "## 4. Scaling",
            "",
            "Batched NMPC.solve (the configured solver) on random states and references (uniform in the training box), "
            "zero start.",
            "",
            f"### OCP vs horizon (B = {sc['base_batch']})",
            "",
            md_table(headers, ocp_rows(sc["horizon"])),
            "",
            f"### OCP vs batch size (H = {sc['base_horizon']})",
            "",
            md_table(headers, ocp_rows(sc["batch"])),
            "",
            "### one step vs batch size (median)",
            "",
            md_table(["B", "PINN f64 [s]", "PINN per sample [s]", "RK4 torch [s]", "RK4 per sample [s]"], step_rows),
            "",
            "Plots: " + (", ".join(sc["plots"]) or "off"),
            "",
        ]
    )


def md_targets(targets: list[dict[str, Any]], network: str) -> str:
    """Section 5: each target next to this run's number and their ratio, then a verdict naming what was met and
    what was missed by how much, so a miss reads as a distance to the target rather than a bare "no"."""
    rows = [[r["what"], limit(r), fmt(r["value"], ".3g"), times(r), "yes" if r["met"] else "**no**"] for r in targets]
    table = md_table(["target", "limit", "this run", "this run / limit", "met"], rows)
    return "\n".join(["## 5. Targets", "", f"Network: {network}.", "", table, "", targets_verdict(targets), ""])


def limit(target: dict[str, Any]) -> str:
    """The limit as the table shows it: a bound from below (a speed-up) with its sign."""
    return ("at least " if target.get("at_least") else "") + fmt(target["limit"], ".3g")


def times(target: dict[str, Any]) -> str:
    """This run's number as a multiple of the limit (below 1: met with room; above 1 for a bound from below)."""
    return f"{target['value'] / target['limit']:.3g}x"


def missed_by(target: dict[str, Any]) -> str:
    """The side of its limit a missed target lies on, and the limit: "> 0.001", or "< 1.5" for a bound from below."""
    return f"{'<' if target.get('at_least') else '>'} {fmt(target['limit'], '.3g')}"


def targets_verdict(targets: list[dict[str, Any]]) -> str:
    """One line: how many targets were met, which, and for each missed one its number against the limit."""
    met = [r["what"] for r in targets if r["met"]]
    missed = [r for r in targets if not r["met"]]
    if not missed:
        return "**Verdict: the target met.**" if len(targets) == 1 else f"**Verdict: all {len(targets)} targets met.**"
    gaps = "; ".join(f"{r['what']} {fmt(r['value'], '.3g')} {missed_by(r)} ({times(r)})" for r in missed)
    passed = f" ({', '.join(met)})" if met else ""
    notes = [note for kind, note in VERDICT_NOTES.items() if any(bool(r.get("speed")) == kind for r in missed)]
    return f"**Verdict: {len(met)} of {len(targets)} targets met**{passed}; missed: {gaps}. " + " ".join(notes)


VERDICT_NOTES = {  # what a miss says, for accuracy (False) and speed (True) targets
    False: "The shipped networks trade accuracy against OCP time; the README says which checkpoint meets what.",
    True: "Speed ratios move with the machine's load, 10% or more between runs (docs/results.md, section 6).",
}


MISMATCH_NOTE = (
    " Rows 'plant friction xF': the plant's friction scaled by F (classical.friction_scales), a model error for"
    " both controllers, so both estimate the offset (the classical NMPC with the PINN controller's estimator)."
)

PRIOR_NOTE = (
    " Rows 'physics prior alone': the PINN controller predicting with the network's physics prior (model.prior)"
    " without the network (controller.model=prior)."
)

EXACT_NOTE = (
    " Rows 'exact values': the PINN controller predicting with the true model's values (RK4 as the classical NMPC's,"
    " compiled, no sensitivities) and the PINN's Jacobians (controller.model=exact_values)."
)


def md_classical(cl: dict[str, Any], system: dict[str, Any], plant: str) -> str:
    """Section 6 table: the PINN controller against the classical NMPC, per joint angle and per solve."""
    title = f"## 6. PINN vs classical NMPC ({system['name']})"
    if "skipped" in cl:
        return "\n".join([title, "", f"Skipped: {cl['skipped']}.", ""])
    angles = system["state_names"][: system["nq"]]
    headers = [
        "controller",
        *(f"MAE {n} [{u}]" for n, u in zip(angles, system["state_units"])),
        "OCP median [s]",
        "OCP p95 [s]",
        "OCP max [s]",
        "failures (fallbacks)",
        "OCP median / plant step median",
        "steps",
    ]
    rows = [
        [
            r["label"] + mode(r) + status_suffix(r["status"]),
            *(fmt(r["mae"][n], ".2e") for n in angles),
            fmt(r["ocp_time_s"]["median"], ".2e"),
            fmt(r["ocp_time_s"]["p95"], ".2e"),
            fmt(r["ocp_time_s"]["max"], ".2e"),
            fmt(r["fallbacks"]),
            fmt(r["ratio_ocp_to_plant"]),
            fmt(r["steps"]),
        ]
        for r in cl["rows"].values()
    ]
    return "\n".join(
        [
            title,
            "",
            f"Reference: {cl['reference']}; horizon {cl['horizon']}; plant {plant}; one process, the same protocol. "
            "The classical NMPC solves the same OCP on the true model (CasADi, compiled; first the arm's default "
            "transcription and QP, conf/system/<arm>.yaml control.casadi); "
            f"taken from the PINN controller: {', '.join(cl['shared']) or 'nothing'}."
            + MISMATCH_NOTE * any("plant_friction_scale" in r for r in cl["rows"].values())
            + EXACT_NOTE * any(r.get("prediction") == "exact_values" for r in cl["rows"].values())
            + PRIOR_NOTE * any(r.get("prediction") == "prior" for r in cl["rows"].values()),
            "",
            md_table(headers, rows),
            "",
            *md_paired_classical(cl.get("paired")),
        ]
    )


def md_paired_classical(paired: dict[str, Any] | None) -> list[str]:
    """Section 6's interleaved line: the classical default's OCP time over the PINN controller's, sample by sample."""
    if not paired:
        return []
    ours, (theirs,) = paired["base"], [k for k in paired["ocp_median_s"] if k != paired["base"]]
    median, mae = paired["ocp_median_s"], paired["worst_mae"]
    return [
        f"Interleaved ({paired['samples']} samples each, bench/paired.py; {paired['status']}): {theirs} / {ours} OCP "
        f"time {fmt(paired['ratio_median'][theirs])} (median of per-sample ratios; medians {fmt(1e3 * median[theirs])} "
        f"and {fmt(1e3 * median[ours])} ms), worst joint MAE {fmt(mae[theirs])} and {fmt(mae[ours])} rad.",
        "",
    ]


def plant_label(plant: dict[str, Any]) -> str:
    """How the tables name the simulated robot: the scipy method, or MuJoCo and the robot it simulates."""
    if plant.get("kind", "scipy") == "mujoco":
        return f"MuJoCo ({plant.get('robot') or 'nominal'} robot)"
    if plant.get("kind") == "franka":
        return f"Franka through libfranka ({plant.get('host') or 'franky-sim'})"
    return str(plant["method"])


def render_markdown(result: dict[str, Any]) -> str:
    """bench.md: readable tables with the paper's numbers side by side where the system has them."""
    system, paper = result["system"], result.get("paper")
    names = system["state_names"]
    plant = plant_label(result["config"]["plant"])
    parts = [f"# pinnmpc benchmark: {system['name']}", "", machine_line(result["machine"]), "", units_line(system), ""]
    if "step" in result:
        parts.append(md_step(result["step"], paper, names))
    if "closed_loop" in result:
        parts.append(md_closed_loop(result["closed_loop"], paper, names, plant, result.get("optimality")))
        if result["closed_loop"].get("references"):
            parts.append(md_other_references(result["closed_loop"], names))
    if "optimality" in result:
        parts.append(md_optimality(result["optimality"]))
    if "scaling" in result:
        parts.append(md_scaling(result["scaling"]))
    if result.get("targets"):
        checkpoint = result["config"].get("checkpoint")
        network = checkpoint or f"the one shipped for {system['name']} (checkpoint=null)"
        parts.append(md_targets(result["targets"], network))
    if "classical" in result:
        parts.append(md_classical(result["classical"], system, plant))
    if "robot" in result:
        parts.append(md_robot(result["robot"], system))
    if "kinds" in result:
        parts.append(md_kinds(result["kinds"], names))
    if "floor" in result:
        parts.append(md_floor(result["floor"], names))
    if "peers" in result:
        parts.append(md_peers(result["peers"]))
    elapsed = ", ".join(f"{k} {v:.1f} s" for k, v in result["elapsed_s"].items())
    parts += [f"Wall time per section: {elapsed}.", ""]
    return "\n".join(parts)
