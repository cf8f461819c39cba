"""The allocator setting every stage starts with (`pipeline.allocator`): the same bytes, fewer page faults."""

import json
import os
import subprocess
import sys

import pytest

from pipeline.allocator import ENV, keep_freed_memory
from pipeline.repo import REPO_ROOT

# a few training steps of make paper's map in a fresh process: its weights' hash and the minor page faults of the steps
STEPS = r"""
import hashlib, json, resource, sys
import torch
from pipeline.allocator import keep_freed_memory
from pipeline.config import build, compose
from pipeline.train.module import PerceptionMap
from pipeline.train.bench import _data
kept = keep_freed_memory()
torch.set_num_threads(1)
torch.manual_seed(0)
model = PerceptionMap(build(compose("train", ["model=keypoint"]).model, "model"))
images, pos = _data(64)
opt = torch.optim.Adam(model.parameters(), lr=1e-3)
model.train()
def step(i):
    idx = torch.arange(i * 16, i * 16 + 16) % 64
    loss = torch.nn.functional.mse_loss(model.position_outputs(model.prepare(images[idx])),
                                        (pos[idx] - model.center) / model.half_range)
    opt.zero_grad(set_to_none=True); loss.backward(); opt.step()
step(0)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for i in range(1, 9):
    step(i)
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
digest = hashlib.sha256(b"".join(p.detach().numpy().tobytes() for p in model.parameters())).hexdigest()
print(json.dumps({"kept": kept, "faults": faults, "weights": digest}))
"""


def _steps(malloc: str) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env[ENV] = malloc
    out = subprocess.run([sys.executable, "-c", STEPS], env=env, cwd=REPO_ROOT, capture_output=True, text=True,
                         timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or os.confstr("CS_GNU_LIBC_VERSION") is None,
                           reason="the setting is glibc's")


@glibc
def test_training_steps_keep_their_bytes_and_fault_less():
    """The same weights to the bit after eight steps of make paper's map, with a fraction of the page faults of
    glibc's defaults (which unmap and trim the freed activations, so every step faults them in again)."""
    system, kept = _steps("system"), _steps("")
    assert (system["kept"], kept["kept"]) == (False, True)
    assert kept["weights"] == system["weights"]
    assert kept["faults"] < 0.5 * system["faults"], (kept, system)


@glibc
def test_the_environment_turns_it_off(monkeypatch):
    monkeypatch.setenv(ENV, "system")
    assert keep_freed_memory() is False
    monkeypatch.setenv(ENV, "")
    assert keep_freed_memory() is True  # this process keeps it too: only bookkeeping changes


def test_every_stage_starts_with_it(monkeypatch):
    """`stage_main`'s entry sets it before anything else (a job of make paper is such a process), even where the
    command line is then refused."""
    from pipeline import cli

    calls = []
    monkeypatch.setattr(cli, "keep_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.setattr(sys, "argv", ["simulate", "no_such_key=1"])
    with pytest.raises(SystemExit) as done:
        cli.stage_main("simulate", run="pipeline.simulate:run", check="pipeline.simulate:check")()
    assert (done.value.code, calls) == (2, [1])
