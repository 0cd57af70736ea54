import itertools

import numpy as np
import pytest

from pipeline.kernels import coding


def _codebook(n_bits):
    words = np.array(list(itertools.product([0, 1], repeat=n_bits)), dtype=np.uint8)
    return words, np.stack([coding.encode(w, "convolutional") for w in words]).astype(np.float64) * 2 - 1


def test_the_encoder_is_the_k7_171_133_code():
    # impulse response of a single 1: the generators' taps, interleaved, then zeros
    word = coding.encode([1, 0, 0, 0, 0, 0, 0], "convolutional")
    g1 = [int(b) for b in format(0o171, "07b")]
    g2 = [int(b) for b in format(0o133, "07b")]
    assert word[:14].tolist() == [b for pair in zip(g1, g2) for b in pair]
    assert not word[14:].any()
    assert len(word) == coding.coded_length(7, "convolutional") == 2 * (7 + 6)


def test_free_distance_is_10():
    _, book = _codebook(8)
    weights = ((book[1:] + 1) / 2).sum(axis=1)   # the all-zero word is word 0; linear code
    assert weights.min() == 10


@pytest.mark.parametrize("sigma", [0.6, 1.0, 1.6])
def test_soft_decoding_is_maximum_likelihood_with_max_log_margins(sigma):
    words, book = _codebook(8)
    rng = np.random.default_rng(int(sigma * 10))
    for _ in range(20):
        sent = words[rng.integers(len(words))]
        z = (2.0 * coding.encode(sent, "convolutional") - 1) + rng.normal(0, sigma, book.shape[1])
        bits, margin = coding.decode_soft(z, 8, "convolutional")
        metric = book @ z
        assert bits.tolist() == words[np.argmax(metric)].tolist()
        for j in range(8):   # max-log-MAP: half the best metric with the bit at 1 minus with it at 0
            best = [metric[words[:, j] == v].max() for v in (0, 1)]
            assert margin[j] == pytest.approx(0.5 * (best[1] - best[0]), abs=1e-9)


def test_the_code_beats_repetition_at_equal_energy():
    # 32 bits on 320 unit-energy chips under the same noise: repetition sums 10
    # chips per bit; the code gives 76 symbols 4 or 5 chips each.
    rng = np.random.default_rng(7)
    n_bits, chips, sigma, trials = 32, 320, 1.6, 200
    groups = coding.chip_groups(coding.coded_length(n_bits, "convolutional"), chips)
    errors = {"repetition": 0, "convolutional": 0}
    for _ in range(trials):
        bits = rng.integers(0, 2, n_bits)
        for code in errors:
            word = coding.encode(bits, code)
            g = np.repeat(np.arange(n_bits), 10) if code == "repetition" else groups
            received = (2.0 * word[g] - 1) + rng.normal(0, sigma, chips)
            sums = np.bincount(g, weights=received)
            z = sums / (sigma * np.sqrt(np.bincount(g)))
            decoded, _ = coding.decode_soft(z, n_bits, code)
            errors[code] += int((decoded != bits).any())
    assert errors["repetition"] > trials // 4 and errors["convolutional"] * 10 < errors["repetition"], errors


def test_chip_groups_share_chips_evenly_and_reduce_to_repetition():
    g = coding.chip_groups(76, 320)
    counts = np.bincount(g)
    assert len(counts) == 76 and set(counts.tolist()) <= {4, 5} and counts.sum() == 320
    assert np.array_equal(coding.chip_groups(32, 320), np.repeat(np.arange(32), 10))
    with pytest.raises(ValueError, match="chip_rate"):
        coding.chip_groups(76, 64)


def test_wrong_lengths_and_names_are_refused():
    with pytest.raises(ValueError, match="scores"):
        coding.decode_soft(np.zeros(10), 8, "convolutional")
    with pytest.raises(ValueError, match="unknown code"):
        coding.encode([1, 0], "turbo")


@pytest.mark.parametrize("n_bits,code,least", [(32, "convolutional", 3), (24, "convolutional", 3), (32, "tailbiting", 3),
                                               (32, "tailbiting-half", 2), (8, "convolutional", 4), (32, "repetition", 1)])
def test_the_least_chip_rate_is_the_first_that_carries_the_coded_word(n_bits, code, least):
    assert coding.least_chip_rate(n_bits, code) == least
    assert n_bits * least >= coding.coded_length(n_bits, code) > n_bits * (least - 1)


# each tail-biting code: its generators and its least weight over 32 bits (its free distance)
TAILBITING = {"tailbiting": (coding.TAILBITING_GENERATORS, 18),
              "tailbiting-half": (coding.TAILBITING_HALF_GENERATORS, 12)}


def _tailbiting_codebook(n_bits, code="tailbiting"):
    words = np.array(list(itertools.product([0, 1], repeat=n_bits)), dtype=np.uint8)
    return words, np.stack([coding.encode(w, code) for w in words]).astype(np.float64) * 2 - 1


