import numpy as np
import pytest

from pipeline.kernels import modulation as mod


def test_hex_round_trip_msb_first():
    bits = mod.hex_to_bits("a5", 8)
    assert bits.tolist() == [1, 0, 1, 0, 0, 1, 0, 1]
    assert mod.bits_to_hex(bits) == "a5"
    assert mod.hex_to_bits("0x1", 4).tolist() == [0, 0, 0, 1]


def test_payload_longer_than_capacity_is_refused():
    with pytest.raises(ValueError, match="capacity"):
        mod.hex_to_bits("1ff", 8)
    with pytest.raises(ValueError, match="not hexadecimal"):
        mod.hex_to_bits("xyz", 8)


@pytest.mark.parametrize("width", [8, 16])
def test_crc_catches_every_single_bit_error(width):
    bits = np.random.default_rng(0).integers(0, 2, 32)
    crc = mod.crc_bits(bits, width)
    for i in range(32):
        flipped = bits.copy()
        flipped[i] ^= 1
        assert not np.array_equal(mod.crc_bits(flipped, width), crc)


def test_crc8_known_answer():
    # CRC-8 (poly 0x07, init 0) of ASCII "123456789" is 0xF4
    bits = np.unpackbits(np.frombuffer(b"123456789", dtype=np.uint8))
    assert mod.bits_to_hex(mod.crc_bits(bits, 8)) == "f4"


def test_spread_then_despread_recovers_equation_5():
    rng = np.random.default_rng(1)
    m, c, alpha = 16, 10, 0.01
    bits = rng.integers(0, 2, m)
    seq = rng.choice([-1.0, 1.0], size=(3, m * c))
    pos = np.arange(m * c)
    delta = mod.spread(bits, c, seq, alpha, pos)
    q, energy = mod.despread(delta, c, seq, pos)
    assert np.allclose(q, c * alpha * (2 * bits - 1))        # q_j = c * alpha * b'_j
    assert np.allclose(energy, 3 * c * alpha**2)


def test_p_value_is_calibrated_under_the_null():
    rng = np.random.default_rng(2)
    m, c = 32, 10
    pos = np.arange(m * c)
    pvals = []
    for _ in range(400):
        delta = rng.normal(size=(m * c, 3)) * rng.uniform(0.1, 3.0, size=(m * c, 1))
        seq = rng.choice([-1.0, 1.0], size=(3, m * c))
        q, e = mod.despread(delta, c, seq, pos)
        pvals.append(mod.p_value_present(mod.combine_scores(q[None], e[None])))
    pvals = np.array(pvals)
    assert 0.03 < (pvals < 0.1).mean() < 0.17
    assert (pvals < 1e-3).mean() < 0.01


def test_combined_scores_grow_with_clusters():
    rng = np.random.default_rng(3)
    bits = rng.integers(0, 2, 8)
    seqs = [rng.choice([-1.0, 1.0], size=(3, 80)) for _ in range(4)]
    pos = np.arange(80)
    qs, es = zip(*[mod.despread(mod.spread(bits, 10, s, 1.0, pos) + rng.normal(0, 2, (80, 3)), 10, s, pos)
                   for s in seqs])
    z1 = mod.combine_scores(np.array(qs[:1]), np.array(es[:1]))
    z4 = mod.combine_scores(np.array(qs), np.array(es))
    assert np.abs(z4).mean() > 1.5 * np.abs(z1).mean()
    assert ((z4 > 0) == bits.astype(bool)).all()


