"""Reinforcement learning baseline (SPEC §6): stable-baselines3 PPO with a CNN policy on the batched vector
environment (`python -m pipeline.learned.ppo`; docs/learned.md states the budget).

:class:`SB3VecEnv` adapts :class:`pipeline.envs.NavigateVectorEnv` (N agents in one batched plant and render call,
same-step autoreset) to SB3's `VecEnv` interface (a list of per-agent infos, `terminal_observation` in the info of
an agent that stopped, `TimeLimit.truncated` on the horizon); its action space is the env's, `[-1, 1]` per
component (the velocity in units of `u_max`, issue 46). The trained model is written to
`outputs/models/ppo-<id>/` (id: this config and the code, :func:`pipeline.lineage.ppo_identity`), with the
learning curve (`curve.csv`: mean episode return and success per rollout).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import VecEnv

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.envs.navigate import NavigateVectorEnv, objects_from
from pipeline.lineage import ppo_folder, ppo_identity
from pipeline.preflight import prepared


class SB3VecEnv(VecEnv):
    """SB3's VecEnv over one batched :class:`NavigateVectorEnv` (autoreset on)."""

    def __init__(self, venv: NavigateVectorEnv):
        self.venv = venv
        self.render_mode = None
        self._actions = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def reset(self):
        seed = self._seeds[0]
        obs, _ = self.venv.reset(seed=seed)
        self._reset_seeds()
        return obs

    def step_async(self, actions):
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, reward, term, trunc, info = self.venv.step(self._actions)
        done = term | trunc
        infos = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(done):
            infos[i] = {"terminal_observation": info["final_obs"][i], "TimeLimit.truncated": bool(trunc[i]),
                        "is_success": bool(info["outcome"][i] == 1)}
        return obs, reward.astype(np.float32), done, infos

    def close(self):
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self, attr_name, None)] * len(self._indices(indices))

    def set_attr(self, attr_name, value, indices=None):
        setattr(self, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        raise NotImplementedError("SB3VecEnv: the agents are one batched environment")

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._indices(indices))

    def _indices(self, indices):
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else indices


def check(cfg: DictConfig):
    """Preflight: the environment's objects and the settings, built once (the run uses them)."""
    return objects_from(cfg), build(cfg.ppo, "ppo")


def run(cfg: DictConfig) -> dict:
    obj, s = prepared(cfg, check)  # the preflight's, when it checked this job
    if s.threads is not None:
        torch.set_num_threads(s.threads)
    id_ = ppo_identity(cfg)
    final = Path(cfg.paths.models_dir) / f"ppo-{id_}"
    if tracking.is_complete(final) and not cfg.get("force", False):  # built: not trained again
        print(f"ppo: up to date -> {final}")
        return {"path": final, "success": tracking.read_manifest(final).get("success_last_200"),
                "wall_s": 0.0}
    env = SB3VecEnv(NavigateVectorEnv(s.num_envs, objects_=obj))
    curve = []

    class Curve(BaseCallback):
        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                if "is_success" in info:
                    curve.append((self.num_timesteps, float(info["is_success"])))
            return True

    model = PPO("CnnPolicy", env, n_steps=s.n_steps, batch_size=s.batch_size, n_epochs=s.n_epochs,
                learning_rate=s.learning_rate, seed=s.seed, verbose=0, device="cpu")
    # no log files: without a logger of its own, `learn` makes an empty tempdir/SB3-<date> folder per run
    model.set_logger(Logger(folder=None, output_formats=[]))
    t0 = time.perf_counter()
    model.learn(total_timesteps=s.total_timesteps, callback=Curve())
    wall = time.perf_counter() - t0
    done = np.array(curve) if curve else np.zeros((0, 2))
    rate = float(done[-min(len(done), 200):, 1].mean()) if len(done) else float("nan")
    meta = {"kind": "ppo", "config": tracking.to_plain(cfg.ppo), "wall_s": wall, "episodes": len(done),
            "success_last_200": rate}
    with tracking.tracked_output(final.parent, "ppo", id_, meta) as tmp:
        model.save(tmp / "model.zip")
        np.savetxt(tmp / "curve.csv", done, delimiter=",", header="timesteps,success", comments="")
    print(f"ppo: {s.total_timesteps} agent-steps in {wall:.0f} s, {len(done)} episodes, success of the last 200 "
          f"{rate:.1%} -> {final}")
    return {"path": final, "success": rate, "wall_s": wall}


class PPONet(torch.nn.Module):
    """`net(float NHWC frames in [0, 255]) -> (N, 2)`: the velocity (world units) of a stable-baselines3 PPO
    `CnnPolicy`'s mean action (its frames channel-first, scaled by the policy itself), the mean clipped to the
    model's action space as SB3 clips its actions; :meth:`action` is that clipped mean as the env's normalised
    action. The env's action space is `[-1, 1]` (issue 46): the velocity is the action times `scale` (the env's,
    `env.core.scale`). A model trained before (on the velocity, `Box(-u_max, u_max)`) acts in velocities: its
    action is its clipped mean over `scale`, so its trajectories are the ones it had."""

    def __init__(self, policy, scale):
        super().__init__()
        space = policy.action_space
        self.policy, self.in_velocity = policy, not np.allclose(space.high, 1.0)
        self.register_buffer("low", torch.as_tensor(space.low, dtype=torch.float32), persistent=False)
        self.register_buffer("high", torch.as_tensor(space.high, dtype=torch.float32), persistent=False)
        self.register_buffer("scale", torch.as_tensor(np.asarray(scale, float), dtype=torch.float32),
                             persistent=False)

    def mean(self, x):
        """The policy's mean action clipped to its action space (SB3's deterministic action)."""
        obs = x.permute(0, 3, 1, 2)
        features = self.policy.extract_features(obs, self.policy.pi_features_extractor)
        mean = self.policy.action_net(self.policy.mlp_extractor.forward_actor(features))
        return mean.clamp(self.low, self.high)

    def action(self, x):
        m = self.mean(x)
        return m / self.scale if self.in_velocity else m

    def forward(self, x):
        m = self.mean(x)
        return m if self.in_velocity else m * self.scale


class PPOPolicy:
    """The end-to-end policy PPO learned (`python -m pipeline.learned.ppo`): its deterministic (mean) action, in
    the env whose unit action is the velocity `scale` (`env.core.scale`)."""

    name = "ppo"

    def __init__(self, model, scale):
        self.net = PPONet(model.policy, scale).eval()

    def reset(self, obs, idx=None) -> None:
        pass

    @torch.no_grad()
    def act(self, obs, restarted=None) -> np.ndarray:
        """The env's normalised action (SB3's `predict(obs, deterministic=True)`)."""
        return self.net.action(torch.from_numpy(np.ascontiguousarray(obs)).float()).double().numpy()

    @torch.no_grad()
    def velocity(self, obs) -> np.ndarray:
        """That action's velocity in world units (what the worst cloud pushes along `d`)."""
        return self.net(torch.from_numpy(np.ascontiguousarray(obs)).float()).double().numpy()


def load_ppo(ref, models_dir, field: str = "policies.ppo"):
    """The PPO model :func:`ppo_folder` finds."""
    folder = ppo_folder(ref, models_dir, field)
    model = PPO.load(folder / "model.zip", device="cpu")
    model.tracked_name = folder.name
    return model

main = stage_main("ppo", run="pipeline.learned.ppo:run", check="pipeline.learned.ppo:check")

if __name__ == "__main__":
    main()
