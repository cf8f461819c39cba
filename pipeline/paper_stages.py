"""The stages of `make paper` after the maps (:mod:`pipeline.paper` orders them): the certified error maps, the
closed loop's bracket, the learned policies (imitation, PPO, their comparison). Each computes the folders its
current config makes, starts its jobs through the runner unless they are up to date (the runner may hold them to run
beside another stage's, :meth:`pipeline.paper_profile.Runner.together`), and copies its table and figure into the
paper folder once they are there; called again after its jobs ran, it finds them up to date and publishes."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline import tracking
from pipeline.bracket.stage import bracket_id
from pipeline.bracket.stage import objects as bracket_objects
from pipeline.config import build, compose
from pipeline.errors import PipelineError
from pipeline.identity import certify_id
from pipeline.jobs import Job
from pipeline.learned.evaluate import inputs as learned_inputs
from pipeline.learned.evaluate import learned_id
from pipeline.learned.imitate import identity as imitation_id
from pipeline.lineage import ppo_identity


def up_to_date(stage: str, expected, said: set | None = None) -> dict[str, Path] | None:
    """`expected()` (name -> folder) when every folder is built and matches its manifest: the stage would do
    nothing, so it is not started; None (run it: it builds, or says in one line what is wrong) otherwise. `said`:
    the stages this run already reported (a stage called again after its pool says it once)."""
    try:
        folders = expected()
        intact = all(tracking.is_complete(f) and not tracking.verify(f, full=None) for f in folders.values())
    except PipelineError:
        return None
    if not intact:
        return None
    if said is None or stage not in said:
        print(f"\n[paper] === {stage}: up to date ({', '.join(f.name for f in folders.values())}); not started",
              flush=True)
    if said is not None:
        said.add(stage)
    return folders


def certified(cfg, names, paths, args, lock, runner, manifests=None) -> dict[str, Path]:
    """The certify stage (docs/certify.md) on the maps `names` this run builds (not started when what the current
    certify config makes is there; `manifests`: the maps' manifests before they are trained,
    :func:`pipeline.lineage.expected_map_manifest`); their tables and heat maps copied into the paper folder
    (`tab_/fig_certified_*`)."""
    argv = {n: [f"maps={lock['maps'][n].name}", *paths, *args["certify"]] for n in names}

    def folders():
        out = {}
        for n, a in argv.items():
            c = compose("certify", a)
            s = tracking.to_plain({k: c[k] for k in c.keys() if k not in ("paths", "hydra")})
            m = (manifests or {}).get(n) or tracking.read_manifest(lock["maps"][n])
            out[n] = Path(cfg.paths.certified_dir) / f"{m['name']}-{certify_id(s, m['id'], m['scene'], m['arena'])}"
        return out

    found = up_to_date("certify", folders, runner.said)
    if found is None:
        runner.stage("certify", [Job("certify", argv[n], f"certify {n}") for n in names])
    for n, folder in (found := found or folders()).items():  # Theorem 1's hypothesis for the map
        publish(folder, Path(cfg.paths.paper_dir), {"table.md": f"tab_certified_{n}.md", "certified_error_map.png": f"fig_certified_{n}.png"})
    return found


def bracket(cfg, tunings, paths, args, lock, runner) -> dict[str, Path]:
    """The closed loop's bracket (docs/bracket.md) per tuning of `tunings` (conf/tuning/), with uniform ε and with the
    certified error map of `bracket_map` (pinned by id), unless up to date; `tab_/fig_bracket_<tuning>` copied."""
    paths = [p for p in paths if not p.startswith("debug=")]  # the bracket's small sizes are args.bracket
    pin = [f"bracket.error_map={lock['certified'][cfg.bracket_map].name}"] if cfg.get("bracket_map") else []
    argv = {t: [f"tuning={t}", *pin, *paths, *args["bracket"]] for t in tunings}

    def folders() -> dict[str, Path]:
        out = {}
        for t, a in argv.items():
            c = compose("bracket", a)
            _, _, bs, _, _, emap, cam, _ = bracket_objects(c)
            out[t] = Path(c.paths.bracket_dir) / f"bracket-{bracket_id(c, bs, emap, cam)[0]}"
        return out

    found = up_to_date("bracket", folders, runner.said)
    if found is None:
        after = (f"certify {cfg.bracket_map}",) if cfg.get("bracket_map") else ()  # its pin: in the same pool
        runner.stage("bracket", [Job("bracket", argv[t], f"bracket {t}", after=after) for t in tunings])
        try:
            found = folders()
        except PipelineError:
            return {}
    for t, folder in found.items():
        publish(folder, Path(cfg.paths.paper_dir), {"table.md": f"tab_bracket_{t}.md", "bracket.png": f"fig_bracket_{t}.png"})
    return found


def publish(folder: Path, paper_dir: Path, names: dict[str, str]) -> None:
    """Copy the files `names` (source -> name in the paper folder) of a complete tracked output into the paper folder;
    an unchanged file is not rewritten (its time says when it was made)."""
    if not tracking.is_complete(folder):
        return
    paper_dir.mkdir(parents=True, exist_ok=True)
    for src, dst in names.items():
        same = (paper_dir / dst).is_file() and (paper_dir / dst).read_bytes() == (folder / src).read_bytes()
        if (folder / src).is_file() and not same:
            shutil.copyfile(folder / src, paper_dir / dst)


def imitations(cfg, configs, paths, args, map_refs, runner) -> dict[str, Path]:
    """The imitation of each config of `configs` (conf/imitate*.yaml; its trunk pinned to the map this run built) and
    PPO (`ppo` among them; `args.ppo`), not started when what their current configs make is there: `{config:
    policy folder}`."""
    paths = [p for p in paths if not p.startswith("debug=")]  # their tiny sizes are args (conf/debug/paper/)
    ppo = "ppo" in configs
    configs = [c for c in configs if c != "ppo"]

    trunks = {c: map_refs.get(compose(c, [*paths, *args["imitate"]]).imitation.trunk_from) for c in configs}
    argv = {c: [*([f"imitation.trunk_from={trunks[c]}"] if trunks[c] else []), *paths, *args["imitate"]]
            for c in configs}
    composed = {c: compose(c, a) for c, a in argv.items()}
    policies = {c: Path(k.paths.models_dir) / f"{k.name}-{imitation_id(k, *([trunks[c]] if trunks[c] else []))}"
                for c, k in composed.items()}  # a trunk this run trains: its folder's name, before it is there
    jobs = [Job("imitate", ["--config-name", c, *a], f"imitate {c}", module="pipeline.learned.imitate")
            for c, a in argv.items()]
    if ppo:
        k = compose("ppo", [*paths, *args["ppo"]])
        policies["ppo"] = Path(k.paths.models_dir) / f"ppo-{ppo_identity(k)}"
        jobs.append(Job("ppo", [*paths, *args["ppo"]], "ppo", module="pipeline.learned.ppo"))
    if up_to_date("imitate", lambda: policies, runner.said) is None:
        runner.stage("imitate", jobs)
    return policies


def learned(cfg, configs, paths, args, map_refs, runner) -> dict[str, Path]:
    """`make learned`'s stages (docs/learned.md): the policies (:func:`imitations`), then the comparison with every
    map and network pinned, not started when what its current config makes is there. The comparison's table and
    figure are copied into the paper folder (`tab_learned.md`, `fig_learned_switching_set.png`)."""
    policies = imitations(cfg, configs, paths, args, map_refs, runner)
    paths = [p for p in paths if not p.startswith("debug=")]
    kinds = compose("learned", paths).maps
    pins = [f"maps.{k}={map_refs[str(n)]}" for k, n in kinds.items() if str(n) in map_refs]
    pins += [f"policies.imitation{'' if c == 'imitate' else '_clouds'}={policies[c]}" for c in configs
             if c in ("imitate", "imitate_heavy")]
    pins += [f"policies.ppo={policies['ppo']}"] if "ppo" in configs else []
    learned_argv = [*pins, *paths, *args["learned"]]

    def comparison() -> dict[str, Path]:
        k = compose("learned", learned_argv)
        folders = learned_inputs(k, build(k.learned, "learned"))
        return {"comparison": Path(k.paths.outputs_dir) / "learned" / f"learned-{learned_id(k, folders)}"}

    found = up_to_date("learned", comparison, runner.said)
    if found is None:
        after = tuple(f"imitate {c}" for c in configs if c != "ppo") + (("ppo",) if "ppo" in configs else ())
        runner.stage("learned", [Job("learned", learned_argv, "learned", module="pipeline.learned.evaluate",
                                     after=after)])  # beside its policies' jobs, once they are done
        try:
            found = comparison()
        except PipelineError:
            found = {}
    out = {**{f"policy {c}": f for c, f in policies.items()}, **found}
    if found.get("comparison") is not None:
        publish(found["comparison"], Path(cfg.paths.paper_dir),
                {"tab_learned.md": "tab_learned.md", "fig_switching_set.png": "fig_learned_switching_set.png"})
    return out
