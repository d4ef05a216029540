"""Real Lightning training on tiny sizes: the loss falls, points are redrawn reproducibly, runs resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import lightning as L
import pytest
import torch
from hydra.utils import instantiate

from pinnmpc import cli
from pinnmpc.cli import LOCK_NAME, discard_own_files, guard, launched_rank, release
from pinnmpc.surrogate import load_surrogate
from pinnmpc.systems import PowerCube
from pinnmpc.systems.registry import build_system
from pinnmpc.training.callbacks import AtomicCheckpoint
from pinnmpc.training.data import CollocationDataModule, lhs_box, reference_flow
from pinnmpc.training.models import build_model
from pinnmpc.training.module import PINNModule
from pinnmpc.training.run import build_datamodule, sha256, train
from tests.conftest import ROOT, TINY_TRAIN

TINY = [*TINY_TRAIN, "self_loop_figure.every_n_epochs=1", "self_loop_figure.steps=3"]
# the paper's L-BFGS training, which these tests were written against; the classes' defaults are conf/module/pinn.yaml's
PAPER_LBFGS = dict(optimizer="lbfgs", kinematic_weight=1.0, weight_anchor=1.0, lbfgs_history=100)


def _tiny_module(make_cfg, *overrides: str) -> tuple[PINNModule, CollocationDataModule]:
    cfg = make_cfg("train", [*TINY, *overrides])
    system = PowerCube()
    model = build_model(cfg, system)
    sizes = dict(n_collocation=256, n_data=16, n_val=64, val_h=1e-3)
    dm = CollocationDataModule(system, tau=0.2, t_max=0.25, **sizes, resample_every=0, n_anchor=0)
    module = PINNModule(system, model, tau=0.2, lbfgs_max_iter=5, residual_form=cfg.module.residual_form, **PAPER_LBFGS)
    return module, dm


def _quiet_trainer(tmp_path, **kwargs) -> L.Trainer:
    """A real Trainer without logger, checkpoints or progress output."""
    defaults = dict(
        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        default_root_dir=tmp_path, num_sanity_val_steps=0,
    )  # fmt: skip
    return L.Trainer(**{**defaults, **kwargs})


@pytest.mark.parametrize("second_order", [False, True])
def test_lbfgs_steps_lower_the_loss_for_both_model_orders(make_cfg, tmp_path, second_order):
    module, dm = _tiny_module(make_cfg, f"model.second_order={second_order}")
    assert module.model.second_order is second_order
    dm.setup()
    before = float(module.losses(dm.batch)["total"].detach())
    _quiet_trainer(tmp_path, max_epochs=3).fit(module, datamodule=dm)
    after = float(module.losses(dm.batch)["total"].detach())
    assert after < 0.5 * before


def test_kinematic_weight_scales_only_the_kinematic_rows(make_cfg):
    cfg = make_cfg("train", TINY)
    system = PowerCube()
    model = build_model(cfg, system)
    plain = PINNModule(system, model, tau=0.2, kinematic_weight=1.0)
    weighted = PINNModule(system, model, tau=0.2, kinematic_weight=3.0)
    t, x0, u = torch.rand(8, 1) * 0.25, torch.rand(8, 4) - 0.5, torch.rand(8, 2) - 0.5
    r1 = plain._scaled_residual({"t": t, "x0": x0, "u": u}).detach()
    r3 = weighted._scaled_residual({"t": t, "x0": x0, "u": u}).detach()
    torch.testing.assert_close(r3[:, :2], 3.0 * r1[:, :2])  # dq/dt - v, weighted
    torch.testing.assert_close(r3[:, 2:], r1[:, 2:])  # the dynamics rows, untouched


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), True])
def test_bad_kinematic_weight_is_refused(make_cfg, bad):
    system = PowerCube()
    with pytest.raises(ValueError, match="kinematic_weight must be a positive number"):
        PINNModule(system, build_model(make_cfg("train", TINY), system), tau=0.2, kinematic_weight=bad)


def test_anchor_state_weight_weighs_each_states_anchor_error(make_cfg):
    system = PowerCube()
    model = build_model(make_cfg("train", TINY), system)
    sizes = dict(n_collocation=64, n_data=0, n_val=8, val_h=1e-2, n_anchor=32)
    dm = CollocationDataModule(system, tau=0.2, t_max=0.25, **sizes)
    dm.setup()
    plain = PINNModule(system, model, tau=0.2, weight_anchor=1.0)
    b = plain._cast(dm.batch)
    err = (model(b["anchor_t"], b["anchor_x0"], b["anchor_u"]) - b["anchor_x0"] - b["anchor_dx"]) / model.out_scale
    w = [1.0, 2.0, 0.5, 4.0]
    weighted = PINNModule(system, model, tau=0.2, weight_anchor=1.0, anchor_state_weight=w)
    expected = (err.square() * torch.tensor(w, dtype=err.dtype)).mean()
    torch.testing.assert_close(weighted.losses(dm.batch)["anchor"].detach(), expected.detach())
    torch.testing.assert_close(plain.losses(dm.batch)["anchor"].detach(), err.square().mean().detach())
    for bad in ([1.0, 1.0], [1.0, 0.0, 1.0, 1.0], [1.0, float("nan"), 1.0, 1.0]):
        said = r"module.anchor_state_weight=.*expected null or a list of 4 entries \(4\), each a finite number > 0"
        with pytest.raises(ValueError, match=said):
            PINNModule(system, model, tau=0.2, anchor_state_weight=bad)


def test_huber_loss_is_squares_below_delta_and_linear_above(make_cfg):
    cfg = make_cfg("train", TINY)
    system = PowerCube()
    model = build_model(cfg, system)
    plain = PINNModule(system, model, tau=0.2, kinematic_weight=1.0)
    dm = CollocationDataModule(
        system, tau=0.2, t_max=0.25, n_collocation=256, n_data=0, n_val=8, val_h=1e-2, n_anchor=0
    )
    dm.setup()
    r = plain._scaled_residual(plain._cast(dm.batch)).detach().abs()
    delta = float(r.quantile(0.7))  # a third of the residuals beyond it
    robust = PINNModule(system, model, tau=0.2, robust_delta=delta, kinematic_weight=1.0)
    expected = torch.where(r <= delta, r.square(), 2 * delta * r - delta**2).mean()
    torch.testing.assert_close(robust.losses(dm.batch)["physics"].detach(), expected)
    assert robust.losses(dm.batch)["physics"] < plain.losses(dm.batch)["physics"]
    huge = PINNModule(system, model, tau=0.2, robust_delta=10 * float(r.max()), kinematic_weight=1.0)  # squares
    torch.testing.assert_close(huge.losses(dm.batch)["physics"], plain.losses(dm.batch)["physics"])


@pytest.mark.parametrize("bad", [0.0, -0.1, float("inf"), float("nan"), "big", True])
def test_bad_robust_delta_is_refused(make_cfg, bad):
    system = PowerCube()
    with pytest.raises(ValueError, match="robust_delta must be a positive number or null"):
        PINNModule(system, build_model(make_cfg("train", TINY), system), tau=0.2, robust_delta=bad)


def test_soft_initial_condition_has_a_data_loss(make_cfg):
    cfg = make_cfg("train", [*TINY, "experiment=paper"])
    system = PowerCube()
    module = PINNModule(system, build_model(cfg, system), tau=0.2, residual_form="mass", kinematic_weight=1.0)
    dm = CollocationDataModule(system, tau=0.2, t_max=0.25, n_collocation=64, n_data=8, n_val=8, val_h=1e-2, n_anchor=0)
    dm.setup()
    parts = module.losses(dm.batch)
    assert set(parts) == {"physics", "data", "total"}
    assert parts["data"] > 0


def test_resampling_changes_points_and_is_reproducible():
    system = PowerCube()
    sizes = dict(n_collocation=128, n_data=8, n_val=8, val_h=1e-2, seed=5, n_anchor=0, resample_every=0)
    a = CollocationDataModule(system, 0.2, 0.25, **sizes)
    b = CollocationDataModule(system, 0.2, 0.25, **sizes)
    a.setup(), b.setup()
    first = {k: v.clone() for k, v in a.batch.items()}
    assert all(torch.equal(first[k], b.batch[k]) for k in first)
    a.draw(), b.draw()
    assert not torch.equal(first["x0"], a.batch["x0"])
    assert all(torch.equal(a.batch[k], b.batch[k]) for k in first)
    assert torch.equal(a.val["x1"], b.val["x1"])
    assert a.due(50) is False and CollocationDataModule(system, 0.2, 0.25, resample_every=10).due(20)


def test_adaptive_redraw_gathers_points_where_the_residual_is_large(make_cfg, tmp_path):
    torch.manual_seed(0)
    module, _ = _tiny_module(make_cfg)
    system = PowerCube()
    dm = CollocationDataModule(
        system, 0.2, 0.25, n_collocation=256, n_data=16, n_val=64, val_h=1e-3, resample_every=1,
        adaptive_pool=8, adaptive_k=2.0, adaptive_c=0.0, n_anchor=0,
    )  # fmt: skip
    _quiet_trainer(tmp_path, max_epochs=3, reload_dataloaders_every_n_epochs=1).fit(module, datamodule=dm)
    assert dm.draws == 3  # the first draw plus two adaptive redraws during training
    dm.draw()  # one more with the trained model frozen, so the score below is the one the draw used
    b = dm.batch
    adaptive = module.pointwise_residual(b["t"], b["x0"], b["u"]).mean()
    plain = CollocationDataModule(system, 0.2, 0.25, n_collocation=256, seed=dm.seed + 7919 * 3, n_anchor=0)
    plain.draw()  # the plain LHS draw of the same size and seed
    p = plain.batch
    uniform = module.pointwise_residual(p["t"], p["x0"], p["u"]).mean()
    assert adaptive > 1.5 * uniform  # a plain draw would give ~1
    low = torch.tensor([0.0, *system.state_box.low, *system.input_box.low], dtype=torch.float64)
    high = torch.tensor([0.25, *system.state_box.high, *system.input_box.high], dtype=torch.float64)
    pts = torch.cat([b["t"], b["x0"], b["u"]], dim=1)
    assert torch.all((pts >= low) & (pts <= high))  # still inside the training box
    assert torch.unique(pts, dim=0).shape[0] == 256  # drawn without replacement


def test_adaptive_without_a_trainer_is_plain_lhs():
    system = PowerCube()
    sizes = dict(n_collocation=64, n_data=8, n_val=8, val_h=1e-2, n_anchor=0)
    a = CollocationDataModule(system, 0.2, 0.25, **sizes, adaptive_pool=4)
    b = CollocationDataModule(system, 0.2, 0.25, **sizes)
    a.draw(), b.draw(), a.draw(), b.draw()
    assert all(torch.equal(a.batch[k], b.batch[k]) for k in a.batch)


@pytest.mark.parametrize(
    "bad", [{"adaptive_pool": 1}, {"adaptive_pool": -2}, {"adaptive_k": -1.0}, {"adaptive_c": -0.5}]
)
def test_bad_adaptive_settings_are_refused(bad):
    with pytest.raises(ValueError, match="adaptive_pool 0 \\(off\\) or >= 2") as err:
        CollocationDataModule(PowerCube(), 0.2, 0.25, **bad)
    assert str(next(iter(bad.values()))) in str(err.value)


def test_t_high_keeps_collocation_times_up_to_tau():
    system = PowerCube()
    sizes = dict(n_collocation=256, n_data=8, n_val=8, val_h=1e-2, n_anchor=0)
    dm = CollocationDataModule(system, 0.2, 0.25, **sizes, t_high=0.2)
    dm.draw()
    t = dm.batch["t"]
    assert float(t.min()) >= 0.0 and float(t.max()) <= 0.2
    assert float(t.max()) > 0.19  # still covers the whole period (LHS: one point per 1/256 of it)
    full = CollocationDataModule(system, 0.2, 0.25, **sizes)
    full.draw()
    assert float(full.batch["t"].max()) > 0.24


def test_anchors_carry_the_accurate_flow_to_their_own_times_and_enter_the_loss(make_cfg, tmp_path):
    system = PowerCube()
    sizes = dict(n_collocation=64, n_data=8, n_val=8, val_h=1e-2, resample_every=0)
    dm = CollocationDataModule(system, 0.2, 0.25, **sizes, n_anchor=32)
    dm.setup()
    b = dm.batch
    t, x0, u = b["anchor_t"], b["anchor_x0"], b["anchor_u"]
    assert t.shape == (32, 1) and float(t.min()) >= 0.0 and float(t.max()) <= 0.25
    row = int(t.argmax())  # one row alone, to its own time, by an independent fine RK4
    alone = reference_flow(system, x0[row : row + 1], u[row : row + 1], float(t[row]), 1e-4) - x0[row]
    torch.testing.assert_close(b["anchor_dx"][row : row + 1], alone, rtol=0.0, atol=1e-6)  # two RK4 step sizes
    assert float(b["anchor_dx"].abs().max()) > 1e-2  # the flow moves: the anchors are not x0
    module = PINNModule(system, build_model(make_cfg("train", TINY), system), tau=0.2, lbfgs_max_iter=5, **PAPER_LBFGS)
    before = float(module.losses(b)["anchor"].detach())
    _quiet_trainer(tmp_path, max_epochs=3).fit(module, datamodule=dm)
    assert float(module.losses(dm.batch)["anchor"].detach()) < 0.5 * before
    off = PINNModule(system, module.model, tau=0.2, weight_anchor=0.0)
    assert "anchor" not in off.losses(b)


def test_anchor_weight_zero_switches_the_anchors_off_so_none_are_integrated(make_cfg):
    system = PowerCube()
    on = build_datamodule(make_cfg("train", [*TINY_TRAIN]), system)
    off = build_datamodule(make_cfg("train", [*TINY_TRAIN, "module.weight_anchor=0.0"]), system)
    assert on.n_anchor == 32 and off.n_anchor == 0
    off.draw()
    assert "anchor_t" not in off.batch


@pytest.mark.parametrize("bad", [dict(n_anchor=-1), dict(n_anchor=4, anchor_h=0.0)])
def test_bad_anchor_settings_are_refused(bad):
    with pytest.raises(ValueError, match="n_anchor|anchor_h"):
        CollocationDataModule(PowerCube(), 0.2, 0.25, **bad)


@pytest.mark.parametrize("bad", [0.1, 0.3])
def test_t_high_outside_tau_to_t_max_is_refused(bad):
    with pytest.raises(ValueError, match=rf"tau \(0.2\) <= t_high <= t_max \(0.25\).*t_high={bad}"):
        CollocationDataModule(PowerCube(), 0.2, 0.25, t_high=bad)


def test_lhs_is_stratified_in_every_coordinate():
    pts = lhs_box(100, [0.0, -1.0], [1.0, 1.0], seed=0)
    for j, (lo, hi) in enumerate([(0.0, 1.0), (-1.0, 1.0)]):
        bins = torch.floor((pts[:, j] - lo) / (hi - lo) * 100).long()
        assert torch.equal(torch.sort(bins).values, torch.arange(100))


def test_train_writes_checkpoints_metrics_and_a_loadable_surrogate(make_cfg, tmp_path):
    cfg = make_cfg("train", [*TINY, "trainer.max_epochs=2"])
    summary = train(cfg, tmp_path)
    for name in ("surrogate.pt", "train_metrics.json", "checkpoints/best.ckpt", "checkpoints/last.ckpt"):
        assert (tmp_path / name).is_file(), name
    assert (tmp_path / "tensorboard").is_dir()
    assert json.loads((tmp_path / "train_metrics.json").read_text())["epochs"] == summary["epochs"] == 2
    for path in (tmp_path / "surrogate.pt", tmp_path / "checkpoints" / "last.ckpt"):
        s = load_surrogate(path)
        x = s.step(torch.zeros(2, 4, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64))
        assert x.shape == (2, 4) and torch.all(torch.isfinite(x))
    assert summary["best_val_rmse_position"] > 0


def test_list_overrides_leave_a_checkpoint_load_surrogate_reads(make_cfg, tmp_path):
    cfg = make_cfg("train", [*TINY, "trainer.max_epochs=1", "module.residual_scale=[0.4,0.5,12.0,14.0]"])
    train(cfg, tmp_path)
    last = tmp_path / "checkpoints" / "last.ckpt"
    hparams = torch.load(last, weights_only=True)["hyper_parameters"]  # plain types only: safe to load
    assert hparams["residual_scale"] == [0.4, 0.5, 12.0, 14.0]
    assert load_surrogate(last).nx == 4


def test_resume_continues_from_last_checkpoint(make_cfg, tmp_path):
    budget = "trainer.max_time=00:00:10:00"  # a wall-time budget brings Lightning's Timer, which resumes too
    train(make_cfg("train", [*TINY, budget, "trainer.max_epochs=2"]), tmp_path)
    first = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    summary = train(make_cfg("train", [*TINY, budget, "trainer.max_epochs=4", "resume=true"]), tmp_path)
    second = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert summary["epochs"] == 4
    # training time also counts the first run's, restored by Lightning's Timer, plus this run's own epochs
    before = first["callbacks"][_timer_key(first)]["time_elapsed"]["train"]
    saved = second["callbacks"][_timer_key(second)]["time_elapsed"]["train"]  # at its last checkpoint
    assert summary["training_time_s"] == pytest.approx(saved, rel=0.05)
    assert before < summary["training_time_s"] < before + summary["wall_time_s"]
    assert second["global_step"] > first["global_step"]
    assert second["epoch"] == first["epoch"] + 2


def test_a_run_resumed_from_another_dir_reports_the_best_it_started_from(make_cfg, tmp_path, capsys):
    first = train(make_cfg("train", [*TINY, "trainer.max_epochs=2"]), tmp_path / "a")
    ckpt = tmp_path / "a" / "checkpoints" / "last.ckpt"
    capsys.readouterr()
    summary = train(make_cfg("train", [*TINY, "trainer.max_epochs=3", f"ckpt_path={ckpt}"]), tmp_path / "b")
    assert summary["resumed_best_val_rmse_position"] == pytest.approx(first["best_val_rmse_position"], rel=1e-12)
    # Lightning forgets the score of a best checkpoint in another dir: a worse continuation says so
    worse = summary["best_val_rmse_position"] > first["best_val_rmse_position"]
    assert ("warning: this run's best validation RMSE" in capsys.readouterr().err) == worse


def test_a_resumed_run_weighs_its_loss_as_configured_now(make_cfg, tmp_path):
    train(make_cfg("train", [*TINY, "trainer.max_epochs=1", "module.kinematic_weight=3.0"]), tmp_path)
    before = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]["res_scale"]
    train(make_cfg("train", [*TINY, "trainer.max_epochs=2", "module.kinematic_weight=12.0", "resume=true"]), tmp_path)
    after = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]["res_scale"]
    torch.testing.assert_close(after[:2], before[:2] / 4)  # kinematic rows: divided by the new weight
    torch.testing.assert_close(after[2:], before[2:])


def _timer_key(ckpt: dict) -> str:
    """Key of Lightning's Timer state among a checkpoint's callback states."""
    return next(k for k in ckpt["callbacks"] if k.startswith("Timer"))


def test_stalled_lbfgs_is_detected_and_recovered(make_cfg, tmp_path):
    module, dm = _tiny_module(make_cfg)
    module.hparams.lbfgs_tolerance_change = 1e3  # any step counts as converged: L-BFGS returns at once
    module.hparams.stall_min_evals = 5
    _quiet_trainer(tmp_path, max_epochs=3, reload_dataloaders_every_n_epochs=1).fit(module, datamodule=dm)
    assert module.stalls >= 2
    assert dm.draws >= 3


def test_an_epoch_without_progress_counts_as_a_stall(make_cfg):
    module, _ = _tiny_module(make_cfg)
    assert module._stalled(start_loss=0.5, end_loss=0.5, evals=60)  # busy but stuck: seen in long float32 runs
    assert module._stalled(start_loss=0.5, end_loss=0.49, evals=2)  # returned at once
    assert not module._stalled(start_loss=0.5, end_loss=0.4999, evals=60)


def test_nan_loss_stops_with_a_message_and_keeps_the_last_good_checkpoint(make_cfg, tmp_path):
    train(make_cfg("train", [*TINY, "trainer.max_epochs=2"]), tmp_path)
    last = tmp_path / "checkpoints" / "last.ckpt"
    good = last.read_bytes()
    module, dm = _tiny_module(make_cfg)
    dm.setup()
    dm.batch["x0"][0, 0] = float("nan")  # a corrupt collocation point poisons the full-batch loss
    keep_last = AtomicCheckpoint(dirpath=tmp_path / "checkpoints", filename="last", enable_version_counter=False)
    trainer = _quiet_trainer(tmp_path, max_epochs=2, callbacks=[keep_last], enable_checkpointing=True)
    with pytest.raises(FloatingPointError, match="training loss became nan"):
        trainer.fit(module, datamodule=dm)
    assert last.read_bytes() == good
    s = load_surrogate(last)
    assert torch.all(torch.isfinite(s.step(torch.zeros(1, 4), torch.zeros(1, 2))))


def test_killed_training_resumes_without_losing_work(make_cfg, tmp_path):
    cmd = [sys.executable, "-m", "pinnmpc.train", *TINY, "trainer.max_epochs=100000", f"hydra.run.dir={tmp_path}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = tmp_path / "checkpoints" / "last.ckpt"
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            if last.is_file() and torch.load(last, weights_only=True)["epoch"] >= 3:
                break
            time.sleep(0.5)
        assert proc.poll() is None, "training ended before it could be killed"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    killed = torch.load(last, weights_only=True)
    summary = train(make_cfg("train", [*TINY, f"trainer.max_epochs={killed['epoch'] + 2}", "resume=true"]), tmp_path)
    resumed = torch.load(last, weights_only=True)
    assert summary["epochs"] == killed["epoch"] + 2
    assert resumed["global_step"] > killed["global_step"]


def test_a_correction_stage_trains_on_a_frozen_base_and_exports_one_network(make_cfg, tmp_path):
    base_dir, stage_dir = tmp_path / "base", tmp_path / "stage"
    train(make_cfg("train", [*TINY, "trainer.max_epochs=2"]), base_dir)
    base = load_surrogate(base_dir / "surrogate.pt")
    stage = [*TINY, f"stage.base={base_dir / 'surrogate.pt'}", "stage.hidden=[8,8]", "stage.samples=64", "stage.h=1e-3"]
    cfg = make_cfg("train", [*stage, "trainer.max_epochs=3"])
    model = build_model(cfg, PowerCube())
    assert not any(p.requires_grad for p in model.base.parameters())
    module = PINNModule(PowerCube(), model, tau=0.2, lbfgs_max_iter=5, **PAPER_LBFGS)
    sizes = dict(n_collocation=256, n_data=0, n_val=8, val_h=1e-2, seed=1, resample_every=0, n_anchor=0)
    dm = CollocationDataModule(PowerCube(), 0.2, 0.25, **sizes)
    dm.setup()
    before = float(module.losses(dm.batch)["total"].detach())
    assert 0.1 < before < 10  # residuals in units of the base's residual level
    _quiet_trainer(tmp_path, max_epochs=3).fit(module, datamodule=dm)
    assert float(module.losses(dm.batch)["total"].detach()) < 0.8 * before
    for got, want in zip(model.base.state_dict().values(), base.model.state_dict().values()):
        torch.testing.assert_close(got, want.to(got.dtype), rtol=0, atol=0)  # the base stayed frozen

    train(cfg, stage_dir)  # the CLI path: export merges base and correction into one plain network
    merged = load_surrogate(stage_dir / "surrogate.pt")
    assert merged.model.config["hidden"] == [24, 24]
    last = load_surrogate(stage_dir / "checkpoints" / "last.ckpt")  # a staged .ckpt loads merged too
    x0, u = torch.rand(5, 4, dtype=torch.float64) - 0.5, torch.rand(5, 2, dtype=torch.float64) - 0.5
    assert (last.step(x0, u) - base.step(x0, u)).abs().max() > 0  # the correction changed the flow
    summary = train(make_cfg("train", [*stage, "trainer.max_epochs=4", "resume=true"]), stage_dir)
    assert summary["epochs"] == 4  # resumes like any run


def test_a_stage_on_a_base_for_another_tau_is_refused(make_cfg, tmp_path):
    train(make_cfg("train", [*TINY, "trainer.max_epochs=1"]), tmp_path)
    cfg = make_cfg(
        "train", [*TINY, f"stage.base={tmp_path / 'surrogate.pt'}", "stage.samples=8", "system.dynamics.tau=0.1"]
    )
    with pytest.raises(ValueError, match="trained for tau=0.2; this run has tau=0.1"):
        build_model(cfg, build_system(cfg.system))


# ---------------------------------------------------------------------------------------------- DDP (trainer=ddp)


def _as_rank(dm: CollocationDataModule, rank: int, world: int) -> CollocationDataModule:
    """The data module as DDP process `rank` of `world` sees it (shard() asks the trainer only for these two)."""
    dm.trainer = SimpleNamespace(global_rank=rank, world_size=world)
    return dm


def test_ddp_shards_are_disjoint_slices_weighted_to_the_global_mean(make_cfg):
    module, _ = _tiny_module(make_cfg)
    system, n = PowerCube(), 257  # not a multiple of the 2 processes: shards of 129 and 128 points
    kwargs = dict(n_collocation=n, n_data=8, n_val=8, val_h=1e-2, seed=3, n_anchor=33, anchor_h=1e-2)
    full = CollocationDataModule(system, 0.2, 0.25, **kwargs)
    full.draw()
    shards = [_as_rank(CollocationDataModule(system, 0.2, 0.25, **kwargs), r, 2) for r in (0, 1)]
    for dm in shards:
        dm.draw()
    pts = [torch.cat([dm.batch["t"], dm.batch["x0"], dm.batch["u"]], dim=1) for dm in shards]
    whole = torch.cat([full.batch["t"], full.batch["x0"], full.batch["u"]], dim=1)
    assert [len(p) for p in pts] == [129, 128]
    assert torch.equal(pts[0], whole[0::2]) and torch.equal(pts[1], whole[1::2])  # one draw, sliced: disjoint
    assert all(torch.equal(dm.batch["data_x0"], full.batch["data_x0"]) for dm in shards)  # data points: shared
    assert [float(dm.batch["share"]) for dm in shards] == [2 * 129 / n, 2 * 128 / n]
    for key in ("anchor_t", "anchor_x0", "anchor_u", "anchor_dx"):  # anchors: sliced too, each integrated once
        assert torch.equal(shards[0].batch[key], full.batch[key][0::2]), key
        assert torch.equal(shards[1].batch[key], full.batch[key][1::2]), key
    assert [float(dm.batch["anchor_share"]) for dm in shards] == [2 * 17 / 33, 2 * 16 / 33]
    with torch.no_grad():  # the mean over processes (what the closure all-reduces) is the loss over all points
        per_rank = [module.losses(dm.batch) for dm in shards]
        want = module.losses(full.batch)
    for key in ("physics", "anchor", "total"):
        torch.testing.assert_close((per_rank[0][key] + per_rank[1][key]) / 2, want[key], rtol=1e-5, atol=0)
    for dm in shards:  # a redraw moves every process to its slice of the same next draw
        dm.draw()
    full.draw()
    assert torch.equal(shards[1].batch["x0"], full.batch["x0"][1::2])
    with pytest.raises(ValueError, match="at least one point per process"):
        _as_rank(CollocationDataModule(system, 0.2, 0.25, n_collocation=1), 0, 2).draw()
    with pytest.raises(ValueError, match="data.n_anchor=1: expected at least one point per process"):
        _as_rank(CollocationDataModule(system, 0.2, 0.25, n_collocation=4, n_anchor=1), 0, 2).draw()


def test_a_ddp_process_of_rank_above_zero_shares_the_run_dir_and_removes_nothing(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / ".hydra").mkdir()
    try:
        guard(run_dir, "train")  # rank 0 holds the dir
        monkeypatch.setenv("LOCAL_RANK", "1")  # what Lightning sets for the process it starts for rank 1
        helper_dir = tmp_path / "elsewhere"
        helper_dir.mkdir()
        (helper_dir / ".hydra").mkdir()
        state = guard(helper_dir, "train_ddp_process_1")
        assert state.helper and state.lock_fd is None and not (helper_dir / LOCK_NAME).exists()
        discard_own_files(helper_dir)  # bad input in rank 1 leaves rank 0's files alone
        assert (helper_dir / ".hydra").is_dir()
    finally:
        for path in (run_dir, tmp_path / "elsewhere"):
            release(path)
            cli._STATE.pop(cli.absolute(path), None)
    assert launched_rank() == 1
    monkeypatch.setenv("LOCAL_RANK", "0")
    assert launched_rank() == 0


@pytest.mark.slow
def test_ddp_two_gloo_processes_train_on_their_shards_with_identical_parameters(make_cfg, tmp_path):
    tiny = [
        *TINY_TRAIN,
        "trainer.max_epochs=3",
        "module.stall_min_evals=100",  # every epoch (<= 6 evaluations) stalls: history reset and redraw each time
        "self_loop_figure.every_n_epochs=1",
        "self_loop_figure.steps=3",
        "progress=false",
    ]
    ddp = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"]
    cmd = [sys.executable, "-m", "pinnmpc.train", *ddp, *tiny, f"hydra.run.dir={tmp_path}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "GLOBAL_RANK: 1, MEMBER: 2/2" in proc.stderr and "distributed_backend=gloo" in proc.stderr
    for name in ("surrogate.pt", "train_metrics.json", "checkpoints/best.ckpt", "checkpoints/last.ckpt"):
        assert (tmp_path / name).is_file(), name
    assert not (tmp_path / LOCK_NAME).exists()  # released by rank 0; rank 1 never took it
    metrics = json.loads((tmp_path / "train_metrics.json").read_text())
    record = metrics["distributed"]
    assert record["world_size"] == 2 and metrics["epochs"] == 3
    ranks = record["ranks"]
    assert [r["rank"] for r in ranks] == [0, 1]
    assert ranks[0]["params_sha256"] == ranks[1]["params_sha256"]  # bit-identical parameters on both processes
    assert ranks[0]["stalls"] == ranks[1]["stalls"] == 3  # the same stall decisions ...
    assert ranks[0]["draws"] == ranks[1]["draws"] == 4  # ... and redraws (the first draw plus one per stall)

    cfg = make_cfg("train", tiny)
    system = build_system(cfg.system)
    data = instantiate(cfg.data, _partial_=True, _convert_="all")
    for r in ranks:  # each process held exactly its half of the same global draw: different points
        dm = _as_rank(data(system=system, tau=system.tau, t_max=cfg.t_max, seed=cfg.seed), r["rank"], 2)
        dm.draws = r["draws"] - 1
        dm.draw()
        assert r["points"] == 128 and r["points_sha256"] == sha256([dm.batch[k] for k in ("t", "x0", "u")])
    assert ranks[0]["points_sha256"] != ranks[1]["points_sha256"]

    L.seed_everything(cfg.seed, verbose=False)  # the network train() starts from (same seed, same construction)
    start = build_model(cfg, system)
    trained = load_surrogate(tmp_path / "checkpoints" / "last.ckpt").model
    assert sha256([p for p in trained.parameters()]) == ranks[0]["params_sha256"]  # rank 0's network was saved
    first = data(system=system, tau=system.tau, t_max=cfg.t_max, seed=cfg.seed)
    first.draw()  # all the points of the first epoch (both shards)
    module = instantiate(cfg.module, _partial_=True, _convert_="all")
    with torch.no_grad():
        before = float(module(system=system, model=start, tau=system.tau).losses(first.batch)["total"])
        after = float(module(system=system, model=trained, tau=system.tau).losses(first.batch)["total"])
    assert after < 0.5 * before  # the loss fell


@pytest.mark.skipif(torch.cuda.is_available() or torch.backends.mps.is_available(), reason="this machine has a GPU")
def test_a_gpu_trainer_without_a_gpu_is_one_line_and_trainer_gpu_falls_back_to_the_cpu(make_cfg, tmp_path):
    with pytest.raises(ValueError, match=r"trainer.accelerator=gpu.*were refused: No supported gpu backend"):
        train(make_cfg("train", [*TINY, "trainer=gpu", "trainer.accelerator=gpu"]), tmp_path / "forced")
    summary = train(make_cfg("train", [*TINY, "trainer=gpu", "trainer.max_epochs=1"]), tmp_path / "auto")
    assert summary["epochs"] == 1 and "distributed" not in summary


def test_threads_zero_takes_every_core_and_a_bad_count_is_refused() -> None:
    from pinnmpc.util.threads import available_cores, use_threads

    before = torch.get_num_threads()
    try:
        use_threads(0)
        assert torch.get_num_threads() == available_cores() >= 1
        use_threads(1)
        assert torch.get_num_threads() == 1
        for bad in (-1, 1.5, True, "2"):
            with pytest.raises(ValueError, match=r"threads=.*; expected a whole number >= 1, or 0 for every"):
                use_threads(bad)
    finally:
        use_threads(before)


def test_a_checkpoint_written_before_priors_carried_their_arm_still_resumes(make_cfg, tmp_path):
    # planar3.pt's checkpoint names its prior's arm only; later networks carry its description too
    ckpt = ROOT / "checkpoints" / "train" / "planar3-prior-last.ckpt"
    epoch = torch.load(ckpt, map_location="cpu", weights_only=False)["epoch"]
    small = [o for o in TINY if not o.startswith(("model.", "module.lbfgs_max_iter"))]
    overrides = ["experiment=planar3", *small, "module.lbfgs_max_iter=1", f"trainer.max_epochs={epoch + 2}"]
    summary = train(make_cfg("train", [*overrides, f"ckpt_path={ckpt}"]), tmp_path / "run")
    assert summary["epochs"] == epoch + 2 and summary["status"] == "ok"
    prior = load_surrogate(tmp_path / "run" / "surrogate.pt").model.config["prior"]
    assert prior["system"] == "planar3" and prior["dynamics"]["name"] == "planar3"  # now with its description
