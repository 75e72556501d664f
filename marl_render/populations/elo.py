"""Elo ratings by maximum likelihood from a matrix of game outcomes.

The model: player i beats j with probability 1 / (1 + 10 ** ((r_j - r_i) / 400)). The ratings that
maximise the likelihood of the observed wins (a draw counts half a win to each) are found with
Hunter's minorise-maximise iteration for the Bradley-Terry model (2004), the method of OpenSpiel's
``elo.compute_ratings_from_matrices``; `smoothing` adds that many wins to each side of every pair
that played, so that a player who won every game still gets a finite rating.

Ratings are defined only where the games tie every player to every other, so ``elo_ratings``
raises a ValueError, never returns NaN or inf, when they are not:

* a player who played no game (an all-zero matrix has only such players);
* two groups of players that never met, directly or through others;
* with ``smoothing=0``, a group that won (or lost) every game it played against the others (a clean
  sweep): its maximum-likelihood rating lies at infinity. Any smoothing > 0 makes it finite.
"""
from __future__ import annotations

import math
import numbers

import numpy as np

SCALE = 400.0


def elo_ratings(wins, draws=None, *, anchor: int = 0, smoothing: float = 0.1, iterations: int = 10_000,
                tolerance: float = 1e-10) -> np.ndarray:
    """Ratings [n] (float64, all finite) from wins[i, j] (games i won against j) and draws[i, j]
    (symmetric or not: i's draws against j are added to both sides), with player `anchor` at 0.
    The diagonal (a player against itself) is ignored. ValueError / TypeError for counts that are
    not finite and >= 0, and for outcomes that leave a rating undefined (see the module docstring)."""
    wins = _counts("wins", wins)
    square = wins.ndim == 2 and wins.shape[0] == wins.shape[1] and wins.shape[0] >= 2
    if not square or not np.isfinite(wins).all() or (wins < 0).any():
        raise ValueError(f"wins must be a square matrix of at least 2 players with finite counts >= 0, got shape "
                         f"{list(wins.shape)}" + ("" if not square else " holding NaN, inf or negative counts"))
    n = wins.shape[0]
    draws = np.zeros_like(wins) if draws is None else _counts("draws", draws)
    if draws.shape != wins.shape or not np.isfinite(draws).all() or (draws < 0).any():
        raise ValueError(f"draws must have the shape of wins {list(wins.shape)} with finite counts >= 0, got "
                         f"shape {list(draws.shape)}" + ("" if draws.shape != wins.shape else
                                                          " holding NaN, inf or negative counts"))
    if isinstance(anchor, (bool, np.bool_)) or not isinstance(anchor, numbers.Integral):
        raise TypeError(f"anchor must be a player index (an int) in [0, {n}), got {anchor!r}")
    if not 0 <= anchor < n:
        raise ValueError(f"anchor must be a player index in [0, {n}), got {anchor}")
    if isinstance(smoothing, bool) or not isinstance(smoothing, numbers.Real) or not (
            math.isfinite(smoothing) and smoothing >= 0):
        raise ValueError(f"smoothing must be a finite number >= 0 (wins added to each side of every pair that "
                         f"played), got {smoothing!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, numbers.Integral) or iterations < 1:
        raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
    if isinstance(tolerance, bool) or not isinstance(tolerance, numbers.Real) or not tolerance > 0:
        raise ValueError(f"tolerance must be a number > 0, got {tolerance!r}")
    with np.errstate(over="ignore"):  # sums past float64's range are refused below, by name
        score = wins + 0.5 * (draws + draws.T)  # i's wins against j, a draw half a win
        np.fill_diagonal(score, 0.0)
        games = score + score.T
        _check_defined(score, games, smoothing)
        score = score + smoothing * (games > 0)
        games = score + score.T
        totals = games.sum(1)
    if not np.isfinite(totals).all():  # sums past float64's range: the iteration would divide inf by inf
        raise ValueError(f"wins, draws and smoothing must give finite game counts (each player's total below "
                         f"{np.finfo(np.float64).max:.3g}), got sums that overflow to inf: scale the counts down "
                         f"(the ratings depend on their ratios)")
    gamma = np.ones(n)
    total = score.sum(1)
    for _ in range(iterations):
        updated = total / (games / (gamma[:, None] + gamma[None, :])).sum(1).clip(min=1e-300)
        updated = updated / math.exp(np.log(updated.clip(min=1e-300)).mean())
        done = np.abs(updated - gamma).max() < tolerance
        gamma = updated
        if done:
            break
    ratings = SCALE * np.log10(gamma.clip(min=1e-300))
    return ratings - ratings[anchor]


def _counts(name: str, value) -> np.ndarray:
    """`value` (an array, nested lists or a tensor, which may require grad) as float64; TypeError
    naming `name` for values that are not real numbers (complex counts lose their imaginary part)."""
    if hasattr(value, "detach"):  # a torch tensor: numpy() refuses one that requires grad
        value = value.detach().cpu().numpy()
    array = np.asarray(value)
    if array.dtype.kind not in "biuf":
        raise TypeError(f"{name} must hold real counts (ints or floats), got dtype {array.dtype}")
    return array.astype(np.float64)


def _check_defined(score: np.ndarray, games: np.ndarray, smoothing: float) -> None:
    """ValueError where the outcomes leave a rating undefined: a player without games, groups that
    never met, or (smoothing 0) a group that won or lost every game against the rest."""
    idle = np.flatnonzero(games.sum(1) == 0)
    if len(idle):
        raise ValueError(f"wins and draws must give every player a game: player(s) {idle.tolist()} played none, so "
                         f"their ratings are undefined (leave them out of the matrix)")
    apart = _unreached(games > 0)
    if len(apart):
        raise ValueError(f"wins and draws must connect every player to every other through games played: player(s) "
                         f"{apart.tolist()} never met player 0 directly or through others, so the two groups' "
                         f"ratings are not comparable")
    if smoothing == 0:  # every player must beat, and be beaten by, every other through a chain of wins
        swept = np.union1d(_unreached(score > 0), _unreached(score.T > 0))
        if len(swept):
            raise ValueError(f"smoothing=0 leaves a rating infinite: player(s) {swept.tolist()} won or lost every "
                             f"game against player 0's group (a clean sweep); pass smoothing > 0 (the default 0.1)")

def _unreached(edges: np.ndarray) -> np.ndarray:
    """The players that player 0 does not reach along `edges` [n, n] (bool, i -> j), sorted."""
    reach = edges | np.eye(len(edges), dtype=bool)
    for _ in range(max(1, math.ceil(math.log2(len(edges))))):  # path lengths double each pass
        reach = reach | ((reach.astype(np.int64) @ reach.astype(np.int64)) > 0)
    return np.flatnonzero(~reach[0])


def win_probability(r_i: float, r_j: float) -> float:
    return 1.0 / (1.0 + 10.0 ** ((r_j - r_i) / SCALE))
