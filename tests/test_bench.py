"""Real bench runs at tiny sizes, PowerCube and planar arm: every section runs, bench.json is sane, bench.md has the
tables, PNGs exist."""

from __future__ import annotations

import json
import math
import os
import shlex
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from pinnmpc.bench import run_bench, run_controller
from pinnmpc.bench.common import bench_reference
from pinnmpc.bench.report import md_targets, targets_verdict
from pinnmpc.bench.settings import BENCH_SECTIONS
from pinnmpc.bench.targets import _per_state, speed_targets
from pinnmpc.surrogate import Surrogate, load_surrogate
from pinnmpc.surrogate.checkpoint import CHECKPOINTS
from pinnmpc.surrogate.flowmap import RK4Model
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems import PowerCube, load_system
from tests.conftest import SHARED

CONF = Path(__file__).resolve().parents[1] / "conf"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
MAX_STEPS = 5  # closed-loop solves per row: enough OCPs for the optimality section
TINY = [
    "progress=false",
    "step.batch_sizes=[1,8]",
    "step.n_states=8",
    "step.repeats=3",
    "step.warmup=1",
    "step.rk45_loop_repeats=1",
    f"closed_loop.max_steps={MAX_STEPS}",
    "closed_loop.more_references=[rest,sine]",
    "controller.solvers.rmsprop.max_iter=30",
    "optimality.n_states=5",
    "optimality.random_starts=0",  # zeros and the solver's own solution: the starts that count here
    "scaling.horizons=[2,3]",
    "scaling.batch_sizes=[1,4]",
    "scaling.step_batch_sizes=[1,8]",
    "scaling.repeats=2",
    "scaling.warmup=1",
    "scaling.step_repeats=2",
    "scaling.step_warmup=1",
    "floor.horizons=[2,4]",
    f"floor.max_steps={MAX_STEPS}",
    "floor.cold.horizon=6",
    f"floor.cold.max_steps={MAX_STEPS}",
    "floor.cold.repeats=2",
    "peers.horizons=[3]",
    f"peers.max_steps={MAX_STEPS}",
    "+targets.floor_ratio.2=100",  # a horizon added to the default's: H = 2 gets a floor target, H = 4 none
]
SECTIONS = ("step", "closed_loop", "optimality", "scaling", "classical", "kinds", "floor", "peers")
SECTIONS_OFF = [f"{s}.enabled=false" for s in SECTIONS]


def _cfg(overrides: list[str]) -> DictConfig:
    """conf/bench.yaml composed the way the CLI composes it."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="bench", overrides=overrides)


def _numbers(obj: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """Every number in a JSON tree, with its key path."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numbers(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numbers(v, f"{path}[{i}]")
    elif isinstance(obj, int | float) and not isinstance(obj, bool):
        yield path, obj


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    """One tiny run shared by the tests below (the run is the expensive part)."""
    run_dir = tmp_path_factory.mktemp("bench")
    return run_bench(_cfg(TINY), run_dir), run_dir


def test_json_round_trips_and_is_finite(bench: tuple[dict[str, Any], Path]) -> None:
    result, run_dir = bench
    on_disk = json.loads((run_dir / "bench.json").read_text())
    assert on_disk == json.loads(json.dumps(result))
    assert {"machine", "system", "paper", *SECTIONS, "elapsed_s"} <= set(on_disk)
    bad = [(p, v) for p, v in _numbers({k: v for k, v in on_disk.items() if k != "machine"}) if not math.isfinite(v)]
    assert not bad


def test_step_table(bench: tuple[dict[str, Any], Path]) -> None:
    step = bench[0]["step"]
    assert set(step["timing"]) == {"1", "8"}
    expected = {"pinn_f64", "pinn_f32", "pinn_numpy", "euler_numpy", "euler_torch", "rk4_numpy", "rk4_torch", "rk45"}
    expected.add("rk4_compiled")  # RK4 of the true model as CasADi-generated C
    for b, rows in step["timing"].items():
        assert set(rows) == expected
        rk45 = step["rk45_median_s"][b]
        assert rk45 == rows["rk45"]["median_s"] > 0
        for row in rows.values():
            assert all(isinstance(row[k], float) and row[k] > 0 for k in ("median_s", "mean_s", "p95_s"))
            assert row["ratio_to_rk45"] == pytest.approx(row["median_s"] / rk45, rel=1e-12)
            assert row["per_sample_median_s"] == pytest.approx(row["median_s"] / int(b), rel=1e-12)
    for key, rmse in step["rmse"].items():
        assert set(rmse) == {"alpha", "beta", "dalpha", "dbeta"}
        assert all(math.isfinite(v) and v > 0 for v in rmse.values()), key
    for name in ("euler", "rk4"):  # numpy and torch run the same formulas: the same answer
        np_rmse, torch_rmse = step["rmse"][f"{name}_numpy"], step["rmse"][f"{name}_torch"]
        assert np_rmse == pytest.approx(torch_rmse, rel=1e-9)
    assert step["rmse"]["rk4_compiled"] == pytest.approx(step["rmse"]["rk4_numpy"], rel=1e-9)  # ... and the C
    for name, size in step["rmse_hold"].items():  # the yardstick: the shipped network is 10x better than standing still
        assert step["rmse"]["pinn_numpy"][name] < size / 10, name


