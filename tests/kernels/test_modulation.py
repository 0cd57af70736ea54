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
