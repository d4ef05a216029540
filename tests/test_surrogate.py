"""The shipped surrogate and its checkpoint format: shapes, dtypes, exact Jacobians, round trips, clear errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import jacrev, vmap

from pinnmpc.plant.integrators import rk4_step
from pinnmpc.surrogate import FORMAT, FORMAT_VERSION, SHIPPED, CheckpointError, Surrogate, load_surrogate, shipped
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.numpy_flow import BlockDiagonal, NumpyFlow
from pinnmpc.systems import PowerCube

torch.set_num_threads(1)  # a training job shares this 2-core machine

NX, NU = 4, 2


@pytest.fixture(scope="module")
def s() -> Surrogate:
    return load_surrogate()


@pytest.fixture(scope="module")
def shipped_obj() -> dict:
    return torch.load(SHIPPED, map_location="cpu", weights_only=True)


def _points(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """States and inputs spread over (most of) the training box."""
    g = torch.Generator().manual_seed(seed)
    x0 = (torch.rand(n, NX, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([3.0, 3.0, 2.4, 2.4])
    u = (torch.rand(n, NU, generator=g, dtype=torch.float64) * 2 - 1) * 0.5
    return x0.to(dtype), u.to(dtype)


def _listing(*folders: Path) -> dict[str, tuple[int, int]]:
    """Every file below the folders with size and modification time, to prove nothing was written."""
    out = {}
    for folder in folders:
        for p in sorted(folder.rglob("*")):
            st = p.stat()
            out[str(p)] = (st.st_size, st.st_mtime_ns)
    return out


def _save_obj(path: Path, obj: object) -> Path:
    torch.save(obj, path)
    return path


# ---------------------------------------------------------------------------------------------------------------
# The shipped surrogate


def test_shipped_facts(s: Surrogate) -> None:
    assert s.tau == 0.2
    assert (s.nx, s.nu) == (NX, NU)
    assert s.dtype == torch.float64
    assert next(s.model.parameters()).dtype == torch.float64


def test_shipped_30min_network_is_anchor_trained_beats_the_pure_pinn_and_the_default_beats_it() -> None:
    default = load_surrogate()
    short = load_surrogate(SHIPPED.parent / "powercube-30min.pt", nx=NX, nu=NU)
    pure = load_surrogate(SHIPPED.parent / "powercube-pinn.pt", nx=NX, nu=NU)
    assert short.meta["config"]["data"]["n_anchor"] > 0 and pure.meta["config"]["data"].get("n_anchor", 0) == 0
    assert short.meta["training_time_s"] <= 31 * 60  # the budget: one 30-min run
    assert default.meta["training_time_s"] <= 4 * 3600 + 60  # the frontier's ~4 h (the timer ends after an epoch)
    x0, u = _points(512, seed=13)
    ref = rk4_step(PowerCube().rhs, x0, u, 0.2, 1e-4)
    nets = (("default", default), ("short", short), ("pure", pure))
    err = {k: (m.step(x0, u) - ref).square().mean(0).sqrt() for k, m in nets}
    assert torch.all(err["short"] < err["pure"])  # measured: angles 2-3x, velocities ~1.4x better
    assert torch.all(err["short"] < torch.tensor([7e-4, 7e-4, 3.5e-3, 3.5e-3], dtype=torch.float64))
    assert torch.all(err["default"] < err["short"])  # the longer run of the same recipe
    assert torch.all(err["default"][:2] <= 2e-4)  # the frontier's one-step target in the angles


def test_shipped_second_order_network_is_accurate_and_consistent() -> None:
    second = load_surrogate(SHIPPED.parent / "powercube-second-order.pt", nx=NX, nu=NU)
    assert second.model.second_order and second.tau == 0.2
    x0, u = _points(64, seed=11)
    ref = rk4_step(PowerCube().rhs, x0, u, 0.2, 1e-3)
    rmse = (second.step(x0, u) - ref).square().mean(0).sqrt()
    assert torch.all(rmse < torch.tensor([5e-3, 8e-3, 3e-2, 6e-2], dtype=torch.float64))  # trained: ~2e-3 / 4e-3 rad
    x1, a, b = NumpyFlow.from_pinn(second.model, second.tau).step_with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(x1, second.step(x0, u).numpy(), rtol=0, atol=1e-12)  # the controller's fast path


def test_shipped_staged_network_is_merged_more_accurate_than_its_base_and_fast_path_exact() -> None:
    s = load_surrogate(SHIPPED.parent / "powercube-lbfgs.pt", nx=NX, nu=NU)  # the stage's base: 120 min of L-BFGS
    staged = load_surrogate(SHIPPED.parent / "powercube-staged.pt", nx=NX, nu=NU)
    assert staged.model.config["hidden"] == [a + 64 for a in s.model.config["hidden"]]  # base + a 4 x 64 stage
    x0, u = _points(256, seed=12)
    ref = rk4_step(PowerCube().rhs, x0, u, 0.2, 1e-3)
    err = {k: (m.step(x0, u) - ref).square().mean(0).sqrt() for k, m in (("base", s), ("staged", staged))}
    assert torch.all(err["staged"] < 0.7 * err["base"])  # measured: about half in every state
    assert torch.all(err["staged"] < torch.tensor([1.5e-3, 1.5e-3, 6e-3, 6e-3], dtype=torch.float64))
    flow = NumpyFlow.from_pinn(staged.model, staged.tau)
    assert all(isinstance(w, BlockDiagonal) and len(w.blocks) == 2 for w, _ in flow.hidden)
    x1, a, b = flow.step_with_jacobian(x0[:8].numpy(), u[:8].numpy())
    np.testing.assert_allclose(x1, staged.step(x0[:8], u[:8]).numpy(), rtol=0, atol=1e-12)


def test_call_shapes_and_dtype(s: Surrogate) -> None:
    x0, u = _points(3)
    t = torch.tensor([[0.05], [0.1], [0.2]], dtype=torch.float64)
    x = s(t, x0, u)
    assert x.shape == (3, NX)
    assert x.dtype == torch.float64
    assert torch.all(torch.isfinite(x))
    # the flow actually moves the state (not a trivial identity)
    assert torch.all((x - x0).abs().amax(-1) > 1e-4)
    # rows are independent problems
    for i in range(3):
        torch.testing.assert_close(s(t[i], x0[i], u[i]), x[i], rtol=1e-12, atol=1e-12)


def test_leading_batch_dimensions(s: Surrogate) -> None:
    x0, u = _points(6, seed=1)
    t = torch.linspace(0.01, 0.2, 6, dtype=torch.float64)[:, None]
    flat = s(t, x0, u)
    x = s(t.reshape(2, 3, 1), x0.reshape(2, 3, NX), u.reshape(2, 3, NU))
    assert x.shape == (2, 3, NX)
    torch.testing.assert_close(x.reshape(6, NX), flat, rtol=1e-12, atol=1e-12)
    x1 = s.step(x0.reshape(2, 3, NX), u.reshape(2, 3, NU))
    assert x1.shape == (2, 3, NX)
    torch.testing.assert_close(x1.reshape(6, NX), s.step(x0, u), rtol=1e-12, atol=1e-12)
    x1, A, B = s.step_with_jacobian(x0.reshape(2, 3, NX), u.reshape(2, 3, NU))
    assert (x1.shape, A.shape, B.shape) == ((2, 3, NX), (2, 3, NX, NX), (2, 3, NX, NU))


def test_numpy_lists_and_broadcast_batches(s: Surrogate) -> None:
    # numpy arrays and lists are taken as they are (torch out); one input for many states broadcasts
    x0, u = _points(4, seed=5)
    want = s.step(x0, u[:1].expand(4, NU))
    torch.testing.assert_close(s.step(x0.numpy(), u[0].numpy()), want, rtol=0, atol=0)
    torch.testing.assert_close(s.step(x0[0].tolist(), u[0].tolist()), want[0], rtol=0, atol=1e-12)  # batch 1
    t = np.full((4, 1), s.tau)
    torch.testing.assert_close(s(t, x0, u[0]), want, rtol=0, atol=0)
    x1, A, B = s.step_with_jacobian(x0[:1], u)  # one state, four inputs
    assert (x1.shape, A.shape, B.shape) == ((4, NX), (4, NX, NX), (4, NX, NU))
    with pytest.raises(ValueError, match=r"same \(or broadcastable\) batch shapes, got x0 \(2, 4\) and u \(3, 2\)"):
        s.step(x0[:2], u[:3])


@pytest.mark.parametrize("system", ["powercube", "planar3", "panda"])
def test_an_empty_batch_gives_an_empty_batch(system: str) -> None:
    # planar3 and the Panda step through a compiled prior, whose CasADi map refused zero rows
    net = load_surrogate(system=system)
    x1, A, B = net.step_with_jacobian(np.zeros((0, net.nx)), np.zeros((0, net.nu)))
    assert net.step(np.zeros((0, net.nx)), np.zeros((0, net.nu))).shape == x1.shape == (0, net.nx)
    assert (A.shape, B.shape) == ((0, net.nx, net.nx), (0, net.nx, net.nu))


def test_step_is_call_at_tau(s: Surrogate) -> None:
    x0, u = _points(5, seed=2)
    t = torch.full((5, 1), s.tau, dtype=torch.float64)
    assert torch.equal(s.step(x0, u), s(t, x0, u))
    # and it is not the same as some other time
    assert not torch.allclose(s.step(x0, u), s(t / 2, x0, u))


def test_float32_inputs_give_float64(s: Surrogate) -> None:
    x0, u = _points(4, seed=3, dtype=torch.float32)
    t = torch.full((4, 1), 0.1, dtype=torch.float32)
    x = s(t, x0, u)
    assert x.dtype == torch.float64
    torch.testing.assert_close(x, s(t.double(), x0.double(), u.double()), rtol=0, atol=0)
    x1 = s.step(x0, u)
    assert x1.dtype == torch.float64
    torch.testing.assert_close(x1, s.step(x0.double(), u.double()), rtol=0, atol=0)
    x1j, A, B = s.step_with_jacobian(x0, u)
    assert x1j.dtype == A.dtype == B.dtype == torch.float64


def test_hard_initial_condition_is_exact(s: Surrogate) -> None:
    x0, u = _points(50, seed=4)
    x = s(torch.zeros(50, 1, dtype=torch.float64), x0, u)
    assert torch.equal(x, x0)


@pytest.mark.parametrize("seed", [5, 6])
def test_step_with_jacobian_matches_autograd(s: Surrogate, seed: int) -> None:
    x0, u = _points(8, seed=seed)
    x1, A, B = s.step_with_jacobian(x0, u)
    torch.testing.assert_close(x1, s.step(x0, u), rtol=0, atol=1e-12)
    A_ref, B_ref = vmap(jacrev(s.step, argnums=(0, 1)))(x0, u)
    assert A.shape == (8, NX, NX) and B.shape == (8, NX, NU)
    assert (A - A_ref).abs().max() < 1e-10
    assert (B - B_ref).abs().max() < 1e-10
    # the Jacobian is not just the identity part of the hard initial condition
    assert B.abs().max() > 1e-3
    assert (A - torch.eye(NX, dtype=A.dtype)).abs().max() > 1e-3
    # unbatched, too
    x1u, Au, Bu = s.step_with_jacobian(x0[0], u[0])
    Ar, Br = jacrev(s.step, argnums=(0, 1))(x0[0], u[0])
    assert (Au - Ar).abs().max() < 1e-10 and (Bu - Br).abs().max() < 1e-10


@pytest.mark.parametrize(
    ("x_shape", "u_shape", "fragment"),
    [
        ((3, 5), (3, 2), "(..., 4)"),
        ((3, 3), (3, 2), "(..., 4)"),
        ((3, 4), (3, 3), "(..., 2)"),
        ((3, 4), (3, 1), "(..., 2)"),
    ],
)
def test_wrong_last_dimension_names_expected_shape(
    s: Surrogate, x_shape: tuple[int, ...], u_shape: tuple[int, ...], fragment: str
) -> None:
    x0, u = torch.zeros(x_shape, dtype=torch.float64), torch.zeros(u_shape, dtype=torch.float64)
    t = torch.full((3, 1), 0.1, dtype=torch.float64)
    for call in (lambda: s(t, x0, u), lambda: s.step(x0, u), lambda: s.step_with_jacobian(x0, u)):
        with pytest.raises(ValueError, match=r"x0 \(\.\.\., 4\).*u \(\.\.\., 2\)") as err:
            call()
        assert fragment in str(err.value)
        assert f"x0 {x_shape}" in str(err.value) and f"u {u_shape}" in str(err.value)


def test_time_outside_the_trained_interval_is_refused_and_broadcasts_inside_it(s: Surrogate) -> None:
    x0, u = _points(1)
    for t in (-0.01, 2 * s.t_max):
        with pytest.raises(ValueError, match=f"t in \\[0, t_max={s.t_max:g}\\] s"):
            s(torch.full((1, 1), t, dtype=torch.float64), x0, u)
    many = s(torch.tensor([[0.0], [s.tau], [s.t_max]], dtype=torch.float64), x0[0], u[0])  # one state, three times
    assert many.shape == (3, NX)
    torch.testing.assert_close(many[1], s.step(x0[0], u[0]))
    torch.testing.assert_close(many[0], x0[0])  # hard initial condition


def test_a_checkpoint_of_another_system_is_refused_and_dtype_may_be_a_name(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="was trained for states \\['alpha'"):
        load_surrogate(shipped("powercube"), system="planar3")
    assert load_surrogate(shipped("powercube"), system="powercube").state_names[0] == "alpha"
    assert load_surrogate(dtype="float32").dtype == torch.float32
    with pytest.raises(TypeError, match="dtype must be a torch floating dtype.*got 'int64'"):
        load_surrogate(dtype="int64")


def test_time_with_wrong_last_dimension(s: Surrogate) -> None:
    x0, u = _points(3)
    with pytest.raises(ValueError, match="last dimension 1"):
        s(torch.zeros(3, 2, dtype=torch.float64), x0, u)


# ---------------------------------------------------------------------------------------------------------------
# Round trips


def test_save_load_round_trip(s: Surrogate, tmp_path: Path) -> None:
    path = s.save(tmp_path / "sub" / "copy.pt")
    assert path.is_file()
    assert sorted(p.name for p in path.parent.iterdir()) == ["copy.pt"]  # no temporary file left behind
    s2 = load_surrogate(path)
    assert (s2.tau, s2.state_names, s2.input_names) == (s.tau, s.state_names, s.input_names)
    assert s2.model.config == s.model.config
    assert s2.meta == s.meta
    x0, u = _points(20, seed=7)
    t = torch.linspace(0.0, 0.25, 20, dtype=torch.float64)[:, None]
    assert torch.equal(s2(t, x0, u), s(t, x0, u))
    assert all(torch.equal(a, b) for a, b in zip(s2.step_with_jacobian(x0, u), s.step_with_jacobian(x0, u)))


def test_a_config_node_in_the_meta_is_saved_as_plain_data(s: Surrogate, tmp_path: Path) -> None:
    """A meta holding OmegaConf nodes (a run's settings) still loads with weights_only: saved as plain lists."""
    from omegaconf import OmegaConf

    copy = load_surrogate(s.save(tmp_path / "a.pt"))
    copy.meta = {**copy.meta, "physics": {"fitted": OmegaConf.create(["payload"]), "x": OmegaConf.create({"a": 1})}}
    back = load_surrogate(copy.save(tmp_path / "b.pt"))
    assert back.meta["physics"] == {"fitted": ["payload"], "x": {"a": 1}}


def test_save_load_round_trip_with_time_gates(s: Surrogate, tmp_path: Path) -> None:
    torch.manual_seed(3)
    model = PINN(**{**s.model.config, "hidden": [16, 16], "ic": "gated", "time_basis": [0.02, 0.045]}).double()
    gated = Surrogate(model, s.tau, s.state_names, s.input_names)
    loaded = load_surrogate(gated.save(tmp_path / "gated.pt"))
    assert loaded.model.config["time_basis"] == [0.02, 0.045] and loaded.model.n_gates == 3
    x0, u = _points(10, seed=9)
    torch.testing.assert_close(loaded.step(x0, u), gated.step(x0, u), rtol=1e-13, atol=1e-13)


def test_save_load_round_trip_of_a_second_order_model(s: Surrogate, tmp_path: Path) -> None:
    torch.manual_seed(4)
    config = {**s.model.config, "hidden": [16, 16], "ic": "gated", "time_basis": [0.02], "second_order": True}
    model = PINN(**config).double()
    second = Surrogate(model, s.tau, s.state_names, s.input_names)
    loaded = load_surrogate(second.save(tmp_path / "second.pt"))
    assert loaded.model.second_order and loaded.model.config == config
    x0, u = _points(10, seed=9)
    for a, b in zip(loaded.step_with_jacobian(x0, u), second.step_with_jacobian(x0, u)):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13)


