"""The objects a scenario computes with, built from the run's composed config: the controllers, disturbances,
camera attacks and cloud levels it compares (by name: `controllers.<name>`, `disturbances.<name>`, `occlusions`)
and a second scene."""

from __future__ import annotations

from pipeline import tracking
from pipeline.config import build
from pipeline.control import Scene
from pipeline.errors import ConfigError
from pipeline.perception.adversary import is_attack
from pipeline.render import load_occlusion


class Composed:
    """The composed objects of `Context` (its `cfg`, `scene` and `vehicle` set by it)."""

    # composed objects --------------------------------------------------------------------------
    def _node(self, group: str, name: str):
        """The node `<group>.<name>` a scenario names (in `experiment.<group>`); recorded in `read` (the cache key
        must hold every node read: :func:`pipeline.experiments.stage.check_reads`)."""
        self.__dict__.setdefault("read", set()).add((group, name))
        nodes = self.cfg[group]
        if name not in nodes:
            raise ConfigError(f"experiment.{group}", f"unknown {group[:-1]} {name!r}; known: {', '.join(nodes)}")
        return nodes[name]

    def controller(self, name: str = "hybrid", scene: Scene | None = None, **params):
        """The controller `controllers.<name>` of the composed config (hybrid: the run's `controller`), on the
        vehicle's steering scene of `scene` (the unicycle's look-ahead point: every disc inflated, SPEC §3.7). The
        run's own controllers are built once (the preflight's, reused by the computation)."""
        scene = scene or self.scene
        built = self.__dict__.setdefault("_built", {})
        done = built.get(("controller", name)) if not params else None
        if done is not None and done[0] is scene:
            return done[1]
        node = self._node("controllers", name)
        node = node if not params else {**tracking.to_plain(node), **params}
        ctrl = self.parts.law(node, "controller" if name == "hybrid" else f"controllers.{name}", scene)
        ctrl.name = name
        if not params:
            built["controller", name] = (scene, ctrl)
        return ctrl

    def disturbance(self, name: str, **params):
        """The disturbance `disturbances.<name>`; `params` set what the scenario sweeps (eps, sigma)."""
        return build(self._node("disturbances", name), f"disturbances.{name}", **params)

    def attack(self, name: str, **params):
        """The camera attack `disturbances.<name>` (pixel_attack, worst_cloud; docs/attacks.md); `params` set what
        the scenario sweeps (kappa, level). The worst cloud's level is checked here (a name of `occlusions`)."""
        att = self.disturbance(name)
        if not is_attack(att):
            raise ConfigError("experiment.attack", f"{name!r} is a state disturbance, not an attack through the camera "
                                                   "(pixel_attack, worst_cloud)")
        if att.kind == "cloud":  # the node's own level too (a sweep sets another): every key's bad value is caught
            self.read.add(("occlusions", att.level))
            load_occlusion(att.level, self.cfg.occlusions, field=f"disturbances.{name}.level")
        att = self.disturbance(name, **params) if params else att
        if att.kind == "cloud":
            self.read.add(("occlusions", att.level))
            load_occlusion(att.level, self.cfg.occlusions, field="experiment.levels")
        return att

    def occlusion(self, level: str | None):
        if level is None:
            return None
        self.__dict__.setdefault("read", set()).add(("occlusions", level))
        built = self.__dict__.setdefault("_built", {})
        if ("occlusion", level) not in built:
            built["occlusion", level] = load_occlusion(level, self.cfg.occlusions, field="experiment.occlusion")
        occ = built["occlusion", level]
        return occ if occ.active else None

    def other_scene(self) -> tuple[str, Scene]:
        node = self.cfg.get("other_scene")
        if node is None:
            raise ConfigError("other_scene", "this experiment needs a second scene (defaults: /scene@other_scene)")
        return str(node.get("name", "other")), build(node, "other_scene")
