"""Warm starts: a trained network grown without changing what it computes, so training adds capacity to it.

A network that has flattened under every loss setting may lack capacity, and starting a bigger one from scratch
throws away hours of training. Widening (Chen et al. 2016, Net2Net) keeps the trained units and adds new ones
whose outgoing weights are zero: the wider network starts at the trained one's exact outputs and the optimiser
moves from there with all parameters free. New time gates (relaxation times appended to the time basis) start
the same way: their output heads are zero, so a flow whose time dependence the old gates cannot span can be
fitted on from the trained network. New angle-sum inputs start deaf: the first layer's weights on them are zero.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems.base import Box, System


def widened(
    base: PINN,
    hidden: Sequence[int],
    seed: int,
    time_basis: Sequence[float] | None = None,
    angle_sums: Sequence[Sequence[int]] | None = None,
    prior_arm: dict[str, Any] | None = None,
    prior_kind: str | None = None,
    inputs: Box | None = None,
) -> PINN:
    """A copy of `base` with hidden widths `hidden` (same depth, none narrower), optionally more time gates
    (`time_basis`: the base's relaxation times first, new ones after), angle-sum inputs (`angle_sums`: the
    base's first), another arm under its prior (`prior_arm`) or another frozen-arm kind (`prior_kind`), more inputs
    (`inputs`: the base's input box first, then the new inputs' bounds; they start deaf), and the same network
    outputs."""
    old = [layer.out_features for layer in base.net.layers[:-1]]
    new = [int(w) for w in hidden]
    if len(new) != len(old) or any(n < o for n, o in zip(new, old)):
        raise ValueError(
            f"model.hidden={new} cannot start from a network of hidden widths {old}: expected the same depth "
            f"({len(old)} layers) and no layer narrower"
        )
    config = {**base.config, "hidden": new}
    if time_basis is not None:
        config.update(_grown_basis(base, time_basis))
    if angle_sums is not None:
        config.update(_grown_sums(base, angle_sums))
    if prior_arm is not None and config.get("prior"):
        config["prior"] = {**config["prior"], "dynamics": dict(prior_arm)}
    if prior_kind is not None and config.get("prior"):
        config["prior"] = {**config["prior"], "kind": str(prior_kind)}
    if inputs is not None:
        config.update(_grown_inputs(base, inputs))
    model = PINN(**config).to(base.out_scale.dtype)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for i, (src, dst) in enumerate(zip(base.net.layers[:-1], model.net.layers[:-1])):
            _embed(src, dst, generator, columns=_input_columns(base, model) if i == 0 else None)
        _embed(base.net.layers[-1], model.net.layers[-1], generator, fresh_rows=False)
        model.load_state_dict({**model.state_dict(), **_buffers(base, model)})
    return model


def _grown_inputs(base: PINN, inputs: Box) -> dict[str, object]:
    """PINN settings for the input box `inputs`, which must extend the base's (its inputs first, same bounds)."""
    low, high = list(inputs.low), list(inputs.high)
    if len(low) < base.nu:
        raise ValueError(
            f"init_from's network takes {base.nu} inputs, this run's system {len(low)}: expected "
            "model.previous_input=true for a network given the previous input"
        )
    have = (base.config["input_low"], base.config["input_high"])
    if (low[: base.nu], high[: base.nu]) != (list(have[0]), list(have[1])):
        raise ValueError(
            f"the inputs' box {low}..{high} cannot start from a network with the input box {have[0]}..{have[1]}: "
            "expected its inputs first, with the same bounds, then any new ones"
        )
    return {"input_low": low, "input_high": high}


def _grown_basis(base: PINN, time_basis: Sequence[float]) -> dict[str, object]:
    """PINN settings for `time_basis`, which must extend the base's (its relaxation times first, in order)."""
    have, want = list(base.config["time_basis"]), [float(v) for v in time_basis]
    if want == have:
        return {}
    if want[: len(have)] != have or base.config["ic"] == "soft":
        raise ValueError(
            f"model.time_basis={want} cannot start from a network with time basis {have} (ic={base.config['ic']!r}): "
            f"expected its relaxation times first, in order, then any new ones"
        )
    return {"time_basis": want, "ic": "gated"}  # past the checks, want is the longer: new gates


def _grown_sums(base: PINN, angle_sums: Sequence[Sequence[int]]) -> dict[str, object]:
    """PINN settings for `angle_sums`, which must extend the base's (its sums first, in order)."""
    have, want = base.config.get("angle_sums", []), [sorted(int(i) for i in c) for c in angle_sums]
    if want[: len(have)] != have:
        raise ValueError(
            f"model.angle_sums={[list(c) for c in angle_sums]} cannot start from a network with angle sums {have}: "
            f"expected its sums first, in order, then any new ones"
        )
    return {"angle_sums": want}


def _input_columns(base: PINN, model: PINN) -> torch.Tensor:
    """Where each network input of `base` sits in `model`'s input: (t, x0, u, cosines) in place, its angle sums'
    sines and cosines at the head of the grown network's (new sums follow each)."""
    (old_sin, _), (new_sin, new_cos) = base.sum_columns, model.sum_columns
    n_old, n_lin = len(base.sum_map), 1 + base.nx + base.nu
    added = model.nu - base.nu  # new inputs sit after the base's, before the cosines
    return torch.cat(
        (
            torch.arange(n_lin),
            n_lin + added + torch.arange(old_sin.start - n_lin),
            new_sin.start + torch.arange(n_old),
            new_cos.start + torch.arange(n_old),
        )
    )


def _embed(
    src: nn.Linear, dst: nn.Linear, generator: torch.Generator, fresh_rows: bool = True, columns: Tensor | None = None
) -> None:
    """dst = src in its leading block, the trained units deaf to new ones below them; new units' rows are fresh
    (fresh_rows), or zero for an output layer, whose new rows are new gates' heads that start switched off.
    columns says where src's inputs sit among dst's (default: the leading ones); the others are new inputs."""
    o, i = src.weight.shape
    columns = torch.arange(i) if columns is None else columns
    fresh = torch.randn(dst.weight.shape, generator=generator, dtype=dst.weight.dtype)
    fresh *= (2.0 / sum(dst.weight.shape)) ** 0.5  # the Xavier-normal scale the network starts with
    if not fresh_rows:
        fresh[o:] = 0.0
    fresh[:o] = 0.0  # the trained units ignore new units and new inputs until training turns them on
    fresh[:o, columns] = src.weight
    dst.weight.copy_(fresh)
    dst.bias.zero_()
    dst.bias[:o] = src.bias


def _buffers(base: PINN, model: PINN) -> dict[str, torch.Tensor]:
    """The base's normalisation and output-scale buffers, which do not depend on the widths; where the grown network
    has more inputs, the base's normalisation leads and the new inputs keep their own."""
    own = model.state_dict()
    out = {}
    for k, v in base.state_dict().items():
        if k.startswith("net."):
            continue
        if v.shape != own[k].shape:
            v = torch.cat((v, own[k][v.shape[0] :]))
        out[k] = v
    return out


def grown_model(
    system: System,
    path: str,
    tau: float,
    t_max: float,
    hidden: Sequence[int],
    seed: int,
    time_basis: Sequence[float] | None = None,
    angle_sums: Sequence[Sequence[int]] | None = None,
    prior: str | None = None,
    form: dict[str, Any] | None = None,
    prior_arm: dict[str, Any] | None = None,
) -> PINN:
    """The trained surrogate at `path` (init_from) grown to `hidden`, `time_basis` and `angle_sums`, checked
    against this run (tau, t_max and whether it has a prior cannot change: they define the function it learned; nor
    can the network's form, `form`: model.activation, ic, second_order, periodic, which widening keeps). prior_arm: the
    description of the arm its frozen-arm prior holds from now on (a model identified from a robot: the prior then
    carries what the fit found, and the network's correction starts from the nominal arm's); None: the same."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"init_from={path} does not exist; expected a trained surrogate.pt or a run's .ckpt")
    surrogate = load_surrogate(path, state_names=tuple(system.state_names))
    base = surrogate.model
    for what, have, want in (("tau", surrogate.tau, tau), ("t_max", base.t_max, t_max)):
        if abs(have - want) > 1e-12:
            raise ValueError(f"init_from={path} was trained with {what}={have}; this run has {what}={want}")
    have_prior = (base.config.get("prior") or {}).get("kind")
    if (have_prior is None) != (prior is None):  # one frozen-arm kind for another: the correction starts as it was
        raise ValueError(
            f"init_from={path} was trained with model.prior={have_prior or 'null'}; this run has "
            f"model.prior={prior or 'null'} "
            f"(override system.network.prior={have_prior or 'null'})"
        )
    for key, want in (form or {}).items():
        have = base.config.get(key)
        if want is not None and have is not None and _plain(have) != _plain(want):
            raise ValueError(
                f"init_from={path} has model.{key}={have}; this run has model.{key}={want}, which widening cannot "
                f"change (expected model.{key}={have}, or a fresh network without init_from)"
            )
    inputs = system.input_box if system.input_box.dim != base.nu else None  # WithPreviousInput: u_prev added
    return widened(base, hidden, seed, time_basis, angle_sums, prior_arm, prior, inputs)


def _plain(value: Any) -> Any:
    """Lists and tuples alike, for comparing a stored setting with a configured one."""
    return list(value) if isinstance(value, (list, tuple)) else value
