"""Learned policies (SPEC §6): the expert's labels, the imitation stage, one evaluation code for every agent."""

import subprocess
import sys

import numpy as np
import pytest
import torch
from shared import run_cli  # tests/shared.py

import pipeline.envs as envs
from pipeline.learned.expert import Expert, mode_flows
from pipeline.learned.network import HEADS, VelocityPolicy
from pipeline.learned.policies import ImitatedPolicy, LearnedHybridPolicy
from pipeline.learned.rollouts import HeadNet, PolicyAttack, run_policy
from pipeline.perception.adversary import proposition1_direction
from pipeline.sim.metrics import Outcome
from tests.test_envs import CentroidMap


def test_expert_rolled_out_in_the_env_is_the_simulators_hybrid_controller_on_the_true_state():
    """The expert's action (head 0) carries its mode along its own trajectory: rolled out in the environment it
    is the simulator's hybrid controller on the true state, frame for frame."""
    from pipeline.sim import CameraSettings, SimSettings, simulate

    venv = envs.make_vector("hycontrol/Navigate-v0", 4, autoreset=False)
    o = venv.objects
    starts = np.array([[-12.0, 2.0], [-30.0, -0.2], [-20.0, 0.1], [10.0, 20.0]])
    res = simulate(o.scene, o.controller, starts, sim=SimSettings(dt=o.sim.dt, horizon=o.sim.horizon, record_every=5),
                   camera=CameraSettings(period=o.camera_settings.period))
    expert = Expert(o.controller, o.plant, o.scene, venv.core.period)
    _, info = venv.reset(seed=0, options={"start": starts})
    p = [info["position"].copy()]
    for _ in range(60):
        labels, mask = expert.labels(info["state"])
        assert labels.shape == (4, HEADS, 2) and mask[:, 0].all()
        _, _, term, trunc, info = venv.step(venv.core.action(labels[:, 0]))
        p.append(info["position"].copy())
    p = np.array(p)
    k = min(len(p), len(res.p))
    live = ~np.isnan(res.metrics["time_to_target"]) & (res.metrics["time_to_target"] > k * 0.05)
    np.testing.assert_allclose(p[:k, live], res.p[:k, live], atol=1e-9)
    np.testing.assert_allclose(p[:k, ~live][:5], res.p[:k, ~live][:5], atol=1e-9)


class _Recorder:
    """The vector env, recording the actions it is handed and the true states it reaches."""

    def __init__(self, venv):
        self.venv, self.actions, self.states = venv, [], []

    def __getattr__(self, name):
        return getattr(self.venv, name)

    def reset(self, **kw):
        obs, info = self.venv.reset(**kw)
        self.states.append(info["state"].copy())
        return obs, info

    def step(self, actions):
        self.actions.append(np.array(actions, dtype=float))
        out = self.venv.step(actions)
        self.states.append(out[4]["state"].copy())
        return out


def _integrate(o, c, u, every):
    """`every` steps of the plant under the velocity `u`, its norm clipped to `u_max` (the env's saturation)."""
    u = u * np.minimum(1.0, o.controller.u_max / np.maximum(np.hypot(*u.T), 1e-300))[:, None]
    for _ in range(every):
        c = o.plant.step(c, u, o.sim.dt)
    return c


def test_the_expert_hands_the_env_its_velocity_over_u_max_and_keeps_the_controllers_trajectory():
    """Issue 46: the imitation's rollout (round 0: the expert acts) hands the env the expert's velocity over `u_max`
    (the normalised action), and the trajectory is the one the controller's velocity gives, integrated by the plant
    without the env, on a fixed seed; its labels are that velocity in world units."""
    from pipeline.learned.imitate import rollout

    starts = [[-12.0, 2.0], [-30.0, -0.2], [-20.0, 0.1], [-40.0, 20.0]]
    venv = envs.make_vector("hycontrol/Navigate-v0", 4, autoreset=False,
                            overrides=["init=points", f"init.points={starts}".replace(" ", "")])
    o, frames = venv.objects, 25
    rec = _Recorder(venv)
    expert = Expert(o.controller, o.plant, o.scene, venv.core.period)  # its scale: the env's controller's u_max
    _, labels, _, outcome = rollout(rec, expert, None, seed=3, max_frames=frames, record_every=1)
    assert (outcome == Outcome.TIMED_OUT).all() and len(rec.actions) == frames  # nobody stopped: every frame recorded
    labels = labels.reshape(frames, 4, HEADS, 2)
    actions = np.array(rec.actions)
    np.testing.assert_array_equal(actions, labels[:, :, 0] / o.controller.u_max)
    assert np.abs(actions).max() <= 1.0 and np.hypot(*actions.reshape(-1, 2).T).max() > 0.99  # saturated: |a| = 1
    reference = Expert(o.controller, o.plant, o.scene, venv.core.period)  # the controller, no env
    c = np.array(starts)
    np.testing.assert_array_equal(rec.states[0], c)
    for k in range(frames):
        u = reference.labels(c)[0][:, 0]
        np.testing.assert_allclose(labels[k, :, 0], u, rtol=0, atol=1e-9)
        c = _integrate(o, c, u, venv.core.every)
        np.testing.assert_allclose(rec.states[k + 1], c, rtol=0, atol=1e-9)