def test_step_skips_rk45_batch_rows_when_asked(tmp_path: Path) -> None:
    off = [o for o in SECTIONS_OFF if not o.startswith("step")]
    result = run_bench(_cfg([*TINY, *off, "step.rk45_batch=skip", "step.compiled_rk4=false"]), tmp_path)
    assert "rk4_compiled" not in result["step"]["rmse"]
    assert "rk45" in result["step"]["timing"]["1"]
    assert "rk45" not in result["step"]["timing"]["8"]
    assert all("ratio_to_rk45" not in row for row in result["step"]["timing"]["8"].values())
    assert "—" in (tmp_path / "bench.md").read_text()


def test_closed_loop_rows(bench: tuple[dict[str, Any], Path]) -> None:
    cl = bench[0]["closed_loop"]
    assert set(cl["rows"]) == {
        "pinn_lifted_gauss_newton",
        "pinn_gauss_newton",
        "pinn_rmsprop",
        "true_rk4_gauss_newton",
        "pinn_lifted_gauss_newton_paper",  # the default controller without offset-free MPC
    }
    assert cl["rows"]["pinn_lifted_gauss_newton_paper"]["disturbance_gain"] == 0.0
    assert cl["rows"]["pinn_lifted_gauss_newton"]["disturbance_gain"] == pytest.approx(0.7)  # conf default
    assert cl["rows"]["pinn_lifted_gauss_newton_paper"]["mae"] != cl["rows"]["pinn_lifted_gauss_newton"]["mae"]
    for key, row in cl["rows"].items():
        assert row["status"] == "ok", key
        assert row["steps"] == MAX_STEPS
        assert all(v > 0 for v in row["mae"].values())
        t = row["ocp_time_s"]
        assert 0 < t["median"] <= t["p95"] <= t["max"]
        assert row["ratio_ocp_to_plant"] == pytest.approx(t["median"] / row["plant_step_median_s"], rel=1e-12)
        assert row["iterations_mean"] > 0 and row["fallbacks"] == 0  # on the nominal plant no solve fails


def test_built_in_reference_rows(bench: tuple[dict[str, Any], Path]) -> None:
    others = bench[0]["closed_loop"]["references"]
    assert list(others) == ["rest", "sine"]
    for row in others.values():
        assert row["status"] == "ok" and row["steps"] == MAX_STEPS
        assert row["solver"] == "lifted_gauss_newton"  # the configured controller
        assert all(v > 0 for v in row["mae"].values())
        assert row["mae_without_disturbance"] != row["mae"]  # the same loop without offset-free MPC
    assert others["rest"]["mae"] != others["sine"]["mae"]  # two different loops, not one row copied


def test_optimality(bench: tuple[dict[str, Any], Path]) -> None:
    per_solver = bench[0]["optimality"]
    assert list(per_solver) == ["lifted_gauss_newton", "gauss_newton", "rmsprop"]  # every PINN row is examined
    for solver, op in per_solver.items():
        assert op["solver"] == solver
        assert op["n_states"] == MAX_STEPS
        assert 0.0 <= op["fraction_within"] <= 1.0
        assert op["rel_gap"]["min"] <= op["rel_gap"]["median"] <= op["rel_gap"]["p95"] <= op["rel_gap"]["max"]
        assert op["rel_gap"]["min"] > -1e-9  # the solver's own solution is among the L-BFGS-B starts
        assert sum(op["best_start_counts"].values()) == op["n_states"]
    assert per_solver["gauss_newton"]["fraction_within"] == 1.0  # the converged fast solver reaches the optimum ...
    lifted = per_solver["lifted_gauss_newton"]  # ... the real-time iteration (the default) one step towards it
    assert lifted["real_time"] and lifted["rel_gap"]["median"] < 1e-2
    assert (
        per_solver["rmsprop"]["rel_gap"]["max"] > per_solver["gauss_newton"]["rel_gap"]["max"]
    )  # ... 30 RMSprop steps not


def test_optimality_of_chosen_solver_without_closed_loop(tmp_path: Path) -> None:
    off = [o for o in SECTIONS_OFF if not o.startswith("optimality")]
    result = run_bench(_cfg([*TINY, *off, "optimality.solvers=[gauss_newton]"]), tmp_path)
    assert list(result["optimality"]) == ["gauss_newton"]
    assert result["optimality"]["gauss_newton"]["n_states"] == MAX_STEPS
    assert "| gauss_newton |" in (tmp_path / "bench.md").read_text()


def test_scaling_and_plots(bench: tuple[dict[str, Any], Path]) -> None:
    result, run_dir = bench
    sc = result["scaling"]
    assert [r["horizon"] for r in sc["horizon"]] == [2, 3]
    assert [r["batch"] for r in sc["batch"]] == [1, 4]
    for r in sc["horizon"] + sc["batch"]:
        assert r["median_s"] > 0
        assert r["problems_per_s"] == pytest.approx(r["batch"] / r["median_s"], rel=1e-12)
    assert all(v > 0 for k, vs in sc["step"].items() for v in vs), sc["step"]
    assert len(sc["plots"]) == 3
    for name in sc["plots"]:
        path = run_dir / name
        assert path.read_bytes()[:8] == PNG_MAGIC
    assert not list(run_dir.glob(".*.tmp"))  # atomic writes left no temp files


