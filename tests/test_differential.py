"""``implementation=fast`` against ``implementation=reference``, one researcher's change a row.

Each row of :data:`CASES` is a change a researcher makes (Hydra overrides, and/or a function that
edits the built components). For every row both implementations run briefly from identical seeds
and initial weights: one ES generation (6 members, 50 steps), one evaluation episode, the first 60
TD3 frames, the buffers' writes and one sampled batch, and 4 TD3 updates on that same batch. The
test proves, part by part of the run:

- each part where :func:`torchrl_esrl.run.implementation.implementations` says a fast piece ran gives
  the reference's outputs up to float32 rounding (bit for bit where the project claims it: the TD3
  collector, the buffers, the ES physics). ES episodes played by the fast population forward are
  checked step by step: each action is the actor module's on the recorded observation, and the
  reference env replays the recorded actions into the recorded observations, rewards and flags bit
  for bit. Where every piece of a part handed over to its reference, the fast run gives the
  reference's outputs bit for bit. Never a fast piece that ran and computes something else;
- the change reached the run: the reference's outputs for the row differ from the unchanged run's
  in the parts the change must touch (every part plays the env; the loss shows in the updates), so a
  change both implementations ignore fails here.

A new change is one line of :data:`CASES`.
"""
from __future__ import annotations

import contextlib
import copy
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torch import nn

from torchrl_esrl.collectors.es_collector import make_es_collector, make_evaluator
from torchrl_esrl.collectors.td3_collector import TD3EnvState, make_frame_batches
from torchrl_esrl.data.multibuffer import TRANSITION_KEYS, make_multibuffer
from torchrl_esrl.envs import EnvSpec, make_train_env, quiet_logs
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.es.openes import make_es
from torchrl_esrl.modules.networks import flat_parameters, make_actor_critic
from torchrl_esrl.objectives.td3 import TD3, make_td3
from torchrl_esrl.run.implementation import FAST_PIECES, implementation_line, implementations
from torchrl_esrl.threads import torch_threads

CONF = Path(__file__).resolve().parents[1] / "conf"
# Every row runs at this size: small networks, a 6-member generation of 50-step episodes, one
# 60-frame TD3 batch, batches of 32 from buffers that are ready as soon as they hold an item.
SMALL = (
    "experiment=tiny", "es.population_size=6", "env.max_episode_steps=50", "td3.frames_per_batch=60",
    "actor.hidden=[32,32]", "td3.critic_hidden=[32,32]", "buffer.batch_size=32", "buffer.min_size=1",
    "buffer.capacity=1000", "td3.num_threads=1",
)
GENERATION_SEEDS, EVALUATION_SEEDS = list(range(10, 16)), [20]  # episodes' reset seeds
UPDATES = 4  # two critic-only updates and two with the actor and targets (policy_delay 2)

# The parts of a run, and the pieces of FAST_PIECES that compute each.
PARTS = {
    "es_generation": ("es_forward", "es_physics"),
    "evaluation": ("es_forward",),  # the evaluator always steps gymnasium; its forward is the piece
    "td3_frames": ("td3_collector",),
    "buffer": ("buffer_writes", "buffer_reads"),
    "td3_updates": ("td3_loss", "soft_update", "adam"),
}
# Where a fast piece ran: (rtol, atol) of float32 rounding, or None: bit for bit (the project's claim).
# The ES parts (episodes played by the population forward) are checked step by step instead, see
# check_episodes: in closed loop, float32 rounding of an action grows through contact dynamics (Ant:
# 6e-8 in an action at step 3, 0.5 in an observation by step 48), however exact each step is.
TOLERANCE = {"td3_frames": None, "buffer": None, "td3_updates": (1e-5, 1e-6)}
FORWARD_ATOL = 1e-6  # an action of the fast population forward against the actor module's
ENV_PARTS = ("es_generation", "evaluation", "td3_frames")  # every part plays the task
ACTOR_PARTS = (*ENV_PARTS, "td3_updates")
LOSS_PARTS = ("td3_updates",)


@dataclass(frozen=True)
class Case:
    """One researcher's change. ``overrides``: Hydra overrides; ``networks(actor, critic)`` edits
    the built networks before TD3 is made; ``td3(cfg, actor, critic, action_spec)`` builds TD3
    instead of ``make_td3``; ``batch(batch)`` edits the batch the updates train on. ``given``:
    overrides of the unchanged run the change is compared with (where the change only shows under
    another setting); ``around()``: a context both implementations' runs are made in (torch's
    global module hooks, removed after the row); ``reaches``: the parts whose reference outputs
    the change must alter; ``pieces``: what the fast run must compute some pieces with
    (``{"td3_loss": "fast"}``: the change is trained through the hand-written gradients, not
    handed over); ``tolerance``: (rtol, atol) per part where the change itself rounds coarser than
    float32 (``td3.precision=bf16``)."""

    id: str
    overrides: tuple[str, ...] = ()
    env: str = "halfcheetah"
    given: tuple[str, ...] = ()
    networks: Callable | None = None
    td3: Callable | None = None
    batch: Callable | None = None
    around: Callable | None = None
    reaches: tuple[str, ...] = ENV_PARTS
    pieces: dict[str, str] = field(default_factory=dict)
    tolerance: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def changed(self) -> bool:
        return bool(self.overrides or self.networks or self.td3 or self.batch or self.around)


