"""The TD3 side's collector (paper, Algorithm 1 "act with exploration noise"): a TorchRL
``Collector`` over the training env, acting with the exploration policy."""
from __future__ import annotations

import numpy as np
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector


def make_td3_collector(env, td3, frames_per_batch: int = 1, device="cpu") -> Collector:
    """TorchRL collector acting with the exploration policy; runs for as long as it is iterated.
    The env steps on its own device (CPU physics), the policy and the collected data are on ``device``."""
    return Collector(
        env,
        td3.exploration_policy,
        frames_per_batch=int(frames_per_batch),
        total_frames=-1,
        auto_register_policy_transforms=False,
        env_device=env.device,
        policy_device=device,
        storing_device=device,
    )


def finished_episode_returns(batch: TensorDictBase) -> list[float]:
    """Returns of the episodes that ended inside a collected batch (from TorchRL's ``RewardSum``)."""
    done = batch.get(("next", "done")).reshape(-1)
    if not done.any():
        return []
    return batch.get(("next", "episode_reward")).reshape(-1)[done].tolist()


# ---------------------------------------------- the TD3 env mid-episode, for checkpoints
_SCALARS = (bool, int, float, str, type(None))


def _gym_layers(gym_env):
    layers = [gym_env]
    while hasattr(layers[-1], "env"):
        layers.append(layers[-1].env)
    return layers


def gym_env_state(gym_env) -> dict:
    """A gymnasium env's state mid-episode: each wrapper's scalar attributes (``TimeLimit``'s
    elapsed steps, ``OrderEnforcing``'s reset flag...), the core env's ``np_random`` and arrays,
    and for MuJoCo envs the full integration state from ``mj_getState``."""
    layers = _gym_layers(gym_env)
    core = layers[-1]
    state = {
        "wrappers": [{k: v for k, v in vars(w).items() if isinstance(v, _SCALARS) and k != "_saved_kwargs"} for w in layers[:-1]],
        "core": {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in vars(core).items() if isinstance(v, (np.ndarray, *_SCALARS)) and not k.startswith("_ezpickle")},
        "np_random": core.np_random.bit_generator.state,
    }
    if hasattr(core, "model") and hasattr(core, "data"):
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        physics = np.empty(mujoco.mj_stateSize(core.model, spec))
        mujoco.mj_getState(core.model, core.data, physics, spec)
        state["mujoco"] = physics
    return state


def load_gym_env_state(gym_env, state: dict) -> None:
    layers = _gym_layers(gym_env)
    for layer, attributes in zip(layers[:-1], state["wrappers"]):
        vars(layer).update(attributes)
    core = layers[-1]
    vars(core).update(state["core"])
    core.np_random.bit_generator.state = state["np_random"]
    if "mujoco" in state:
        import mujoco

        mujoco.mj_setState(core.model, core.data, np.asarray(state["mujoco"], dtype=np.float64), mujoco.mjtState.mjSTATE_INTEGRATION)


class TD3EnvState:
    """The TD3 side's environment, as iterated by a TorchRL ``Collector`` across phases.

    TorchRL's ``Collector.state_dict`` covers its counters and the transforms' buffers but not
    the carried tensordict nor the simulator, so both are saved here as well.
    """

    def __init__(self, collector):
        self.collector = collector

    def _gym_env(self):
        env = self.collector.env
        while not hasattr(env, "_env"):
            env = env.base_env
        return env._env

    def state_dict(self) -> dict:
        collector_state = {k: v for k, v in self.collector.state_dict().items() if k != "policy_state_dict"}  # policy: saved with TD3
        return {
            "collector": collector_state,
            "carrier": self.collector._carrier.to_dict(),
            "gym": gym_env_state(self._gym_env()),
        }

    def load_state_dict(self, state: dict) -> None:
        collector = self.collector
        collector.env.transform.load_state_dict(state["collector"]["env_state_dict"])
        collector._frames, collector._iter = int(state["collector"]["frames"]), int(state["collector"]["iter"])
        if "traj_pool" in state["collector"]:
            collector._traj_pool.load_state_dict(state["collector"]["traj_pool"])
        collector._carrier = TensorDict(state["carrier"], batch_size=collector._carrier.batch_size)
        load_gym_env_state(self._gym_env(), state["gym"])
