"""Spread-spectrum modulation of spectral coefficients (paper, equations 2-5).

Embedding: each payload bit a_j is repeated ``chip_rate`` times (eq. 2),
mapped to b'_i in {-1, 1} (eq. 3), multiplied by the key's sequence p_i and
the amplitude alpha, and added to the spectral coefficients of x, y and z
(eq. 4).  Detection correlates the coefficient differences with the same
sequence (eq. 5).

The "layout" maps chip i to a coefficient: ``consecutive`` is the paper's
(chips of bit j on coefficients j*c ... (j+1)*c - 1); ``interleaved`` spreads
each bit over the whole band with a key-dependent permutation, so no bit sits
only on the noisiest or the most registration-sensitive frequencies.

:func:`along_normals` is the optional normal-direction synthesis: only the
part of a displacement across the surface survives resampling and noise, so
it keeps that part, scaled back to the paper's RMS and capped at its peak.
"""

from __future__ import annotations

import numpy as np
from scipy import special

__all__ = [
    "hex_to_bits", "bits_to_hex", "crc_bits", "chips", "spread", "despread",
    "combine_scores", "p_value_present", "p_value_payload", "p_value_codeword", "along_normals", "spread_reach",
]

_CRC_POLYS = {8: 0x07, 16: 0x1021}


def hex_to_bits(message, n_bits):
    """Payload bits of a HEX string, most significant bit first.

    Strict: only the digits 0-9, a-f, A-F, optionally after ``0x``; no sign,
    no spaces, no underscores, at most ``ceil(n_bits / 4)`` digits.  Fewer
    digits are a number padded with leading zeros (``1`` is ``00000001`` for
    32 bits); the value must fit in ``n_bits``.

    Parameters
    ----------
    message : str
        Hexadecimal, optionally prefixed ``0x``.
    n_bits : int

    Returns
    -------
    (n_bits,) uint8

    Raises
    ------
    ValueError
        Saying what is wrong with the message.
    """
    text = message[2:] if message[:2] in ("0x", "0X") else message
    digits = (n_bits + 3) // 4
    if not text:
        raise ValueError(f"message {message!r} is empty; give {digits} hex digits")
    bad = [c for c in text if c not in "0123456789abcdefABCDEF"]
    if bad:
        raise ValueError(f"message {message!r} is not hexadecimal (character {bad[0]!r}); "
                         f"use only 0-9 and a-f, no sign, spaces or underscores")
    if len(text) > digits:
        raise ValueError(f"message {message!r} has {len(text)} hex digits, more than the {digits} of "
                         f"the payload capacity n_bits={n_bits}; shorten it or raise n_bits")
    value = int(text, 16)
    if value >= 1 << n_bits:
        raise ValueError(
            f"message {message!r} needs {value.bit_length()} bits, more than the payload "
            f"capacity n_bits={n_bits}; shorten it or raise n_bits"
        )
    return np.array([(value >> (n_bits - 1 - i)) & 1 for i in range(n_bits)], dtype=np.uint8)


def bits_to_hex(bits):
    """HEX string (MSB first, zero-padded to whole digits) of a bit vector."""
    bits = np.asarray(bits, dtype=np.int64)
    value = 0
    for b in bits:
        value = (value << 1) | int(b)
    return format(value, f"0{(len(bits) + 3) // 4}x")


def crc_bits(bits, width):
    """CRC of a bit vector (CRC-8 poly 0x07, CRC-16-CCITT poly 0x1021), MSB first.

    Returns
    -------
    (width,) uint8
    """
    if width == 0:
        return np.zeros(0, dtype=np.uint8)
    poly = _CRC_POLYS[width]
    top = 1 << (width - 1)
    mask = (1 << width) - 1
    reg = 0
    for b in np.asarray(bits, dtype=np.int64):
        feedback = ((reg & top) != 0) ^ bool(b)
        reg = ((reg << 1) & mask) ^ (poly if feedback else 0)
    return np.array([(reg >> (width - 1 - i)) & 1 for i in range(width)], dtype=np.uint8)


