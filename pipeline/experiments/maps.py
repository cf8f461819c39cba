"""The perception maps and error maps a scenario reads, by id (`maps.<kind>`, `errormaps.<kind>`: resolved through
`pipeline.lineage`, never "the newest folder"), loaded lazily, and what their manifests say (the camera that rendered
a map's images, its scene, its heading output, its flag gate)."""

from __future__ import annotations

import functools

from pipeline import lineage, tracking
from pipeline.config import build
from pipeline.control import Scene
from pipeline.errormap.read import load_error_map
from pipeline.errors import ConfigError, DatasetError, ModelError
from pipeline.perception.measure import OracleMap


class MapsById:
    """The maps of `Context` (its `cfg`, `perception`, `settings`, `vehicle`, `camera_settings`, `used`, `_maps` and
    `_load_map` set by it)."""

    # perception ------------------------------------------------------------------------------
    def map_folder(self, kind: str = "clean"):
        """The folder of map `kind` (`maps.<kind>`: resolved by id, not loaded); None with a perfect map."""
        if self.perception == "oracle":
            return None
        ref = (tracking.to_plain(self.cfg.maps) or {}).get(kind)
        if ref is None:
            raise ConfigError(f"maps.{kind}", "no perception map configured")
        try:
            return lineage.resolve_map(ref, self.cfg.paths.models_dir, field=f"maps.{kind}",
                                       overrides=lineage.debug_overrides(self.cfg))
        except DatasetError as err:  # unknown name/id: the map's error, as load_perception_map reports it
            raise ModelError(str(err)) from None

    def perception_map(self, kind: str = "clean"):
        if kind in self._maps:
            return self._maps[kind]
        if self.perception == "oracle":
            self.used[f"map:{kind}"] = "oracle (perfect map)"
            self._maps[kind] = OracleMap()
            return self._maps[kind]
        if self._load_map is None:
            raise RuntimeError("this Context loads no perception map (built for a preflight check)")
        pm = self._load_map(self.map_folder(kind), models_dir=self.cfg.paths.models_dir, device=self.settings.device)
        self.used[f"map:{kind}"] = f"{pm.name}-{pm.id} (dataset {pm.manifest.get('dataset_name')}-{pm.manifest.get('dataset_id')})"
        self._maps[kind] = pm
        return pm

    def map_ids(self, kinds) -> dict:
        """Ids of the maps a scenario will use (part of its cache key), from their folders."""
        out = {}
        for k in kinds:
            folder = self.map_folder(k)
            out[k] = "oracle" if folder is None else folder.name.rsplit("-", 1)[1]
        return out

    @functools.cache  # noqa: B019
    def error_map(self, kind: str = "clean") -> dict | None:
        """Summary of the error map of map `kind` (`errormaps.<kind>`: an id, or null for the one the current
        errormap config computes for the map); None with a perfect map."""
        folder = self.map_folder(kind)
        if folder is None:
            return None
        map_id = folder.name.rsplit("-", 1)[1]
        ref = (tracking.to_plain(self.cfg.get("errormaps")) or {}).get(kind)
        em = lineage.resolve_errormap(ref, self.cfg.paths.errormaps_dir, folder, lineage.debug_overrides(self.cfg))
        s = load_error_map(em)
        if s.get("model", {}).get("id") != map_id:
            raise ConfigError(f"errormaps.{kind}", f"{em.name} is the error map of map {s['model'].get('id')}, "
                                                   f"not of {folder.name}")
        self.used[f"errormap:{kind}"] = em.name
        return s

    def eps_perception(self, kind: str = "clean", level: str = "none") -> tuple[float, str]:
        """ε of the error map of a perception map at an occlusion level (p95 over the operational set)."""
        s = self.error_map(kind)
        if s is None:
            return 0.0, "oracle"
        if level not in s.get("levels", {}):
            raise ConfigError("errormaps", f"{s['path'].name} has no occlusion level {level!r}")
        return float(s["levels"][level]["p95"]), s["path"].name

    @functools.cache  # noqa: B019
    def camera(self, kind: str = "clean"):
        """The camera that rendered map `kind`'s training images (a perfect map: the composed render config)."""
        folder = self.map_folder(kind)
        if folder is None:
            return build(self.cfg.render, "render", scene=self.scene)
        m = tracking.read_manifest(folder)
        return build(m["render"], "render", scene=build(m["scene"], "scene"))

    def map_scene(self, kind: str = "clean") -> Scene | None:
        """The scene map `kind`'s training images show (from its manifest; None with a perfect map)."""
        folder = self.map_folder(kind)
        return None if folder is None else build(tracking.read_manifest(folder)["scene"], "scene")

    def check_heading(self, kind: str = "clean") -> None:
        """A vehicle with a heading read from the camera (`camera.heading: camera`) needs a pose map: one line
        otherwise (read from the map's manifest: no map loaded)."""
        if not self.vehicle.heading or self.camera_settings.heading != "camera":
            return
        folder = self.map_folder(kind)
        if folder is None:  # a perfect map returns the true pose
            return
        outputs = (tracking.read_manifest(folder).get("model") or {}).get("outputs", "position")
        if outputs != "pose":
            raise ConfigError("camera.heading", f"'camera' needs a pose map, and {folder.name} (maps.{kind}) predicts no "
                                                "heading: train one (python -m pipeline.train data=unicycle model=pose) "
                                                "or read it from an onboard sensor (camera.heading=imu)")

    def map_gate(self, kind: str = "clean") -> float | None:
        """Map `kind`'s own flag threshold in world units: the clean-image gate its training fitted
        (`calibration.clean_gate_px`, docs/train.md) over its pixels per unit; None without an uncertainty head."""
        pm = self.perception_map(kind)
        px = (getattr(pm, "manifest", {}).get("metrics", {}).get("calibration") or {}).get("clean_gate_px")
        if px is None or not getattr(pm, "has_uncertainty", False):
            return None
        return float(px) / float(pm.px_per_unit)
