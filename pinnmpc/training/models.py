"""The network a training run starts from: fresh, staged, or grown from a given checkpoint."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.prior import ArmPrior
from pinnmpc.surrogate.staged import StagedPINN
from pinnmpc.systems.base import System
from pinnmpc.training.correction import staged_model
from pinnmpc.training.data import flow_scale
from pinnmpc.training.grow import grown_model


def build_model(cfg: DictConfig, system: System, prior_arm: dict | None = None) -> PINN | StagedPINN:
    """The network for this system's training box (output scale estimated from the flow when 'auto'), or with
    stage.base a correction network on top of that trained one, or with init_from that one widened to model.hidden;
    prior_arm: the description of the arm a frozen-arm prior holds still (an identified model's; None: the system's)."""
    if cfg.stage.base:
        return build_staged(cfg, system)
    if cfg.get("init_from"):
        hidden, basis, sums = list(cfg.model.hidden), list(cfg.model.time_basis), _angle_sums(cfg)
        prior = cfg.model.get("prior")
        keys = ("activation", "ic", "second_order", "periodic")
        form = {
            k: OmegaConf.to_object(v) if OmegaConf.is_config(v) else v
            for k in keys
            if (v := cfg.model.get(k)) is not None
        }
        net = grown_model(
            system, cfg.init_from, system.tau, cfg.t_max, hidden, cfg.seed, basis, sums, prior, form, prior_arm
        )
        if cfg.data.get("logs") and isinstance(net, PINN):
            from pinnmpc.training.rescale import live_features, log_transitions, period_miss, widen_heads

            logged = log_transitions(system, [str(p) for p in cfg.data.logs])
            if not live_features(net, logged):
                raise ValueError(
                    f"init_from={cfg.init_from}: no unit of its last hidden layer is alive on the logs (its prior "
                    "made it exact, its features saturated), so fine-tuning cannot move it; expected a live network: "
                    "train from a fresh one (init_from=null)"
                )
            if cfg.model.get("rescale_to_logs"):
                widen_heads(net, period_miss(net, system, logged))
        return net
    return fresh_model(cfg, system, prior_arm)


def fresh_model(cfg: DictConfig, system: System, prior_arm: dict | None = None) -> PINN:
    """A new network of cfg.model for this system's training box (output scale estimated from the flow when
    'auto'): what training and the capacity check start from; prior_arm as in build_model."""
    kind = cfg.model.get("prior")
    # the arm's own description travels with the network: a user's arm outside conf/system, or one whose name a
    # shipped arm shares, rebuilds the same prior wherever the network is loaded
    dynamics = OmegaConf.to_container(cfg.system.dynamics, resolve=True) if "dynamics" in cfg.system else None
    if dynamics is not None and getattr(system, "urdf", None):  # the file the arm was built from, found anywhere
        from pinnmpc.systems.urdf import portable_urdf

        dynamics["urdf"] = portable_urdf(system.urdf)
    dynamics = prior_arm or dynamics
    prior = None if kind is None else {"kind": str(kind), "system": system.name, "dynamics": dynamics}
    scale = cfg.model.output_scale
    if scale == "auto":
        a = cfg.model.auto_scale
        start = None if prior is None else ArmPrior(prior_arm or system, prior["kind"])
        scale = flow_scale(system, cfg.t_max, a.samples, a.h, a.quantile, cfg.seed, start)
    net = PINN(
        state_low=system.state_box.low,
        state_high=system.state_box.high,
        input_low=system.input_box.low,
        input_high=system.input_box.high,
        t_max=cfg.t_max,
        hidden=list(cfg.model.hidden),
        activation=cfg.model.activation,
        ic=cfg.model.ic,
        output_scale=None if scale is None else list(scale),
        time_basis=list(cfg.model.time_basis) if cfg.model.ic == "gated" else [],
        second_order=cfg.model.get("second_order", False),
        periodic=list(cfg.model.get("periodic", [])),
        angle_sums=_angle_sums(cfg),
        prior=prior,
    )
    if cfg.model.get("zero_output"):
        if prior is None:
            raise ValueError("model.zero_output=true needs model.prior (a network of zero output is x0, not a model)")
        last = net.net.layers[-1]
        last.weight.data.zero_()
        last.bias.data.zero_()
    return net


def _angle_sums(cfg: DictConfig) -> list[list[int]]:
    """model.angle_sums as plain lists (none when the model config predates the setting)."""
    return [list(c) for c in cfg.model.get("angle_sums") or []]


def build_staged(cfg: DictConfig, system: System) -> StagedPINN:
    """stage.base frozen plus a correction network of stage.hidden; the base fixes box, t_max and form."""
    st = cfg.stage
    model = staged_model(
        system, st.base, system.tau, list(st.hidden), st.error_scale, st.first_layer_gain, st.last_layer_gain,
        st.samples, st.h, cfg.seed,
    )  # fmt: skip
    if abs(model.t_max - cfg.t_max) > 1e-12:
        raise ValueError(f"stage.base was trained on t in [0, {model.t_max}]; set t_max={model.t_max}, got {cfg.t_max}")
    return model
