"""Stage: imitation of the hybrid controller from camera frames, BC + DAgger (`python -m pipeline.learned.imitate`).

Round 0 rolls the expert (the hybrid controller at the true state) out in the vector environment from
`imitation.agents` random starts and records every `record_every`-th frame with its labels
(:class:`pipeline.learned.expert.Expert`: the expert's velocity, its mode carried along, and each mode's flow;
velocities in world units, the network's targets; the env is handed their normalised action, `u / scale`);
the network (:class:`pipeline.learned.network.VelocityPolicy`) is fitted for `epochs` with the project's
Lightning trainer (the `trainer` node). Each DAgger round rolls the *learner* out from fresh starts, the expert
labelling the frames it visits (its mode carried along the learner's trajectory, initialised by §3.3's rule),
adds them to the data and fits `round_epochs` more. Output: `outputs/models/<name>-<id>/` with `model.pt`
(weights), the manifest (config, per-round data sizes, the learner's success in each round, wall times).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build, compose
from pipeline.envs.core import OUTCOMES
from pipeline.envs.navigate import NavigateVectorEnv, objects_from
from pipeline.errors import ConfigError
from pipeline.lineage import resolve_map
from pipeline.preflight import prepared
from pipeline.repo import CONF_DIR
from pipeline.schema import NonNegativeInt, PositiveInt, checked
from pipeline.train.callbacks import epoch_line

# the code that makes the weights (not the evaluation's: `make learned` evaluates without retraining)
CODE = ("envs", "learned/imitate", "learned/expert", "learned/network", "learned/spec", "learned/policies", "control", "render",
        "plants", "sim", "hybrid", "perception")


@checked("imitation")
@dataclass(frozen=True)
class ImitationSettings:
    agents: PositiveInt = 200
    rounds: NonNegativeInt = 2
    epochs: PositiveInt = 6
    round_epochs: PositiveInt = 3
    batch_size: PositiveInt = 128
    max_frames: PositiveInt = 300
    record_every: PositiveInt = 1
    seed: NonNegativeInt = 0
    threads: PositiveInt | None = None
    trunk_from: str | None = None


_UNRESOLVED = object()


def trunk_source(cfg: DictConfig) -> str | None:
    """The folder name of the perception map whose trunk initialises the network (`imitation.trunk_from`
    resolved as a map name means: the map the current train config makes), or the checkpoint's file name."""
    ref = cfg.imitation.get("trunk_from")
    if ref is None:
        return None
    if str(ref).endswith(".ckpt"):
        if not Path(str(ref)).is_file():
            raise ConfigError("imitation.trunk_from", f"no checkpoint {ref}")
        return Path(str(ref)).name
    return resolve_map(ref, cfg.paths.models_dir, field="imitation.trunk_from").name


def identity(cfg: DictConfig, trunk: str | None | object = _UNRESOLVED) -> str:
    """The id of the weights: the config that determines them (not paths, not where it runs), the trunk's map
    (by its id: a name means the map the current train config makes; `trunk`: :func:`trunk_source` already
    resolved) and the code."""
    trunk = trunk_source(cfg) if trunk is _UNRESOLVED else trunk
    plain = OmegaConf.to_container(cfg, resolve=False)
    for key in ("paths", "hydra", "force", "name"):
        plain.pop(key, None)
    trainer = {k: v for k, v in plain.pop("trainer", {}).items()
               if k not in ("accelerator", "devices", "strategy", "num_nodes", "enable_progress_bar",
                            "default_root_dir", "log_every_n_steps")}
    return tracking.content_id(plain, trainer, trunk, tracking.code_version(*CODE))


def rollout(venv: NavigateVectorEnv, expert, learner, seed: int, max_frames: int, record_every: int):
    """Frames, labels and masks along the trajectories of `learner` (None: the expert acts), and the outcomes."""
    obs, info = venv.reset(seed=seed)
    expert.policy.x = None
    if learner is not None and hasattr(learner, "reset"):
        learner.reset(obs)
    frames, labels, masks = [], [], []
    outcome = np.zeros(venv.num_envs, dtype=np.int8)
    for k in range(max_frames):
        alive = ~venv.done
        lab, mask = expert.labels(info["state"])
        if k % record_every == 0:
            frames.append(obs[alive])
            labels.append(lab[alive])
            masks.append(mask[alive])
        action = venv.core.action(lab[:, 0]) if learner is None else learner.act(obs)  # the env's unit action
        obs, _, term, trunc, info = venv.step(action)
        outcome[(term | trunc) & (outcome == 0)] = info["outcome"][(term | trunc) & (outcome == 0)]
        if venv.done.all():
            break
    outcome[outcome == 0] = OUTCOMES.index("timed_out")
    return np.concatenate(frames), np.concatenate(labels), np.concatenate(masks), outcome


def fit(model, trainer_node, data, epochs: int, batch_size: int, seed: int, label: str = "fit") -> float:
    """`epochs` of the project's Lightning trainer on `data` (frames, labels, masks); returns the wall time."""
    import lightning as L
    import torch
    from torch.utils.data import DataLoader, TensorDataset

    frames, labels, masks = data
    L.seed_everything(seed, verbose=False)
    trainer = build(trainer_node, "trainer", max_epochs=int(epochs), callbacks=[epoch_line(label, "train_loss")])
    t0 = time.perf_counter()
    # a frozen keypoint trunk on the CPU: its readings once, not every epoch (the same bits: frozen_readings)
    read = model.frozen_readings(frames, batch_size) if trainer.strategy.root_device.type == "cpu" else None
    model.readings = None if read is None else (min(batch_size, len(frames)), read)
    index = [] if read is None else [torch.arange(len(frames))]
    ds = TensorDataset(torch.from_numpy(frames), *index, torch.from_numpy(labels).float(), torch.from_numpy(masks))
    loader = DataLoader(ds, batch_size=batch_size, shuffle=True, generator=torch.Generator().manual_seed(seed))
    try:
        trainer.fit(model, loader)
    finally:
        model.readings = None
    return time.perf_counter() - t0


