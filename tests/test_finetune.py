"""Fine-tuning on a robot's logs: real MuJoCo robot, real closed loops to log, real Lightning training on them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant.mujoco_robot import make_mujoco_plant
from pinnmpc.references import Reference
from pinnmpc.robot_data.residual_model import physics_model
from pinnmpc.surrogate.prior import ArmPrior
from pinnmpc.systems import system_config
from pinnmpc.training.run import train
from tests.conftest import TINY_TRAIN, write_test_log

FINE = 5  # samples per control period in the test log
TINY = [*TINY_TRAIN, "system=planar3", "model.auto_scale.h=1e-3", "progress=false", "data.n_anchor=0"]
# RK4 at 1e-2 diverges here; no anchors: with logs they need an identified model (physics=...)


def _episode(system, controller, plant, ref: Reference, t0: float, ep: int) -> tuple[list, list]:
    """One closed loop on the robot, recorded at the control rate and FINE times per period."""
    coarse, fine = [], []
    x = ref.x[0].copy()
    controller.reset()
    for k in range(len(ref) - 6):
        u = np.clip(controller.make_step(x, ref.x[k + 1 : k + 6]), system.input_box.low, system.input_box.high)
        coarse.append((t0 + k * system.tau, x.copy(), u, ep))
        for j in range(FINE):
            fine.append((t0 + (k + j / FINE) * system.tau, x.copy(), ep))
            x = plant.step(x, u)
    coarse.append((t0 + (len(ref) - 6) * system.tau, x.copy(), coarse[-1][2], ep))
    fine.append((coarse[-1][0], x.copy(), ep))
    return coarse, fine


@pytest.fixture(scope="module")
def lab_log(tmp_path_factory) -> str:
    """Four 8-s episodes of planar3's lab robot under the shipped controller, as `pinnmpc.collect` writes them."""
    system = load_system("planar3")
    robots = OmegaConf.to_container(system_config("planar3").robots, resolve=True)
    plant = make_mujoco_plant(system, system.tau / FINE, robots, "lab")
    flow = load_surrogate(system="planar3")
    controller = build_nmpc({"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6]}, flow, system)
    coarse, fine = [], []
    t = np.arange(0.0, 8.0, system.tau)
    for ep, (amp, freq) in enumerate([(0.3, 0.5), (0.4, 0.7), (0.25, 0.9), (0.35, 0.6)]):
        q = amp * np.sin(np.outer(t, [freq, 1.3 * freq, 1.7 * freq]))
        ref = Reference(t, np.hstack([q, np.gradient(q, t, axis=0)]), f"sine-{ep}")
        c, f = _episode(system, controller, plant, ref, 10.0 * ep, ep)
        coarse += c
        fine += f
    return write_test_log(tmp_path_factory.mktemp("logs") / "lab", system, "lab", FINE, coarse, fine)


def test_training_on_logs_fits_the_robot_and_records_them(make_cfg, tmp_path, lab_log):
    overrides = [*TINY, "trainer.max_epochs=3", f"data.logs=[{lab_log}]"]
    cfg = make_cfg("train", overrides)
    summary = train(cfg, tmp_path)
    net = load_surrogate(tmp_path / "surrogate.pt")
    assert net.meta["robot_logs"][0]["robot"] == "lab" and net.meta["robot_logs"][0]["system"] == "planar3"
    metrics = summary["final_metrics"]
    assert "train/loss_robot" in metrics and np.isfinite(metrics["train/loss_robot"])
    # the validation set is the held-out episode's one-period transitions on the robot, not the model's flow
    dm_val = summary["best_val_rmse_position"]
    assert dm_val is not None and np.isfinite(dm_val)


def test_the_robot_loss_pulls_the_network_towards_the_logs(make_cfg, tmp_path, lab_log):
    # the same tiny training with and without the logs: with them, the network predicts the robot's steps closer
    from pinnmpc.robot_data.episodes import transitions
    from pinnmpc.robot_data.logs import read_log

    system = load_system("planar3")
    t, x0, u, xt = transitions([read_log(lab_log, system)], system.tau)
    at_tau = (t[:, 0] - system.tau).abs() < 1e-9
    errors = []
    for extra in ([], [f"data.logs=[{lab_log}]", "module.weight_robot=1e4"]):
        cfg = make_cfg("train", [*TINY, "trainer.max_epochs=6", *extra])
        train(cfg, tmp_path / str(len(extra)))
        net = load_surrogate(tmp_path / str(len(extra)) / "surrogate.pt")
        with torch.no_grad():
            pred = net.step(x0[at_tau], u[at_tau])
        errors.append(float((pred - xt[at_tau])[:, :3].square().mean().sqrt()))
    assert errors[1] < 0.7 * errors[0], errors


@pytest.mark.parametrize(
    ("override", "says"),
    [
        ("data.val_episodes=1.5", "data.val_episodes=1.5"),
        ("data.n_robot=-1", "data.n_robot=-1"),
        ("module.robot_delta=-1", "module.robot_delta=-1"),
        ("data.robot_max_input_step=0", "data.robot_max_input_step=0"),
        ("data.logs=[/nonexistent/log.npz]", "/nonexistent/log.npz"),
    ],
)
def test_bad_fine_tuning_settings_are_named(make_cfg, tmp_path, override, says):
    cfg = make_cfg("train", [*TINY, "trainer.max_epochs=1", override])
    with pytest.raises((ValueError, FileNotFoundError), match=says.replace("[", r"\[").replace(".", r"\.")):
        train(cfg, tmp_path)


def test_a_warm_solve_of_the_fine_tuned_network_stays_within_its_iteration_cap(make_cfg) -> None:
    """The shipped fine-tuned planar3 network at a held pose, solved fully at every sample (rti=false; its default
    real-time iteration solves such samples fully too, beyond its trust bound): its learnt stick-slip makes
    Gauss-Newton crawl, so a cold solve runs to cold_max_iter + max_iter; a warm-started one stops its fallback at
    warm_max_iter."""
    converged = "controller.rti=false"
    cfg = make_cfg("closed_loop", ["system=planar3", "controller.disturbance.gain=0", converged])
    surrogate = load_surrogate("pinnmpc/checkpoints/planar3-lab.pt")
    nmpc = build_nmpc(cfg.controller, surrogate, load_system("planar3"))
    solver = nmpc.solver
    caps = (solver.cold_max_iter, solver.lifted_max_iter, solver.max_iter, solver.warm_max_iter)
    assert not solver.rti and caps == (10, 5, 30, 10)
    x = np.array([-0.26, -0.165, 0.19, 0.0, 0.0, 0.0])  # check_contract's held pose
    ref = np.tile(x, (nmpc.horizon, 1))
    for _ in range(3):
        nmpc.make_step(x, ref)
    cold, *warm = [s.iterations for s in nmpc.stats]
    assert cold == 40 and all(w <= 15 for w in warm), (cold, warm)
    assert not any(s.fallback for s in nmpc.stats)


def _fitted_planar3(path, origin: str = "planar3", tau: float | None = None):
    """A system config as pinnmpc.identify writes it: planar3 with a payload, identified from `origin`."""
    cfg = OmegaConf.to_container(system_config("planar3"), resolve=True)
    cfg["dynamics"]["name"] = "planar3_fit"
    cfg["dynamics"]["tau"] = tau or cfg["dynamics"]["tau"]
    cfg["dynamics"]["joint_prefix"] = "planar3_"
    cfg["dynamics"]["payload"] = {"mass": 0.5}
    cfg["identified_from"] = {"system": origin, "logs": ["lab.npz"], "fitted": ["payload"]}
    path.parent.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(OmegaConf.create(cfg), path)
    return path


def test_the_physics_residual_of_an_identified_model(make_cfg, tmp_path, lab_log):
    """physics=<identified .yaml>: the same seeded fine-tuning with the fitted model's residual ends elsewhere than
    with the nominal one's, and the network records which model it was; another arm's model is refused."""
    fitted = _fitted_planar3(tmp_path / "fits" / "planar3_fit.yaml")
    outs = []
    for extra in ([], [f"physics={fitted}"]):
        cfg = make_cfg("train", [*TINY, "trainer.max_epochs=2", f"data.logs=[{lab_log}]", *extra])
        train(cfg, tmp_path / str(len(extra)))
        outs.append(load_surrogate(tmp_path / str(len(extra)) / "surrogate.pt"))
    assert "physics" not in outs[0].meta
    physics = outs[1].meta["physics"]
    assert physics["name"] == "planar3_fit" and physics["identified_from"] == "planar3"
    assert physics["coefficients"]["payload"]["mass"] == 0.5 and physics["fitted"] == ["payload"]
    x0, u = torch.zeros(4, 6, dtype=torch.float64), torch.full((4, 3), 0.5, dtype=torch.float64)
    with torch.no_grad():
        assert not torch.allclose(outs[0].step(x0, u), outs[1].step(x0, u))
    # the frozen-arm prior is the fitted arm's too, and survives the save
    arms = [out.model.config["prior"]["dynamics"] for out in outs]
    assert arms[0]["name"] == "planar3" and arms[1]["name"] == "planar3_fit" and arms[1]["payload"]["mass"] == 0.5
    t = torch.full((4, 1), 0.1, dtype=torch.float64)
    fitted_prior = ArmPrior(load_system(fitted))(t, x0, u)[0]
    np.testing.assert_allclose(outs[1].model.prior(t, x0, u)[0].numpy(), fitted_prior.numpy(), atol=1e-12)
    assert not torch.allclose(outs[0].model.prior(t, x0, u)[0], fitted_prior, atol=1e-4)
    other = _fitted_planar3(tmp_path / "other" / "planar3_fit.yaml", origin="powercube")
    slower = _fitted_planar3(tmp_path / "slower" / "planar3_fit.yaml", tau=0.2)
    for bad, says in ((other, "identified from 'powercube'; expected a model of 'planar3'"),
                      (slower, "its tau, state names or boxes differ from planar3's"),
                      (tmp_path / "none.yaml", "no such file")):  # fmt: skip
        cfg = make_cfg("train", [*TINY, "trainer.max_epochs=1", f"data.logs=[{lab_log}]", f"physics={bad}"])
        with pytest.raises(ValueError, match=f"physics={bad}: {says}"):
            train(cfg, tmp_path / "bad")
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


def test_a_servos_identified_friction_enters_the_prior_smoothed(tmp_path):
    """physics_model: a servo model's dry friction goes to the frozen-arm prior at physics_prior_slope (0: not at all;
    recorded in the meta), the residual's model keeps its own; a torque arm's too (its frozen_arm prior leaves the
    friction out, frozen_arm_friction integrates it), its required coulomb zeroed at 0."""
    cfg = {"dynamics": OmegaConf.to_container(system_config("panda").dynamics, resolve=True)}
    cfg["dynamics"].update(
        name="panda_fit", joint_prefix="panda_", coulomb=[3.0, 2.8, 1.5, 1.0, 0.1, 0.1, 0.02], coulomb_slope=50.0
    )
    cfg["identified_from"] = {"system": "panda", "logs": ["lab.npz"], "fitted": ["coulomb"]}
    path = tmp_path / "panda_fit.yaml"
    OmegaConf.save(OmegaConf.create(cfg), path)
    panda = load_system("panda")
    model, record, arm = physics_model(str(path), panda, 3.0)
    assert model.coulomb_slope == 50.0 and arm["coulomb_slope"] == 3.0 and record["prior_coulomb_slope"] == 3.0
    assert physics_model(str(path), panda, None)[2]["coulomb_slope"] == 50.0
    model, record, arm = physics_model(str(path), panda, 0.0)  # 0: the friction left to the network
    assert model.coulomb and "coulomb" not in arm and record["prior_coulomb_slope"] == 0.0
    assert physics_model(str(path), panda)[1].get("prior_coulomb_slope") is None
    planar = _fitted_planar3(tmp_path / "planar3_fit.yaml")
    model, record, arm = physics_model(str(planar), load_system("planar3"), 3.0)
    assert model.coulomb_slope == 50.0 and arm["coulomb_slope"] == 3.0 and record["prior_coulomb_slope"] == 3.0
    assert physics_model(str(planar), load_system("planar3"), 0.0)[2]["coulomb"] == [0.0, 0.0, 0.0]


def test_anchors_with_logs_need_an_identified_model(make_cfg, tmp_path, lab_log):
    """Nominal anchors beside robot logs are refused with the fix named; an identified model's anchors train."""
    fitted = _fitted_planar3(tmp_path / "fits" / "planar3_fit.yaml")
    base = [*TINY, "trainer.max_epochs=1", f"data.logs=[{lab_log}]", "data.n_anchor=32"]
    with pytest.raises(ValueError, match=r"data.n_anchor=32 with data.logs and physics=null: anchors of the nominal"):
        train(make_cfg("train", base), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
    train(make_cfg("train", [*base, f"physics={fitted}"]), tmp_path / "ok")
    assert load_surrogate(tmp_path / "ok" / "surrogate.pt").meta["physics"]["name"] == "planar3_fit"


def test_held_out_rmse_of_networks_and_models(lab_log):
    """The bench's held-out one-step RMSE: a model with the lab robot's payload and armature predicts its steps
    closer than the nominal model, both by RK4, beside the shipped network's figure."""
    import dataclasses

    from pinnmpc.bench.robot import held_out_rmse

    system = load_system("planar3")
    lab = system_config("planar3").robots.lab
    known = dataclasses.replace(system, payload=dict(lab.payload), armature=list(lab.armature))
    out = held_out_rmse(system, {"pinn_shipped": load_surrogate(system="planar3")}, [lab_log],
                        {"nominal": system, "known": known}, rk4_steps=25)  # fmt: skip
    assert out["transitions"]["count"] > 100 and set(out) == {"pinn_shipped", "nominal", "known", "transitions"}
    angles = list(system.state_names[:3])
    assert all(out["known"][n] < 0.5 * out["nominal"][n] for n in angles), out


def test_fine_tuning_from_a_network_widens_its_scale_to_the_robots_miss(make_cfg, tmp_path, lab_log):
    from pinnmpc.training.models import build_model

    first = tmp_path / "first"
    train(make_cfg("train", [*TINY, "trainer.max_epochs=1"]), first)
    base = load_surrogate(first / "surrogate.pt").model
    overrides = [*TINY, f"init_from={first / 'surrogate.pt'}", f"data.logs=[{lab_log}]"]
    plain = build_model(make_cfg("train", overrides), load_system("planar3"))
    widened = build_model(make_cfg("train", [*overrides, "model.rescale_to_logs=true"]), load_system("planar3"))
    assert torch.equal(plain.out_scale, base.out_scale)
    assert torch.all(widened.out_scale >= base.out_scale) and torch.any(widened.out_scale > base.out_scale)


def test_a_network_without_live_features_is_refused_for_fine_tuning(make_cfg, tmp_path, lab_log):
    """A network whose last hidden layer is saturated everywhere on the logs (as fr3.pt's, which its prior made
    exact) gets no gradient: fine-tuning from it is refused in one line naming init_from; a live one is not."""
    from pinnmpc.training.models import build_model
    from pinnmpc.training.rescale import live_features, log_transitions

    first = tmp_path / "first"
    train(make_cfg("train", [*TINY, "trainer.max_epochs=1"]), first)
    live = load_surrogate(first / "surrogate.pt").model
    logged = log_transitions(load_system("planar3"), [lab_log])
    assert live_features(live, logged) > 0
    saved = torch.load(first / "surrogate.pt", weights_only=False)
    last_hidden = max(int(k.split(".")[2]) for k in saved["state_dict"] if k.startswith("net.layers.")) - 1
    saved["state_dict"][f"net.layers.{last_hidden}.weight"].zero_()
    saved["state_dict"][f"net.layers.{last_hidden}.bias"].fill_(-1000.0)  # silu(-1000): no unit alive
    dead = tmp_path / "dead.pt"
    torch.save(saved, dead)
    assert live_features(load_surrogate(dead).model, logged) == 0
    with pytest.raises(ValueError, match=r"init_from=.*dead.pt: no unit of its last hidden layer is alive"):
        build_model(make_cfg("train", [*TINY, f"init_from={dead}", f"data.logs=[{lab_log}]"]), load_system("planar3"))


def test_a_zero_output_network_starts_as_its_prior_and_still_learns(make_cfg, tmp_path, lab_log):
    """model.zero_output: a fresh network is exactly its prior (fine-tuning from an identified model's prior starts
    at that model), and a training on the logs moves it away from there; without a prior it is refused."""
    from pinnmpc.training.models import build_model

    system = load_system("planar3")
    net = build_model(make_cfg("train", [*TINY, "model.zero_output=true"]), system)
    t, x0, u = torch.full((64, 1), system.tau), torch.zeros(64, 6), torch.linspace(-1, 1, 64)[:, None].repeat(1, 3)
    with torch.no_grad():
        assert torch.equal(net(t, x0, u), net.prior(t, x0, u)[0])
    train(make_cfg("train", [*TINY, "model.zero_output=true", "trainer.max_epochs=2", f"data.logs=[{lab_log}]"]),
          tmp_path)  # fmt: skip
    trained = load_surrogate(tmp_path / "surrogate.pt").model
    t, x0, u = (a.to(trained.out_scale.dtype) for a in (t, x0, u))
    with torch.no_grad():
        moved = (trained(t, x0, u) - trained.prior(t, x0, u)[0]).abs().max()
    assert 0 < moved < 1 and torch.isfinite(moved)
    with pytest.raises(ValueError, match="model.zero_output=true needs model.prior"):
        build_model(make_cfg("train", [*TINY, "model.zero_output=true", "model.prior=null"]), system)


def test_the_robot_loss_is_huber_beyond_robot_delta(make_cfg, lab_log):
    """module.robot_delta: errors beyond it count linearly, so the robot loss drops below the squares; a delta above
    every error leaves it the squares."""
    from hydra.utils import instantiate

    from pinnmpc.training.models import build_model
    from pinnmpc.training.run import build_datamodule

    system, losses = load_system("planar3"), {}
    for delta in ("null", "1e9", "1e-3"):
        cfg = make_cfg("train", [*TINY, f"data.logs=[{lab_log}]", f"module.robot_delta={delta}"])
        torch.manual_seed(0)  # the same network each time
        model = build_model(cfg, system)
        module = instantiate(cfg.module, _partial_=True, _convert_="all")(system=system, model=model, tau=system.tau)
        data = build_datamodule(cfg, system)
        data.setup("fit")
        with torch.no_grad():
            losses[delta] = float(module.losses(next(iter(data.train_dataloader())))["robot"])
    assert losses["1e9"] == pytest.approx(losses["null"], rel=1e-6)
    assert 0 < losses["1e-3"] < 0.5 * losses["null"], losses


def test_periods_whose_input_jumped_can_be_left_out(lab_log):
    """data.robot_max_input_step: the transitions (and held-out steps) of periods whose input moved further than
    that from the previous period's are left out; an episode's first period has no previous input and stays."""
    from pinnmpc.robot_data.episodes import input_steps, transitions
    from pinnmpc.robot_data.logs import read_log

    system = load_system("planar3")
    log = read_log(lab_log, system)
    steps = input_steps(log)
    first = np.r_[True, log.episode[1:] != log.episode[:-1]]
    assert np.all(steps[first] == 0)
    assert np.allclose(steps[~first], np.abs(np.diff(log.u, axis=0)).max(axis=1)[~first[1:]])
    limit = float(np.median(steps[~first]))
    t_all = transitions([log], system.tau)[0]
    t_calm = transitions([log], system.tau, limit)[0]
    one_period = lambda t: int(((t[:, 0] - system.tau).abs() < 1e-9).sum())  # noqa: E731
    periods = np.r_[log.episode[1:] == log.episode[:-1], False]  # rows that start a period
    assert one_period(t_all) == int(periods.sum())
    assert one_period(t_calm) == int((periods & (steps <= limit)).sum()) < one_period(t_all)
