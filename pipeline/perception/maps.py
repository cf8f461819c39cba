"""Loading a trained perception map for the next stages: batched inference on uint8 images, on any device.

Inference runs a `FoldedPerceptionNet` (BatchNorm and input scaling folded into the convolutions,
channels_last) on the device of `resolve_device(device)`; `compile=True` (or `"auto"`: when a C++ compiler
is on PATH) adds `torch.compile`, falling back to the folded eager network if compilation fails.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
from pathlib import Path

import numpy as np
import torch

from pipeline import tracking
from pipeline.config import build
from pipeline.errors import ConfigError, DatasetError, ModelError, PipelineError
from pipeline.lineage import resolve_map
from pipeline.perception.network import FoldedPerceptionNet, PerceptionNet
from pipeline.repo import REPO_ROOT
from pipeline.schema import Device, check_value

DEFAULT_MODELS_DIR = REPO_ROOT / "outputs" / "models"
log = logging.getLogger(__name__)


def resolve_device(spec="auto") -> torch.device:
    """`auto` (CUDA when present, else CPU) | `cpu` | `cuda` | `cuda:N` -> a usable `torch.device`.

    A CUDA device that is not there is a `ConfigError("device", ...)`, not a CUDA traceback later.
    """
    if isinstance(spec, torch.device):
        spec = str(spec)
    if spec is None or spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    check_value(spec, Device, "device")
    dev = torch.device(spec)
    if dev.type == "cpu":
        return dev
    if not torch.cuda.is_available():
        raise ConfigError("device", f"{spec!r} requested but no CUDA device is available on this machine "
                                    "(use device=auto or device=cpu)")
    n = torch.cuda.device_count()
    if dev.index is not None and dev.index >= n:
        raise ConfigError("device", f"{spec!r} requested but this machine has {n} CUDA device(s)")
    return dev


def _compiler_present() -> bool:
    return any(shutil.which(c) for c in ("cc", "gcc", "clang", "g++", "c++"))


# below glibc's own largest mmap threshold (32 MiB), so a chunk's activations reuse the heap even with glibc's defaults
# (every stage raises the threshold, pipeline.allocator); the chunk also fixes the outputs' float32 rounding
CHUNK_BYTES = 24 * 2**20


def activation_bytes(model: PerceptionNet) -> int:
    """The largest convolution output of one image, fp32 bytes (what sizes an inference chunk on the CPU)."""
    h, w, _ = model.image_shape
    most = 0
    for m in model.features:
        if isinstance(m, torch.nn.Conv2d):
            most = max(most, 4 * h * w * m.out_channels)
        elif isinstance(m, torch.nn.MaxPool2d):
            h, w = h // 2, w // 2
    return most


def cpu_chunk(model: PerceptionNet) -> int:
    """Images per inference call on the CPU: as many as keep the largest activation under `CHUNK_BYTES`. A larger
    one is mmap'ed and unmapped at every call, and its page faults cost more than the convolutions (measured
    2026-12-05, make paper's keypoint map, 2 threads: 1,019 img/s at 1,024 images a call, 7.2 s of system time in
    3 passes over 2,048 images; 3,361 img/s at 64, none). Outputs differ from one call by float32 rounding at
    most (none at the default chunk on the maps measured; small chunks on one thread: 2e-6 to 8e-6 world units;
    tests/test_inference_chunk.py)."""
    return int(max(8, min(1024, CHUNK_BYTES // max(1, activation_bytes(model)))))


class PerceptionMapPredictor:
    """`predict(images uint8 (N, H, W, 3)) -> float64 (N, 2)` world coordinates, in inference mode.

    `device`: see `resolve_device`. `fold=True` runs the folded network (`FoldedPerceptionNet`), `False`
    the training module itself (the reference). `compile`: `True`, `False` or `"auto"` (when a compiler is
    on PATH); a failed compilation falls back to eager with a warning.
    """

    def __init__(self, model: PerceptionNet, manifest: dict | None = None, path: Path | None = None,
                 batch_size: int | None = None, device="cpu", fold: bool = True, compile=False):
        self.model = model.eval()
        self.device = resolve_device(device)
        self.manifest = manifest or {}
        self.path = Path(path) if path else None
        self.batch_size = int(batch_size) if batch_size else cpu_chunk(model) if self.device.type == "cpu" else 1024
        self.id = self.manifest.get("id")
        self.name = self.manifest.get("name", model.spec.name)
        self.image_shape = model.image_shape
        self.px_per_unit = model.px_per_unit
        self.has_uncertainty = getattr(model, "uncertainty", "none") != "none"
        self.pose = bool(getattr(model, "pose", False))  # a pose map: (x, y, θ)
        self._n_est = 3 if self.pose else 2
        self._n_out = self._n_est + (2 if self.has_uncertainty else 0)
        self._fold = fold
        if compile == "auto":
            compile = _compiler_present()
        self._compile_wanted = bool(compile)
        self.refresh()

    def refresh(self) -> None:
        """(Re)build the inference network from the model (after its weights or calibration changed)."""
        self.net = (FoldedPerceptionNet(self.model) if self._fold else self.model).to(self.device)
        self.compiled = False
        if self._compile_wanted:
            self._compile()

    def _compile(self) -> None:
        eager = self.net
        try:
            net = torch.compile(eager, dynamic=False)
            with torch.inference_mode():  # compile now (a small batch), not in the middle of a run
                net(torch.zeros((2, *self.image_shape), dtype=torch.uint8, device=self.device))
            self.net, self.compiled = net, True
        except Exception as err:  # noqa: BLE001 - any compiler/toolchain failure: eager is still correct
            log.warning("torch.compile unavailable (%s: %s); using eager inference",
                        type(err).__name__, str(err).splitlines()[0] if str(err) else "")
            self.net = eager

    def __repr__(self) -> str:
        return f"PerceptionMapPredictor({self.name}-{self.id} on {self.device})"

    def to_device(self, images) -> torch.Tensor:
        """uint8 images (N, H, W, 3) (numpy or tensor) as one tensor on the predictor's device."""
        if isinstance(images, torch.Tensor):
            return images.to(self.device, non_blocking=True)
        images = np.asarray(images)
        if not (images.flags.writeable and images.flags.c_contiguous):
            images = np.array(images)  # memory-mapped/read-only input: torch wants a writable buffer
        return torch.from_numpy(images).to(self.device, non_blocking=True)

    def predict(self, images) -> np.ndarray:
        """Positions `(N, 2)` (world units); a pose map's poses `(N, 3)` (x, y, θ in radians)."""
        return self._run(images)[:, : self._n_est]

    def predict_with_sigma(self, images) -> tuple[np.ndarray, np.ndarray | None]:
        """Positions `(N, 2)` and the map's own calibrated standard deviation per coordinate `(N, 2)` (world
        units), or `None` for a map trained without `model.uncertainty`."""
        out = self._run(images)
        k = self._n_est
        return out[:, :k], (out[:, k:] if self.has_uncertainty else None)

    def predicted_error(self, images) -> tuple[np.ndarray, np.ndarray | None]:
        """Positions and the predicted Euclidean error `sqrt(sx^2 + sy^2)` (world units; RMS under the model),
        or `None` without an uncertainty head."""
        pos, sigma = self.predict_with_sigma(images)
        return pos, (None if sigma is None else np.hypot(sigma[:, 0], sigma[:, 1]))

    def _run(self, images) -> np.ndarray:
        if isinstance(images, torch.Tensor):
            shape = tuple(images.shape)
        else:
            images = np.asarray(images)
            shape = images.shape
        if len(shape) == 3:
            images, shape = images[None], (1, *shape)
        if len(shape) != 4 or tuple(shape[1:]) != self.image_shape:
            raise ModelError(f"perception map {self.name}: image shape {tuple(shape[1:])} does not "
                             f"match the model's {self.image_shape}")
        out = torch.empty((shape[0], self._n_out), dtype=torch.float64)
        with torch.inference_mode(), _one_thread(self.device.type == "cpu" and shape[0] <= SMALL_BATCH):
            for s in range(0, shape[0], self.batch_size):
                batch = self.to_device(images[s : s + self.batch_size])  # one host->device copy per batch
                out[s : s + len(batch)] = self.net(batch).to("cpu", torch.float64)
        return out.numpy()

    __call__ = predict

    def camera(self):
        """The Camera that rendered this map's training data (scene, arena, colours, sizes)."""
        try:
            render, scene = self.manifest["render"], self.manifest["scene"]
        except KeyError as err:
            raise ModelError(f"perception map {self.name}: manifest has no {err.args[0]!r} config") from None
        return build(render, "render", scene=build(scene, "scene"))


