"""Tests for mash.analysis.metrics (hand-computed expectations in comments)."""

import warnings

import numpy as np
import pytest

from mash.analysis import metrics

# 1000 samples, period 100 -> exactly 10 periods, so the FFT-based Hilbert
# transform is exact (no edge trimming needed).
T_GAIT = 1000
PERIOD = 100
TT = np.arange(T_GAIT)
W = 2 * np.pi * TT / PERIOD


# ----------------------------------------------------------------- C_limb
def test_c_limb_antiphase_is_zero():
  # phi_L - phi_R = pi exactly; minus target pi -> 0.
  c = metrics.limb_coordination(0.3 + np.sin(W), -0.2 - np.sin(W))
  assert c < 1e-2


def test_c_limb_inphase_is_pi():
  # phi_L - phi_R = 0; |wrap(0 - pi)| = |pi| = pi.
  c = metrics.limb_coordination(np.sin(W), 2.0 * np.sin(W))
  assert c == pytest.approx(np.pi, abs=1e-2)


def test_c_limb_quarter_phase():
  # Right lags by pi/2 -> diff pi/2; |wrap(pi/2 - pi)| = pi/2.
  c = metrics.limb_coordination(np.sin(W), np.sin(W - np.pi / 2))
  assert c == pytest.approx(np.pi / 2, abs=1e-2)


def test_c_limb_batched_is_mean_over_episodes():
  # Episode 0 antiphase (0), episode 1 in phase (pi) -> mean pi/2.
  left = np.stack([np.sin(W), np.sin(W)])
  right = np.stack([-np.sin(W), np.sin(W)])
  assert metrics.limb_coordination(left, right) == pytest.approx(np.pi / 2, abs=1e-2)


# --------------------------------------------------------------- S_action
def test_constant_action_is_zero():
  a = np.full((50, 4), 0.7)
  assert metrics.action_smoothness(a) == 0.0
  assert metrics.action_smoothness_2nd(a) == 0.0


def test_action_smoothness_hand_computed():
  # diffs 1, 2 -> (1 + 4) / T=3 = 5/3 (1/T, not 1/(T-1)).
  a = np.array([[0.0], [1.0], [3.0]])
  assert metrics.action_smoothness(a) == pytest.approx(5.0 / 3.0)
  # 2nd diff: 3 - 2*1 + 0 = 1 -> 1 / 3.
  assert metrics.action_smoothness_2nd(a) == pytest.approx(1.0 / 3.0)


def test_action_smoothness_sums_over_dims():
  # dim0 diffs 1,2 -> 5; dim1 diffs -1,-1 -> 2; total 7 / T=3.
  a = np.array([[0.0, 0.0], [1.0, -1.0], [3.0, -2.0]])
  assert metrics.action_smoothness(a) == pytest.approx(7.0 / 3.0)


def test_linear_ramp_second_difference_zero():
  # a_t = 2t - 1: first diffs all 2 -> 19 * 2^2 / 20 = 3.8; second diffs 0.
  a = (2.0 * np.arange(20) - 1.0)[:, None]
  assert metrics.action_smoothness(a) == pytest.approx(3.8)
  assert metrics.action_smoothness_2nd(a) == pytest.approx(0.0, abs=1e-12)


def test_action_smoothness_batched():
  # Episode 0: 5/3 (above); episode 1 constant: 0 -> mean 5/6.
  a = np.stack([np.array([[0.0], [1.0], [3.0]]), np.zeros((3, 1))])
  assert metrics.action_smoothness(a) == pytest.approx(5.0 / 6.0)


