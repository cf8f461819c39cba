"""The Gymnasium environments (SPEC §6): the API checker, the simulator's trajectories, the vector environment."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import pipeline.envs as envs
from pipeline.envs.policies import ArchitecturePolicy, RandomPolicy
from pipeline.errors import ConfigError
from pipeline.sim.metrics import Outcome


class CentroidMap:
    """The bright (robot) pixels' intensity centroid in world units: a deterministic stand-in perception map."""

    def __init__(self, camera):
        self.camera = camera

    def predict(self, images):
        g = np.clip(np.asarray(images, float).mean(-1) - 150.0, 0.0, None)
        h, w = g.shape[1:]
        tot = g.sum((1, 2)) + 1e-12
        u = (g.sum(1) * (np.arange(w) + 0.5)).sum(1) / tot
        v = (g.sum(2) * (np.arange(h) + 0.5)).sum(1) / tot
        return self.camera.pixel_to_world(np.stack([u, v], 1))


@pytest.mark.parametrize("env_id", list(envs.IDS))
def test_check_env_passes_for_every_id(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs) and info["outcome"] == "running"
    frame = env.render()  # the camera's image of the first agent (was `... if env.render_mode else True`: never checked)
    assert frame.dtype == np.uint8 and frame.shape == (*env.unwrapped.objects.camera.shape, 3)
    image = obs["image"] if isinstance(obs, dict) else obs
    np.testing.assert_array_equal(frame, image)


@pytest.mark.parametrize("env_id", list(envs.IDS))
def test_check_env_passes_with_warnings_as_errors_on_the_normalised_action(env_id):
    """Issue 46: the action space is `[-1, 1]` per component (the velocity in units of `u_max`, the unicycle's
    `(v / u_max, ω / ω_max)`), so neither Gymnasium's nor SB3's checker warns (it recommended a normalised space)."""
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped, warn=True)
    assert env.action_space.shape == (2,)
    np.testing.assert_array_equal(env.action_space.low, -1.0)
    np.testing.assert_array_equal(env.action_space.high, 1.0)
    venv = envs.make_vector(env_id, 2)
    np.testing.assert_array_equal(venv.single_action_space.high, 1.0)


def _old_velocity_step(o, c, u, every):
    """The state after one frame under the velocity `u` as the env took it before issue 46 (the norm clipped to
    `u_max`; the unicycle's `v` to `u_max`, `ω` to `ω_max`), integrated by the plant itself in `every` steps."""
    u_max = o.controller.u_max
    if o.plant.heading:
        u = np.array([np.clip(u[0], -u_max, u_max), np.clip(u[1], -o.plant.omega_max, o.plant.omega_max)])
    else:
        u = u * min(1.0, u_max / np.hypot(*u))
    c = np.array(c, float)[None]
    for _ in range(every):
        c = o.plant.step(c, u[None], o.sim.dt)
    return c[0]


@pytest.mark.parametrize("env_id", list(envs.IDS))
def test_a_normalised_action_moves_the_vehicle_exactly_as_its_velocity_did(env_id):
    """`u / scale` (scale `u_max`, the unicycle's `(u_max, ω_max)`) moves the vehicle exactly as the velocity `u`
    did: inside the limits, and past them (the action's norm clipped to 1 is the velocity's clipped to `u_max`)."""
    env = gym.make(env_id)
    o, core = env.unwrapped.objects, env.unwrapped.core
    u_max = o.controller.u_max
    scale = np.array([u_max, o.plant.omega_max if o.plant.heading else u_max])
    for u in ([3.0, -4.0], [7.5, 2.0], [-6.0, 1.5], [20.0, 15.0], [-15.0, -30.0]):
        u = np.array(u)
        assert np.array_equal(u / scale * scale, u)  # the test's velocities survive the round trip bit for bit
        _, info = env.reset(seed=0, options={"start": [-40.0, 20.0], "heading": 0.3})
        c0 = info["state"]
        _, _, term, trunc, info = env.step((u / scale).astype(np.float64))
        assert not (term or trunc)
        np.testing.assert_array_equal(info["state"], _old_velocity_step(o, c0, u, core.every))
        np.testing.assert_array_equal(core.action(u), u / scale)  # the inverse, for agents that compute velocities
    np.testing.assert_array_equal(core.scale, scale)


def test_unicycle_observes_its_heading_when_asked():
    env = gym.make("hycontrol/NavigateUnicycle-v0", overrides=["env.observe_heading=true"])
    check_env(env.unwrapped)
    obs, info = env.reset(seed=0)
    th = info["state"][2]
    np.testing.assert_allclose(obs["heading"], [np.cos(th), np.sin(th)], atol=1e-6)


@pytest.mark.parametrize("overrides, field", [(["occlusion=foo"], "occlusion"), (["env.progres=1"], "env.progres"),
                                              (["env.arrival=-1"], "env.arrival"),
                                              (["camera.period=0.013"], "camera.period"),
                                              (["controller.u_max=null"], "controller.u_max")])
