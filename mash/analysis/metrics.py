"""Evaluation metrics of the MASH paper (host-side NumPy/SciPy).

These run after the jitted rollouts, on arrays pulled back to the host, so they
use plain NumPy/SciPy rather than JAX. The four paper metrics are:

* ``T_conv``  -- :func:`convergence_iteration`, iterations to reach and stay
  within 5% of the asymptotic reward.
* ``S_action`` -- :func:`action_smoothness` (first difference) and
  :func:`action_smoothness_2nd` (second difference), lower is smoother.
* ``S_torso`` -- :func:`torso_stability`, weighted variance of base height and
  torso Euler angles, lower is more stable.
* ``C_limb`` -- :func:`limb_coordination`, mean absolute deviation (radians) of
  the left/right hip-pitch phase difference from a target (pi = antiphase gait).

:func:`all_metrics` computes all of them from a trajectory dict, and
:func:`seed_summary` / :func:`welch_ttest` aggregate results across seeds for
the MASH-vs-PPO comparison table.
"""

from __future__ import annotations

import warnings
from typing import Mapping, Sequence

import numpy as np
from scipy import signal, stats

__all__ = [
    "convergence_iteration",
    "smooth",
    "reach_iteration",
    "common_threshold_t_conv",
    "action_smoothness",
    "action_smoothness_2nd",
    "torso_stability",
    "limb_coordination",
    "arm_leg_coordination",
    "all_metrics",
    "seed_summary",
    "welch_ttest",
    "bootstrap_ci",
    "holm",
    "hedges_g",
    "verdict",
]


def _as_array(x, name: str, ndims: Sequence[int], expected: str) -> np.ndarray:
  """Converts ``x`` to a float64 array and checks its rank."""
  arr = np.asarray(x, dtype=np.float64)
  if arr.ndim not in ndims:
    raise ValueError(f"`{name}` must have shape {expected}, got shape {arr.shape}")
  if arr.size == 0:
    raise ValueError(f"`{name}` must be non-empty with shape {expected}, got {arr.shape}")
  return arr


def smooth(rewards, window: int) -> np.ndarray:
  """Trailing moving average ``[N]``: entry ``i`` is the mean of ``rewards[max(0, i - window +
  1) : i + 1]`` (shorter at the start)."""
  r = _as_array(rewards, "rewards", (1,), "[N] (N >= 1)")
  if window < 1:
    raise ValueError(f"`window` must be >= 1, got {window}")
  csum = np.concatenate([[0.0], np.cumsum(r)])
  idx = np.arange(r.shape[0])
  start = np.maximum(0, idx - window + 1)
  return (csum[idx + 1] - csum[start]) / (idx + 1 - start)


def reach_iteration(rewards, threshold: float, window: int) -> int | None:
  """The first iteration (1-based) at which the ``window``-smoothed curve reaches ``threshold``;
  None when it never does."""
  hit = np.flatnonzero(smooth(rewards, window) >= threshold)
  return int(hit[0]) + 1 if hit.size else None