# ---------------------------------------------------------------- S_torso
def test_torso_stability_known_variances():
  # h = 1 +/- 0.2 -> Var 0.04; roll const -> 0; pitch +/- 0.1 -> 0.01;
  # yaw alternates pi-0.05 / -pi+0.05: unwrapped pi -/+ 0.05 -> Var 0.0025.
  # S = 2*0.04 + 3*(0 + 0.01 + 0.0025) = 0.08 + 0.0375 = 0.1175.
  sgn = np.where(np.arange(100) % 2 == 0, 1.0, -1.0)
  h = 1.0 + 0.2 * sgn
  euler = np.stack(
      [np.full(100, 0.3), 0.1 * sgn,
       np.where(sgn > 0, np.pi - 0.05, -np.pi + 0.05)],
      axis=-1,
  )
  assert metrics.torso_stability(h, euler) == pytest.approx(0.04 + 0.01 + 0.0025)
  assert metrics.torso_stability(h, euler, w_h=2.0, w_theta=3.0) == pytest.approx(0.1175)


def test_torso_stability_batched():
  # Episode 0: Var(h) = a^2 = 0.25; episode 1: all constant -> 0; mean 0.125.
  sgn = np.where(np.arange(10) % 2 == 0, 1.0, -1.0)
  h = np.stack([0.5 * sgn, np.ones(10)])
  euler = np.zeros((2, 10, 3))
  assert metrics.torso_stability(h, euler) == pytest.approx(0.125)


# ----------------------------------------------------------------- T_conv
def test_t_conv_exponential_rise():
  # r_i = 1 - exp(-i/100), i = 0..999. Asymptote = mean over i=900..999
  # = 1 - e^-9 (1 - e^-1) / (100 (1 - e^-0.01)) ~= 1 - 7.84e-5 = 0.9999216.
  # Threshold 0.95 * 0.9999216 = 0.9499255 -> exp(-i/100) <= 0.0500745
  # -> i >= 100 * ln(1/0.0500745) ~= 299.42 -> T_conv = 300.
  r = 1.0 - np.exp(-np.arange(1000) / 100.0)
  t, info = metrics.convergence_iteration(r, window=1)
  assert t == 300
  assert info["asymptote"] == pytest.approx(0.9999216, abs=1e-6)
  assert info["threshold"] == pytest.approx(0.95 * info["asymptote"])
  assert info["window"] == 1 and info["converged"]


def test_t_conv_late_dip_moves_after_dip():
  # Converged by 300, but iterations 700..709 drop to 0 -> last index below
  # threshold is 709 -> T_conv = 710.
  r = 1.0 - np.exp(-np.arange(1000) / 100.0)
  r[700:710] = 0.0
  t, _ = metrics.convergence_iteration(r, window=1)
  assert t == 710


def test_t_conv_default_window_and_smoothing():
  # Step at 500 from 0 to 1, N=1000 -> default window 20. Trailing mean at
  # index i >= 500 is (i - 499)/20; >= 0.95 first at i - 499 = 19 -> i = 518.
  r = np.where(np.arange(1000) >= 500, 1.0, 0.0)
  t, info = metrics.convergence_iteration(r)
  assert info["window"] == 20
  assert t == 518


def test_t_conv_negative_asymptote():
  # Rewards rise from -10 to -2 at i=400. Asymptote -2, threshold
  # -2 - 0.05*2 = -2.1 (0.95 * -2 = -1.9 would be unreachable) -> T_conv 400.
  r = np.where(np.arange(1000) >= 400, -2.0, -10.0)
  t, info = metrics.convergence_iteration(r, window=1)
  assert info["threshold"] == pytest.approx(-2.1)
  assert t == 400


def test_t_conv_not_converged():
  # Last value far below asymptote of the last 10% -> never stays -> N.
  r = np.ones(100)
  r[-1] = 0.0
  t, info = metrics.convergence_iteration(r, window=1)
  assert t == 100 and not info["converged"]


# ----------------------------------------------------- all_metrics / stats
def test_all_metrics_batched_shapes_and_types():
  e, t, a = 3, T_GAIT, 6
  rng = np.random.default_rng(0)
  traj = {
      "actions": rng.normal(size=(e, t, a)),
      "base_height": 1.0 + 0.01 * rng.normal(size=(e, t)),
      "euler": 0.01 * rng.normal(size=(e, t, 3)),
      "hip_pitch": np.stack(
          [np.tile(np.sin(W), (e, 1)), np.tile(-np.sin(W), (e, 1))], -1),
  }
  out = metrics.all_metrics(traj, rewards_per_iteration=1.0 - np.exp(-np.arange(1000) / 100.0))
  assert set(out) == {"S_action", "S_action_2nd", "S_torso", "C_limb", "T_conv"}
  assert all(isinstance(v, float) for v in out.values())
  assert out["C_limb"] < 1e-2
  # iid N(0,1) actions: E[S_action] ~= 2*A*(T-1)/T ~= 12.
  assert out["S_action"] == pytest.approx(12.0, rel=0.1)
  assert "T_conv" not in metrics.all_metrics(traj)


