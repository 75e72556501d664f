"""Elo ratings by maximum likelihood from a matrix of game outcomes.

The model: player i beats j with probability 1 / (1 + 10 ** ((r_j - r_i) / 400)). The ratings that
maximise the likelihood of the observed wins (a draw counts half a win to each) are found with
Hunter's minorise-maximise iteration for the Bradley-Terry model (2004), the method of OpenSpiel's
``elo.compute_ratings_from_matrices``; `smoothing` adds that many wins to each side of every pair
that played, so that a player who won every game still gets a finite rating.
"""
from __future__ import annotations

import math

import numpy as np

SCALE = 400.0


def elo_ratings(wins, draws=None, *, anchor: int = 0, smoothing: float = 0.1, iterations: int = 10_000,
                tolerance: float = 1e-10) -> np.ndarray:
    """Ratings [n] from wins[i, j] (games i won against j) and draws[i, j] (symmetric or not: i's draws
    against j are added to both sides), with player `anchor` at 0."""
    wins = np.asarray(wins, dtype=np.float64)
    n = wins.shape[0]
    if wins.ndim != 2 or wins.shape != (n, n) or n < 2 or (wins < 0).any() or not np.isfinite(wins).all():
        raise ValueError(f"wins must be a square matrix of at least 2 players with counts >= 0, got shape "
                         f"{list(wins.shape)}")
    draws = np.zeros_like(wins) if draws is None else np.asarray(draws, dtype=np.float64)
    if draws.shape != wins.shape or (draws < 0).any():
        raise ValueError(f"draws must have the shape of wins {list(wins.shape)} with counts >= 0, got "
                         f"{list(draws.shape)}")
    if not 0 <= anchor < n:
        raise ValueError(f"anchor must be a player index in [0, {n}), got {anchor}")
    score = wins + 0.5 * (draws + draws.T)  # i's wins against j, a draw half a win
    games = score + score.T
    score = score + smoothing * (games > 0)
    games = score + score.T
    np.fill_diagonal(games, 0.0)
    gamma = np.ones(n)
    total = score.sum(1) - np.diag(score)
    for _ in range(iterations):
        updated = total / (games / (gamma[:, None] + gamma[None, :])).sum(1).clip(min=1e-300)
        updated = updated / math.exp(np.log(updated.clip(min=1e-300)).mean())
        done = np.abs(updated - gamma).max() < tolerance
        gamma = updated
        if done:
            break
    ratings = SCALE * np.log10(gamma.clip(min=1e-300))
    return ratings - ratings[anchor]


def win_probability(r_i: float, r_j: float) -> float:
    return 1.0 / (1.0 + 10.0 ** ((r_j - r_i) / SCALE))