# A closed loop infers a few images per camera frame. For so few, intra-op threads gain little on a CPU, and on a
# busy machine they wait for each other at every layer: one image took 260 ms with 2 threads and 19 ms with one
# (2 cores, load average 15; scripts of issue 21). Small batches run on one thread.
SMALL_BATCH = 16


@contextlib.contextmanager
def _one_thread(enabled: bool):
    n = torch.get_num_threads()
    if not enabled or n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def load_perception_map(ref, models_dir=None, *, verify: bool = False, device="auto",
                        compile=False) -> PerceptionMapPredictor:
    """A trained map by path, `name-id`, id, or name (the map the current train config makes for that
    dataset recipe; see :mod:`pipeline.lineage`), for inference on `device`."""
    root = Path(models_dir) if models_dir else DEFAULT_MODELS_DIR
    try:
        folder = resolve_map(ref, root)
    except DatasetError as err:  # unknown name/id: reported as the model's error
        raise ModelError(str(err)) from None
    dev = resolve_device(device)
    if verify:
        problems = tracking.verify(folder)
        if problems:
            raise ModelError(f"perception map {folder.name} fails verification: {problems[0]}")
    manifest = tracking.read_manifest(folder)
    blob = torch.load(folder / "model.pt", map_location="cpu", weights_only=True)
    hparams = dict(blob["hparams"])
    model = PerceptionNet.of(**hparams)
    model.load_state_dict(blob["state_dict"])
    return PerceptionMapPredictor(model, manifest=manifest, path=folder, device=dev, compile=compile)


