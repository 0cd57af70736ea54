import numpy as np
import pytest

import hashlib

from pipeline.kernels.keys import derive_key_material, key_fingerprint, key_permutation, pseudo_random_signs


def test_sequences_are_deterministic_balanced_and_key_dependent():
    m1 = derive_key_material(b"s" * 16, "k1")
    a = pseudo_random_signs(m1, "cluster=0/axis=0", 4000)
    assert np.array_equal(a, pseudo_random_signs(m1, "cluster=0/axis=0", 4000))
    assert set(np.unique(a)) == {-1, 1}
    assert abs(a.mean()) < 0.06
    b = pseudo_random_signs(derive_key_material(b"s" * 16, "k2"), "cluster=0/axis=0", 4000)
    c = pseudo_random_signs(m1, "cluster=1/axis=0", 4000)
    assert abs((a * b).mean()) < 0.06 and abs((a * c).mean()) < 0.06


def test_sequence_follows_its_documented_definition():
    # recomputed here from the definition: a silent change would orphan issued watermarks
    import hashlib
    import hmac

    m = hmac.new(b"secret-of-16-bytes", b"pointmark/key/key", hashlib.sha256).digest()
    assert derive_key_material(b"secret-of-16-bytes", "key") == m
    block = hmac.new(m, b"signs/x/" + (0).to_bytes(8, "big"), hashlib.sha256).digest()
    bits = np.unpackbits(np.frombuffer(block, dtype=np.uint8))[:64]
    assert pseudo_random_signs(m, "x", 64).tolist() == (2 * bits.astype(int) - 1).tolist()
    assert pseudo_random_signs(m, "x", 16).tolist() == pseudo_random_signs(m, "x", 64)[:16].tolist()


def test_key_fingerprint_is_salted_slow_and_does_not_reveal_the_secret():
    import time

    secret, salt = b"hunter2-hunter2-hunter2", "00" * 16
    t0 = time.perf_counter()
    fp = key_fingerprint(secret, salt)
    assert time.perf_counter() - t0 > 0.005          # scrypt, not a bare hash
    assert len(fp) == 16 and "hunter2" not in fp and fp == key_fingerprint(secret, salt)
    assert fp != key_fingerprint(b"hunter3-hunter3-hunter3", salt)
    assert fp != key_fingerprint(secret, "11" * 16)                 # another deployment, another fingerprint
    assert fp != hashlib.sha256(b"pointmark/fingerprint/" + secret).hexdigest()[:16]


def test_a_short_master_secret_is_refused():
    with pytest.raises(ValueError, match="8 bytes; at least 16"):
        derive_key_material(b"12345678", "k")


def test_permutation_is_a_permutation():
    p = key_permutation(derive_key_material(b"s" * 16, "k"), "layout", 320)
    assert sorted(p.tolist()) == list(range(320))


def test_empty_secret_is_refused():
    with pytest.raises(ValueError, match="0 bytes; at least 16"):
        derive_key_material(b"", "k")