@dataclass
class Prepared:
    """What the preflight built for a run: the objects, the settings and the trunk's map (resolved once)."""

    obj: object
    settings: ImitationSettings
    trunk: str | None


def check(cfg: DictConfig) -> Prepared:
    """Preflight: every object built and the trunk's map found (no rollout, no training)."""
    obj = objects_from(cfg)
    if obj.plant.heading:  # the plant says what it is (not its class name)
        raise ConfigError("vehicle", "imitation is implemented for the single integrator (vehicle=integrator)")
    return Prepared(obj, build(cfg.imitation, "imitation"), trunk_source(cfg))


def run(cfg: DictConfig) -> dict:
    import torch  # torch and the torch modules below: not in the preflight (this module is the stage's entry)

    from pipeline.learned.expert import Expert  # torch
    from pipeline.learned.network import VelocityPolicy  # torch, Lightning
    from pipeline.learned.policies import ImitatedPolicy, load_map  # torch

    ready = prepared(cfg, check)  # the preflight's, when it checked this job
    obj, s = ready.obj, ready.settings
    id_ = identity(cfg, ready.trunk)
    root = Path(cfg.paths.models_dir)
    final = root / f"{cfg.name}-{id_}"
    if final.is_dir() and tracking.is_complete(final) and not cfg.force:
        print(f"imitate: up to date -> {final}")
        return {"path": final, "id": id_}
    if s.threads is not None:
        torch.set_num_threads(s.threads)
    torch.manual_seed(s.seed)
    model = VelocityPolicy(build(cfg.model, "model", image_shape=(*obj.camera.shape, 3)))
    if s.trunk_from is not None:
        ckpt = str(s.trunk_from).endswith(".ckpt")  # else the map folder check() resolved (by its id)
        ref = s.trunk_from if ckpt else Path(cfg.paths.models_dir) / ready.trunk
        model.load_trunk(load_map(ref, cfg.paths.models_dir).model)
    venv = NavigateVectorEnv(s.agents, objects_=obj, autoreset=False)
    expert = Expert(obj.controller, obj.plant, obj.scene, venv.core.period, scale=venv.core.scale)
    data, rounds = None, []
    for r in range(s.rounds + 1):
        t0 = time.perf_counter()
        learner = None if r == 0 else ImitatedPolicy(model, venv.core.scale)
        new = rollout(venv, expert, learner, seed=s.seed * 1000 + r, max_frames=s.max_frames,
                      record_every=s.record_every)
        data = new[:3] if data is None else tuple(np.concatenate([a, b]) for a, b in zip(data, new[:3]))
        t_roll = time.perf_counter() - t0
        t_fit = fit(model, cfg.trainer, data, s.epochs if r == 0 else s.round_epochs, s.batch_size, s.seed + r,
                    label=f"round {r}")
        success = float(np.mean(new[3] == 1))
        rounds.append({"round": r, "actor": "expert" if r == 0 else "learner", "new_frames": len(new[0]),
                       "frames": len(data[0]), "actor_success": success, "rollout_s": t_roll, "fit_s": t_fit})
        print(f"imitate: round {r} ({rounds[-1]['actor']}): {len(new[0])} new frames, {len(data[0])} in all, "
              f"actor success {success:.1%}, rollout {t_roll:.0f} s, fit {t_fit:.0f} s")
    meta = {"kind": "imitation", "config": tracking.to_plain(cfg), "rounds": rounds,
            "hparams": dict(model.hparams), "settings": asdict(s)}
    with tracking.tracked_output(root, str(cfg.name), id_, meta) as tmp:
        torch.save(model.state_dict(), tmp / "model.pt")
    print(f"imitate: -> {final}")
    return {"path": final, "id": id_, "rounds": rounds}


def policy_folder(ref, models_dir, field: str = "policies.imitation") -> Path:
    """The folder of a trained imitation network by path, name-id, id or name (a name means the network its config
    makes now: `imitation` the one of conf/imitate.yaml, `imitation_<x>` the one of conf/imitate_<x>.yaml, as a
    map's name means the current train config's; another name: the only one)."""
    def config_of(name: str) -> str | None:
        config = "imitate" + name.removeprefix("imitation")
        return config if name.startswith("imitation") and (CONF_DIR / f"{config}.yaml").is_file() else None

    def expected(name: str) -> str | None:  # the name means what its imitate config makes now
        config = config_of(name)
        return None if config is None else identity(compose(config, [f"paths.models_dir={Path(models_dir).resolve()}"]))

    def command(name: str) -> str:
        config = config_of(name)
        return "python -m pipeline.learned.imitate" + (f" --config-name {config}" if config not in (None, "imitate") else "")

    return tracking.resolve(Path(models_dir), ref, kind="imitation policy", field=field, command=command,
                            expected=expected)


main = stage_main("imitate", run="pipeline.learned.imitate:run", check="pipeline.learned.imitate:check")

if __name__ == "__main__":
    main()