def trained_maps(models_dir=None) -> list[Path]:
    """The perception maps under `models_dir` (default outputs/models), newest first. The folder holds other tracked
    outputs too: `make run` ends with `make learned`'s imitation policy (and `ppo-<id>`), whose model.pt is a bare
    state dict with no map `hparams` (as the newest entry it made the benchmarks' rows "trained model unusable")."""
    maps = []
    for d in tracking.entries(Path(models_dir) if models_dir else DEFAULT_MODELS_DIR):
        try:
            kind = tracking.read_manifest(d).get("kind")
        except PipelineError:
            continue
        if kind in (None, "perception_map"):  # None: a map from before manifests said what they hold
            maps.append(d)
    return maps


def newest_perception_map(models_dir=None, device="cpu") -> tuple[PerceptionMapPredictor | None, str]:
    """The newest trained perception map that loads (benchmarks: the map `make run` deploys), and a note saying
    which, or why none (None: the caller falls back to an untrained network of the same cost)."""
    note = "no trained model"
    for folder in trained_maps(models_dir):
        try:
            pmap = load_perception_map(folder, models_dir=models_dir, device=device)
            return pmap, f"model {pmap.name}-{pmap.id}"
        except Exception as err:  # noqa: BLE001 - try an older map, else none, and say so
            note = f"trained model {folder.name} unusable ({type(err).__name__})"
    return None, note

