"""Fig. 4 drawn from code, and the leader-follower GIF (issue 12 §3, §4)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

from pipeline.control import Scene
from pipeline.experiments.paper.animation import frame_indices, leader_follower_gif
from pipeline.experiments.paper.scheme import scheme_figure


def _texts(fig: Figure) -> str:
    out = [t.get_text() for ax in fig.axes for t in ax.texts]
    out += [ax.get_title() for ax in fig.axes]
    return "\n".join(out)


def test_scheme_draws_the_named_blocks():
    fig = scheme_figure()
    assert isinstance(fig, Figure)
    text = _texts(fig)
    for name in (r"h(p)", r"\ell(\theta)", "flow set $C$", "jump set $D$", "mode $q", r"-k \nabla V_q",
                 r"\dot p = u", "disturbance $e$", "p_{fail}", "occlusion", "hybrid supervisor", "camera",
                 "perception map", "vehicle", r"\chi V_{3-q}", r"(\chi-\lambda) V_{3-q}"):
        assert name in text, name
    # the mathtext renders (a typo in a formula fails here)
    fig.canvas.draw()


def test_frame_indices():
    np.testing.assert_array_equal(frame_indices(5, 10), np.arange(5))
    idx = frame_indices(1000, 60)
    assert len(idx) == 60 and idx[0] == 0 and idx[-1] == 999 and np.all(np.diff(idx) > 0)
    with pytest.raises(ValueError):
        frame_indices(0, 5)


@pytest.mark.parametrize("callable_frames", [False, True])
def test_leader_follower_gif(tmp_path, callable_frames):
    scene = Scene(target=(40.0, 0.0))
    T, H, W = 40, 12, 20
    t = np.linspace(0, 4, T)
    lead = np.stack([np.linspace(-40, 30, T), np.linspace(10, 0, T)], axis=1)
    foll = lead - [5.0, 2.0]
    seen = lead + np.random.default_rng(0).normal(0, 0.5, (T, 2))
    seen[5] = np.nan  # no estimate at that frame
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 255, (T, H, W, 3), dtype=np.uint8)
    calls = []

    def render(k):
        calls.append(k)
        return frames[k]

    out = leader_follower_gif(tmp_path / "lf.gif", scene, ((-50, 50), (-30, 30)), t, lead, foll, seen,
                              render if callable_frames else frames, fps=5, max_frames=7, dpi=40, title="test")
    assert out == tmp_path / "lf.gif" and out.exists()
    with Image.open(out) as img:
        assert img.format == "GIF"
        assert img.n_frames == 7
        assert img.size == (400, 144)  # figsize (10, 3.6) at dpi 40
    if callable_frames:
        assert set(calls) <= set(frame_indices(T, 7).tolist())  # only the frames drawn are rendered
    with pytest.raises(ValueError, match="foll_p"):
        leader_follower_gif(tmp_path / "x.gif", scene, ((-50, 50), (-30, 30)), t, lead, foll[:-1], seen, frames)


def test_a_gif_is_the_bytes_funcanimation_writes_each_frame_drawn_once(tmp_path):
    """`pipeline.viz.save_gif` (every GIF of the experiments) writes the bytes matplotlib's `FuncAnimation.save`
    with the Pillow writer writes, drawing each frame once where that draws it twice."""
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    from pipeline.viz import save_gif

    def figure():
        fig, ax = plt.subplots(figsize=(3, 2))
        line, = ax.plot([], [], "-o")
        ax.set_xlim(0, 6)
        ax.set_ylim(-1, 1)
        title = ax.set_title("")
        draws = []
        fig.canvas.mpl_connect("draw_event", lambda _: draws.append(1))

        def update(j):
            x = np.linspace(0, j + 1, 20)
            line.set_data(x, np.sin(3 * x))
            title.set_text(f"frame {j}")
        return fig, update, draws

    fig, update, draws_before = figure()
    FuncAnimation(fig, update, frames=5, blit=False).save(tmp_path / "a.gif", writer=PillowWriter(fps=4), dpi=50)
    plt.close(fig)
    fig, update, draws = figure()
    assert save_gif(fig, update, 5, tmp_path / "b.gif", fps=4, dpi=50) == tmp_path / "b.gif"
    assert (tmp_path / "b.gif").read_bytes() == (tmp_path / "a.gif").read_bytes()
    assert len(draws) == 5 and len(draws_before) > 5