@pytest.mark.parametrize(
    "fn, args",
    [
        (metrics.action_smoothness, (np.zeros(5),)),
        (metrics.action_smoothness_2nd, (np.zeros((2, 2, 2, 2)),)),
        (metrics.torso_stability, (np.zeros((2, 10)), np.zeros((2, 10, 2)))),
        (metrics.limb_coordination, (np.zeros((2, 10)), np.zeros(10))),
        (metrics.convergence_iteration, (np.zeros((10, 2)),)),
        (metrics.convergence_iteration, (np.zeros(0),)),
    ],
)
def test_bad_shapes_raise(fn, args):
  with pytest.raises(ValueError, match="shape"):
    fn(*args)


def test_all_metrics_bad_hip_shape():
  traj = {
      "actions": np.zeros((1, 10, 2)),
      "base_height": np.zeros((1, 10)),
      "euler": np.zeros((1, 10, 3)),
      "hip_pitch": np.zeros((1, 10, 3)),
  }
  with pytest.raises(ValueError, match="hip_pitch"):
    metrics.all_metrics(traj)


def test_seed_summary_and_welch():
  # mean 2, sample std sqrt(((1)^2 + 0 + 1^2)/2) = 1.
  s = metrics.seed_summary([1.0, 2.0, 3.0])
  assert s == {"mean": 2.0, "std": pytest.approx(1.0), "n": 3}
  assert metrics.seed_summary([5.0])["std"] == 0.0
  # Means 2 vs 12, both std 1, n=3: t = -10 / sqrt(1/3 + 1/3) ~= -12.247.
  r = metrics.welch_ttest([1.0, 2.0, 3.0], [11.0, 12.0, 13.0])
  assert r["t"] == pytest.approx(-10.0 / np.sqrt(2.0 / 3.0))
  assert r["p"] < 1e-3
  assert np.isnan(metrics.welch_ttest([1.0], [2.0, 3.0])["p"])


def test_welch_on_tied_fall_rates_is_exact_and_quiet():
  # Two seeds falling on 2/128 episodes each vs 3/128 and 4/128: the tied sample has variance 0,
  # so t = (2 - 3.5) / 128 / (std(3, 4) / 128 / sqrt(2)) = -1.5 / 0.5 = -3.
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    r = metrics.welch_ttest([2 / 128, 2 / 128], [3 / 128, 4 / 128])
  assert r["t"] == pytest.approx(-3.0)


def test_bootstrap_ci_of_the_mean():
  # Constant values: the interval is the value itself; one value: (v, v).
  assert metrics.bootstrap_ci([2.0, 2.0, 2.0]) == (2.0, 2.0)
  assert metrics.bootstrap_ci([1.5]) == (1.5, 1.5)
  # Seeds 0..9: the mean 4.5 lies inside, the interval inside [0, 9], narrower than the range,
  # and the same seed gives the same interval.
  lo, hi = metrics.bootstrap_ci(np.arange(10.0))
  assert 0.0 < lo < 4.5 < hi < 9.0 and (hi - lo) < 5.0
  assert metrics.bootstrap_ci(np.arange(10.0)) == (lo, hi)
  assert all(np.isnan(metrics.bootstrap_ci([])))


