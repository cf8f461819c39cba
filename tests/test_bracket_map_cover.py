"""How a grid cell of the abstraction reads the certified error map (issue 48): the largest `eps_bar` of the table
cells meeting its box, `inf` where they do not cover it. Found 2026-12-05: the grid reaches one cell past the arena
and certify's tables tile it (the operational set, the diamond, the border apart), so every grid cell at the
arena's edge or on a seam between tables read `inf`, and the map certified 80 start cells where a bound capped at
2 everywhere certified 144. A grid cell is now read on its part inside the arena, and tables that tile are read as
one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.bracket.bounds import CellTable, Finest
from tests.test_bracket_map_falsifier import tables_and_points


def _brute(cells: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The reading by every pair (the implementation before the bucket index): the largest bound of the cells
    meeting the box, `inf` where the area they cover falls short of the box's."""
    ox = np.minimum(hi[:, None, 0], cells[None, :, 1]) - np.maximum(lo[:, None, 0], cells[None, :, 0])
    oy = np.minimum(hi[:, None, 1], cells[None, :, 3]) - np.maximum(lo[:, None, 1], cells[None, :, 2])
    meet = (ox >= 0) & (oy >= 0)
    out = np.where(meet, cells[None, :, 4], -np.inf).max(axis=1)
    covered = (np.clip(ox, 0, None) * np.clip(oy, 0, None)).sum(axis=1)
    area = (hi[:, 0] - lo[:, 0]) * (hi[:, 1] - lo[:, 1])
    return np.where(covered < area * (1 - 1e-9), np.inf, out)


@st.composite
def tables_and_boxes(draw):
    """A grid of square cells, some split in four, some missing (the falsifier's test's tables, as the certify stage
    writes them), and boxes of any size anywhere, edges on the cells' lines included."""
    cells, _ = draw(tables_and_points())
    h = float((cells[:, 1] - cells[:, 0]).max())
    origin = cells[:, [0, 2]].min(axis=0)
    k = draw(st.integers(1, 25))
    q = st.integers(-2, 16)
    a = np.array(draw(st.lists(st.tuples(q, q, st.integers(0, 6), st.integers(0, 6)), min_size=k, max_size=k)), float)
    lo = origin + a[:, :2] * h / 2
    hi = lo + a[:, 2:] * h / 3 + 1e-3
    return cells, lo, hi


@given(tables_and_boxes())
@settings(max_examples=120, deadline=None)
def test_a_grid_cell_reads_the_largest_bound_meeting_it_or_inf_where_uncovered(case):
    cells, lo, hi = case
    boxes = np.column_stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]])
    np.testing.assert_array_equal(CellTable(cells)(None, boxes), _brute(cells, lo, hi))


def _grid(x0, x1, y0, y1, eps, h=0.25):
    xs, ys = np.arange(x0, x1, h), np.arange(y0, y1, h)
    return np.array([(x, x + h, y, y + h, eps(x, y)) for x in xs for y in ys])


def test_tables_that_tile_are_read_as_one_and_overlapping_ones_are_not():
    left = _grid(-2.0, 0.0, -1.0, 1.0, lambda x, y: 1.0)
    right = _grid(0.0, 2.0, -1.0, 1.0, lambda x, y: 2.0)
    seam = np.array([[-0.5, 0.5, -0.5, 0.5]])  # half in each
    a, b = CellTable(left), CellTable(right)
    assert np.isinf(a(None, seam)).all() and np.isinf(b(None, seam)).all()
    tiled = Finest([a, b])
    assert tiled.union is not None
    np.testing.assert_array_equal(tiled(None, seam), [2.0])  # the largest bound meeting it
    np.testing.assert_array_equal(tiled(None, np.array([[-1.5, -1.0, 0.0, 0.5]])), [1.0])  # one table alone
    finer = CellTable(_grid(-1.0, 1.0, -1.0, 1.0, lambda x, y: 0.5, h=0.125))  # overlaps both, not identical
    both = Finest([a, b, finer])
    assert both.union is None  # its area would count twice: no union
    np.testing.assert_array_equal(both(None, seam), [0.5])  # the finer table covers it alone
    np.testing.assert_array_equal(both(None, np.array([[-1.75, 0.25, 0.0, 0.5]])), [np.inf])  # no table alone
    same = Finest([CellTable(left), CellTable(np.column_stack([left[:, :4], left[:, 4] * 3]))])
    assert same.union is not None  # identical cells: the smaller bound
    np.testing.assert_array_equal(same(None, np.array([[-1.0, -0.5, 0.0, 0.5]])), [1.0])


def test_a_grid_cell_is_read_on_its_part_inside_the_arena():
    arena = ((-2.0, 2.0), (-1.0, 1.0))
    cells = _grid(-2.0, 2.0, -1.0, 1.0, lambda x, y: 1.0 + (x < -1.5))
    straddles = np.array([[-2.5, -1.6, 0.0, 0.5], [1.5, 2.5, 0.5, 1.5]])
    outside = np.array([[-3.0, -2.5, 0.0, 0.5]])
    assert np.isinf(CellTable(cells)(None, straddles)).all()  # the part outside the arena has no cell
    t = CellTable(cells, arena=arena)
    np.testing.assert_array_equal(t(None, straddles), [2.0, 1.0])
    assert np.isinf(t(None, outside)).all()  # no part inside: as before
    with pytest.raises(ValueError, match="grid cells"):
        t(np.zeros((1, 2)))
