"""Gymnasium environments of the project (SPEC §6; docs/learned.md). Importing this package registers the ids:

- `hycontrol/Navigate-v0`: the default scene, the single integrator (action: the velocity in units of `u_max`,
  `Box(-1, 1, (2,))`, its norm clipped to 1: the velocity `u = u_max * action`, `|u| <= u_max`);
- `hycontrol/NavigateField-v0`: the seeded 5-disc field (`scene=field`);
- `hycontrol/NavigateUnicycle-v0`: the default scene, the unicycle (action `(v / u_max, ω / ω_max)`, each in [-1, 1]).

An agent that computes a velocity hands the env `env.unwrapped.core.action(u)` (`u / scale`, the scale of
:func:`pipeline.envs.core.action_scale`); the env maps it back (`core.velocity`).

`gymnasium.make(id, overrides=[...])` composes conf/env.yaml with the id's overrides and the caller's (the
caller's last); `make_vector(id, num_envs, overrides=[...])` gives the batched :class:`NavigateVectorEnv`.
"""

from __future__ import annotations

import gymnasium as gym

from pipeline.envs.core import OUTCOMES, EnvSettings, NavigationCore
from pipeline.envs.navigate import NavigateEnv, NavigateVectorEnv, compose_env, objects
from pipeline.errors import ConfigError

IDS = {
    "hycontrol/Navigate-v0": [],
    "hycontrol/NavigateField-v0": ["scene=field"],
    "hycontrol/NavigateUnicycle-v0": ["vehicle=unicycle"],
}

__all__ = ["IDS", "OUTCOMES", "EnvSettings", "NavigateEnv", "NavigateVectorEnv", "NavigationCore", "compose_env",
           "make_env", "make_vector", "objects"]


def make_env(base: list[str] | None = None, overrides: list[str] | None = None, render_mode: str | None = None):
    """The entry point of every id: the id's `base` overrides, then the caller's."""
    return NavigateEnv([*(base or []), *(overrides or [])], render_mode=render_mode)


def make_vector(env_id: str, num_envs: int, overrides: list[str] | None = None, render_mode: str | None = None,
                autoreset: bool = True) -> NavigateVectorEnv:
    """The batched environment of a registered id."""
    if env_id not in IDS:
        raise ConfigError("env_id", f"unknown id {env_id!r}; known: {', '.join(IDS)}")
    return NavigateVectorEnv(num_envs, [*IDS[env_id], *(overrides or [])], render_mode=render_mode,
                             autoreset=autoreset)


for _id, _base in IDS.items():
    if _id not in gym.registry:
        gym.register(_id, entry_point="pipeline.envs:make_env", kwargs={"base": _base},
                     disable_env_checker=False, order_enforce=True)