def test_the_imitated_policy_through_the_evaluation_follows_its_networks_velocity():
    """The imitated policy (a fixed-seed tiny network) through the evaluation's code: its action is the network's
    velocity over `u_max`, and the paths are the ones the network's velocity on the frames of the path gives,
    integrated by the plant without the env."""
    o = envs.objects()
    model = _tiny_model(5).eval()
    policy = ImitatedPolicy(model, np.full(2, o.controller.u_max))  # the env's scale
    starts, frames = np.array([[-40.0, 20.0], [-40.0, -20.0], [10.0, -20.0]]), 12
    res = run_policy(o, policy, starts, frames=frames)
    p, every = starts.copy(), round(o.camera_settings.period / o.sim.dt)
    for k in range(frames):
        images = o.camera.render(p)
        u = model.act(torch.from_numpy(images), 0).double().numpy()
        np.testing.assert_allclose(policy.act(images) * o.controller.u_max, u, rtol=0, atol=1e-12)
        p = _integrate(o, p, u, every)
        np.testing.assert_allclose(res["paths"][k + 1], p, rtol=0, atol=1e-9)
    assert np.abs(res["paths"][-1] - starts).max() > 0.1  # it moved


def test_a_ppo_model_of_the_velocity_action_space_acts_as_it_did(tmp_path):
    """A PPO model trained before issue 46 (action space `Box(-u_max, u_max)`: its actions are velocities) hands the
    env its clipped mean over `u_max`, so the velocity is the one it had; the attack's net gives that velocity."""
    from gymnasium import spaces
    from stable_baselines3 import PPO

    from pipeline.learned.ppo import PPOPolicy, SB3VecEnv

    env = SB3VecEnv(envs.make_vector("hycontrol/Navigate-v0", 2))
    env.action_space = spaces.Box(-10.0, 10.0, (2,), dtype=np.float32)  # the old env's
    model = PPO("CnnPolicy", env, n_steps=8, batch_size=16, n_epochs=1, seed=0, device="cpu")
    with torch.no_grad():
        model.policy.action_net.bias.copy_(torch.tensor([30.0, -0.5]))
    obs = env.reset()
    old = model.predict(obs, deterministic=True)[0]  # its velocity, clipped to ±10 as SB3 clips
    agent = PPOPolicy(model, scale=[10.0, 10.0])
    np.testing.assert_allclose(agent.act(obs), old / 10.0, atol=1e-6)
    assert np.all(agent.act(obs)[:, 0] == 1.0)
    np.testing.assert_allclose(agent.velocity(obs), old, atol=1e-5)


def test_each_modes_flow_passes_the_obstacle_on_its_own_side():
    """Just behind the obstacle, on the line b = 0: mode 1 steers below it (b < 0), mode 2 above; both are in their
    flow sets there; far from the obstacle the two flows agree."""
    o = envs.objects()
    a = np.linspace(-18.0, -12.0, 6)
    p = o.scene.covering(0).from_frame(a, np.zeros_like(a))
    flows, inside = mode_flows(o.controller, p, np.zeros(len(p), dtype=np.int64), 0.05)
    eb = np.asarray(o.scene.e_b)
    assert inside.all()
    across = flows @ eb  # (N, 2): the velocity across the axis in each mode
    assert np.all(across[:, 0] <= 0) and np.all(across[:, 1] >= 0)
    assert across[-1, 0] < -1.0 and across[-1, 1] > 1.0  # next to the diamond: each mode turns to its side
    far, inside = mode_flows(o.controller, np.array([[-45.0, 25.0]]), np.zeros(1, dtype=np.int64), 0.05)
    np.testing.assert_allclose(far[:, 0], far[:, 1])