def common_threshold_t_conv(curves: Mapping[str, np.ndarray], fraction: float = 0.9,
                            windows: Sequence[int] | None = None) -> dict:
  """``T_conv`` of several methods against one threshold, at several smoothing windows.

  The threshold is ``fraction`` of the lowest of the methods' final rewards (each the mean over
  its seeds of the mean of their last 10 % of iterations), so every method's curve can reach it
  and the first to do so converged faster; unlike the first iteration after which a curve
  *stays* near its own end, it does not hinge on the noise at the run's end.

  Args:
    curves: method -> ``[S, N]`` reward per iteration of each seed (the same N for all).
    fraction: share of the lowest final reward that counts as converged.
    windows: smoothing windows (iterations); default ``N/100, N/50, N/25`` (at least 1).

  Returns:
    ``{'threshold', 'windows', 'final': {method: ...}, 't_conv': {method: {window: [S] first
    iteration or None}}}``.
  """
  arrays = {k: np.atleast_2d(np.asarray(v, np.float64)) for k, v in curves.items()}
  n = next(iter(arrays.values())).shape[1]
  if any(a.shape[1] != n for a in arrays.values()):
    raise ValueError("every curve must have the same number of iterations")
  tail = max(1, int(round(0.1 * n)))
  final = {k: float(a[:, -tail:].mean()) for k, a in arrays.items()}
  lowest = min(final.values())
  threshold = lowest * fraction if lowest >= 0 else lowest * (2.0 - fraction)
  windows = [max(1, n // d) for d in (100, 50, 25)] if windows is None else list(windows)
  return {
      "threshold": float(threshold), "windows": windows, "final": final, "t_conv": {
          k: {w: [reach_iteration(row, threshold, w) for row in a] for w in windows}
          for k, a in arrays.items()
      }
  }


def convergence_iteration(rewards, window: int | None = None) -> tuple[int, dict]:
  """Iterations to convergence, ``T_conv``.

  The curve is smoothed with a *trailing* moving average: ``smoothed[i]`` is the
  mean of ``rewards[max(0, i - window + 1) : i + 1]`` (the first ``window - 1``
  points average over the shorter available prefix). The asymptote is the mean
  of the *raw* rewards over the last 10% of iterations (at least one).
  ``T_conv`` is the first index ``i`` such that ``smoothed[j] >= threshold`` for
  every ``j >= i``, where ``threshold = asymptote - 0.05 * |asymptote|``. For a
  positive asymptote this is exactly ``0.95 * asymptote``; for a negative one it
  means "within 5% of ``|asymptote|`` below it" (``0.95 * asymptote`` would lie
  *above* a negative asymptote and be unreachable).

  Args:
    rewards: Mean episode reward per training iteration, shape ``[N]``.
    window: Moving-average length in iterations. Defaults to
      ``max(1, N // 50)``.

  Returns:
    ``(T_conv, info)``, where ``info`` has keys ``asymptote``, ``window``,
    ``threshold`` and ``converged``. If even the last smoothed value is below
    the threshold, ``T_conv = N`` and ``converged`` is ``False``.

  Raises:
    ValueError: If ``rewards`` is not a non-empty 1-D array or ``window < 1``.
  """
  r = _as_array(rewards, "rewards", (1,), "[N] (N >= 1)")
  n = r.shape[0]
  window = max(1, n // 50) if window is None else int(window)
  if window < 1:
    raise ValueError(f"`window` must be >= 1, got {window}")
  csum = np.concatenate([[0.0], np.cumsum(r)])
  idx = np.arange(n)
  start = np.maximum(0, idx - window + 1)
  smoothed = (csum[idx + 1] - csum[start]) / (idx + 1 - start)
  tail = max(1, int(round(0.1 * n)))
  asymptote = float(np.mean(r[-tail:]))
  threshold = asymptote - 0.05 * abs(asymptote)
  below = np.nonzero(smoothed < threshold)[0]
  t_conv = 0 if below.size == 0 else int(below[-1]) + 1
  info = {
      "asymptote": asymptote,
      "window": window,
      "threshold": float(threshold),
      "converged": t_conv < n,
  }
  return t_conv, info


def _smoothness(actions, order: int) -> float:
  a = _as_array(actions, "actions", (2, 3), "[T, A] or [E, T, A]")
  if a.ndim == 2:
    a = a[None]
  t = a.shape[1]
  d = np.diff(a, n=order, axis=1)  # [E, T - order, A]; empty if T <= order
  per_episode = np.sum(d**2, axis=(1, 2)) / t
  return float(np.mean(per_episode))


def action_smoothness(actions) -> float:
  """First-difference action smoothness, ``S_action``.

  ``S_action = (1/T) * sum_{t=1}^{T-1} sum_i (a_{i,t+1} - a_{i,t})^2``; note the
  normalisation is ``1/T`` (not ``1/(T-1)``), as in the paper.

  Args:
    actions: Actions, shape ``[T, A]`` or ``[E, T, A]`` (then averaged over
      the ``E`` episodes).

  Returns:
    The metric as a Python float (0 when ``T < 2``).
  """
  return _smoothness(actions, 1)


def action_smoothness_2nd(actions) -> float:
  """Second-difference action smoothness, ``S_action_2nd``.

  ``(1/T) * sum_{t=2}^{T-1} sum_i (a_{i,t+1} - 2 a_{i,t} + a_{i,t-1})^2``.

  Args:
    actions: Actions, shape ``[T, A]`` or ``[E, T, A]`` (then averaged over
      the ``E`` episodes).

  Returns:
    The metric as a Python float (0 when ``T < 3``).
  """
  return _smoothness(actions, 2)


def torso_stability(base_height, euler, w_h: float = 1.0, w_theta: float = 1.0) -> float:
  """Torso stability, ``S_torso = w_h Var(h) + w_theta sum_k Var(theta_k)``.

  Variances are population variances (``ddof=0``) over time; ``k`` runs over
  roll, pitch and yaw. Yaw (``euler[..., 2]``) is unwrapped along time with
  ``np.unwrap`` first so a heading crossing +-pi does not inflate the variance.

  Args:
    base_height: Torso height, shape ``[T]`` or ``[E, T]``.
    euler: Torso (roll, pitch, yaw) in radians, shape ``[T, 3]`` or
      ``[E, T, 3]``, matching ``base_height``.
    w_h: Weight of the height variance.
    w_theta: Weight of the summed angle variances.

  Returns:
    The metric as a Python float, averaged over episodes when batched.
  """
  h = _as_array(base_height, "base_height", (1, 2), "[T] or [E, T]")
  e = np.asarray(euler, dtype=np.float64)
  if e.shape != h.shape + (3,):
    raise ValueError(f"`euler` must have shape {h.shape + (3,)} ([T, 3] or [E, T, 3] matching "
                     f"`base_height`), got shape {e.shape}")
  if h.ndim == 1:
    h, e = h[None], e[None]
  e = e.copy()
  e[..., 2] = np.unwrap(e[..., 2], axis=1)
  per_episode = w_h * np.var(h, axis=1) + w_theta * np.sum(np.var(e, axis=1), axis=-1)
  return float(np.mean(per_episode))


def _wrap(x: np.ndarray) -> np.ndarray:
  """Wraps angles to ``(-pi, pi]``."""
  return np.pi - np.mod(np.pi - x, 2.0 * np.pi)


def limb_coordination(hip_left, hip_right, target: float = np.pi) -> float:
  """Limb coordination, ``C_limb`` (radians, lower is better).

  The instantaneous phase of each mean-removed hip-pitch trajectory is the
  angle of its analytic signal (``scipy.signal.hilbert``, FFT-based over the
  whole trajectory, no edge trimming). Then
  ``C_limb = mean_t |wrap(phi_left - phi_right - target)|`` with ``wrap`` onto
  ``(-pi, pi]``. The Hilbert transform is exact for trajectories spanning an
  integer number of periods; otherwise the first/last few samples carry edge
  error, which is negligible for long rollouts.

  Args:
    hip_left: Left hip-pitch angle, shape ``[T]`` or ``[E, T]``.
    hip_right: Right hip-pitch angle, same shape as ``hip_left``.
    target: Desired phase difference; ``pi`` for an alternating gait.

  Returns:
    The metric as a Python float in ``[0, pi]``, averaged over episodes.
  """
  left = _as_array(hip_left, "hip_left", (1, 2), "[T] or [E, T]")
  right = np.asarray(hip_right, dtype=np.float64)
  if right.shape != left.shape:
    raise ValueError(
        f"`hip_right` must have the same shape as `hip_left` {left.shape}, got {right.shape}")
  if left.ndim == 1:
    left, right = left[None], right[None]

  def phase(x: np.ndarray) -> np.ndarray:
    return np.angle(signal.hilbert(x - x.mean(axis=1, keepdims=True), axis=1))

  dev = np.abs(_wrap(phase(left) - phase(right) - target))
  return float(np.mean(dev))


def arm_leg_coordination(shoulder_pitch, hip_pitch) -> float:
  """Arm-leg coordination (radians, lower is better): each arm should swing in phase with the
  opposite leg (on the T1 a negative angle moves the hand and the foot forward), so the mean of
  ``limb_coordination(shoulder_left, hip_right, target=0)`` and ``limb_coordination(
  shoulder_right, hip_left, target=0)``.

  Args:
    shoulder_pitch: ``[T, 2]`` or ``[E, T, 2]`` (left, right).
    hip_pitch: the same shape (left, right).
  """
  s = np.asarray(shoulder_pitch, dtype=np.float64)
  h = np.asarray(hip_pitch, dtype=np.float64)
  if s.shape != h.shape or s.shape[-1] != 2:
    raise ValueError(f"`shoulder_pitch` and `hip_pitch` must share a shape [..., T, 2], got "
                     f"{s.shape} and {h.shape}")
  return 0.5 * (limb_coordination(s[..., 0], h[..., 1], target=0.0) +
                limb_coordination(s[..., 1], h[..., 0], target=0.0))


def all_metrics(trajectories: Mapping[str, np.ndarray], rewards_per_iteration=None) -> dict:
  """Computes every paper metric from evaluation rollouts.

  Args:
    trajectories: Dict with ``actions [E, T, A]``, ``base_height [E, T]``,
      ``euler [E, T, 3]`` and ``hip_pitch [E, T, 2]`` (left, right).
    rewards_per_iteration: Optional training curve ``[N]``; when given,
      ``T_conv`` is included.

  Returns:
    Dict of Python floats with keys ``S_action``, ``S_action_2nd``,
    ``S_torso``, ``C_limb`` and, if rewards are given, ``T_conv``.
  """
  missing = {"actions", "base_height", "euler", "hip_pitch"} - set(trajectories)
  if missing:
    raise ValueError(f"`trajectories` is missing keys {sorted(missing)}")
  hip = np.asarray(trajectories["hip_pitch"], dtype=np.float64)
  if hip.ndim not in (2, 3) or hip.shape[-1] != 2:
    raise ValueError(f"`hip_pitch` must have shape [E, T, 2], got shape {hip.shape}")
  out = {
      "S_action": action_smoothness(trajectories["actions"]),
      "S_action_2nd": action_smoothness_2nd(trajectories["actions"]),
      "S_torso": torso_stability(trajectories["base_height"], trajectories["euler"]),
      "C_limb": limb_coordination(hip[..., 0], hip[..., 1]),
  }
  if rewards_per_iteration is not None:
    out["T_conv"] = float(convergence_iteration(rewards_per_iteration)[0])
  return out


def seed_summary(values: Sequence[float]) -> dict:
  """Mean and sample standard deviation (``ddof=1``) across seeds.

  Args:
    values: One metric value per seed, shape ``[S]``.

  Returns:
    ``{"mean", "std", "n"}``; ``std`` is 0.0 for a single seed, and ``mean``
    and ``std`` are NaN when ``values`` is empty.
  """
  v = np.asarray(values, dtype=np.float64).reshape(-1)
  n = int(v.size)
  if n == 0:
    return {"mean": float("nan"), "std": float("nan"), "n": 0}
  std = float(np.std(v, ddof=1)) if n > 1 else 0.0
  return {"mean": float(np.mean(v)), "std": std, "n": n}


def welch_ttest(a: Sequence[float], b: Sequence[float]) -> dict:
  """Welch's unequal-variance two-sample t-test (e.g. MASH vs PPO seeds).

  Args:
    a: Per-seed values of the first method, shape ``[S_a]``.
    b: Per-seed values of the second method, shape ``[S_b]``.

  Returns:
    ``{"t", "p"}`` (two-sided); both NaN when either sample has < 2 values.
  """
  a = np.asarray(a, dtype=np.float64).reshape(-1)
  b = np.asarray(b, dtype=np.float64).reshape(-1)
  if a.size < 2 or b.size < 2:
    return {"t": float("nan"), "p": float("nan")}
  with warnings.catch_warnings():
    # Per-seed fall rates sit on a 1/episodes grid, so one method's seeds often tie; scipy then
    # warns of precision loss in the variance although the statistic it returns is exact.
    warnings.filterwarnings("ignore", message="Precision loss occurred", category=RuntimeWarning)
    res = stats.ttest_ind(a, b, equal_var=False)
  return {"t": float(res.statistic), "p": float(res.pvalue)}


def bootstrap_ci(values: Sequence[float], level: float = 0.95, resamples: int = 10_000,
                 seed: int = 0) -> tuple[float, float]:
  """Percentile bootstrap confidence interval of the mean over seeds.

  Args:
    values: one value per seed, ``[S]``.
    level: coverage of the interval.
    resamples: bootstrap resamples (seeds drawn with replacement).
    seed: random seed of the resampling (the interval is reproducible).

  Returns:
    ``(lo, hi)``; ``(nan, nan)`` for no values, ``(v, v)`` for one.
  """
  v = np.asarray(values, dtype=np.float64).reshape(-1)
  if v.size == 0:
    return float("nan"), float("nan")
  rng = np.random.default_rng(seed)
  means = v[rng.integers(0, v.size, size=(resamples, v.size))].mean(axis=1)
  tail = (1.0 - level) / 2.0
  return float(np.quantile(means, tail)), float(np.quantile(means, 1.0 - tail))


def holm(pvalues: Sequence[float]) -> list[float]:
  """Holm-Bonferroni adjusted p-values (family-wise error over the metrics of one comparison).

  The i-th smallest of m p-values is multiplied by ``m - i`` (i from 0), made non-decreasing in
  that order and capped at 1; NaN p-values stay NaN and do not count in m.
  """
  p = np.asarray(pvalues, dtype=np.float64).reshape(-1)
  out = np.full_like(p, np.nan)
  finite = np.flatnonzero(np.isfinite(p))
  order = finite[np.argsort(p[finite], kind="stable")]
  m, running = len(order), 0.0
  for i, idx in enumerate(order):
    running = max(running, min(1.0, (m - i) * p[idx]))
    out[idx] = running
  return [float(x) for x in out]


def hedges_g(a: Sequence[float], b: Sequence[float]) -> float:
  """Standardized mean difference ``(mean a - mean b) / pooled std``, small-sample corrected by
  ``1 - 3 / (4 (n_a + n_b) - 9)``; NaN with fewer than 2 values a side or no spread at all."""
  a = np.asarray(a, dtype=np.float64).reshape(-1)
  b = np.asarray(b, dtype=np.float64).reshape(-1)
  if a.size < 2 or b.size < 2:
    return float("nan")
  pooled = np.sqrt(
      ((a.size - 1) * a.var(ddof=1) + (b.size - 1) * b.var(ddof=1)) / (a.size + b.size - 2))
  if pooled == 0:
    return float("nan")
  correction = 1.0 - 3.0 / (4.0 * (a.size + b.size) - 9.0)
  return float((a.mean() - b.mean()) / pooled * correction)


def verdict(mean_a: float, mean_b: float, p_adjusted: float, lower_is_better: bool,
            names: tuple[str, str] = ("MASH", "PPO"), alpha: float = 0.05) -> str:
  """``'<a> better'``, ``'<b> better'`` or ``'no difference at this power'``: a side is better
  only when the (Holm-adjusted) p is below ``alpha`` and its mean is on the better side."""
  if not (np.isfinite(p_adjusted) and p_adjusted < alpha and np.isfinite(mean_a) and
          np.isfinite(mean_b)) or mean_a == mean_b:
    return "no difference at this power"
  a_better = (mean_a < mean_b) == lower_is_better
  return f"{names[0] if a_better else names[1]} better"


def t_test_power(effect: float, n_a: int, n_b: int, alpha: float) -> float:
  """Power of a two-sided two-sample t-test at level ``alpha`` to detect a standardized mean
  difference ``effect`` (Cohen's d, or Hedges' g as an estimate of it) with ``n_a`` and ``n_b``
  seeds: the noncentral t with ``n_a + n_b - 2`` degrees of freedom and noncentrality
  ``|effect| sqrt(n_a n_b / (n_a + n_b))`` beyond the test's critical values. NaN for fewer than 2
  values a side or a NaN effect."""
  if n_a < 2 or n_b < 2 or not np.isfinite(effect):
    return float("nan")
  df = n_a + n_b - 2
  nc = abs(effect) * np.sqrt(n_a * n_b / (n_a + n_b))
  t = stats.t.ppf(1.0 - alpha / 2.0, df)
  upper = stats.nct.sf(t, df, nc)  # scipy returns NaN far in the tail: there it is 1 (or 0)
  lower = stats.nct.cdf(-t, df, nc)
  upper = 1.0 if np.isnan(upper) else float(upper)
  lower = 0.0 if np.isnan(lower) else float(lower)
  return min(1.0, upper + lower)


def detectable_effect(n_a: int, n_b: int, alpha: float, power: float = 0.8) -> float:
  """The smallest standardized effect (Cohen's d) that :func:`t_test_power` detects with
  ``power`` at ``alpha`` with ``n_a`` and ``n_b`` seeds (bisection; NaN below 2 values a side)."""
  if n_a < 2 or n_b < 2:
    return float("nan")
  lo, hi = 0.0, 1.0
  while t_test_power(hi, n_a, n_b, alpha) < power:
    lo, hi = hi, 2.0 * hi
  for _ in range(60):
    mid = 0.5 * (lo + hi)
    lo, hi = (mid, hi) if t_test_power(mid, n_a, n_b, alpha) < power else (lo, mid)
  return hi