def test_periodic_model_round_trip_and_domain(s: Surrogate, tmp_path: Path) -> None:
    torch.manual_seed(5)
    config = {**s.model.config, "hidden": [16, 16], "activation": "silu", "periodic": [0, 1]}
    periodic = Surrogate(PINN(**config).double(), s.tau, s.state_names, s.input_names)
    loaded = load_surrogate(periodic.save(tmp_path / "periodic.pt"))
    assert loaded.model.config == config
    x0, u = _points(10, seed=12)
    turn = torch.tensor([2 * torch.pi, -4 * torch.pi, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(loaded.step(x0 + turn, u) - turn, periodic.step(x0, u), rtol=0, atol=1e-12)
    # the closed loop warns when leaving the domain: the angles are unbounded there, the velocities are not
    assert loaded.domain.low[:2] == (-float("inf"),) * 2 and loaded.domain.high[2:] == s.state_box.high[2:]
    linear = Surrogate(PINN(**{**config, "periodic": []}), s.tau, s.state_names, s.input_names)
    assert linear.domain == linear.state_box  # with linear angle inputs the domain is the training box
    limited = {**config, "state_low": [-2.0, *config["state_low"][1:]], "state_high": [1.0, *config["state_high"][1:]]}
    part = Surrogate(PINN(**limited), s.tau, s.state_names, s.input_names)  # joint 1 periodic, its box under a turn
    assert part.domain.low[:2] == (-2.0, -float("inf")) and part.domain.high[:2] == (1.0, float("inf"))


def test_save_load_round_trip_keeps_float64_weights(s: Surrogate, tmp_path: Path) -> None:
    model = PINN(**s.model.config)
    model.load_state_dict(s.model.state_dict())
    model = model.double()
    with torch.no_grad():  # what a float64 training step does: weights no longer representable in float32
        for p in model.parameters():
            p.mul_(1 + 1e-9)
    fresh = Surrogate(model, s.tau, s.state_names, s.input_names)
    loaded = load_surrogate(fresh.save(tmp_path / "f64.pt"))
    x0, u = _points(10, seed=8)
    torch.testing.assert_close(loaded.step(x0, u), fresh.step(x0, u), rtol=1e-13, atol=1e-13)


def test_lightning_style_checkpoint(s: Surrogate, shipped_obj: dict, tmp_path: Path) -> None:
    ckpt = {
        "epoch": 6,
        "global_step": 120,
        "pytorch-lightning_version": "2.4.0",
        "state_dict": {
            **{"model." + k: v for k, v in shipped_obj["state_dict"].items()},
            "res_scale": torch.ones(NX),  # the module's own buffer: not part of the surrogate
        },
        "optimizer_states": [],
        "lr_schedulers": [],
        "pinnmpc": {
            "version": 1,
            "tau": 0.2,
            "state_names": ["alpha", "beta", "dalpha", "dbeta"],
            "input_names": ["u1", "u2"],
            "model": shipped_obj["model"],
        },
    }
    path = _save_obj(tmp_path / "last.ckpt", ckpt)
    s2 = load_surrogate(path, nx=NX, nu=NU)
    assert s2.tau == 0.2
    assert s2.state_names == ("alpha", "beta", "dalpha", "dbeta") and s2.input_names == ("u1", "u2")
    x0, u = _points(10, seed=9)
    assert torch.equal(s2.step(x0, u), s.step(x0, u))


# ---------------------------------------------------------------------------------------------------------------
# Bad checkpoints


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="not found") as err:
        load_surrogate(tmp_path / "nope.pt")
    assert "nope.pt" in str(err.value)


def test_directory(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="folder") as err:
        load_surrogate(tmp_path)
    assert str(tmp_path) in str(err.value)


def test_truncated_copy(tmp_path: Path) -> None:
    data = SHIPPED.read_bytes()
    path = tmp_path / "half.pt"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="corrupt") as err:
        load_surrogate(path)
    assert "truncated" in str(err.value) and str(path) in str(err.value)