def test_markdown_has_every_table(bench: tuple[dict[str, Any], Path]) -> None:
    md = (bench[1] / "bench.md").read_text()
    for text in (
        "Machine:",
        "torch threads 1",
        "## 1. One-step cost",
        "### batch 1",
        "### batch 8",
        "| PINN float64 (torch) |",
        "RMSE alpha",
        "## 2. Closed loop",
        "| PINN-MPC, lifted_gauss_newton, real-time iteration, offset-free (gain 0.7) |",
        "| PINN-MPC, lifted_gauss_newton, real-time iteration, paper's controller |",
        "| PINN-MPC, gauss_newton, offset-free (gain 0.7) |",
        "without offset-free",
        "true model (RK4 h=0.02), gauss_newton",
        "autodiff through RK4 in torch",
        "### Built-in references",
        "| rest | lifted_gauss_newton, offset-free (gain 0.7) |",
        "## 3. OCP optimality",
        "optimality rel gap max",
        "| rmsprop |",
        "## 4. Scaling",
        "### OCP vs horizon",
        "## 5. Targets",
        "| one-step RMSE alpha | 0.001 |",
        "| OCP median / plant step median | 1 |",
        "Units: alpha [rad], beta [rad], dalpha [rad/s], dbeta [rad/s].",
        "| RK4 h=0.02 (compiled C, CasADi) |",
        "## 6. PINN vs classical NMPC (powercube)",
        "| classical NMPC, casadi-sqpmethod |",
        "MAE alpha [rad]",
    ):
        assert text in md, text
    assert "4.14e-04" in md and "1.77e-03" in md  # the paper's one-step numbers sit next to ours
    on_paper = (SHARED / "reference" / "y_soll.mat").is_file()  # reference.path=auto tracked the paper's reference
    assert ("paper (RMSprop" in md) == ("7.53e-03" in md) == on_paper


@pytest.mark.parametrize("case", ["paper", "missing", "builtin"])
def test_the_papers_closed_loop_row_stands_only_beside_loops_on_the_papers_reference(
    tmp_path: Path, request: pytest.FixtureRequest, case: str
) -> None:
    only = [*TINY, *(o for o in SECTIONS_OFF if not o.startswith("closed_loop")), "closed_loop.max_steps=2"]
    only += ["closed_loop.solvers=[lifted_gauss_newton]", "closed_loop.true_model=false"]
    only += ["closed_loop.paper_controller=false", "closed_loop.more_references=[]"]
    extra = {
        "missing": ["system.paper_reference=no/such/folder"],  # auto without the paper's data: the built-in
        "builtin": ["reference.path=null"],
    }.get(case) or [f"reference.path={request.getfixturevalue('paper_reference_dir')}"]  # the paper's, named outright
    result = run_bench(_cfg([*only, *extra]), tmp_path)
    md = (tmp_path / "bench.md").read_text()
    paper = result["paper"]
    assert ("closed_loop" in paper) == ("paper (RMSprop" in md) == (case == "paper")
    assert paper["step_mean_s"]["pinn"] == 4.14e-4  # the one-step costs do not depend on the reference
    if case != "paper":
        assert "builtin:default" in paper["closed_loop_left_out"]
        assert "The paper's row is left out: it was measured on the paper's reference" in md
        on_disk = json.loads((tmp_path / "bench.json").read_text())["paper"]
        assert "closed_loop" not in on_disk and on_disk["closed_loop_left_out"] == paper["closed_loop_left_out"]


def test_targets_sit_next_to_the_measured_numbers(bench: tuple[dict[str, Any], Path]) -> None:
    result = bench[0]
    targets = {t["what"]: t for t in result["targets"]}
    rmse = result["step"]["rmse"]["pinn_numpy"]
    assert targets["one-step RMSE dbeta"]["value"] == rmse["dbeta"] and targets["one-step RMSE dbeta"]["limit"] == 1e-2
    row = result["closed_loop"]["rows"]["pinn_lifted_gauss_newton"]
    mae = next(t for w, t in targets.items() if w.endswith("MAE alpha"))
    assert mae["value"] == row["mae"]["alpha"] and mae["met"] == (row["mae"]["alpha"] <= 5e-4)
    assert not any(w.endswith("MAE dalpha") for w in targets)  # null: no target for velocities
    ratio = targets["OCP median / plant step median"]
    assert ratio["value"] == pytest.approx(row["ratio_ocp_to_plant"]) and ratio["met"] == (ratio["value"] <= 1.0)


def test_the_speed_targets_sit_next_to_the_floor_the_cold_start_and_the_peers(
    bench: tuple[dict[str, Any], Path],
) -> None:
    """Section 5 also holds the network controller's speed targets, each the number its section measured."""
    result, run_dir = bench
    targets = {t["what"]: t for t in result["targets"]}
    floor = {r["horizon"]: r for r in result["floor"]["rows"]}
    at_2 = targets["OCP / floor (median), H = 2"]
    assert at_2["value"] == floor[2]["ratio_median"] and at_2["limit"] == 100.0
    assert at_2["met"] == (at_2["value"] <= 100.0) and not at_2["at_least"]
    assert not any(w.startswith("OCP / floor (median), H = 4") for w in targets)  # not listed: no target
    plain, jump = result["floor"]["cold"]
    assert targets["cold start at H = 6: iterations"]["value"] == plain["cold_iterations"]
    assert targets["cold start at H = 6, after a jump: time / warm median"]["value"] == jump["ratio"]
    peer = targets["fastest peer's OCP / ours, H = 3"]
    pairs = result["peers"]["rows"][0]["pairs"]
    assert peer["at_least"] and peer["value"] == min(p["ratio_median"][k] for k, p in pairs.items())
    assert peer["limit"] == 1.5 and peer["met"] == (peer["value"] >= 1.5)
    assert not any(w.startswith("classical NMPC's OCP") for w in targets)  # the PowerCube has none (null)
    assert "| fastest peer's OCP / ours, H = 3 | at least 1.5 |" in (run_dir / "bench.md").read_text()