def actor_edit(edit: Callable[[nn.Module], None]):
    """A ``Case.networks`` that applies ``edit`` to the actor's MLP (``actor[0].module``)."""

    def networks(actor, critic):
        edit(actor[0].module)
        return actor, critic

    return networks


def every_second_unit_zeroed(gradient):
    """A gradient with every second unit of its last dimension zeroed (Adam undoes a constant scale)."""
    return None if gradient is None else gradient * (torch.arange(gradient.shape[-1]) % 2)


def halved_linear_output(module, args, output):
    """A forward hook: the output of an ``nn.Linear`` halved (other modules untouched)."""
    return output * 0.5 if type(module) is nn.Linear else None


def doubled_linear_input(module, args):
    """A forward pre-hook: the input of an ``nn.Linear`` doubled."""
    return (args[0] * 2,) if type(module) is nn.Linear else None


def masked_linear_input_gradient(module, grad_input, grad_output):
    """A full backward hook: the gradient an ``nn.Linear`` passes to its input, every second unit zeroed."""
    return tuple(every_second_unit_zeroed(g) for g in grad_input) if type(module) is nn.Linear else None


def masked_linear_output_gradient(module, grad_output):
    """A full backward pre-hook: the gradient of an ``nn.Linear``'s output, every second unit zeroed."""
    return tuple(every_second_unit_zeroed(g) for g in grad_output) if type(module) is nn.Linear else None


def global_hook(register: Callable, hook: Callable):
    """A ``Case.around``: ``hook`` registered with torch's ``register`` (a global module hook) for the row."""

    @contextlib.contextmanager
    def around():
        handle = register(hook)
        try:
            yield
        finally:
            handle.remove()

    return around


class Halved(nn.Module):
    """A parametrization: the parameter halved."""

    def forward(self, weight):
        return weight * 0.5


def dropout_after_first_activation(mlp):
    mlp.insert(2, nn.Dropout(0.1))


def rrelu_after_first_linear(mlp):
    mlp[1] = nn.RReLU()  # random slopes in training mode


def scale_buffer(mlp):
    """A buffer on the first Linear that no forward reads."""
    mlp[0].register_buffer("scale", torch.full((mlp[0].out_features,), 2.0))


# ---------------------------------------------------------------------------- component edits
def layer_norm_in_actor(actor, critic):
    """A LayerNorm after the actor's first Linear."""
    mlp = actor[0].module
    mlp.insert(1, nn.LayerNorm(mlp[0].out_features))
    return actor, critic


def td3_built(td3_class: type[TD3] = TD3, loss: Callable[[type], type] | None = None, **td3_kwargs):
    """TD3 built as ``make_td3`` builds it, as ``td3_class`` (a ``TD3`` subclass), with
    ``loss(loss class make_td3 picks)`` as its loss (None: that class) and ``td3_kwargs``
    (``num_qvalue_nets``) passed on."""

    def build(cfg, actor, critic, action_spec):
        chosen = make_td3(cfg, copy.deepcopy(actor), copy.deepcopy(critic), action_spec)
        c = cfg.td3
        torch.manual_seed(1)  # as the run seeds make_td3 (TD3Loss draws the second critic)
        return td3_class(
            actor, critic, action_spec, lr=c.lr, gamma=c.gamma, tau=c.tau, policy_noise=c.policy_noise,
            noise_clip=c.noise_clip, policy_delay=c.policy_delay, exploration_noise=c.exploration_noise,
            loss_function=c.loss_function, loss_class=type(chosen.loss) if loss is None else loss(type(chosen.loss)),
            target_update_class=type(chosen.target_update), optimizer_impl=chosen.optimizer_impl,
            num_threads=chosen.num_threads, **td3_kwargs,
        )

    return build


def td3_edited(edit: Callable[[TD3], None]):
    """``make_td3``'s TD3, then ``edit(td3)`` (hooks, frozen parameters) before it trains."""

    def build(cfg, actor, critic, action_spec):
        td3 = make_td3(cfg, actor, critic, action_spec)
        edit(td3)
        return td3

    return build


def doubled_value_loss(base: type) -> type:
    class DoubledValueLoss(base):
        def value_loss(self, tensordict):
            loss, metadata = super().value_loss(tensordict)
            return 2 * loss, metadata

    return DoubledValueLoss


class L2PenaltyTD3(TD3):
    """TD3 with an L2 penalty on the trained network's parameters added to each loss."""

    def backward(self, loss, optimizer):
        super().backward(loss + 1e-1 * sum(p.pow(2).sum() for p in optimizer.param_groups[0]["params"]), optimizer)