def chips(bits, chip_rate):
    """Chip sequence b' of equations 2 and 3.

    Parameters
    ----------
    bits : (m,) {0, 1}
        Payload bits, or the symbols of a coded word.
    chip_rate : int or (n_chips,) int
        c (each bit repeated c times, the paper's), or the symbol of every
        chip (:func:`pipeline.kernels.coding.chip_groups`).

    Returns
    -------
    (n_chips,) float in {-1, +1}, n_chips = m * c for an int chip rate
    """
    signs = 2.0 * np.asarray(bits, dtype=np.float64) - 1.0
    return signs[_groups(chip_rate, len(signs))]


def _groups(chip_rate, n_symbols):
    if np.ndim(chip_rate) == 0:
        return np.repeat(np.arange(n_symbols), int(chip_rate))
    return np.asarray(chip_rate, dtype=np.int64)


def spread(bits, chip_rate, sequences, amplitude, positions):
    """Coefficient changes of equation 4 for one cluster.

    Parameters
    ----------
    bits : (m,) {0, 1}
    chip_rate : int or (n_chips,) int
        As in :func:`chips`.
    sequences : (3, n_chips) {-1, +1}
        The key's sequence p_i for the spectral axes s, t, u (x, y, z).
    amplitude : float
        alpha = beta * phi.
    positions : (n_chips,) int
        Coefficient index of each chip (the layout).

    Returns
    -------
    delta : (n_coefficients, 3) float, n_coefficients = positions.max() + 1
    """
    b = chips(bits, chip_rate)
    delta = np.zeros((int(positions.max()) + 1, 3))
    delta[positions, :] = amplitude * (b[None, :] * sequences).T
    return delta


def spread_reach(basis, amplitude):
    """How far two marks spread on ``basis`` can move each point: 4 sqrt(6) amplitude ||E_j||.

    Each coefficient moves by +-amplitude with a key's signs, so along each
    axis point j moves with standard deviation amplitude ||E_j||; three axes
    and two marks (a message and a fingerprint) give sqrt(6) of that.

    Parameters
    ----------
    basis : (n_c, n_chips) float
        The columns the chips use.
    amplitude : float
        alpha.

    Returns
    -------
    (n_c,) float
    """
    return 4.0 * np.sqrt(6.0) * amplitude * np.linalg.norm(basis, axis=1)


def despread(delta, chip_rate, sequences, positions):
    """Correlator of equation 5, with the statistics a p-value needs.

    Parameters
    ----------
    delta : (n_coefficients, 3) float
        Estimated coefficient differences r-hat - r.
    chip_rate : int or (n_chips,) int
        As in :func:`chips`; an int means m = n_chips / c symbols.
    sequences : (3, n_chips)
    positions : (n_chips,) int

    Returns
    -------
    q : (m,) float
        q_j of equation 5 (sign gives the bit or symbol).
    energy : (m,) float
        Sum of squared differences that q_j sums over; under "no watermark of
        this key", q_j * 3 has mean 0 and variance ``energy`` given the data.
    """
    d = delta[positions, :].T  # (3, n_chips)
    if np.ndim(chip_rate) == 0:
        m = d.shape[1] // int(chip_rate)
    else:
        m = int(np.max(chip_rate)) + 1
    groups = _groups(chip_rate, m)
    q = np.bincount(groups, weights=(d * sequences).sum(axis=0), minlength=m) / 3.0
    energy = np.bincount(groups, weights=(d**2).sum(axis=0), minlength=m)
    return q, energy