def test_the_panda_asks_the_network_controller_to_be_twice_as_fast_as_the_classical_one() -> None:
    """system.targets.classical_speedup (the Panda's 2) is checked on section 6's interleaved line, from below."""
    cfg = _cfg(["system=panda"])
    assert cfg.targets.classical_speedup == 2.0 and _cfg([]).targets.classical_speedup is None
    paired = {"base": "pinn_lifted_gauss_newton", "ratio_median": {"pinn_lifted_gauss_newton": 1.0, "hpipm": 1.87}}
    (row,) = speed_targets(cfg.targets, {"classical": {"paired": paired}})
    assert (row["value"], row["limit"], row["met"], row["at_least"]) == (1.87, 2.0, False, True)
    verdict = targets_verdict([row])
    assert "classical NMPC's OCP / ours, interleaved 1.87 < 2 (0.935x)" in verdict
    assert "Speed ratios move with the machine's load" in verdict and "trade accuracy" not in verdict


def test_make_evaluate_runs_the_step_table_alone() -> None:
    """`make evaluate` promises the bench's step table only: any other section its command left on (the floor, the
    peers and the kinds are on by default) would run closed loops."""
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}  # under `make test`
    dry = subprocess.run(
        ["make", "-n", "--no-print-directory", "evaluate"], capture_output=True, text=True, cwd=CONF.parent, env=env
    )
    assert dry.returncode == 0, dry.stderr
    (line,) = [ln for ln in dry.stdout.replace("\\\n", " ").splitlines() if "pinnmpc.bench" in ln]
    words = shlex.split(line)
    overrides = words[words.index("pinnmpc.bench") + 1 :]
    cfg = _cfg(overrides)
    assert [s for s in BENCH_SECTIONS if cfg[s].enabled] == ["step"]


def test_targets_verdict_says_what_was_missed_and_by_how_much() -> None:
    targets = [
        {"what": "one-step RMSE alpha", "value": 1.51e-3, "limit": 1e-3, "met": False},
        {"what": "one-step RMSE dalpha", "value": 5.34e-3, "limit": 1e-2, "met": True},
    ]
    md = md_targets(targets, "the one shipped for powercube (checkpoint=null)")
    assert "Network: the one shipped for powercube (checkpoint=null)." in md
    assert "| one-step RMSE alpha | 0.001 | 0.00151 | 1.51x | **no** |" in md
    assert "| one-step RMSE dalpha | 0.01 | 0.00534 | 0.534x | yes |" in md
    verdict = "**Verdict: 1 of 2 targets met** (one-step RMSE dalpha); missed: one-step RMSE alpha 0.00151 > 0.001"
    assert verdict + " (1.51x)." in md
    assert "**Verdict: the target met.**" in md_targets(targets[1:], "x")


