"""init_from: a trained network widened with its outputs unchanged, then trained on with all parameters free."""

from __future__ import annotations

import pytest
import torch

from pinnmpc.surrogate import load_surrogate, shipped
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems import PowerCube, build_system, load_system
from pinnmpc.training.curves import read_curve
from pinnmpc.training.grow import widened
from pinnmpc.training.job_settings import validate_train
from pinnmpc.training.models import build_model
from pinnmpc.training.pipeline import base_training_time
from pinnmpc.training.run import train
from pinnmpc.util.checks import SettingError
from tests.conftest import TINY_TRAIN


@pytest.fixture
def base_run(make_cfg, tmp_path):
    """A real two-epoch training run to start from."""
    train(make_cfg("train", [*TINY_TRAIN, "trainer.max_epochs=2"]), tmp_path / "base")
    return tmp_path / "base" / "surrogate.pt"


def _points(n: int = 50) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random (t, x0, u) in and a little beyond the PowerCube's box."""
    g = torch.Generator().manual_seed(3)
    t = 0.25 * torch.rand(n, 1, generator=g, dtype=torch.float64)
    x0 = 4 * torch.rand(n, 4, generator=g, dtype=torch.float64) - 2
    u = 2 * torch.rand(n, 2, generator=g, dtype=torch.float64) - 1
    return t, x0, u


def test_a_widened_network_starts_at_the_trained_outputs_and_trains_on(make_cfg, base_run, tmp_path):
    base = load_surrogate(base_run)
    more_gates = "model.time_basis=[0.02,0.045,0.005]"  # the PowerCube's gates and a faster one
    cfg = make_cfg(
        "train", [*TINY_TRAIN, f"init_from={base_run}", "model.hidden=[24,20]", more_gates, "trainer.max_epochs=2"]
    )
    model = build_model(cfg, PowerCube()).double()
    assert [layer.out_features for layer in model.net.layers[:-1]] == [24, 20]
    assert model.n_gates == base.model.n_gates + 1
    t, x0, u = _points()
    torch.testing.assert_close(model(t, x0, u), base.model(t, x0, u), rtol=0, atol=1e-13)
    assert all(p.requires_grad for p in model.parameters())

    summary = train(cfg, tmp_path / "grown")
    grown = load_surrogate(tmp_path / "grown" / "surrogate.pt")
    assert grown.model.config["hidden"] == [24, 20]
    assert (grown.model(t, x0, u) - base.model(t, x0, u)).abs().max() > 1e-9  # training moved it
    # the new units took part: their outgoing weights left zero
    assert grown.model.net.layers[1].weight[:16, 16:].abs().max() > 0
    assert grown.model.net.layers[-1].weight[-4:].abs().max() > 0  # and so did the new gate's head
    assert summary["training_time_s"] > base.meta["training_time_s"]  # the base's time is counted
    assert summary["base_training_time_s"] == base.meta["training_time_s"]
    grown_ckpt = str(tmp_path / "grown" / "checkpoints" / "last.ckpt")  # a later run from it counts both
    assert base_training_time(grown_ckpt) > base.meta["training_time_s"]
    assert read_curve(tmp_path / "grown").minutes[0] * 60 > base.meta["training_time_s"]  # its curve starts there


@pytest.mark.parametrize("new_gates", [[], [0.002, 0.008]])
def test_widening_keeps_a_gated_network_with_periodic_angles_exact(new_gates):
    base = _planar3_net()
    model = widened(base, [w + 8 for w in base.config["hidden"]], 0, base.config["time_basis"] + new_gates)
    assert model.n_gates == base.n_gates + len(new_gates)
    g = torch.Generator().manual_seed(0)
    t = 0.1 * torch.rand(20, 1, generator=g, dtype=torch.float64)
    x0, u = 2 * torch.rand(20, 6, generator=g, dtype=torch.float64) - 1, torch.rand(20, 3, dtype=torch.float64)
    torch.testing.assert_close(model(t, x0, u), base(t, x0, u), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("hidden", "match"),
    [("[8,16]", "no layer narrower"), ("[16,16,16]", "the same depth")],
)
def test_a_narrower_or_deeper_target_is_refused(make_cfg, base_run, hidden, match):
    cfg = make_cfg("train", [*TINY_TRAIN, f"init_from={base_run}", f"model.hidden={hidden}"])
    with pytest.raises(ValueError, match=match):
        build_model(cfg, PowerCube())