GRADIENT_NORM = 0.05  # below the first updates' gradient norms: the clipping acts


def clip_gradient_norm(optimizer, *_) -> None:
    torch.nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], GRADIENT_NORM)


class ClippedTD3(TD3):
    """TD3 that clips each network's gradient norm after ``loss.backward()``."""

    def backward(self, loss, optimizer):
        super().backward(loss, optimizer)
        clip_gradient_norm(optimizer)


def clip_in_step_pre_hooks(td3):
    """Gradient-norm clipping in the optimizers' step pre-hooks (fused Adam's direct kernel call runs them)."""
    for optimizer in (td3.actor_optimizer, td3.critic_optimizer):
        optimizer.register_step_pre_hook(clip_gradient_norm)


def scale_critic_gradient(td3):
    """A gradient hook on the critics' first weight: its rows alternately zeroed and halved (Adam
    undoes a constant scale; the zeroed rows are what shows)."""
    weight = td3.loss.qvalue_network_params.get(("module", "0", "weight"))
    scale = torch.where(torch.arange(weight.shape[-2]) % 2 == 0, 0.0, 0.5).unsqueeze(-1)
    weight.register_hook(lambda grad: grad * scale)


def zero_actor_gradient_rows(td3):
    """A post-accumulate-grad hook on the actor's first weight: every second row of its ``.grad``
    zeroed once the gradient is in ``.grad``."""
    weight = td3.actor[0].module[0].weight
    keep = (torch.arange(weight.shape[0]) % 2 == 1).unsqueeze(-1)

    def zero_rows(parameter):
        parameter.grad.mul_(keep)

    weight.register_post_accumulate_grad_hook(zero_rows)


def freeze_actor_layer(td3):
    td3.actor[0].module[0].requires_grad_(False)


def freeze_critic_layer(td3):
    for kind in ("weight", "bias"):
        td3.loss.qvalue_network_params.get(("module", "0", kind)).requires_grad_(False)


def priority_weights(batch):
    """Prioritised-replay weights on every item (as a PrioritizedSampler would set them)."""
    batch.set("priority_weight", 0.25 + 1.5 * torch.rand(batch.shape[0], generator=torch.Generator().manual_seed(4)))
    return batch


# ---------------------------------------------------------------------------- the table
def kwarg(env: str, name: str, value: str, given: tuple[str, ...] = ()) -> Case:
    return Case(f"{env}-{name}", (f"++env.kwargs.{name}={value}",), env=env, given=given)


def wrappers(name: str, entry: str) -> Case:
    return Case(f"wrapper-{name}", (f"env.wrappers=[{entry}]",))


def transforms(name: str, entry: str) -> Case:
    return Case(f"transform-{name}", (f"env.transforms=[{entry}]",))


BASE = [Case(f"BASE-{env}", env=env) for env in ("halfcheetah", "walker2d", "hopper", "swimmer", "ant")]

# Every keyword argument of the v5 constructors except xml_file (another model: its own task, not a
# setting of this one) and default_camera_config (rendering only); the rendering keywords of
# MujocoEnv (render_mode, width, height, camera_id, camera_name, visual_options) go through **kwargs
# and change no number of the run. Values chosen to show within 50 steps of a near-initial actor.
TERMINATES = ("++env.kwargs.healthy_z_range=[1.2,2.0]",)  # Walker2d falls below 1.2 within a few steps
ENV_KWARGS = [
    *(kwarg(env, name, value) for env in ("halfcheetah", "swimmer") for name, value in (
        ("frame_skip", "2"), ("forward_reward_weight", "2.0"), ("ctrl_cost_weight", "1.0"),
        ("reset_noise_scale", "0.5"), ("exclude_current_positions_from_observation", "false"),
    )),
    *(kwarg(env, name, value) for env in ("walker2d", "hopper") for name, value in (
        ("frame_skip", "2"), ("forward_reward_weight", "2.0"), ("ctrl_cost_weight", "1.0"),
        ("healthy_reward", "5.0"), ("healthy_angle_range", "[-0.05,0.05]"), ("reset_noise_scale", "0.1"),
        ("exclude_current_positions_from_observation", "false"),
    )),
    kwarg("walker2d", "healthy_z_range", "[1.2,2.0]"),
    kwarg("walker2d", "terminate_when_unhealthy", "false", given=TERMINATES),
    kwarg("hopper", "healthy_z_range", "[1.3,2.0]"),  # it starts at 1.25
    kwarg("hopper", "healthy_state_range", "[-0.5,0.5]"),
    kwarg("hopper", "terminate_when_unhealthy", "false"),  # the hopper falls within 50 steps as it is
    *(kwarg("ant", name, value) for name, value in (
        ("frame_skip", "2"), ("forward_reward_weight", "2.0"), ("ctrl_cost_weight", "1.0"),
        ("contact_cost_weight", "0.5"), ("healthy_reward", "5.0"), ("main_body", "3"),  # aux_1 (body 2, front_left_leg, sits at the torso's origin: the same x)
        ("healthy_z_range", "[0.8,1.0]"), ("contact_force_range", "[-0.1,0.1]"), ("reset_noise_scale", "0.5"),
        ("exclude_current_positions_from_observation", "false"), ("include_cfrc_ext_in_observation", "false"),
    )),
    kwarg("ant", "terminate_when_unhealthy", "false", given=("++env.kwargs.healthy_z_range=[0.8,1.0]",)),
]