def test_classical_rows(bench: tuple[dict[str, Any], Path]) -> None:
    result = bench[0]
    cl = result["classical"]
    assert not any("offset-free" in r["label"] for r in cl["rows"].values())  # the table adds the mode, once
    mismatch = ["pinn_lifted_gauss_newton_friction_0.8", "classical_friction_0.8"]
    mismatch += ["pinn_lifted_gauss_newton_friction_1.2", "classical_friction_1.2"]
    exact_rows = ["pinn_lifted_gauss_newton_exact_values", "pinn_lifted_gauss_newton_exact_values_rti"]
    rti_rows = [
        "pinn_lifted_gauss_newton_converged",
        *exact_rows,
        "classical_sqpmethod",
        "classical_sqpmethod_converged",
    ]
    assert list(cl["rows"]) == ["pinn_lifted_gauss_newton", *rti_rows, *mismatch]
    exact, exact_rti = (cl["rows"][r] for r in exact_rows)  # the true model's values, the PINN's Jacobians
    assert exact["prediction"] == exact_rti["prediction"] == "exact_values" and exact["status"] == "ok"
    assert exact_rti["converged_fraction"] <= 1 / MAX_STEPS  # at most the cold start (a real-time iteration's is
    #   handed on after cold_rti_max_iter, converged or not: with inexact Jacobians, not)
    assert cl["rows"]["pinn_lifted_gauss_newton"]["prediction"] == "surrogate"
    surrogate_only = cl["rows"]["pinn_lifted_gauss_newton"]["mae"]
    assert all(exact["mae"][k] < 0.1 * surrogate_only[k] for k in ("alpha", "beta"))  # measured: 1/285 and 1/71
    pinn, classical = cl["rows"]["pinn_lifted_gauss_newton"], cl["rows"]["classical_sqpmethod_converged"]
    rti = cl["rows"]["classical_sqpmethod"]  # the arm's default: one SQP step per sample from the shifted solution
    assert rti["solver"] == "casadi-sqpmethod-rti" and rti["status"] == "ok" and rti["steps"] == MAX_STEPS
    # the shipped network's default (rti=null): one lifted step per sample, unconverged after the first; the
    # converged solve beside it
    assert pinn["real_time"] and pinn["status"] == "ok" and pinn["converged_fraction"] == pytest.approx(1 / MAX_STEPS)
    converged = cl["rows"]["pinn_lifted_gauss_newton_converged"]
    assert not converged["real_time"] and converged["status"] == "ok" and converged["converged_fraction"] == 1.0
    md = (bench[1] / "bench.md").read_text()
    assert "| classical NMPC, casadi-sqpmethod-rti |" in md and "| PINN-MPC, lifted_gauss_newton, real-time" in md
    assert "Rows 'exact values': the PINN controller predicting with the true model's values" in md
    assert (bench[1] / "classical.png").read_bytes()[:8] == PNG_MAGIC  # every row: worst MAE against OCP time
    assert "| PINN-MPC, lifted_gauss_newton, exact values (true model's values, PINN's Jacobians), offset-free" in md
    assert pinn["mae"] == result["closed_loop"]["rows"]["pinn_lifted_gauss_newton"]["mae"]  # reused, same process
    assert classical["solver"] == "casadi-sqpmethod" and classical["model"] == "classical"
    assert classical["status"] == "ok" and classical["steps"] == MAX_STEPS
    assert all(v > 0 for v in classical["mae"].values())
    t = classical["ocp_time_s"]
    assert 0 < t["median"] <= t["p95"] <= t["max"]
    assert classical["ratio_ocp_to_plant"] == pytest.approx(t["median"] / classical["plant_step_median_s"], rel=1e-12)
    assert cl["shared"] == ["horizon", "Q", "R", "R_rate", "u_low", "u_high"]
    paired = cl["paired"]  # the PINN controller and the classical default again, their samples interleaved
    assert paired["base"] == "pinn_lifted_gauss_newton" and paired["status"] == "ok"
    assert set(paired["ocp_median_s"]) == {"pinn_lifted_gauss_newton", "casadi-sqpmethod-rti"}
    assert paired["samples"] == MAX_STEPS and paired["ratio_median"]["casadi-sqpmethod-rti"] > 0
    assert paired["worst_mae"]["pinn_lifted_gauss_newton"] > paired["worst_mae"]["casadi-sqpmethod-rti"] > 0
    assert "Interleaved (" in md and "casadi-sqpmethod-rti / pinn_lifted_gauss_newton OCP time" in md
    for scale in ("0.8", "1.2"):  # a plant off the model: the classical NMPC estimates the offset, as the PINN one
        off = cl["rows"][f"classical_friction_{scale}"]
        assert off["status"] == "ok" and off["disturbance_gain"] == pinn["disturbance_gain"] > 0
        assert classical["disturbance_gain"] == 0  # exact model: nothing to estimate
        assert all(off["mae"][n] > 10 * classical["mae"][n] for n in ("alpha", "beta"))  # its model is not exact now
        assert cl["rows"][f"pinn_lifted_gauss_newton_friction_{scale}"]["mae"] != pinn["mae"]
        label = f"| classical NMPC, casadi-sqpmethod-rti, plant friction x{scale}, offset-free"
        assert label in (bench[1] / "bench.md").read_text()


def test_classical_alone_runs_its_own_pinn_row_and_extra_solvers(tmp_path: Path) -> None:
    off = [o for o in SECTIONS_OFF if not o.startswith("classical")]
    overrides = [*TINY, *off, "classical.enabled=true", "classical.solvers=[ipopt]", "closed_loop.max_steps=3"]
    overrides += ["classical.friction_scales=[]", "classical.rti=false", "classical.exact_values=false"]
    cl = run_bench(_cfg(overrides), tmp_path)["classical"]
    assert list(cl["rows"]) == ["pinn_lifted_gauss_newton", "classical_sqpmethod", "classical_ipopt"]
    assert all(r["steps"] == 3 and r["status"] == "ok" for r in cl["rows"].values())
    assert "| classical NMPC, casadi-ipopt |" in (tmp_path / "bench.md").read_text()


def test_a_network_with_a_prior_gets_a_row_on_that_prior_alone(tmp_path: Path) -> None:
    off = [o for o in SECTIONS_OFF if not o.startswith("classical")]
    overrides = [*TINY, *off, "system=planar3", "classical.enabled=true", "closed_loop.max_steps=3"]
    overrides += ["classical.friction_scales=[]", "classical.rti=false", "classical.exact_values=false"]
    cl = run_bench(_cfg(overrides), tmp_path)["classical"]
    assert list(cl["rows"])[:2] == ["pinn_lifted_gauss_newton", "pinn_lifted_gauss_newton_prior"]  # then classical
    prior = cl["rows"]["pinn_lifted_gauss_newton_prior"]
    assert prior["prediction"] == "prior" and prior["status"] == "ok" and prior["steps"] == 3
    md = (tmp_path / "bench.md").read_text()
    assert "| PINN-MPC, lifted_gauss_newton, physics prior alone (no network)" in md and "Rows 'physics prior" in md