def _tiny_model(seed=0):
    torch.manual_seed(seed)
    return VelocityPolicy.of(filters=(4, 8, 8), hidden=8, u_max=10.0)


def test_policy_network_masks_the_loss_of_heads_without_labels():
    model = _tiny_model().eval()  # no dropout: the same outputs each call
    images = torch.randint(0, 255, (5, 60, 100, 3), dtype=torch.uint8)
    labels = torch.randn(5, HEADS, 2)
    mask = torch.ones(5, HEADS, dtype=torch.bool)
    mask[:, 2] = False
    base = model.loss((images, labels, mask))
    labels2 = labels.clone()
    labels2[:, 2] += 100.0  # a masked head's label does not count
    assert torch.allclose(model.loss((images, labels2, mask)), base)
    labels2[:, 1] += 100.0
    assert model.loss((images, labels2, mask)) > base + 1.0


def test_attack_on_the_imitated_policy_pushes_its_velocity_across_the_axis():
    """PGD on the policy's own network at κ: its velocity moves along d = -sign(b) e_b on every frame."""
    o = envs.objects()
    model = _tiny_model(3)
    a = np.linspace(-30.0, -15.0, 8)
    p = o.scene.covering(0).from_frame(a, np.tile([0.3, -0.3], 4))
    images = o.camera.render(p)
    att = PolicyAttack(HeadNet(model, 0), proposition1_direction(o.scene), kappa=4.0, steps=3)
    out = att(images, p, np.ones(len(p), dtype=bool))
    assert np.abs(out.astype(int) - images.astype(int)).max() <= 4
    along, norm = att.summary()
    assert along > 0 and norm >= along


def test_one_evaluation_code_runs_the_architecture_and_the_learned_policies():
    """From starts near K: the map + hybrid reaches; a (random-weight) imitated and learned hybrid policy run
    through the same code; outcomes are classes of the documented set."""
    o = envs.objects()
    from pipeline.envs.policies import ArchitecturePolicy

    pm = CentroidMap(o.camera)
    near = o.scene.covering(0).from_frame(np.array([-20.0, -30.0]), np.array([0.2, -0.2]))
    hybrid = ArchitecturePolicy(pm, o.controller, o.plant, o.scene, 0.05)
    res = run_policy(o, hybrid, near, frames=200)
    assert (res["outcome"] == "reached").all() and np.all(res["time"] > 0)
    model = _tiny_model()
    for policy in (ImitatedPolicy(model, o.scale), LearnedHybridPolicy(model, pm, o.controller, o.plant, o.scene, 0.05)):
        res = run_policy(o, policy, near, frames=30)
        assert set(res["outcome"]) <= {"reached", "collided", "left_view", "stalled", "timed_out"}


def test_imitation_stage_writes_a_tracked_policy_that_reloads(tmp_path):
    from pipeline.cli import compose
    from pipeline.learned.comparison import load_policy_model
    from pipeline.learned.imitate import run

    cfg = compose("imitate", ["imitation.agents=4", "imitation.rounds=1", "imitation.epochs=1",
                              "imitation.round_epochs=1", "imitation.max_frames=6", "model.filters=[4,8,8]",
                              "model.hidden=8", "imitation.trunk_from=null", "model.freeze_trunk=false",
                              f"paths.models_dir={tmp_path}", f"paths.output_dir={tmp_path}"])
    out = run(cfg)
    assert out["path"].name == f"imitation-{out['id']}" and len(out["rounds"]) == 2
    assert out["rounds"][1]["frames"] > out["rounds"][0]["frames"]
    model = load_policy_model(out["id"], tmp_path)
    images = torch.randint(0, 255, (3, 60, 100, 3), dtype=torch.uint8)
    assert model.act(images).shape == (3, 2)
    assert run(cfg)["path"] == out["path"]  # up to date: same id, nothing retrained