# gymnasium wrappers (ClipAction is not here: it makes the action space unbounded, which the tanh
# actor cannot take and EnvSpec.sizes() refuses).
WRAPPERS = [
    wrappers("ClipReward", "{_target_:gymnasium.wrappers.ClipReward,min_reward:-0.02,max_reward:0.02}"),
    wrappers("TimeLimit", "{_target_:gymnasium.wrappers.TimeLimit,max_episode_steps:30}"),
    wrappers("RescaleAction", "{_target_:gymnasium.wrappers.RescaleAction,min_action:-0.5,max_action:0.5}"),
    wrappers("TransformReward", "{_target_:gymnasium.wrappers.TransformReward,func:{_target_:operator.mul,_partial_:true,_args_:[0.5]}}"),
    wrappers("TransformObservation", "{_target_:gymnasium.wrappers.TransformObservation,func:{_target_:numpy.multiply,_partial_:true,_args_:[2.0]},observation_space:null}"),
]

# TorchRL transforms without running state (a stateful one is refused: see the test below).
TRANSFORMS = [
    transforms("RewardScaling", "{_target_:torchrl.envs.RewardScaling,loc:0.0,scale:0.5}"),
    transforms("ObservationNorm", "{_target_:torchrl.envs.ObservationNorm,loc:0.5,scale:2.0,in_keys:[observation]}"),
    transforms("ClipTransform", "{_target_:torchrl.envs.ClipTransform,in_keys:[observation],low:-1.0,high:1.0}"),
    transforms("StepCounter", "{_target_:torchrl.envs.StepCounter,max_steps:30}"),
    transforms("RewardClipping", "{_target_:torchrl.envs.RewardClipping,clamp_min:-0.02,clamp_max:0.02}"),
    # a frame stack: its state is an episode's own, which every env that plays the task keeps for itself
    transforms("CatFrames", "{_target_:torchrl.envs.CatFrames,N:2,dim:-1,in_keys:[observation]}"),
]

NETWORKS = [
    Case("actor-elu", ("actor.activation=elu",), reaches=ACTOR_PARTS),
    Case("actor-relu", ("actor.activation=relu",), reaches=ACTOR_PARTS),
    Case("actor-layer-norm", networks=layer_norm_in_actor, reaches=ACTOR_PARTS),
    Case("actor-hidden-32", ("actor.hidden=[32]",), reaches=ACTOR_PARTS),
    Case("critic-hidden-64-32", ("td3.critic_hidden=[64,32]",), reaches=LOSS_PARTS),
    Case("critic-tanh", ("td3.critic_activation=tanh",), reaches=LOSS_PARTS),
]

# What the actor computes beside its layers' classes: hooks of every kind (the module's own, torch's
# global ones), parametrizations, random layers in training mode, buffers. The batched forward and
# the TD3 collector hand over where the actor computes more than its Linear layers, tanh and
# TanhModule; the ES physics plays the module in worker threads, so it hands over where the
# actor's forward is not a deterministic function of its observation. Backward hooks do not run
# in a forward without gradient: only the loss hands over, the forwards stay fast.
def handed_over(reason: str, physics: str = "fast") -> dict[str, str]:
    """The pieces of a row whose actor computes more than its layers: the forwards and the loss hand
    over with ``reason``; the ES physics plays the module in its worker threads, or hands over."""
    return {piece: f"reference ({reason})" for piece in ("es_forward", "td3_collector", "td3_loss")} | {"es_physics": physics}