def test_bad_override_is_one_line_naming_the_field(overrides, field):
    with pytest.raises(ConfigError) as err:
        gym.make("hycontrol/Navigate-v0", overrides=overrides)
    assert err.value.field == field and "\n" not in str(err.value)


@pytest.mark.parametrize("scene", ["default", "field"])
def test_trajectories_equal_the_simulators_for_the_same_policy(scene):
    """The paper's architecture (a map + the hybrid law) through the vector environment and through
    `pipeline.sim.simulate` with the camera in the loop: the same positions at every frame, the same outcome."""
    from pipeline.perception.measure import CameraMeasure
    from pipeline.sim import CameraSettings, SimSettings, simulate

    venv = envs.make_vector("hycontrol/Navigate-v0", 6, overrides=[f"scene={scene}"], autoreset=False)
    o = venv.objects
    pm = CentroidMap(o.camera)
    starts = np.array([[-12.0, 2.0], [-37.0, -17.0], [-40.0, 20.0], [10.0, -20.0], [-20.0, 0.3], [30.0, 25.0]])
    res = simulate(o.scene, o.controller, starts, sim=SimSettings(dt=o.sim.dt, horizon=o.sim.horizon, record_every=5),
                   camera=CameraSettings(period=o.camera_settings.period), measure=CameraMeasure(o.camera, pm), seed=0)
    policy = ArchitecturePolicy(pm, o.controller, o.plant, o.scene, venv.core.period)
    obs, _ = venv.reset(seed=0, options={"start": starts})
    p, code = [venv.core.position().copy()], np.zeros(len(starts), dtype=int)
    ended = np.zeros(len(starts), dtype=bool)
    for _ in range(venv.core.frames):
        obs, r, term, trunc, info = venv.step(policy.act(obs))
        code[(term | trunc) & ~ended] = info["outcome"][(term | trunc) & ~ended]
        ended |= term | trunc
        p.append(venv.core.position().copy())
        if ended.all():
            break
    p = np.array(p)
    assert (code == Outcome.REACHED).sum() >= 5
    np.testing.assert_array_equal(code == Outcome.REACHED, res.metrics["success"])
    np.testing.assert_array_equal(code == Outcome.COLLIDED, res.metrics["collision"])
    t_env = np.argmax((p[:, :, 0] - 40.0) ** 2 + p[:, :, 1] ** 2 <= 1.0, axis=0)  # frames to arrival
    for a in np.flatnonzero(code == Outcome.REACHED):
        k = t_env[a]  # every frame up to the arrival frame is the simulator's (one frame engine), to rounding
        np.testing.assert_allclose(p[:k + 1, a], res.p[:k + 1, a], atol=1e-9)
        assert abs(k * venv.core.period - res.metrics["time_to_target"][a]) < venv.core.period


def test_random_agent_and_the_hybrid_policy_through_gymnasium_make():
    env = gym.make("hycontrol/Navigate-v0")
    rand = RandomPolicy(env.action_space, seed=0)
    obs, _ = env.reset(seed=1)
    total, n = 0.0, 0
    while True:
        obs, r, term, trunc, info = env.step(rand.act(obs[None])[0])
        total, n = total + r, n + 1
        if term or trunc:
            break
    assert info["outcome"] in ("reached", "collided", "left_view", "timed_out") and np.isfinite(total)
    o = env.unwrapped.objects
    policy = ArchitecturePolicy(CentroidMap(o.camera), o.controller, o.plant, o.scene, env.unwrapped.core.period)
    obs, info = env.reset(seed=1, options={"start": [-12.0, 2.0]})
    d0, total = info["distance"], 0.0
    while True:
        obs, r, term, trunc, info = env.step(policy.act(obs[None])[0])
        total += r
        if term or trunc:
            break
    assert info["outcome"] == "reached" and info["is_success"]
    # the shaped reward: progress telescopes to the distance gained, plus the arrival bonus
    assert total == pytest.approx(d0 - info["distance"] + o.settings.arrival)


def test_vector_env_autoresets_and_reports_the_final_state():
    venv = envs.make_vector("hycontrol/Navigate-v0", 4)
    obs, info = venv.reset(seed=0, options={"start": [[39.5, 0.0], [-40.0, 0.0], [0.0, 4.3], [-49.8, 0.0]]})
    obs, r, term, trunc, info = venv.step(np.array([[1.0, 0.0], [0.0, 0.0], [0.0, -1.0], [-1.0, 0.0]]))  # ±u_max
    assert term.tolist() == [True, False, True, True]
    assert info["outcome"].tolist() == [1, 0, 2, 3]
    assert info["_final_obs"].tolist() == [True, False, True, True]
    assert np.hypot(*(info["final_state"][0] - [40.0, 0.0])) <= 1.0
    assert r[0] > 0 and r[2] < -5 and r[3] < -5
    assert not np.allclose(info["state"][0], info["final_state"][0])  # restarted elsewhere