@pytest.mark.parametrize("module, arg, field", [("pipeline.learned.imitate", "imitation.agents=0", "imitation.agents"),
                                                ("pipeline.learned.imitate", "imitation.foo=1", "imitation.foo"),
                                                ("pipeline.learned.evaluate", "learned.kappas=[-1]", "learned.kappas"),
                                                ("pipeline.learned.evaluate", "learned.agents_list=[dqn]",
                                                 "learned.agents_list"),
                                                ("pipeline.learned.evaluate", "learned.candidates=0", "learned.candidates"),
                                                ("pipeline.learned.evaluate", "learned.cloud_attack_list=[dqn]",
                                                 "learned.cloud_attack_list"),
                                                ("pipeline.learned.evaluate", "clouds=fog", "clouds"),
                                                ("pipeline.learned.evaluate", "vehicle=unicycle", "vehicle"),
                                                ("pipeline.learned.imitate", "model.reads=pixels", "model.reads"),
                                                ("pipeline.paper", "learned=[bogus]", "learned"),
                                                ("pipeline.paper", "learned=[imitate_nope]", "learned")])
def test_bad_keys_are_one_line_and_exit_2(module, arg, field):
    if arg in ("imitation.agents=0", "learned.kappas=[-1]"):  # each stage's first case in a fresh interpreter
        out = subprocess.run([sys.executable, "-m", module, arg], capture_output=True, text=True, timeout=120)
    else:  # the same entry in this process (tests/shared.py)
        out = run_cli(module, arg)
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and field in lines[0], out.stderr


def test_the_imitation_id_follows_its_trunk_map_and_a_missing_one_is_one_line(tmp_path):
    """The trunk's map is an input of the weights: its id (not the name in the config) enters the imitation's id;
    a trunk map that is not built is one line naming the map and the command that builds it, exit 2, before any
    rollout."""
    from pipeline.cli import compose
    from pipeline.learned.imitate import identity

    ids = []
    for stem in ("a", "b"):
        (tmp_path / f"{stem}.ckpt").write_bytes(b"")
        ids.append(identity(compose("imitate", [f"imitation.trunk_from={tmp_path / f'{stem}.ckpt'}",
                                                f"paths.models_dir={tmp_path}"])))
    assert ids[0] != ids[1]
    # in this process (tests/shared.py): the stage's fresh-interpreter case is test_bad_keys_are_one_line_and_exit_2's
    out = run_cli("pipeline.learned.imitate", f"paths.models_dir={tmp_path / 'none'}", f"paths.output_dir={tmp_path}")
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert out.returncode == 2 and len(lines) == 1 and "perception map 'clean_keypoint'" in lines[0], out.stderr
    assert "python -m pipeline.train data=clean model=keypoint" in lines[0]


def test_ppo_runs_on_the_vector_environment_through_sb3(tmp_path, monkeypatch):
    """SB3's PPO on the batched environment (a few agent-steps): episodes end, the model and its curve are written,
    and nothing else: no `SB3-<date>` folder is left in the temporary directory (SB3's default logger made one per
    run)."""
    import tempfile

    from pipeline.cli import compose
    from pipeline.learned.ppo import SB3VecEnv, run

    venv = envs.make_vector("hycontrol/Navigate-v0", 3)
    env = SB3VecEnv(venv)
    obs = env.reset()
    obs, r, done, infos = env.step(np.array([[1.0, 0.0], [0.0, 0.0], [-1.0, 0.0]]))  # ±u_max along x
    assert obs.shape == (3, 60, 100, 3) and r.dtype == np.float32 and len(infos) == 3
    cfg = compose("ppo", ["ppo.num_envs=4", "ppo.total_timesteps=32", "ppo.n_steps=8", "ppo.batch_size=16",
                          "ppo.n_epochs=1", "init=points", "init.points=[[39.0,0.5]]",
                          f"paths.models_dir={tmp_path / 'models'}", f"paths.output_dir={tmp_path / 'models'}"])
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    out = run(cfg)
    assert (out["path"] / "model.zip").is_file()
    assert list(scratch.iterdir()) == []
    curve = np.loadtxt(out["path"] / "curve.csv", delimiter=",", skiprows=1, ndmin=2)
    assert len(curve) >= 1 and set(curve[:, 1]) <= {0.0, 1.0}  # starts 1.1 units from the target: episodes end
    made = (out["path"] / "model.zip").stat().st_mtime_ns
    again = run(cfg)  # built: not trained again (make learned runs it every time)
    assert again["path"] == out["path"] and again["wall_s"] == 0.0
    assert (out["path"] / "model.zip").stat().st_mtime_ns == made