def test_a_time_basis_that_does_not_extend_the_trained_one_is_refused(make_cfg, base_run):
    cfg = make_cfg("train", [*TINY_TRAIN, f"init_from={base_run}", "model.time_basis=[0.005,0.02,0.045]"])
    with pytest.raises(ValueError, match=r"expected its relaxation times first, in order"):
        build_model(cfg, PowerCube())


def test_init_from_another_tau_or_together_with_a_stage_is_refused(make_cfg, base_run):
    cfg = make_cfg("train", [*TINY_TRAIN, f"init_from={base_run}", "system.dynamics.tau=0.1"])
    with pytest.raises(ValueError, match="trained with tau=0.2; this run has tau=0.1"):
        build_model(cfg, build_system(cfg.system))
    cfg = make_cfg("train", [*TINY_TRAIN, f"init_from={base_run}", f"stage.base={base_run}"])
    with pytest.raises(SettingError, match="expected stage.base=null and stage.split=null"):
        validate_train(cfg, PowerCube())


def test_init_from_a_network_of_another_system_is_refused(make_cfg):
    cfg = make_cfg("train", [*TINY_TRAIN, f"init_from={shipped('planar3')}"])
    with pytest.raises(ValueError, match="trained for states"):
        build_model(cfg, PowerCube())


def test_init_from_a_network_without_the_configured_prior_is_refused(make_cfg):
    have = (load_surrogate(system="planar3").model.config.get("prior") or {}).get("kind")
    other = "null" if have else "frozen_arm"  # whichever prior the shipped network has, the other is refused
    overrides = [f"init_from={shipped('planar3')}", f"system.network.prior={other}"]
    cfg = make_cfg("train", ["system=planar3", *TINY_TRAIN, *overrides])
    said = f"trained with model.prior={have or 'null'}; this run has model.prior={other}"
    with pytest.raises(ValueError, match=said):
        build_model(cfg, load_system("planar3"))


def test_init_from_a_frozen_arm_network_may_move_its_friction_into_the_prior(make_cfg):
    """frozen_arm to frozen_arm_friction: the weights stay, the prior under them changes (nominal planar3's Coulomb
    friction now integrated at the moving velocity)."""
    overrides = [
        f"init_from={shipped('planar3')}",
        "system.network.prior=frozen_arm_friction",
        "model.hidden=[64,64,64,64]",
    ]
    cfg = make_cfg("train", ["system=planar3", *TINY_TRAIN, *overrides])
    model = build_model(cfg, load_system("planar3"))
    base = load_surrogate(system="planar3").model
    assert model.config["prior"]["kind"] == "frozen_arm_friction" and model.prior.steps > 0
    assert all(torch.equal(a, b) for a, b in zip(model.net.parameters(), base.net.parameters()))
    arm, g = load_system("planar3"), torch.Generator().manual_seed(3)
    (low, high), (ulow, uhigh) = arm.state_box.tensors(), arm.input_box.tensors()
    x0 = low + (high - low) * torch.rand(50, 6, generator=g, dtype=torch.float64)
    u = ulow + (uhigh - ulow) * torch.rand(50, 3, generator=g, dtype=torch.float64)
    t = torch.full((50, 1), arm.tau, dtype=torch.float64)
    dtype = model.out_scale.dtype
    moved = (model(t.to(dtype), x0.to(dtype), u.to(dtype)) - base(t.to(dtype), x0.to(dtype), u.to(dtype))).abs().max()
    assert 1e-4 < float(moved) < 0.1  # the same correction on another prior


def _planar3_net() -> PINN:
    """A planar3 network with periodic angles, gates and no angle sums (seeded weights: any outputs will do)."""
    arm = load_system("planar3")
    torch.manual_seed(1)
    return PINN(
        *arm.state_box.tensors(), *arm.input_box.tensors(), t_max=0.125, hidden=[16, 16], activation="silu",
        ic="gated", time_basis=[0.004, 0.015, 0.05], periodic=[0, 1, 2],
    ).double()  # fmt: skip


