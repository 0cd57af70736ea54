"""Recipient fingerprints: the code, the scores and the accusation threshold."""

import numpy as np
import pytest

from pipeline.kernels import fingerprint as fp

MATERIAL = b"m" * 32


def test_chips_are_deterministic_balanced_and_depend_on_every_input():
    bank = fp.chip_bank(MATERIAL, "asset/g1", ["alice", "bob"], 4800)
    assert bank.shape == (2, 600) and bank.dtype == np.uint8
    assert np.array_equal(bank, fp.chip_bank(MATERIAL, "asset/g1", ["alice", "bob"], 4800))
    x = fp.signs(bank, 4800)
    assert set(np.unique(x)) == {-1.0, 1.0} and abs(x.mean()) < 0.05
    others = [fp.chip_bank(b"n" * 32, "asset/g1", ["alice"], 4800), fp.chip_bank(MATERIAL, "asset/g2", ["alice"], 4800),
              fp.chip_bank(MATERIAL, "asset/g1", ["alice2"], 4800)]
    for other in others:
        assert abs((fp.signs(other, 4800)[0] * x[0]).mean()) < 0.06
    # fields are length-prefixed: ("a", "bc") and ("ab", "c") are different copies
    assert not np.array_equal(fp.chip_bank(MATERIAL, "a", ["bc"], 64), fp.chip_bank(MATERIAL, "ab", ["c"], 64))


def test_scores_are_the_normalised_correlation():
    rng = np.random.default_rng(0)
    bank = fp.chip_bank(MATERIAL, "a", [f"r{i}" for i in range(300)], 1234)
    y = rng.normal(size=1234)
    q = fp.quantize(y)
    assert np.abs(q).max() == 127 and np.abs(q / 127 * np.abs(y).max() - y).max() <= np.abs(y).max() / 254
    exact = fp.signs(bank, 1234) @ q / np.linalg.norm(q)          # the score is exact for q
    assert np.allclose(fp.scores(y, bank, chunk=64), exact, atol=1e-12)
    assert np.allclose(fp.scores(y, bank), fp.signs(bank, 1234) @ y / np.linalg.norm(y), atol=0.05)
    assert np.array_equal(fp.scores(np.zeros(1234), bank), np.zeros(300))


@pytest.mark.parametrize("kind", ["noise", "noise-free colluders", "one spike"])
def test_innocent_scores_obey_the_hoeffding_bound_for_any_observation(kind):
    """Given y, an innocent's score exceeds t with probability at most exp(-t^2/2)."""
    rng = np.random.default_rng(1)
    n, length = 20000, 960
    colluders = fp.signs(fp.chip_bank(MATERIAL, "a", ["c1", "c2", "c3"], length), length)
    y = {"noise": rng.normal(size=length), "noise-free colluders": colluders.mean(axis=0),
         "one spike": np.r_[50.0, rng.normal(size=length - 1) * 1e-3]}[kind]
    s = fp.scores(y, fp.chip_bank(MATERIAL, "b", [f"innocent-{i}" for i in range(n)], length))
    assert abs(s.mean()) < 0.05 and abs(s.var() - 1.0) < 0.05
    for t in (1.5, 2.0, 2.5, 3.0):
        assert (s >= t).mean() <= np.exp(-t * t / 2)


def test_false_accusations_stay_below_epsilon():
    """4,000 suspects x 50 recipients, none of them present: accusations at eps = 0.05."""
    rng = np.random.default_rng(2)
    eps, n, length = 0.05, 50, 480
    accusations = 0
    for trial in range(4000):
        bank = fp.chip_bank(MATERIAL, f"t{trial}", [f"r{i}" for i in range(n)], length)
        accused, _ = fp.accuse(fp.scores(rng.normal(size=length), bank), n, eps)
        accusations += len(accused) > 0
    assert accusations / 4000 <= eps          # Hoeffding + union bound: conservative


def test_averaging_colluders_are_all_accused_and_nobody_else():
    length, names = 4800, [f"r{i}" for i in range(1000)]
    bank = fp.chip_bank(MATERIAL, "a", names, length)
    x = fp.signs(bank, length)
    for k in (2, 3, 5):
        y = x[:k].mean(axis=0)
        accused, margin = fp.accuse(fp.scores(y, bank), 1000, 1e-6)
        assert sorted(accused.tolist()) == list(range(k)) and (margin > 10).all()
    assert fp.threshold(1000, 1e-6) == pytest.approx(np.sqrt(2 * np.log(1e9)))
    assert fp.corrected_p(fp.threshold(1000, 1e-6), 1000) == pytest.approx(1e-6)
    assert fp.corrected_p(-3.0, 1000) == 1.0


def test_presence_is_uniform_without_a_mark_and_tiny_with_one():
    rng = np.random.default_rng(3)
    bank = fp.chip_bank(MATERIAL, "a", [f"r{i}" for i in range(200)], 960)
    null = [fp.presence(fp.scores(rng.normal(size=960), bank)) for _ in range(200)]
    assert 0.3 < np.mean(null) < 0.7
    # twelve colluders: each under the accusation threshold, the mark plainly there ("inconclusive")
    marked = fp.signs(bank, 960)[:12].mean(axis=0) + rng.normal(size=960) * 0.5
    s = fp.scores(marked, bank)
    assert len(fp.accuse(s, 200, 1e-6)[0]) == 0 and fp.presence(s) < 1e-8


def test_observation_weights_clusters_by_coverage_over_energy():
    d1 = np.ones((10, 3))
    d2 = 3 * np.ones((10, 3))
    y = fp.observation([d1, d2], [1.0, 0.5], first=2, count=4)
    assert y.shape == (2 * 3 * 4,)
    assert np.allclose(y[:12], 1.0) and np.allclose(y[12:], 0.5 * 3 / 9)


def test_the_best_score_over_poses_is_each_recipients_maximum_and_keeps_the_bound_when_counted():
    rng = np.random.default_rng(4)
    n, length, poses = 2000, 480, 8
    bank = fp.chip_bank(MATERIAL, "sym", [f"r{i}" for i in range(n)], length)
    ys = [rng.normal(size=length) for _ in range(poses)]
    best, pose, table = fp.scores_over_poses(ys, bank)
    assert np.array_equal(table, np.stack([fp.scores(y, bank) for y in ys]))
    assert np.array_equal(best, table.max(axis=0)) and np.array_equal(table[pose, np.arange(n)], best)
    one, at, _ = fp.scores_over_poses(ys[:1], bank)
    assert np.array_equal(one, fp.scores(ys[0], bank)) and not at.any()
    # a mark at any pose: one pose is presence itself, more the best pose's p times their number
    assert fp.presence_over_poses(table[:1]) == fp.presence(table[0])
    assert fp.presence_over_poses(table) == min(1.0, poses * min(fp.presence(s) for s in table))
    # the maximum of 8 poses exceeds t as often as 8 tests can, never more: count every pose
    for t in (2.0, 2.5, 3.0):
        assert (best >= t).mean() <= poses * np.exp(-t * t / 2)
    assert fp.accuse(best, n * poses, 1e-3)[0].size == 0
