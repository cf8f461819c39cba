"""Certified training (pipeline.train.certified, SPEC §5.2 "Certifiable maps"): the schedule, the term's
gradient, off by default, a tiny Lightning run whose certified bound the term lowers, and bad keys."""

from __future__ import annotations

from types import SimpleNamespace

import lightning as L
import numpy as np
import pytest
import torch
from budget import examples  # tests/budget.py: more examples under make test-explore
from hypothesis import example, given, settings
from hypothesis import strategies as st
from shared import run_cli

from pipeline.certify import certified_error_bound, prepare
from pipeline.cli import compose
from pipeline.errors import ConfigError
from pipeline.render import Camera
from pipeline.train.certified import CertifiedTerm
from pipeline.train.module import PerceptionMap
from pipeline.train.settings import CertifiedTraining

SCENE = SimpleNamespace(obstacle_center=(0.0, 0.0), obstacle_radius=4.0, target=(40.0, 0.0))


@pytest.fixture(scope="module")
def camera():
    return Camera(SCENE)


@settings(max_examples=examples(60), deadline=None)
@example(warm=1.0, ramp=2e-228, ibp=0.0, t1=1.0, t2=1.0)  # a ramp below the warm-up's float spacing (a bug fixed)
@given(warm=st.floats(0, 5), ramp=st.floats(0, 5), ibp=st.floats(0, 5), t1=st.floats(0, 20), t2=st.floats(0, 20))
def test_schedule_ramps_as_documented(warm, ramp, ibp, t1, t2):
    s = CertifiedTraining(weight=0.3, cell=0.25, cell_start=0.05, warmup_epochs=warm, ramp_epochs=ramp,
                          ibp_epochs=ibp, mode="crown")
    a, b = sorted((t1, t2))
    wa, ca, ma = s.schedule(a)
    wb, cb, mb = s.schedule(b)
    assert 0 <= wa <= wb <= 0.3 and 0.05 - 1e-12 <= ca <= cb <= 0.25 + 1e-12  # monotone, within the ends
    if a < warm:
        assert wa == 0 and ca == pytest.approx(0.05)  # the warm-up: regression only
    if a >= warm + ramp:
        assert wa == pytest.approx(0.3) and ca == pytest.approx(0.25)  # ramped up, and stays
    if warm <= a < warm + ramp:  # linear in between
        assert wa == pytest.approx(0.3 * (a - warm) / ramp)
    assert ma == ("ibp" if a < warm + ibp else "crown")
    assert not (ma == "crown" and mb == "ibp")  # cheap bounds early, the tight one later


def _batch(camera, n, seed):
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.uniform(-44, 44, n), rng.uniform(-24, 24, n)])
    return torch.from_numpy(camera.render(p)), torch.from_numpy(p).float()


def _model(seed=0):
    torch.manual_seed(seed)
    return PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", dropout=0.0, schedule="constant", lr=3e-3)


def test_off_by_default_leaves_the_loss_identical(camera):
    cfg = compose("train", [])
    assert cfg.get("certified") is None  # conf/train.yaml: off
    images, labels = _batch(camera, 8, 0)
    m = _model()
    assert m.certified_term is None
    with torch.no_grad():
        got = m.training_step((images, labels), 0)
        want = torch.nn.functional.mse_loss(m.head_outputs(*m.encode(m.prepare(images))), m.targets(labels))
    assert torch.equal(got, want)


def test_the_term_has_a_gradient_and_is_off_in_the_warm_up(camera):
    m = _model()
    _, labels = _batch(camera, 4, 1)
    term = CertifiedTerm(CertifiedTraining(weight=1.0, target=0.0, warmup_epochs=1, ramp_epochs=0, ibp_epochs=0),
                         camera)
    assert term(m, labels, 0.5) is None  # the warm-up computes nothing
    for mode in ("ibp", "crown"):
        m.zero_grad()
        t = CertifiedTerm(CertifiedTraining(weight=1.0, target=0.0, warmup_epochs=0, ramp_epochs=0, ibp_epochs=0,
                                            mode=mode), camera)(m, labels, 0.0)
        assert t is not None and float(t.detach()) > 0
        t.backward()
        grads = [p.grad for p in m.features.parameters() if p.grad is not None]
        assert grads and any(float(g.abs().sum()) > 0 for g in grads)  # it moves the conv weights too


def _eps(model, camera, cells):
    with torch.no_grad():
        return certified_error_bound(prepare(model.eval(), camera), cells, "crown").eps


def test_a_tiny_run_with_the_term_lowers_the_certified_bound(camera):
    """The same Lightning run (same data, seed and steps) with and without the term: the crown bound on held-out
    cells is lower with it, and the regression still learns."""
    images, labels = _batch(camera, 256, 2)
    _, held = _batch(camera, 32, 3)
    cells = torch.stack([held[:, 0] - 0.125, held[:, 0] + 0.125, held[:, 1] - 0.125, held[:, 1] + 0.125], 1)
    out = {}
    for on in (False, True):
        L.seed_everything(0, verbose=False)
        m = _model()
        if on:
            m.certified_term = CertifiedTerm(CertifiedTraining(weight=0.05, target=0.0, cell=0.25, cell_start=0.05,
                                                               warmup_epochs=1, ramp_epochs=1, ibp_epochs=1,
                                                               cells_per_step=8), camera)
        dl = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(images, labels), batch_size=32)
        trainer = L.Trainer(max_epochs=6, accelerator="cpu", logger=False, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False)
        trainer.fit(m, dl)
        out[on] = float(_eps(m, camera, cells).mean())
        if on:
            assert m.certified_term.last["mode"] == "crown" and m.certified_term.last["weight"] == 0.05
    assert out[True] < 0.8 * out[False], out


@pytest.mark.parametrize(("override", "field"), [
    ("certified.weight=-1", "certified.weight"), ("+certified.bogus=1", "certified.bogus"),
    ("certified.cell_start=1", "certified.cell_start"), ("certified.mode=tight", "certified.mode"),
    ("certified.cells_per_step=0", "certified.cells_per_step")])
def test_bad_keys_are_one_config_error(override, field):
    from pipeline.train.checks import check_settings

    with pytest.raises(ConfigError) as info:
        check_settings(compose("train", ["certified=on", override]))
    assert info.value.field == field and "\n" not in str(info.value)


def test_cli_bad_key_one_line_exit_2(tmp_path):
    proc = run_cli("pipeline.train", "certified=on", "certified.ramp_epochs=-1", f"paths.models_dir={tmp_path / 'm'}",
                   f"hydra.run.dir={tmp_path / 'run'}")  # `python -m pipeline.train`, in this process (tests/shared.py)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "certified.ramp_epochs" in lines[0], proc.stderr


def test_the_term_is_in_the_map_id():
    from pipeline import identity, tracking

    ids = [identity.map_identity(tracking.to_plain_lenient(compose("train", o)), "clean", "x")[1]
           for o in ([], ["certified=on"], ["certified=on", "certified.weight=0.01"])]
    assert len(set(ids)) == 3
