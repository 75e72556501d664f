"""elo_ratings never returns NaN silently: undefined ratings and bad arguments are clear errors."""
from __future__ import annotations

import math

import numpy as np
import pytest

from marl_render.elo import elo_ratings


@pytest.mark.parametrize("wins, draws, words", [
    ([[0, 3, 0], [1, 0, 0], [0, 0, 0]], None, r"player\(s\) \[2\] played none"),
    (np.zeros((3, 3)), None, r"player\(s\) \[0, 1, 2\] played none"),
    ([[0, 0], [0, 0]], [[0, 0], [0, 0]], r"played none"),
    # Two pairs that never met each other: the groups' ratings are not comparable.
    ([[0, 2, 0, 0], [1, 0, 0, 0], [0, 0, 0, 2], [0, 0, 1, 0]], None, r"player\(s\) \[2, 3\] never met player 0"),
    ([[0, 1], [1, 0]], [[0, math.nan], [0, 0]], r"draws must .* finite counts >= 0.*NaN, inf or negative"),
    ([[0, 1], [1, 0]], [[0, math.inf], [0, 0]], r"draws must .* finite counts >= 0.*NaN, inf or negative"),
    ([[0, math.nan], [1, 0]], None, r"wins must be a square matrix .* NaN, inf or negative"),
])
def test_undefined_ratings_are_errors(wins, draws, words):
    with pytest.raises(ValueError, match=words):
        elo_ratings(wins, draws)


@pytest.mark.parametrize("smoothing", [-1, math.nan, math.inf, "0.1", True])
def test_smoothing_must_be_a_finite_number_at_least_zero(smoothing):
    with pytest.raises(ValueError, match=r"smoothing must be a finite number >= 0 .*got"):
        elo_ratings([[0, 3], [1, 0]], smoothing=smoothing)


def test_smoothing_zero_with_a_clean_sweep_is_an_error_and_smoothing_makes_it_finite():
    sweep = [[0, 5, 4], [0, 0, 2], [0, 1, 0]]  # player 0 won every game it played
    with pytest.raises(ValueError, match=r"smoothing=0 leaves a rating infinite: player\(s\) \[1, 2\]"):
        elo_ratings(sweep, smoothing=0.0)
    ratings = elo_ratings(sweep)  # the default smoothing: finite, the sweeper on top
    assert ratings.shape == (3,) and np.isfinite(ratings).all() and ratings[0] == 0 and (ratings[1:] < 0).all()
    # Draws tie the players both ways: no sweep, a finite maximum-likelihood rating without smoothing.
    assert np.isfinite(elo_ratings([[0, 1], [0, 0]], [[0, 1], [0, 0]], smoothing=0.0)).all()


@pytest.mark.parametrize("anchor, error", [(True, TypeError), (1.5, TypeError), (np.float64(1.0), TypeError),
                                           (2, ValueError), (-1, ValueError)])
def test_anchor_must_be_a_player_index(anchor, error):
    with pytest.raises(error, match=r"anchor must be a player index"):
        elo_ratings([[0, 3], [1, 0]], anchor=anchor)


def test_anchor_picks_the_zero_and_the_result_is_one_dimensional():
    ratings = elo_ratings([[0, 3], [1, 0]], anchor=np.int64(1))
    assert ratings.shape == (2,) and ratings[1] == 0 and ratings[0] > 0


@pytest.mark.parametrize("wins", [3, 3.0, [1, 2], [[[0]]], [[0]]])
def test_wins_that_are_not_a_square_matrix_are_refused(wins):
    with pytest.raises(ValueError, match=r"wins must be a square matrix of at least 2 players"):
        elo_ratings(wins)