@pytest.mark.parametrize("code", TAILBITING)
def test_the_tailbiting_word_turns_with_its_bits(code):
    # tail-biting: no tail, and the encoder starts where its last bits leave it,
    # so turning the bits by one turns the word by one group of symbols
    generators, _ = TAILBITING[code]
    n = len(generators)
    bits = np.random.default_rng(3).integers(0, 2, 32)
    word = coding.encode(bits, code)
    assert len(word) == coding.coded_length(32, code) == 32 * n
    assert np.array_equal(coding.encode(np.roll(bits, 5), code), np.roll(word, 5 * n))
    taps = [[int(b) for b in format(g, "09b")] for g in generators]
    impulse = coding.encode(np.eye(32, dtype=int)[0], code)      # a single 1 at the start
    assert impulse[:9 * n].tolist() == [b for group in zip(*taps) for b in group]
    assert not impulse[9 * n:].any()


@pytest.mark.parametrize("code", TAILBITING)
def test_the_tailbiting_free_distance_on_32_bits(code):
    # every nonzero 32-bit word, through the trellis: per start state, the least output weight
    # of a path that returns to it, with and without a 1 fed so far (min-plus recursion)
    generators, distance = TAILBITING[code]
    nxt, out = coding._trellis(generators, coding.TAILBITING_CONSTRAINT)
    weight = (out > 0).sum(axis=-1)                                   # (S, 2)
    states = len(nxt)
    least = np.full((2, states, states), np.inf)                      # [fed a 1, start, state]
    least[0][np.arange(states), np.arange(states)] = 0
    for _ in range(32):
        step = np.full_like(least, np.inf)
        for u in (0, 1):
            moved = least + weight[:, u]                              # (2, S0, S)
            for flag in (0, 1):
                target = 1 if u else flag
                np.minimum.at(step[target], (slice(None), nxt[:, u]), moved[flag])
        least = step
    assert least[1][np.arange(states), np.arange(states)].min() == distance
    ones = np.zeros(32, dtype=int)                                    # and a word that reaches it
    weights = []
    for w in (1, 2, 3):
        for at in itertools.combinations(range(32), w):
            ones[:] = 0
            ones[list(at)] = 1
            weights.append(int(coding.encode(ones, code).sum()))
    assert min(weights) == distance


@pytest.mark.parametrize("code", TAILBITING)
@pytest.mark.parametrize("sigma", [0.6, 1.2, 2.0])
def test_tailbiting_decoding_is_maximum_likelihood_with_max_log_margins(sigma, code):
    words, book = _tailbiting_codebook(10, code)
    rng = np.random.default_rng(int(sigma * 10))
    for _ in range(12):
        z = book[rng.integers(len(words))] + rng.normal(0, sigma, book.shape[1])
        bits, margin = coding.decode_soft(z, 10, code)
        metric = book @ z
        assert bits.tolist() == words[np.argmax(metric)].tolist()
        for j in range(10):
            best = [metric[words[:, j] == v].max() for v in (0, 1)]
            assert margin[j] == pytest.approx(0.5 * (best[1] - best[0]), abs=1e-9)


def test_the_tailbiting_code_beats_the_terminated_code_on_the_same_chips():
    # 32 bits on the 96 chips of chip rate 3, each chip +-0.9 in unit noise:
    # 76 terminated symbols (some on two chips) against 96 tail-biting ones
    rng = np.random.default_rng(11)
    errors = {"convolutional": 0, "tailbiting": 0}
    for _ in range(80):
        bits = rng.integers(0, 2, 32)
        for code in errors:
            n = coding.coded_length(32, code)
            g = coding.chip_groups(n, 96)
            received = 0.9 * (2.0 * coding.encode(bits, code)[g] - 1) + rng.normal(0, 1, 96)
            z = np.bincount(g, weights=received, minlength=n) / np.sqrt(np.bincount(g, minlength=n))
            decoded, _ = coding.decode_soft(z, 32, code)
            errors[code] += int((decoded != bits).any())
    assert errors["convolutional"] >= 10 and 2 * errors["tailbiting"] < errors["convolutional"], errors


@pytest.mark.parametrize("code", TAILBITING)
@pytest.mark.parametrize("n_bits", range(1, 10))
def test_short_tailbiting_words_round_trip(n_bits, code):
    # fewer bits than the register's memory: the start state is the one the repeated word leaves
    words = np.array(list(itertools.product([0, 1], repeat=n_bits)), dtype=np.uint8)
    coded = np.stack([coding.encode(w, code) for w in words])
    assert len({c.tobytes() for c in coded}) == len(words)                    # every word its own
    for i in np.random.default_rng(n_bits).permutation(len(words))[:24]:
        w, c = words[i], coded[i]
        bits, _ = coding.decode_soft(2.0 * c - 1, n_bits, code)
        assert bits.tolist() == w.tolist()