def _small(ic: str, time_basis: list[float]) -> PINN:
    """An untrained PowerCube-box network of the given form (init weights: any outputs will do)."""
    box = PowerCube()
    low, high = box.state_box, box.input_box
    torch.manual_seed(0)
    return PINN(low.low, low.high, high.low, high.high, 0.25, [8, 8], ic=ic, time_basis=time_basis).double()


def test_gates_go_on_a_hard_ic_network_exactly_and_a_soft_one_keeps_its_form():
    hard = _small("hard", [])
    gated = widened(hard, [8, 8], 0, [0.01])
    assert gated.ic == "gated" and gated.n_gates == 2
    t, x0, u = _points()
    torch.testing.assert_close(gated(t, x0, u), hard(t, x0, u), rtol=0, atol=1e-13)
    soft = _small("soft", [])
    torch.testing.assert_close(widened(soft, [12, 8], 0, [])(t, x0, u), soft(t, x0, u), rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match=r"cannot start from a network with time basis \[\] \(ic='soft'\)"):
        widened(soft, [8, 8], 0, [0.01])


def test_angle_sums_grown_onto_a_trained_network_start_deaf():
    base = _planar3_net()
    hidden, basis = base.config["hidden"], base.config["time_basis"]
    two = widened(base, hidden, 0, basis, angle_sums=[[0, 1], [0, 1, 2]])
    three = widened(two, hidden, 1, basis, angle_sums=[[0, 1], [0, 1, 2], [1, 2]])  # old sums' columns move
    assert three.net.layers[0].in_features == base.net.layers[0].in_features + 6
    g = torch.Generator().manual_seed(0)
    t = 0.1 * torch.rand(20, 1, generator=g, dtype=torch.float64)
    x0, u = 2 * torch.rand(20, 6, generator=g, dtype=torch.float64) - 1, torch.rand(20, 3, dtype=torch.float64)
    for model in (two, three):
        torch.testing.assert_close(model(t, x0, u), base(t, x0, u), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=r"cannot start from a network with angle sums \[\[0, 1\], \[0, 1, 2\]\]"):
        widened(two, hidden, 0, basis, angle_sums=[[1, 2]])


def test_a_run_started_from_a_checkpoint_counts_its_training_time(make_cfg, base_run, tmp_path):
    last = base_run.parent / "checkpoints" / "last.ckpt"
    spent = torch.load(last, weights_only=True)["callbacks"]["Timer"]["time_elapsed"]["train"]
    assert base_training_time(str(last)) == spent > 0
    assert base_training_time(str(base_run)) == load_surrogate(base_run).meta["training_time_s"]
    assert base_training_time(str(tmp_path / "nope.ckpt")) == 0.0


def test_a_widened_run_resumes_without_its_starting_file_and_keeps_its_time(make_cfg, base_run, tmp_path):
    start = tmp_path / "start.pt"
    start.write_bytes(base_run.read_bytes())
    grown = [*TINY_TRAIN, f"init_from={start}", "model.hidden=[24,20]"]
    first = train(make_cfg("train", [*grown, "trainer.max_epochs=2"]), tmp_path / "grown")
    start.unlink()  # the checkpoint holds the whole network, and the time behind it
    again = train(make_cfg("train", [*grown, "trainer.max_epochs=3", "resume=true"]), tmp_path / "grown")
    assert again["epochs"] == 3 and again["base_training_time_s"] == first["base_training_time_s"] > 0
    assert again["training_time_s"] > first["training_time_s"]


def test_widening_refuses_a_network_form_it_cannot_change(make_cfg, base_run):
    cfg = make_cfg("train", [*TINY_TRAIN, f"init_from={base_run}", "model.hidden=[24,20]", "model.activation=tanh"])
    with pytest.raises(ValueError, match="has model.activation=silu; this run has model.activation=tanh"):
        build_model(cfg, PowerCube())  # it would have exported a silu network labelled tanh