def test_rk4_model_jacobians_agree() -> None:
    system = PowerCube()
    x0 = torch.tensor([[0.3, -0.4, 0.5, 1e-3], [-1.0, 0.8, -0.2, 0.7]], dtype=torch.float64)
    u = torch.tensor([[0.1, -0.2], [0.4, 0.3]], dtype=torch.float64)
    fwd, rev = RK4Model(system, 0.2, 0.02, "jacfwd"), RK4Model(system, 0.2, 0.02, "reverse")
    x1f, Af, Bf = fwd.step_with_jacobian(x0, u)
    x1r, Ar, Br = rev.step_with_jacobian(x0, u)
    assert Af.shape == (2, 4, 4) and Bf.shape == (2, 4, 2)
    torch.testing.assert_close(x1f, fwd.step(x0, u), rtol=0, atol=1e-14)
    torch.testing.assert_close((x1r, Ar, Br), (x1f, Af, Bf), rtol=1e-10, atol=1e-12)
    eps = 1e-6  # central differences along u1 of the second sample (away from dbeta = 0)
    du = torch.tensor([eps, 0.0], dtype=torch.float64)
    fd = (rev.step(x0[1], u[1] + du) - rev.step(x0[1], u[1] - du)) / (2 * eps)
    torch.testing.assert_close(Br[1, :, 0], fd, rtol=1e-5, atol=1e-7)