def test_garbage_bytes(tmp_path: Path) -> None:
    path = tmp_path / "garbage.pt"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(CheckpointError, match="corrupt") as err:
        load_surrogate(path)
    assert str(path) in str(err.value)


def test_many_garbage_files_all_raise_checkpoint_error(tmp_path: Path) -> None:
    """Random bytes make torch.load fail in many ways (IndexError for seeds 17 and 21, UnicodeDecodeError, ...)."""
    escaped = {}
    for seed in range(40):
        path = tmp_path / f"garbage{seed}.pt"
        path.write_bytes(np.random.default_rng(seed).bytes(4096))
        try:
            load_surrogate(path)
        except CheckpointError:
            continue
        except Exception as e:  # collected for the assertion message
            escaped[seed] = type(e).__name__
        else:
            escaped[seed] = "loaded"
    assert not escaped, f"not a CheckpointError: {escaped}"


def test_foreign_dict(tmp_path: Path) -> None:
    path = _save_obj(tmp_path / "foo.pt", {"foo": 1})
    with pytest.raises(CheckpointError, match="not a pinnmpc checkpoint") as err:
        load_surrogate(path)
    assert str(path) in str(err.value)


class _Touch:
    """A pickle that creates a file when unpickled: stands in for a malicious checkpoint."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self) -> tuple:
        return (open, (self.marker, "w"))


def test_checkpoint_cannot_run_code(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = _save_obj(tmp_path / "evil.pt", {"format": FORMAT, "payload": _Touch(marker)})
    with pytest.raises(CheckpointError):
        load_surrogate(path)
    assert not marker.exists(), "load_surrogate executed code from the checkpoint (weights_only=False)"


def test_list(tmp_path: Path) -> None:
    path = _save_obj(tmp_path / "list.pt", [1, 2, 3])
    with pytest.raises(CheckpointError, match="holds a list"):
        load_surrogate(path)


@pytest.mark.parametrize(
    ("kwargs", "fragment"), [({"nx": 6}, "state dimension 4; expected 6"), ({"nu": 3}, "input dimension 2; expected 3")]
)
def test_dimension_mismatch(kwargs: dict, fragment: str) -> None:
    with pytest.raises(CheckpointError, match=fragment):
        load_surrogate(None, **kwargs)
    load_surrogate(None, nx=NX, nu=NU)  # the right dimensions pass


@pytest.mark.parametrize("hidden", [[32, 64, 64, 64], [64, 64, 64], [64, 64, 64, 64, 64]])
def test_weights_do_not_fit_config(shipped_obj: dict, tmp_path: Path, hidden: list[int]) -> None:
    obj = {**shipped_obj, "model": {**shipped_obj["model"], "hidden": hidden}}
    path = _save_obj(tmp_path / "bad.pt", obj)
    with pytest.raises(CheckpointError, match="weights do not fit"):
        load_surrogate(path)


def test_newer_format_version(shipped_obj: dict, tmp_path: Path) -> None:
    path = _save_obj(tmp_path / "future.pt", {**shipped_obj, "version": FORMAT_VERSION + 1})
    with pytest.raises(CheckpointError, match="format version"):
        load_surrogate(path)


@pytest.mark.parametrize("missing", ["state_dict", "model", "tau"])
def test_tagged_checkpoint_missing_fields(shipped_obj: dict, tmp_path: Path, missing: str) -> None:
    obj = {k: v for k, v in shipped_obj.items() if k != missing}
    assert obj["format"] == FORMAT
    path = _save_obj(tmp_path / "partial.pt", obj)
    with pytest.raises(CheckpointError):
        load_surrogate(path)


def test_loading_never_writes(shipped_obj: dict, tmp_path: Path) -> None:
    shutil.copy(SHIPPED, tmp_path / "copy.pt")
    data = SHIPPED.read_bytes()
    (tmp_path / "half.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.pt").write_bytes(np.random.default_rng(0).bytes(1024))
    _save_obj(tmp_path / "foo.pt", {"foo": 1})
    _save_obj(tmp_path / "wide.pt", {**shipped_obj, "model": {**shipped_obj["model"], "hidden": [32, 64, 64, 64]}})
    (tmp_path / "folder").mkdir()
    before = _listing(tmp_path, SHIPPED.parent)
    load_surrogate(None)
    load_surrogate(tmp_path / "copy.pt")
    for name in ["half.pt", "junk.pt", "foo.pt", "wide.pt", "folder", "missing.pt"]:
        with pytest.raises(CheckpointError):
            load_surrogate(tmp_path / name)
    assert _listing(tmp_path, SHIPPED.parent) == before


def test_a_network_whose_tau_lies_beyond_its_training_interval_is_refused():
    net = load_surrogate(system="planar3")
    with pytest.raises(CheckpointError, match=r"tau=0.2 s lies outside the interval \(0, t_max=0.125\]"):
        Surrogate(net.model, 0.2, net.state_names, net.input_names)