ORDER = "and the worker threads play members in an order that differs from run to run"
RANDOM = f"reference (actor: its forward draws random numbers, {ORDER})"
STATEFUL = f"reference (actor: two calls on the same observation give different actions, {ORDER})"
PARAMETRIZED = "actor MLP: 0: a parametrization of its weight (torch.nn.utils.parametrize)"
BACKWARD_HANDED = {"es_forward": "fast", "td3_collector": "fast", "td3_loss": "reference (module hooks)", "es_physics": "fast"}
ACTOR_EXTRAS = [
    Case("actor-forward-hook", networks=actor_edit(lambda mlp: mlp.register_forward_hook(lambda m, args, out: out * 0.5)), reaches=ACTOR_PARTS,
         pieces=handed_over("a forward hook on module.0.module")),
    Case("actor-forward-pre-hook", networks=actor_edit(lambda mlp: mlp.register_forward_pre_hook(lambda m, args: (args[0] * 2,))), reaches=ACTOR_PARTS,
         pieces=handed_over("a forward pre hook on module.0.module")),
    Case("actor-backward-hook", networks=actor_edit(lambda mlp: mlp[2].register_full_backward_hook(masked_linear_input_gradient)), reaches=LOSS_PARTS, pieces=BACKWARD_HANDED),
    Case("actor-backward-pre-hook", networks=actor_edit(lambda mlp: mlp[2].register_full_backward_pre_hook(masked_linear_output_gradient)), reaches=LOSS_PARTS, pieces=BACKWARD_HANDED),
    Case("global-forward-hook", around=global_hook(torch.nn.modules.module.register_module_forward_hook, halved_linear_output), reaches=ACTOR_PARTS,
         pieces=handed_over("torch's global forward hooks")),
    Case("global-forward-pre-hook", around=global_hook(torch.nn.modules.module.register_module_forward_pre_hook, doubled_linear_input), reaches=ACTOR_PARTS,
         pieces=handed_over("torch's global forward pre hooks")),
    Case("global-backward-hook", around=global_hook(torch.nn.modules.module.register_module_full_backward_hook, masked_linear_input_gradient), reaches=LOSS_PARTS, pieces=BACKWARD_HANDED),
    # spectral_norm computes the weight in a forward pre-hook, and its power iteration updates its buffers at every call in training mode
    Case("actor-spectral-norm", networks=actor_edit(lambda mlp: torch.nn.utils.spectral_norm(mlp[0])), reaches=ACTOR_PARTS,
         pieces=handed_over("a forward pre hook on module.0.module.0", STATEFUL)),
    Case("actor-parametrize", networks=actor_edit(lambda mlp: torch.nn.utils.parametrize.register_parametrization(mlp[0], "weight", Halved())), reaches=ACTOR_PARTS,
         pieces=handed_over(PARAMETRIZED)),
    Case("actor-parametrizations-spectral-norm", networks=actor_edit(lambda mlp: torch.nn.utils.parametrizations.spectral_norm(mlp[0])), reaches=ACTOR_PARTS,
         pieces=handed_over(PARAMETRIZED, STATEFUL)),
    Case("actor-dropout", networks=actor_edit(dropout_after_first_activation), reaches=ACTOR_PARTS,
         pieces=handed_over("actor MLP: Dropout (the fast pieces compute Linear, Tanh, ReLU)", RANDOM)),
    Case("actor-rrelu", networks=actor_edit(rrelu_after_first_linear), reaches=ACTOR_PARTS,
         pieces=handed_over("actor MLP: RReLU (the fast pieces compute Linear, Tanh, ReLU)", RANDOM)),
    # no forward reads it: every piece computes the same
    Case("actor-buffer", networks=actor_edit(scale_buffer), reaches=(), pieces={piece: "fast" for piece in ("es_forward", "td3_collector", "td3_loss", "es_physics")}),
]

LOSSES = [
    Case("loss-l1", ("td3.loss_function=l1",), reaches=LOSS_PARTS),
    Case("loss-smooth-l1", ("td3.loss_function=smooth_l1",), reaches=LOSS_PARTS),
    Case("gamma", ("td3.gamma=0.5",), reaches=LOSS_PARTS),
    Case("policy-noise", ("td3.policy_noise=0.6",), reaches=LOSS_PARTS),
    Case("noise-clip", ("td3.noise_clip=0.05",), reaches=LOSS_PARTS),
    Case("tau", ("td3.tau=0.5",), reaches=LOSS_PARTS),
    Case("lr", ("td3.lr=0.01",), reaches=LOSS_PARTS),
    Case("loss-subclass-value-loss", td3=td3_built(loss=doubled_value_loss), reaches=LOSS_PARTS),
    Case("priority-weights", batch=priority_weights, reaches=LOSS_PARTS),
    # the losses under autocast to bfloat16: the hand-written ones compute in bfloat16 (not handed over),
    # equal to TD3Loss's under autocast to bfloat16 rounding
    Case("precision-bf16", ("td3.precision=bf16",), reaches=LOSS_PARTS, pieces={"td3_loss": "fast"}, tolerance={"td3_updates": (2e-2, 3e-3)}),
]

# TD3 trained through loss.backward(): other numbers of critics (the hand-written loss is for the
# twin pair: it hands over), and edits the hand-written gradients must take as autograd's do.
MANUAL_GRADIENTS = {"td3_loss": "fast"}
BACKWARD = [
    *(Case(f"num-qvalue-nets-{n}", td3=td3_built(num_qvalue_nets=n), reaches=LOSS_PARTS,
           pieces={"td3_loss": f"reference (num_qvalue_nets={n})"}) for n in (1, 3)),
    Case("backward-l2-term", td3=td3_built(L2PenaltyTD3), reaches=LOSS_PARTS, pieces=MANUAL_GRADIENTS),
    Case("backward-clip-grad-norm", td3=td3_built(ClippedTD3), reaches=LOSS_PARTS, pieces=MANUAL_GRADIENTS),
    Case("clip-in-step-pre-hook", td3=td3_edited(clip_in_step_pre_hooks), reaches=LOSS_PARTS, pieces={**MANUAL_GRADIENTS, "adam": "fast"}),
    Case("critic-gradient-hook", td3=td3_edited(scale_critic_gradient), reaches=LOSS_PARTS, pieces=MANUAL_GRADIENTS),
    Case("actor-post-accumulate-grad-hook", td3=td3_edited(zero_actor_gradient_rows), reaches=LOSS_PARTS, pieces=MANUAL_GRADIENTS),
    Case("actor-frozen-layer", td3=td3_edited(freeze_actor_layer), reaches=LOSS_PARTS, pieces=MANUAL_GRADIENTS),
    Case("critic-frozen-layer", td3=td3_edited(freeze_critic_layer), reaches=LOSS_PARTS, pieces=MANUAL_GRADIENTS),
]