def test_trunk_from_a_perception_map_is_copied_and_stays_frozen():
    """`load_trunk` copies the map's blocks; with `freeze_trunk` a training step changes the head only."""
    from pipeline.train.module import PerceptionMap

    pm = PerceptionMap.of(filters=(4, 8, 8), uncertainty="none")
    model = VelocityPolicy.of(filters=(4, 8, 8), hidden=8, freeze_trunk=True)
    model.load_trunk(pm)
    for a, b in zip(model.features.state_dict().values(), pm.features.state_dict().values()):
        assert torch.equal(a, b)
    opt = model.configure_optimizers()
    head0 = [p.clone() for p in model.head.parameters()]
    trunk0 = {k: v.clone() for k, v in model.features.state_dict().items()}
    model.train()
    model.on_train_epoch_start()
    images = torch.randint(0, 255, (8, 60, 100, 3), dtype=torch.uint8)
    model.loss((images, torch.randn(8, HEADS, 2), torch.ones(8, HEADS, dtype=torch.bool))).backward()
    opt.step()
    assert all(torch.equal(v, trunk0[k]) for k, v in model.features.state_dict().items())  # BN stats too
    assert any(not torch.equal(a, b) for a, b in zip(model.head.parameters(), head0))


@pytest.mark.parametrize("n", [75, 20])
def test_a_fit_on_the_frozen_keypoints_read_once_learns_the_same_bits(n, tmp_path):
    """`reads: keypoint` with the map's trunk frozen: the imitation fit reads each frame's keypoint once
    (`frozen_readings`, in batches of the loader's size; an epoch's smaller last batch reads its frames again), not
    every epoch, and the head it learns is bit for bit the one the fit reading every frame each epoch learns. The
    trunk at make paper's size (filters 16-32-64) on one thread, whose convolutions give other bits in a batch of 11
    than in one of 32 here (75 frames: a last batch of 11; 20: one batch): every batch's keypoints reach the head
    with the same bits, which fails when the last batch takes the readings of the full ones (tried)."""
    import copy

    from pipeline.config import compose
    from pipeline.learned.imitate import fit
    from pipeline.train.module import PerceptionMap

    torch.manual_seed(0)
    pm = PerceptionMap.of(filters=(16, 32, 64), position_head="keypoint", uncertainty="none").eval()
    model = VelocityPolicy.of(filters=(16, 32, 64), hidden=8, freeze_trunk=True, reads="keypoint")
    model.load_trunk(pm)
    rng = np.random.default_rng(0)
    data = (rng.integers(0, 255, (n, 60, 100, 3), dtype=np.uint8), rng.normal(size=(n, HEADS, 2)),
            rng.random((n, HEADS)) < 0.7)
    every_epoch = copy.deepcopy(model)
    every_epoch.frozen_readings = lambda images, batch: None  # the fit before: the trunk on every batch
    heard = ([], [])  # what each model's head is given, batch by batch
    for m, got in zip((model, every_epoch), heard):
        m.head.register_forward_pre_hook(lambda _, args, got=got: got.append(args[0].detach().clone()))
    trainer = compose("imitate", [f"paths.output_dir={tmp_path}"]).trainer
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a make paper job's (on two threads this trunk gives one batch size's bits for all)
    try:
        for m in (model, every_epoch):
            fit(m, trainer, data, epochs=3, batch_size=32, seed=0)
    finally:
        torch.set_num_threads(threads)
    assert model.readings is None  # a fit's readings do not outlive it
    assert len(heard[0]) == len(heard[1]) == 3 * -(-n // 32)
    for a, b in zip(*heard):  # every batch's keypoints, bit for bit
        assert torch.equal(a, b), (len(a), (a - b).abs().max())
    for (k, a), b in zip(model.state_dict().items(), every_epoch.state_dict().values()):
        assert torch.equal(a, b), k
    assert model.frozen_readings(data[0], 32) is not None
    learning = VelocityPolicy.of(filters=(4, 8, 8), hidden=8, freeze_trunk=False, reads="keypoint")
    assert learning.frozen_readings(data[0], 32) is None  # a trunk that learns is read every batch


def test_table_rows_count_outcomes_with_wilson_intervals(tmp_path):
    import pandas as pd

    from pipeline.learned.comparison import rows
    from pipeline.learned.report import write_tables

    res = {"outcome": np.array(["reached", "stalled", "reached", "collided"]), "time": np.array([3.0, np.nan, 5.0,
                                                                                                 np.nan])}
    r = rows("imitated", "near K, clean", res, (0.5, 0.7))
    assert (r["reached"], r["stalled"], r["collided"], r["timed_out"]) == (0.5, 0.25, 0.25, 0.0)
    lo, hi = (float(v) for v in r["reached_ci"].strip("[]").split(","))
    assert lo < 0.5 < hi and r["median_time_s"] == 4.0
    write_tables(pd.DataFrame([r]), tmp_path)
    assert "| imitated | near K, clean | 4 | 50% |" in (tmp_path / "tab_learned.md").read_text()


class _Creep:
    """A policy that creeps along +x at `speed` units/s (no camera needed): the env's action `speed / u_max`."""

    def __init__(self, speed, u_max=10.0):
        self.speed, self.u_max = speed, u_max

    def act(self, obs):
        return np.tile(np.array([self.speed / self.u_max, 0.0]), (len(obs), 1))


@pytest.mark.parametrize(("share", "expected"), [(0.2, "stalled"), (0.05, "timed_out")])
def test_the_stall_class_follows_the_sims_share_of_u_max_when_stall_speed_is_null(share, expected):
    """`sim.stall_speed: null` (the default) means `sim.stall_share` of `u_max` (10): a vehicle creeping at 1 unit/s
    is stalled under a threshold of 2, still moving under 0.5 (before the fix: a TypeError from None * float)."""
    o = envs.objects([f"sim.stall_share={share}", "sim.stall_time=1.0", "sim.horizon=2.0"])
    assert o.sim.stall_speed is None
    res = run_policy(o, _Creep(1.0), np.array([[-45.0, 20.0], [-45.0, -20.0]]))
    assert list(res["outcome"]) == [expected, expected]


def test_a_policy_reading_the_keypoint_copies_the_maps_head_and_is_its_position_through_the_mlp():
    """`reads: keypoint`: the map's trunk and keypoint head copied and frozen, the velocity a function of the
    map's normalised position alone (two frames the map puts at the same place get the same velocity); a map
    without a keypoint head is one ConfigError naming `model.reads`."""
    from pipeline.errors import ConfigError
    from pipeline.train.module import PerceptionMap

    torch.manual_seed(0)
    pm = PerceptionMap.of(filters=(4, 8, 8), position_head="keypoint", uncertainty="none").eval()
    model = VelocityPolicy.of(filters=(4, 8, 8), hidden=8, freeze_trunk=True, reads="keypoint")
    model.load_trunk(pm)
    for a, b in zip(model.keypoint.state_dict().values(), pm.head.state_dict().values()):
        assert torch.equal(a, b)
    assert not any(p.requires_grad for p in [*model.features.parameters(), *model.keypoint.parameters()])
    images = torch.randint(0, 255, (4, 60, 100, 3), dtype=torch.uint8)
    model.eval()
    z = pm.position_outputs(pm.prepare(images))
    np.testing.assert_allclose(model.normalised(images).reshape(4, -1).detach(), model.head(z).detach(), atol=1e-5)
    with pytest.raises(ConfigError, match="model.reads"):
        VelocityPolicy.of(filters=(4, 8, 8), hidden=8, reads="keypoint").load_trunk(
            PerceptionMap.of(filters=(4, 8, 8), uncertainty="none"))


def test_worst_cloud_on_a_policy_picks_for_each_live_agent_the_cloud_its_network_likes_least():
    """The worst cloud through a decision network: each live agent's frame is replaced by the candidate that
    pushes the network's output furthest along `d` (here an output that grows with the image's brightness along
    `d`: the brightest cloud, brighter than the clear frame); a stopped agent's frame is left alone."""
    from pipeline.learned.rollouts import PolicyWorstCloud
    from pipeline.render import Occlusion

    o = envs.objects()
    p = np.array([[-20.0, 0.3], [10.0, 5.0], [-30.0, -0.2]])
    clear = o.camera.render(p)
    d = np.array([[0.0, 1.0]] * 3)
    bright = lambda images: images.reshape(len(images), -1).mean(1, dtype=np.float64)[:, None] * d[:1]  # noqa: E731
    clouds = Occlusion(name="heavy", probability=1.0, blobs=(5, 9), radius=(8.0, 20.0), opacity=(0.65, 0.95),
                       aspect=(0.5, 1.0), softness=0.5, color=(185, 205, 255), bank=16, seed=3)
    hook = PolicyWorstCloud(o.camera, clouds, bright, lambda q: d[: len(q)], candidates=3, seed=1)
    alive = np.array([True, False, True])
    out = hook(clear, p, alive)
    assert np.array_equal(out[1], clear[1]) and not np.array_equal(out[0], clear[0])
    along, norm = hook.summary()
    assert along > 0 and norm >= along  # the chosen clouds brighten the frame: the output moves along d
    again = PolicyWorstCloud(o.camera, clouds, lambda images: -bright(images), lambda q: d[: len(q)], candidates=3,
                             seed=1)
    darkest = again(clear, p, alive)
    assert bright(out[[0, 2]])[:, 1].min() >= bright(darkest[[0, 2]])[:, 1].max() - 1e-9


def test_the_ppo_agent_acts_as_sb3_predicts_and_its_attack_net_is_that_action(tmp_path):
    """The PPO agent of the comparison is SB3's deterministic action (frames channel-first inside, clipped), and
    the network the pixel attack differentiates gives that action on float frames."""
    from stable_baselines3 import PPO

    from pipeline.learned.ppo import PPOPolicy, SB3VecEnv

    env = SB3VecEnv(envs.make_vector("hycontrol/Navigate-v0", 2))
    model = PPO("CnnPolicy", env, n_steps=8, batch_size=16, n_epochs=1, seed=0, device="cpu")
    with torch.no_grad():  # a bias that pushes the mean action past the bound: clipped like SB3's
        model.policy.action_net.bias.copy_(torch.tensor([30.0, -0.5]))
    obs = env.reset()
    agent = PPOPolicy(model, scale=[10.0, 10.0])
    np.testing.assert_allclose(agent.act(obs), model.predict(obs, deterministic=True)[0], atol=1e-5)
    assert np.all(agent.act(obs)[:, 0] == 1.0)  # the env's action space is [-1, 1] (issue 46): u_max
    net_out = agent.net(torch.from_numpy(obs).float()).detach().numpy()  # the attack's: the velocity (units/s)
    np.testing.assert_allclose(net_out, 10.0 * agent.act(obs), atol=1e-5)
    np.testing.assert_allclose(agent.velocity(obs), net_out, atol=1e-6)


def test_make_learned_end_to_end_on_tiny_maps_with_clouds_and_the_worst_cloud(tiny_maps, tmp_path, monkeypatch):
    """`make learned` on tiny maps: the clean and the clouded imitation (each trunk from its map), then the
    comparison with every row (clean, pixel attack, the clouds' level, the worst cloud), tracked by id: a second
    run is up to date, and another clouded network changes the id."""
    from pipeline.cli import compose
    from pipeline.learned.comparison import run as evaluate
    from pipeline.learned.imitate import run as imitate

    root, ids = tiny_maps
    tiny = ["imitation.agents=3", "imitation.rounds=1", "imitation.epochs=1", "imitation.round_epochs=1",
            "imitation.max_frames=4", "model.hidden=8", f"paths.models_dir={root / 'models'}",
            f"paths.output_dir={tmp_path}"]
    import pipeline.learned.imitate as imitate_module

    resolved = []  # the trunk's map is resolved once per run (it composes the train config to find the map's id)
    real = imitate_module.trunk_source
    monkeypatch.setattr(imitate_module, "trunk_source", lambda cfg: resolved.append(1) or real(cfg))
    clean = imitate(compose("imitate", [*tiny, f"imitation.trunk_from={ids['clean']}"]))
    assert len(resolved) == 1
    heavy = imitate(compose("imitate_heavy", [*tiny, f"imitation.trunk_from={ids['occluded']}",
                                              "model.reads=features"]))  # the tiny maps' heads are flat
    assert clean["id"] != heavy["id"] and heavy["path"].name.startswith("imitation_heavy-")
    args = [f"maps.clean={ids['clean']}", f"maps.occluded={ids['occluded']}", f"policies.imitation={clean['path']}",
            f"policies.imitation_clouds={heavy['path']}", "learned.agents=2", "learned.near_k=2",
            "learned.agents_list=[hybrid,imitated]", "learned.attack_list=[imitated]", "learned.kappas=[1,3]",
            "learned.clouds_list=[hybrid,learned_hybrid]", "learned.cloud_attack_list=[imitated,hybrid]",
            "learned.candidates=2", "learned.attack_steps=1", "sim.horizon=1", "learned.grid=[5,4]",
            f"paths.models_dir={root / 'models'}", f"paths.outputs_dir={tmp_path / 'out'}",
            f"paths.output_dir={tmp_path}"]
    out = evaluate(compose("learned", args))
    df = out["table"]
    got = set(zip(df.agent, df.condition))
    assert got == {("hybrid", "random, clean"), ("hybrid", "near K, clean"), ("imitated", "random, clean"),
                   ("imitated", "near K, clean"), ("imitated", "near K, pixel attack κ=1"),
                   ("imitated", "near K, pixel attack κ=3"), ("hybrid", "random, heavy clouds"), ("hybrid", "near K, heavy clouds"),
                   ("learned_hybrid", "random, heavy clouds"), ("learned_hybrid", "near K, heavy clouds"),
                   ("imitated", "near K, worst of 2 heavy clouds"), ("hybrid", "near K, worst of 2 heavy clouds")}
    worst = df[df.condition.str.startswith("near K, worst")]
    assert np.all(np.isfinite(worst.induced_norm)) and np.all(worst.induced_norm >= worst.induced_along)
    assert (df.n == 2).all() and np.allclose(df[["reached", "collided", "stalled", "left_view", "timed_out"]]
                                             .sum(1), 1.0)
    import json

    manifest = json.loads((out["path"] / "manifest.json").read_text())
    assert manifest["inputs"]["model_clouds"] == heavy["path"].name
    assert manifest["inputs"]["map_clouds"] == ids["occluded"]
    again = evaluate(compose("learned", args))  # up to date: the same folder, nothing evaluated again
    assert again["path"] == out["path"] and "table" not in again
    other = imitate(compose("imitate_heavy", [*tiny, f"imitation.trunk_from={ids['occluded']}", "imitation.seed=1",
                                              "model.reads=features"]))
    from pipeline.config import build
    from pipeline.learned.evaluate import inputs, learned_id

    for pin, same in ((heavy["path"], True), (other["path"], False)):
        cfg = compose("learned", [*args, f"policies.imitation_clouds={pin}"])
        assert (out["path"].name == f"learned-{learned_id(cfg, inputs(cfg, build(cfg.learned, 'learned')))}") == same


def test_the_table_says_what_its_attack_rows_show():
    """The line under `tab_learned.md` (issue 46): each attacked agent's curve, and where none loses a run, that the
    budgets are below what separates the agents (make run's small version)."""
    import pandas as pd

    from pipeline.learned.report import attack_note

    def table(smooth_at_2):
        rows = [("hybrid", "near K, clean", 1.0, np.nan), ("hybrid", "near K, pixel attack κ=1", 1.0, 0.14),
                ("hybrid", "near K, pixel attack κ=2", 1.0, 0.25), ("smooth", "near K, clean", 0.6, np.nan),
                ("smooth", "near K, pixel attack κ=1", 0.6, 0.14), ("smooth", "near K, pixel attack κ=2", smooth_at_2, 0.26)]
        return pd.DataFrame(rows, columns=["agent", "condition", "reached", "induced_norm"])

    held = attack_note(table(0.6))
    assert "κ = 1/2" in held and "hybrid 100/100%" in held and "smooth 60/60%" in held and "No agent loses" in held
    lost = attack_note(table(0.2))
    assert "smooth 60/20%" in lost and "No agent loses" not in lost
    assert attack_note(table(0.6)[lambda d: ~d.condition.str.contains("attack")]) == ""