def combine_scores(q, energy, weights=None, coverage=None):
    """Soft combination of the clusters' correlators into one z-score per bit.

    Parameters
    ----------
    q : (k, m) float
    energy : (k, m) float
    weights : (k,) float, optional
        Cluster weights chosen without the key (default: coverage over mean
        energy, so clusters measured with less noise count more).
    coverage : (k,) float in [0, 1], optional
        Fraction of each cluster the suspect covers (default 1).  A cluster
        with a handful of suspect points has a small, shrunken estimate whose
        inverse energy alone would give it the largest weight.

    Returns
    -------
    z : (m,) float
        Approximately N(0, 1) per bit when no watermark of this key is present.
    """
    q = np.atleast_2d(q)
    energy = np.atleast_2d(energy)
    if weights is None:
        mean_energy = energy.mean(axis=1)
        weights = np.where(mean_energy > 0, 1.0 / np.maximum(mean_energy, 1e-300), 0.0)
        if coverage is not None:
            weights = weights * np.clip(np.asarray(coverage, dtype=np.float64), 0.0, 1.0)
    num = 3.0 * (weights[:, None] * q).sum(axis=0)
    den = np.sqrt((weights[:, None] ** 2 * energy).sum(axis=0))
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def p_value_present(z):
    """p-value of "a watermark of this key is present", payload unknown.

    Under the null the z_j are independent N(0, 1) (a Rademacher sum, whose
    tails are no heavier than Gaussian), so sum(z_j^2) ~ chi-square(m).
    """
    z = np.asarray(z, dtype=np.float64)
    return float(special.gammaincc(len(z) / 2.0, float(z @ z) / 2.0))   # chi-square survival


def p_value_payload(z, bits):
    """p-value of "this key and this payload are present" (one-sided).

    sum(z_j * b'_j) / sqrt(m) ~ N(0, 1) under the null.
    """
    signs = 2.0 * np.asarray(bits, dtype=np.float64) - 1.0
    return float(0.5 * special.erfc(float(z @ signs) / np.sqrt(2.0 * len(z))))  # normal survival


def p_value_codeword(z, word, n_bits):
    """p-value of "a watermark of this key is present", from the decoded codeword.

    The correlation of the symbol scores with the re-encoded decoded word,
    sum(z_k c_k) / sqrt(n), is N(0, 1) under the null for any one codeword;
    the decoder picked the best of 2^n_bits, so the union bound multiplies
    the tail by 2^n_bits.  Where a code spreads the energy over more symbols
    than bits, this sees the mark with less energy than the chi-square test.

    Parameters
    ----------
    z : (n,) float
        Symbol scores.
    word : (n,) {0, 1}
        The decoded word, re-encoded.
    n_bits : int
        Payload bits (CRC included): the decoder chose among 2^n_bits words.
    """
    signs = 2.0 * np.asarray(word, dtype=np.float64) - 1.0
    t = float(np.asarray(z, dtype=np.float64) @ signs) / np.sqrt(len(signs))
    log_tail = special.log_ndtr(-t) + n_bits * np.log(2.0)
    return float(min(1.0, np.exp(log_tail)))


def along_normals(displacement, normals, cap=None, iterations=60):
    """Normal-direction version of a displacement, at the same RMS and peak.

    Each point keeps only its displacement along its normal, h_i = n_i . d_i.
    That part is scaled by one factor gamma and clipped at ``cap`` (default:
    the input's largest displacement), with gamma chosen so that the RMS is the
    input's.  So the RMSE is unchanged and no point moves farther than the cap,
    while all of the motion is across the surface, where a resampled or noisy
    copy still shows it.

    Parameters
    ----------
    displacement : (n, 3) float
    normals : (n, 3) float, unit (either orientation)
    cap : float, optional
        Largest displacement of the result.
    iterations : int
        Bisection steps for gamma (60 reach float precision).

    Returns
    -------
    moved : (n, 3) float
    gamma : float
        The scale (about sqrt(3) when the displacement directions are random).
    """
    h = np.einsum("ni,ni->n", displacement, normals)
    size = np.abs(h)
    if cap is None:
        cap = float(np.sqrt((displacement**2).sum(axis=1).max()))
    target = float((displacement**2).sum(axis=1).mean())
    if target == 0.0 or not size.any():
        return np.zeros_like(displacement), 1.0
    lo, hi = 0.0, cap / float(size[size > 0].min())   # at hi every point sits at the cap
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if float((np.minimum(mid * size, cap) ** 2).mean()) < target:
            lo = mid
        else:
            hi = mid
    gamma = 0.5 * (lo + hi)
    return (np.sign(h) * np.minimum(gamma * size, cap))[:, None] * normals, gamma