CASES = [*BASE, *ENV_KWARGS, *WRAPPERS, *TRANSFORMS, *NETWORKS, *ACTOR_EXTRAS, *LOSSES, *BACKWARD]


# ---------------------------------------------------------------------------- running a row
def config(implementation: str, env: str, overrides=()):
    with initialize_config_dir(str(CONF), version_base=None):
        return compose("config", overrides=[*SMALL, f"env={env}", f"implementation={implementation}", *overrides])


@dataclass
class Played:
    """One implementation's run of a row: its outputs by part, what computed each piece, and what
    the updates and the other implementation's buffers need."""

    outputs: dict[str, dict[str, torch.Tensor]]
    pieces: dict[str, str]
    evaluation_forward: str
    td3: TD3
    generation: object
    frames: object
    sample: object
    episodes: dict  # part -> (Generation, members' flat parameters, reset seeds), for check_episodes
    spec: EnvSpec
    actor: nn.Module


def _transitions(td, keys) -> dict[str, torch.Tensor]:
    return {"/".join(k) if isinstance(k, tuple) else k: td.get(k).clone() for k in keys}


EPISODE_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "terminated"), ("next", "truncated"))


def play(case: Case, cfg, write=None) -> Played:
    """The row's run of ``cfg`` up to the updates. ``write``: the ES generation and TD3 frames the
    buffers are fed (the reference's, so that both implementations' buffers get the same items);
    None: this run's."""
    quiet_logs()
    torch.manual_seed(0)
    env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, env)
    if case.networks is not None:
        actor, critic = case.networks(actor, critic)
    torch.manual_seed(1)
    td3 = (case.td3 or make_td3)(cfg, actor, critic, env.action_spec)

    es, es_collector = make_es(cfg, actor), make_es_collector(cfg, actor)
    population = es.ask()
    generation = es_collector.evaluate(population, GENERATION_SEEDS, mirrored=es.mirrored(population))
    evaluator = make_evaluator(cfg, actor)
    vector = flat_parameters(actor)
    evaluation = evaluator.evaluate_policy(vector, 1, EVALUATION_SEEDS)
    torch.manual_seed(2)  # the exploration noise
    collector, batches = make_frame_batches(cfg, env, td3)
    frames = next(batches)

    buffer = make_multibuffer(cfg)
    fed_generation, fed_frames = write if write is not None else (generation, frames)
    good = fed_generation.returns >= fed_generation.returns.median()
    buffer.extend(fed_generation.transitions[fed_generation.member_mask(good)], "good")
    buffer.extend(fed_generation.transitions[fed_generation.member_mask(~good)], "bad")
    buffer.extend(fed_frames, "noisy")
    torch.manual_seed(3)
    sample = buffer.sample()

    pieces = implementations(cfg, td3=td3, td3_env=TD3EnvState(collector), buffer=buffer, es_collector=es_collector)
    evaluation_forward = implementations(cfg, es_collector=evaluator)["es_forward"]
    collector.shutdown()
    outputs = {
        "es_generation": {"returns": generation.returns, "lengths": generation.lengths, **_transitions(generation.transitions, EPISODE_KEYS)},
        "evaluation": {"returns": evaluation.returns, "lengths": evaluation.lengths, **_transitions(evaluation.transitions, EPISODE_KEYS)},
        "td3_frames": _transitions(frames, (*TRANSITION_KEYS, ("next", "episode_reward"))),
        "buffer": {"sizes": torch.tensor(list(buffer.sizes().values())), **_transitions(sample, (*TRANSITION_KEYS, buffer.source_key))},
    }
    episodes = {"es_generation": (generation, population, GENERATION_SEEDS), "evaluation": (evaluation, vector.unsqueeze(0), EVALUATION_SEEDS)}
    return Played(outputs, pieces, evaluation_forward, td3, generation, frames, sample, episodes, EnvSpec.from_config(cfg.env), copy.deepcopy(actor))