def test_holm_adjusts_in_order():
  # m = 3: sorted 0.01, 0.02, 0.04 -> x3, x2, x1 = 0.03, 0.04, 0.04 (kept non-decreasing).
  np.testing.assert_allclose(metrics.holm([0.04, 0.01, 0.02]), [0.04, 0.03, 0.04])
  # NaN stays NaN and does not count: m = 2 -> 0.3 x 2 = 0.6, then max(0.6, 0.6 x 1) = 0.6.
  out = metrics.holm([0.6, float("nan"), 0.3])
  assert out[0] == pytest.approx(0.6) and np.isnan(out[1]) and out[2] == pytest.approx(0.6)
  # Capped at 1: 0.6 x 2 = 1.2 -> 1, then max(1, 0.7) = 1.
  assert metrics.holm([0.6, 0.7]) == [1.0, 1.0]


def test_hedges_g_hand_value():
  # a = 1, 2, 3 (mean 2, var 1); b = 4, 5, 6 (mean 5, var 1): pooled sd 1, d = -3,
  # correction 1 - 3 / (4 * 6 - 9) = 0.8 -> g = -2.4.
  assert metrics.hedges_g([1, 2, 3], [4, 5, 6]) == pytest.approx(-2.4)
  assert np.isnan(metrics.hedges_g([1], [2, 3]))
  assert np.isnan(metrics.hedges_g([1, 1], [1, 1]))


def test_verdict_needs_significance_and_direction():
  assert metrics.verdict(0.1, 0.5, 0.01, lower_is_better=True) == "MASH better"
  assert metrics.verdict(0.1, 0.5, 0.01, lower_is_better=False) == "PPO better"
  assert metrics.verdict(0.1, 0.5, 0.2, lower_is_better=True) == "no difference at this power"
  assert metrics.verdict(0.1, 0.5, float("nan"), True) == "no difference at this power"


def test_reach_iteration_and_a_common_threshold():
  # Trailing mean of 2 over 0, 2, 4, 6: 0, 1, 3, 5 -> first >= 3 at index 2, iteration 3.
  assert metrics.reach_iteration([0.0, 2.0, 4.0, 6.0], 3.0, 2) == 3
  assert metrics.reach_iteration([0.0, 2.0, 4.0, 6.0], 7.0, 1) is None
  # Method a rises to 10 by iteration 40, b to 8 by iteration 75 (100 iterations each); finals
  # 10 and 8 -> threshold 0.9 * 8 = 7.2: a (0.25 i) reaches it at i >= 28.8 -> 29, b (8 i / 75)
  # at i >= 67.5 -> 68, unsmoothed (window 1).
  it = np.arange(1, 101, dtype=float)
  a = np.minimum(10.0, 0.25 * it)
  b = np.minimum(8.0, 8.0 * it / 75)
  out = metrics.common_threshold_t_conv({"a": [a, a], "b": [b]}, windows=[1, 2, 3])
  assert out["threshold"] == pytest.approx(7.2) and out["final"] == {"a": 10.0, "b": 8.0}
  assert out["t_conv"]["a"][1] == [29, 29] and out["t_conv"]["b"][1] == [68]
  # A trailing window w lags a linear rise by (w - 1) / 2: a at w = 2: 0.25 (i - 0.5) >= 7.2 ->
  # i >= 29.3 -> 30; b at w = 3: 8 (i - 1) / 75 >= 7.2 -> i >= 68.5 -> 69.
  assert out["t_conv"]["a"][2] == [30, 30] and out["t_conv"]["b"][3] == [69]
  assert metrics.common_threshold_t_conv({"a": [a]})["windows"] == [1, 2, 4]


def test_arm_leg_coordination_in_phase_with_the_opposite_leg():
  # Left arm with the right leg and right arm with the left leg, legs in antiphase: 0.
  left_hip, right_hip = np.sin(W), -np.sin(W)
  shoulders = np.stack([right_hip, left_hip], -1) * 0.5
  hips = np.stack([left_hip, right_hip], -1)
  assert metrics.arm_leg_coordination(shoulders, hips) < 1e-2
  # Each arm with its own leg instead: half a cycle off, pi.
  assert metrics.arm_leg_coordination(hips * 0.5, hips) == pytest.approx(np.pi, abs=1e-2)
  with pytest.raises(ValueError, match="share a shape"):
    metrics.arm_leg_coordination(shoulders[:, :1], hips)