def test_rk4_model_jacobians_agree_on_a_urdf_arm_in_a_batch() -> None:
    # torch 2.13's linalg.solve differentiated by vmap(jacfwd) was wrong past the first row (off by 1e165)
    system = load_system("planar3")
    g = torch.Generator().manual_seed(4)
    x0 = (torch.rand(3, 6, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([3.0, 3.0, 3.0, 2.0, 2.0, 2.0])
    u = (torch.rand(3, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([20.0, 8.0, 2.0])
    fwd = RK4Model(system, system.tau, 0.0125, "jacfwd").step_with_jacobian(x0, u)
    rev = RK4Model(system, system.tau, 0.0125, "reverse").step_with_jacobian(x0, u)
    torch.testing.assert_close(fwd, rev, rtol=1e-10, atol=1e-12)


def test_true_model_baseline_runs_a_closed_loop() -> None:
    cfg = _cfg(["closed_loop.max_steps=2", "progress=false"])
    system = PowerCube()
    ref = bench_reference(cfg, system, 0.2, "default")
    row, _ = run_controller(cfg, system, RK4Model(system, 0.2, 0.02), ref, "lifted_gauss_newton", record=False)
    assert row["status"] == "ok" and row["steps"] == 2  # the controller takes the true model like a surrogate


def test_a_bench_loop_whose_every_solve_fails_is_failed_not_ok() -> None:
    cfg = _cfg(["closed_loop.max_steps=3", "progress=false"])
    system, s = PowerCube(), load_surrogate()
    for p in s.model.parameters():
        p.data.fill_(math.nan)  # a network that predicts NaN: every solve falls back
    ref = bench_reference(cfg, system, 0.2, "default")
    row, _ = run_controller(cfg, system, s, ref, "lifted_gauss_newton", record=False)
    assert row["fallbacks"] == 3 and row["status"].startswith("failed")  # as pinnmpc.closed_loop says it


def test_reference_auto_is_the_papers_only_where_the_paper_ran() -> None:
    planar = _cfg(["system=planar3"])
    assert planar.paper is None and planar.step.h == 0.0025  # conf/bench/system/planar3.yaml
    ref = bench_reference(planar, load_system("planar3"), 0.1)
    assert ref.name == "builtin:default" and ref.x.shape[1] == 6


# ---------------------------------------------------------------------------------------------------------------
# The planar 3-link arm: the same bench with names, units, targets and references from its config

P3_STEPS = 2  # closed-loop solves per row
P3_TINY = [
    "system=planar3",
    "progress=false",
    "step.batch_sizes=[1,4]",
    "step.n_states=4",
    "step.repeats=2",
    "step.warmup=0",
    "step.h=0.01",  # 10 RK4 steps a period: few calls of the URDF arm's torch rhs, the costly one
    "step.ref_h=1.0e-3",
    f"closed_loop.max_steps={P3_STEPS}",
    "closed_loop.solvers=[lifted_gauss_newton]",
    "closed_loop.true_model_solvers=[lifted_gauss_newton]",
    "closed_loop.more_references=[sine]",
    "closed_loop.paper_controller=false",
    "optimality.enabled=false",
    "scaling.enabled=false",
    "peers.enabled=false",
]


@pytest.fixture(scope="module")
def planar3(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    """A tiny untrained network for the planar arm's boxes, saved like a trained one, and one bench run on it."""
    folder = tmp_path_factory.mktemp("bench_planar3")
    system = load_system("planar3")
    torch.manual_seed(0)
    box, ubox = system.state_box, system.input_box
    model = PINN(box.low, box.high, ubox.low, ubox.high, t_max=0.125, hidden=[16, 16], periodic=[0, 1, 2])
    path = Surrogate(model, system.tau, system.state_names, system.input_names).save(folder / "surrogate.pt")
    return run_bench(_cfg([*P3_TINY, f"checkpoint={path}"]), folder), folder


def test_planar3_bench_is_generic(planar3: tuple[dict[str, Any], Path]) -> None:
    result, run_dir = planar3
    names = ["q_joint1", "q_joint2", "q_joint3", "v_joint1", "v_joint2", "v_joint3"]
    assert result["system"]["name"] == "planar3" and result["system"]["state_names"] == names
    assert result["paper"] is None and {"step", "closed_loop", "classical"} <= set(result)
    assert {"optimality", "scaling"}.isdisjoint(result)
    step = result["step"]
    assert step["tau_s"] == 0.1 and step["h_s"] == 0.01
    assert all(set(r) == set(names) for r in step["rmse"].values())
    assert all(math.isfinite(v) for k in ("pinn_f64", "pinn_numpy") for v in step["rmse"][k].values())
    assert step["rmse"]["rk4_compiled"] == pytest.approx(step["rmse"]["rk4_numpy"], rel=1e-9)
    cl = result["closed_loop"]
    assert cl["reference"] == "builtin:default" and list(cl["references"]) == ["sine"]
    assert cl["true_model_backend"] == "compiled"  # the torch rhs of a URDF arm is far too slow for a controller
    assert set(cl["rows"]) == {"pinn_lifted_gauss_newton", "true_rk4_lifted_gauss_newton"}
    for row in [*cl["rows"].values(), *cl["references"].values(), *result["classical"]["rows"].values()]:
        assert row["steps"] == P3_STEPS and set(row["mae"]) == set(names)
    mismatch = [f"{who}_friction_{f}" for f in ("0.8", "1.2") for who in ("pinn_lifted_gauss_newton", "classical")]
    rows = ["pinn_lifted_gauss_newton", "pinn_lifted_gauss_newton_converged", "pinn_lifted_gauss_newton_exact_values"]
    rows += ["pinn_lifted_gauss_newton_exact_values_rti", "classical_sqpmethod", "classical_sqpmethod_converged"]
    rows += ["classical_sqpmethod_rk4", *mismatch]  # planar3's default: Radau, a real-time iteration; then the others
    assert list(result["classical"]["rows"]) == rows
    targets = {t["what"]: t for t in result["targets"]}
    assert targets["one-step RMSE q_joint1"]["limit"] == 1e-3  # conf/system/planar3.yaml
    md = (run_dir / "bench.md").read_text()
    for text in (
        "# pinnmpc benchmark: planar3",
        "Units: q_joint1 [rad]",
        "| RMSE q_joint1 |",
        "true model (RK4 h=0.0025, compiled), lifted_gauss_newton",  # conf/bench/system/planar3.yaml
        "## 6. PINN vs classical NMPC (planar3)",
        "MAE q_joint3 [rad]",
    ):
        assert text in md, text
    for text in ("paper", "alpha", "Table 1"):  # the PowerCube's publication stays out of another arm's report
        assert text not in md, text


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("step.batch_sizes=[]", "step.batch_sizes=[]: expected a non-empty list, each entry an integer >= 1"),
        ("step.batch_sizes=[0]", "step.batch_sizes=[0]: expected a non-empty list"),
        ("scaling.horizons=[0]", "scaling.horizons=[0]: expected a non-empty list"),
        ("optimality.n_states=0", "optimality.n_states=0: expected an integer >= 1"),
        (" ".join(SECTIONS_OFF), "every bench section is off"),
    ],
)
def test_bad_sizes_are_refused_before_any_work(tmp_path: Path, override: str, message: str) -> None:
    from pinnmpc.util.checks import SettingError

    with pytest.raises(SettingError) as e:
        run_bench(_cfg([*TINY, *override.split()]), tmp_path)
    assert str(e.value).startswith(message) and not list(tmp_path.iterdir())


def test_the_floor_section_times_the_network_beside_each_solve(bench: tuple[dict[str, Any], Path]) -> None:
    """Section 9: per horizon, the controller's OCP time and the network's own evaluation at its nodes, timed after
    each solve of one closed loop; the controller's time includes that evaluation, so the ratio is above 1."""
    result, run_dir = bench
    rows = result["floor"]["rows"]
    assert [r["horizon"] for r in rows] == [2, 4] and all(r["steps"] == MAX_STEPS for r in rows)
    assert all(0 < r["floor_median_s"] < r["ocp_median_s"] and r["ratio_median"] > 1 for r in rows)
    assert "## 9. The network controller against its floor" in (run_dir / "bench.md").read_text()


def test_the_floor_probe_hands_the_closed_loops_dead_time_to_its_controller() -> None:
    """A plant that runs each command a period late (plant=franka) sets delay_periods on the controller it is given:
    through the floor's probe it must reach the controller that plans, or that loop rings (plant.delay_periods)."""
    from pinnmpc.bench.common import controller_cfg
    from pinnmpc.bench.floor import FloorProbe
    from pinnmpc.controller.build import build_nmpc

    cfg = _cfg(TINY)
    surrogate = load_surrogate(system="powercube")
    probe = FloorProbe(build_nmpc(controller_cfg(cfg), surrogate, PowerCube()), surrogate)
    assert probe.delay_periods == 0
    probe.delay_periods = 1
    assert probe.inner.delay_periods == 1 and "delay_periods" not in vars(probe)


def test_the_floor_section_times_a_cold_start_with_and_without_a_jump(bench: tuple[dict[str, Any], Path]) -> None:
    """Section 9's cold start: a closed loop's first solve on the reference and on it with a jump inside the first
    horizon, each against its loop's warm median; the jump costs the cold solve more iterations, never fewer."""
    result, run_dir = bench
    plain, jump = result["floor"]["cold"]
    assert "+0.3 rad from sample 4" in jump["reference"] and plain["horizon"] == jump["horizon"] == 6
    assert 1 <= plain["cold_iterations"] <= jump["cold_iterations"] <= 10
    assert all(r["cold_s"] > 0 and r["warm_median_s"] > 0 and r["ratio"] > 0 for r in (plain, jump))
    assert "| cold iterations |" in (run_dir / "bench.md").read_text()


def test_the_peers_section_runs_casadi_on_the_same_network_interleaved(bench: tuple[dict[str, Any], Path]) -> None:
    """Section 10: ours and CasADi's real-time iteration on the exported flow map (qrqp, HPIPM) track the reference
    pair by pair with their samples interleaved: the same network, OCP and estimator track alike; absent peers get a
    line each."""
    result, run_dir = bench
    section = result["peers"]
    (row,) = section["rows"]
    assert row["horizon"] == 3 and list(row["pairs"]) == ["casadi_rti_qrqp", "casadi_rti_hpipm"]
    for peer, pair in row["pairs"].items():  # each peer with ours alone
        assert pair["samples"] == MAX_STEPS and pair["status"] == "ok" and pair["base"] == "pinn"
        assert list(pair["ocp_median_s"]) == ["pinn", peer]
        assert pair["ratio_median"]["pinn"] == 1.0 and pair["ratio_median"][peer] > 0
        mae = list(pair["worst_mae"].values())
        assert min(mae) > 0 and max(mae) <= 1.05 * min(mae)
    ours = [pair["worst_mae"]["pinn"] for pair in row["pairs"].values()]
    assert ours[0] == ours[1]  # the same loop in each pair: reset, same plant, same reference
    assert set(section["missing"]) <= {"acados", "l4casadi"}
    assert all(why.startswith("skipped: ") for why in section["missing"].values())
    md = (run_dir / "bench.md").read_text()
    assert "## 10. Peers on the same network" in md and "| 3 | casadi_rti_hpipm |" in md


def test_a_zero_target_is_a_target_and_null_is_none() -> None:
    rows = _per_state("one-step RMSE", {"a": 1e-9, "b": 0.0, "c": 1.0}, ["a", "b", "c"], [0.0, 0.0, None])
    assert [(r["what"], r["met"]) for r in rows] == [("one-step RMSE a", False), ("one-step RMSE b", True)]


def test_the_robot_section_runs_every_controller_on_the_robot(tmp_path: Path) -> None:
    off = [f"{s}.enabled=false" for s in ("step", "closed_loop", "optimality", "scaling", "classical")]
    cfg = _cfg(
        ["system=planar3", "plant=mujoco", "plant.robot=lab", *off, "robot.enabled=true", "closed_loop.max_steps=3",
         f"robot.adapted={CHECKPOINTS / 'planar3-lab.pt'}", "robot.references=[default]", "progress=false"]
    )  # fmt: skip
    robot = run_bench(cfg, tmp_path)["robot"]
    classical = ["casadi_nominal", "casadi_nominal_converged", "casadi_nominal_est", "casadi_nominal_converged_est"]
    keys = [*classical, "pinn_shipped", "pinn_adapted", "pinn_shipped_nominal"]
    assert list(robot["rows"]) == [f"{k}@builtin:default" for k in keys]
    assert robot["rows"]["casadi_nominal_est@builtin:default"]["disturbance_gain"] == 0.7
    assert robot["rows"]["casadi_nominal@builtin:default"]["real_time"] is True  # planar3: a real-time iteration
    assert robot["rows"]["casadi_nominal_converged@builtin:default"]["real_time"] is False
    best = robot["best_classical"]["builtin:default"]
    mae = {k: max(robot["rows"][f"{k}@builtin:default"]["mae"][f"q_joint{j}"] for j in (1, 2, 3)) for k in classical}
    assert best in classical and mae[best] == min(mae.values())
    assert all(r["status"] == "ok" and r["steps"] == 3 for r in robot["rows"].values())
    (paired,) = robot["paired_ocp"]  # the two networks' loops again, their samples interleaved
    assert (paired["samples"], paired["status"], paired["base"]) == (3, "ok", "pinn_shipped")
    assert paired["ratio_median"]["pinn_shipped"] == 1.0 and paired["ratio_median"]["pinn_adapted"] > 0
    assert all(0 < paired["ocp_median_s"][k] <= paired["ocp_p95_s"][k] for k in ("pinn_shipped", "pinn_adapted"))
    report = (tmp_path / "bench.md").read_text()
    assert "## 7. On the robot `lab`" in report and "samples interleaved in one process" in report
    assert "Best classical per reference" in report
    with pytest.raises(ValueError, match="expected plant=mujoco plant.robot=<name>"):
        run_bench(_cfg(["system=planar3", *off, "robot.enabled=true", "progress=false"]), tmp_path / "b")


def test_the_peers_are_skipped_in_one_line_without_the_classical_config(tmp_path: Path) -> None:
    """The peers are the classical NMPC on the network: without its config the section says so, nothing runs."""
    off = [o for o in SECTIONS_OFF if o != "peers.enabled=false"]
    result = run_bench(_cfg([*TINY, *off, "~controller@classical.controller"]), tmp_path)
    assert result["peers"] == {"skipped": "conf/controller/casadi.yaml is absent"}
    assert "Skipped: conf/controller/casadi.yaml is absent." in (tmp_path / "bench.md").read_text()