def train(td3: TD3, batch) -> dict[str, torch.Tensor]:
    """``UPDATES`` TD3 updates on ``batch`` (the same noise stream for both implementations): the
    losses, and every parameter of the loss after them (actor, critics, targets)."""
    torch.manual_seed(5)
    outs = [td3.update(batch.clone()) for _ in range(UPDATES)]
    losses = {key: torch.tensor([out[key] for out in outs if key in out], dtype=torch.float64) for key in ("critic_loss", "actor_loss")}
    params = TensorDict({
        name: getattr(td3.loss, name).detach().clone()
        for name in ("actor_network_params", "qvalue_network_params", "target_actor_network_params", "target_qvalue_network_params")
    }).flatten_keys("/")
    return {**losses, **dict(params.items())}


def run_row(case: Case, overrides, fast: bool = True) -> tuple[Played, Played | None]:
    """The reference's run of the row and, with ``fast``, the fast one's; both train on the batch the
    reference's buffer gave (through ``case.batch``). On one torch thread: the machine's cores are
    shared, and the small networks' products gain nothing from a second thread."""
    cfg = config("reference", case.env, overrides)
    with torch_threads(1):
        reference = play(case, cfg)
        batch = reference.sample.clone()
        if case.batch is not None:
            batch = case.batch(batch)
        reference.outputs["td3_updates"] = train(reference.td3, batch)
        if not fast:
            return reference, None
        cfg.implementation = "fast"  # the one key the two runs differ by
        played = play(case, cfg, write=(reference.generation, reference.frames))
        played.outputs["td3_updates"] = train(played.td3, batch)
    return reference, played


_UNCHANGED: dict[tuple, dict] = {}  # the reference's outputs of unchanged runs, by (env, given)


def unchanged(case: Case) -> dict:
    key = (case.env, case.given)
    if key not in _UNCHANGED:
        _UNCHANGED[key] = run_row(Case("unchanged", env=case.env), case.given, fast=False)[0].outputs
    return _UNCHANGED[key]


EXACT_DTYPES = (torch.bool, torch.int64, torch.int32)  # lengths, flags, buffer ids: equal whatever the piece


def compare(reference: dict, fast: dict, tolerance, part: str) -> float:
    """Assert ``fast`` equals ``reference``: bit for bit (``tolerance`` None) or within (rtol, atol).
    Returns the largest absolute difference of the floating-point outputs."""
    assert reference.keys() == fast.keys(), part
    largest = 0.0
    for key, expected in reference.items():
        got = fast[key]
        assert got.shape == expected.shape and got.dtype == expected.dtype, (part, key, got.shape, expected.shape)
        if tolerance is None or expected.dtype in EXACT_DTYPES:
            assert torch.equal(got, expected), f"{part}: {key} differs (max {(got.double() - expected.double()).abs().max().item():.3g}), bit for bit expected"
        else:
            torch.testing.assert_close(got, expected, rtol=tolerance[0], atol=tolerance[1], msg=lambda m, key=key: f"{part}: {key}: {m}")
        if expected.is_floating_point() and expected.numel():
            largest = max(largest, (got.double() - expected.double()).abs().max().item())
    return largest


def check_episodes(played: Played, part: str, actor, label: str) -> float:
    """The episodes of ``part`` in ``played``, step by step against the reference: every action is
    what the actor module computes with the member's parameters on the recorded observation (within
    ``FORWARD_ATOL``), and the reference env (gymnasium, or the TorchRL env where the spec has
    transforms), reset with the member's seed and stepped with the recorded actions, gives the
    recorded observations, rewards and flags bit for bit, and the return. Returns the largest action
    difference."""
    from torch.func import functional_call

    from torchrl_esrl.collectors.gym_backend import TorchRLMember
    from torchrl_esrl.modules.population import ModulePopulation

    generation, params, seeds = played.episodes[part]
    members = ModulePopulation(actor).split(params)
    transitions, largest = generation.transitions, 0.0
    ids = transitions.get(("collector", "traj_ids"))
    for p, seed in enumerate(seeds):
        rows = transitions[ids == p]
        n = rows.shape[0]
        assert n == int(generation.lengths[p]) > 0, (label, p)
        with torch.no_grad():
            expected = functional_call(actor, members[p], (TensorDict(observation=rows["observation"], batch_size=[n]),))["action"]
        torch.testing.assert_close(rows["action"], expected, rtol=0, atol=FORWARD_ATOL, msg=lambda m, p=p: f"{label}: member {p}'s actions are not the actor's: {m}")
        largest = max(largest, (rows["action"] - expected).abs().max().item())
        env = TorchRLMember(played.spec) if played.spec.transforms else played.spec.make_gym()
        observation = env.reset(seed=int(seed))[0]
        rewards = np.zeros(n)
        for t in range(n):
            assert np.array_equal(np.asarray(observation, dtype=np.float32), rows["observation"][t].numpy()), f"{label}: member {p}, step {t}: the observation is not the reference env's"
            observation, reward, terminated, truncated, _ = env.step(rows["action"][t].numpy())
            rewards[t] = reward
            step = rows[t]
            assert np.array_equal(np.asarray(observation, dtype=np.float32), step["next", "observation"].numpy()), f"{label}: member {p}, step {t}: the next observation is not the reference env's"
            assert np.float32(reward) == step["next", "reward"].item(), f"{label}: member {p}, step {t}: reward {step['next', 'reward'].item()} is not the reference env's {reward}"
            assert (terminated, truncated) == (step["next", "terminated"].item(), step["next", "truncated"].item()), f"{label}: member {p}, step {t}: the flags are not the reference env's"
        assert terminated or truncated, f"{label}: member {p}'s episode stops at {n} steps, the reference env's goes on"
        # float64 sums over the backend's padded episode arrays: equal up to the order of the additions
        assert generation.returns[p].item() == pytest.approx(rewards.sum(), rel=1e-12, abs=1e-12), f"{label}: member {p}'s return {generation.returns[p].item()} is not the sum of the reference env's rewards {rewards.sum()}"
    return largest


