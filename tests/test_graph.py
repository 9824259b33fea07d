import math

import numpy as np
import pytest

from sb3_hgrn.envs import graph
from sb3_hgrn.envs.graph import grid_neighbors


def brute_force_neighbors(cells: np.ndarray, radius: float, max_neighbors: int, metric: str) -> np.ndarray:
    """Reference: per agent, sort every other agent in range by (float distance, index)."""
    neighbor_lists = np.full((len(cells), max_neighbors), -1, dtype=np.int64)
    for i, (x, y) in enumerate(cells.tolist()):
        in_range = []
        for j, (other_x, other_y) in enumerate(cells.tolist()):
            dx, dy = other_x - x, other_y - y
            distance = max(abs(dx), abs(dy)) if metric == "chebyshev" else math.hypot(dx, dy)
            if j != i and distance <= radius:
                in_range.append((distance, j))
        row = [i] + [j for _, j in sorted(in_range)]
        row = row[:max_neighbors]
        neighbor_lists[i, : len(row)] = row
    return neighbor_lists


@pytest.fixture(params=["dense", "blocked"])
def search_path(request, monkeypatch):
    """Run a test through both the dense (all pairs) and the blocked (linear) search."""
    if request.param == "blocked":
        monkeypatch.setattr(graph, "DENSE_MAX_AGENTS", 0)
    return request.param


@pytest.mark.parametrize("metric", ["chebyshev", "euclidean"])
def test_matches_brute_force_on_random_inputs(metric, search_path):
    rng = np.random.default_rng(0)
    for _ in range(25):
        n_agents = int(rng.integers(1, 120))
        size = int(rng.integers(2, 25))
        lowest = int(rng.integers(-20, 20))
        cells = rng.integers(lowest, lowest + size, size=(n_agents, 2))
        cells[: n_agents // 4] = cells[0]  # many agents on one cell
        radius = float(rng.choice([0.0, 1.0, 2.5, 3.0, 5.0, 18.0]))
        max_neighbors = int(rng.integers(1, 20))  # rows often truncated
        expected = brute_force_neighbors(cells, radius, max_neighbors, metric)
        result = grid_neighbors(cells, radius, max_neighbors, metric)
        assert result.dtype == np.int64
        np.testing.assert_array_equal(result, expected)


@pytest.mark.parametrize("metric", ["chebyshev", "euclidean"])
def test_far_apart_and_huge_radius(metric, search_path):
    rng = np.random.default_rng(1)
    cells = rng.integers(-100_000, 100_000, size=(60, 2))
    cells[30:] = cells[:30] + rng.integers(-2, 3, size=(30, 2))
    for radius in (2.0, 1e9):
        expected = brute_force_neighbors(cells, radius, 70, metric)
        np.testing.assert_array_equal(grid_neighbors(cells, radius, 70, metric), expected)


def test_hand_computed_rows():
    cells = np.array([[5, 5], [5, 5], [6, 7], [5, 6], [9, 9], [4, 4]])
    result = grid_neighbors(cells, 2, 5, "chebyshev")
    expected = np.array(
        [
            [0, 1, 3, 5, 2],  # distance 0: agent 1; distance 1: agents 3 and 5; distance 2: agent 2
            [1, 0, 3, 5, 2],  # self first even though agent 0 shares the cell and has a lower index
            [2, 3, 0, 1, -1],  # agent 3 at distance 1, agents 0 and 1 at distance 2
            [3, 0, 1, 2, 5],
            [4, -1, -1, -1, -1],  # nobody in range: only self, then padding
            [5, 0, 1, 3, -1],
        ]
    )
    np.testing.assert_array_equal(result, expected)


def test_euclidean_excludes_corners_that_chebyshev_includes():
    cells = np.array([[0, 0], [2, 2], [2, 0]])
    np.testing.assert_array_equal(grid_neighbors(cells, 2, 3, "chebyshev")[0], [0, 1, 2])
    np.testing.assert_array_equal(grid_neighbors(cells, 2, 3, "euclidean")[0], [0, 2, -1])


def test_large_population_uses_linear_path_and_is_correct():
    rng = np.random.default_rng(2)
    n_agents = 600
    assert n_agents > graph.DENSE_MAX_AGENTS
    cells = rng.integers(0, 80, size=(n_agents, 2))
    result = grid_neighbors(cells, 3, 12)
    expected = brute_force_neighbors(cells, 3, 12, "chebyshev")
    np.testing.assert_array_equal(result, expected)


def test_more_columns_than_agents_are_padded():
    result = grid_neighbors(np.array([[0, 0], [0, 1]]), 1, 4)
    np.testing.assert_array_equal(result, [[0, 1, -1, -1], [1, 0, -1, -1]])
    assert grid_neighbors(np.zeros((0, 2), dtype=np.int64), 1, 3).shape == (0, 3)


@pytest.mark.parametrize(
    "cells, radius, max_neighbors, metric",
    [
        (np.zeros((3, 3), dtype=np.int64), 1, 4, "chebyshev"),
        (np.zeros((3, 2)), 1, 4, "chebyshev"),
        (np.zeros((3, 2), dtype=np.int64), -1, 4, "chebyshev"),
        (np.zeros((3, 2), dtype=np.int64), 1, 0, "chebyshev"),
        (np.zeros((3, 2), dtype=np.int64), 1, 4, "manhattan"),
    ],
)
def test_invalid_arguments_raise(cells, radius, max_neighbors, metric):
    with pytest.raises(ValueError):
        grid_neighbors(cells, radius, max_neighbors, metric)