def test_along_normals_keeps_rmse_and_peak_and_moves_across_the_surface():
    rng = np.random.default_rng(5)
    displacement = rng.normal(size=(2000, 3))
    normals = rng.normal(size=(2000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    moved, gamma = mod.along_normals(displacement, normals)
    rms = lambda d: np.sqrt((d**2).sum(axis=1).mean())   # noqa: E731
    assert rms(moved) == pytest.approx(rms(displacement), rel=1e-9)
    assert np.linalg.norm(moved, axis=1).max() <= np.linalg.norm(displacement, axis=1).max() * (1 + 1e-12)
    assert np.allclose(np.cross(moved, normals), 0.0)           # parallel to the normals
    # same side as the original normal component; random directions give gamma near sqrt(3)
    h = np.einsum("ni,ni->n", displacement, normals)
    assert (np.einsum("ni,ni->n", moved, normals) * h >= 0).all()
    assert 1.5 < gamma < 2.0
    # normals of either orientation give the same displacement
    again, _ = mod.along_normals(displacement, -normals)
    assert np.allclose(again, moved)


def test_a_nearly_empty_cluster_does_not_outvote_the_covered_ones():
    # Cluster 0 is seen whole; cluster 1 by a handful of points, so its
    # estimate is tiny (low energy) and unrelated to the payload.  By inverse
    # energy alone it would dominate; weighted by coverage it does not.
    rng = np.random.default_rng(2)
    m, c = 32, 10
    bits = rng.integers(0, 2, m)
    seq = rng.choice([-1.0, 1.0], size=(3, m * c))
    pos = np.arange(m * c)
    good = mod.spread(bits, c, seq, 1.0, pos) + rng.normal(0, 1.0, (m * c, 3))
    junk = rng.normal(0, 0.1, (m * c, 3))          # energy 100 x lower, as measured on a crop
    q, e = zip(*(mod.despread(d, c, seq, pos) for d in (good, junk)))
    q, e = np.array(q), np.array(e)
    unweighted = mod.combine_scores(q, e)
    weighted = mod.combine_scores(q, e, coverage=[1.0, 6 / 4000])
    assert ((weighted > 0) == bits.astype(bool)).all()
    assert ((unweighted > 0) != bits.astype(bool)).sum() > 5


def test_the_codeword_p_value_is_valid_under_the_null_and_sees_a_weak_coded_mark():
    from pipeline.kernels import coding

    rng = np.random.default_rng(11)
    n_bits = 32
    n = coding.coded_length(n_bits, "convolutional")
    null = []
    for _ in range(2000):
        z = rng.normal(size=n)
        bits, _ = coding.decode_soft(z, n_bits, "convolutional")
        null.append(mod.p_value_codeword(z, coding.encode(bits, "convolutional"), n_bits))
    null = np.array(null)
    for t in (0.5, 0.1, 0.01):
        assert (null < t).mean() <= t            # a union bound: never anti-conservative
    # a mark with total noncentrality 70 over 76 symbols: the chi-square test
    # misses it at 1e-6 more often than not, the decoded word sees it
    hits = {"chi2": 0, "word": 0}
    for _ in range(50):
        sent = rng.integers(0, 2, n_bits)
        word = coding.encode(sent, "convolutional")
        z = (2.0 * word - 1) * np.sqrt(70 / n) + rng.normal(size=n)
        bits, _ = coding.decode_soft(z, n_bits, "convolutional")
        hits["chi2"] += mod.p_value_present(z) < 1e-6
        hits["word"] += mod.p_value_codeword(z, coding.encode(bits, "convolutional"), n_bits) < 1e-6
    assert hits["word"] > hits["chi2"] + 10, hits


def test_spread_reach_bounds_two_marks_and_scales_with_alpha():
    rng = np.random.default_rng(11)
    basis = np.linalg.qr(rng.normal(size=(2000, 320)))[0]
    reach = mod.spread_reach(basis, 0.5)
    two = sum(basis @ (0.5 * rng.choice([-1.0, 1.0], size=(320, 3))) for _ in range(2))
    distance = np.linalg.norm(two, axis=1)
    assert (distance <= reach).all() and distance.max() > 0.3 * reach.max()
    assert np.allclose(mod.spread_reach(basis, 1.0), 2.0 * reach)