def differs(a: dict, b: dict) -> bool:
    return a.keys() != b.keys() or any(a[k].shape != b[k].shape or not torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------------- the tests
@pytest.mark.parametrize("case", CASES, ids=lambda case: case.id)
def test_fast_computes_what_the_reference_does_or_hands_over(case):
    with case.around() if case.around is not None else contextlib.nullcontext():
        reference = fast_against_reference(case)
    if not case.changed:
        return
    base = unchanged(case)
    untouched = [part for part in case.reaches if not differs(reference.outputs[part], base[part])]
    assert not untouched, f"{case.id}: the reference's {untouched} are those of the unchanged run: the change did not reach them"


def fast_against_reference(case: Case):
    """The row's two runs, part by part (see the module's docstring); the reference's run."""
    reference, fast = run_row(case, (*case.given, *case.overrides))
    assert set(reference.pieces.values()) == {"reference"} and reference.evaluation_forward == "reference"
    assert set(fast.pieces) == set(FAST_PIECES)
    assert {piece: fast.pieces[piece] for piece in case.pieces} == case.pieces, fast.pieces
    assert all(what == "fast" or what.startswith("reference (") for what in fast.pieces.values()), f"a hand-over without its reason: {fast.pieces}"
    largest = {}
    for part, pieces in PARTS.items():
        what = [fast.evaluation_forward] if part == "evaluation" else [fast.pieces[piece] for piece in pieces]
        label = f"{part} [{'; '.join(what)}]"
        if part in fast.episodes:  # the same members and seeds
            assert all(torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b for a, b in zip(fast.episodes[part][1:], reference.episodes[part][1:])), part
        if part in fast.episodes and what[0] == "fast":  # the population forward ran fast
            largest[part] = check_episodes(fast, part, reference.actor, label)
        else:  # every piece handed over, or only the physics is fast (bit for bit): the reference's episodes
            largest[part] = compare(reference.outputs[part], fast.outputs[part], (TOLERANCE | case.tolerance).get(part) if "fast" in what else None, label)
    print(f"{case.id}: {implementation_line(fast.pieces)}; evaluation es_forward {fast.evaluation_forward}; largest |fast - reference| {largest}")
    if not case.changed:
        _UNCHANGED.setdefault((case.env, case.given), reference.outputs)
        if not case.given:  # the registered tasks, as gymnasium defines them: every piece is fast
            assert set(fast.pieces.values()) == {"fast"} and fast.evaluation_forward == "fast", fast.pieces
    return reference


# Changes no run can take: a one-line ConfigError at start-up (EnvSpec.sizes(), the run's check).
REFUSED = [
    # VecNorm keeps running statistics that TD3's env, every ES member and every evaluation would each update apart.
    pytest.param("env.transforms=[{_target_:torchrl.envs.VecNorm,in_keys:[observation]}]", "env.transforms:", id="transform-VecNorm"),
    # ClipAction makes the action space unbounded: the tanh actor has no bounds to squash into.
    pytest.param("env.wrappers=[{_target_:gymnasium.wrappers.ClipAction}]", "env.wrappers:", id="wrapper-ClipAction"),
    # NormalizeObservation keeps running statistics across episodes, as VecNorm does.
    pytest.param("env.wrappers=[{_target_:gymnasium.wrappers.NormalizeObservation}]", "env.wrappers: NormalizeObservation", id="wrapper-NormalizeObservation"),
    # the time limit twice, with two values (env.max_episode_steps=50 in every row): neither would win silently
    pytest.param("++env.kwargs.max_episode_steps=37", "env.kwargs.max_episode_steps: 37 and env.max_episode_steps: 50", id="kwargs-max_episode_steps-twice"),
]


@pytest.mark.parametrize(("override", "field"), REFUSED)
def test_a_change_no_run_can_take_is_a_one_line_config_error(override, field):
    cfg = config("fast", "halfcheetah", (override,))
    with pytest.raises(ConfigError) as error:
        EnvSpec.from_config(cfg.env).sizes()
    message = str(error.value)
    assert "\n" not in message and message.startswith(field), message
