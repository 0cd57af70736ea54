"""Channel codes for the payload: the paper's repetition and a convolutional code.

The paper repeats every bit ``chip_rate`` times (eq. 2): a repetition code,
which at equal energy per payload bit gains nothing over sending each bit
once.  The convolutional code here spreads the same number of chips over a
coded word instead: rate 1/2, constraint length 7, generators 171 and 133
(octal, the NASA/CCSDS code, free distance 10), terminated with K - 1 zero
tail bits.  Decoding is soft: max-log-MAP (the BCJR recursion in the log
domain) over the per-coded-bit z-scores, whose hard decisions are those of
the soft Viterbi decoder and whose margins are per-bit reliabilities.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CODES", "CONSTRAINT", "GENERATORS", "coded_length", "least_chip_rate", "encode", "decode_soft",
           "chip_groups"]

CODES = ("repetition", "convolutional")
GENERATORS = (0o171, 0o133)
CONSTRAINT = 7


def coded_length(n_bits, code):
    """Number of coded symbols for ``n_bits`` payload bits (CRC included)."""
    if code == "repetition":
        return int(n_bits)
    if code == "convolutional":
        return len(GENERATORS) * (int(n_bits) + CONSTRAINT - 1)
    raise ValueError(f"unknown code {code!r}; use one of {', '.join(CODES)}")


def least_chip_rate(n_bits, code):
    """Smallest chip rate whose ``n_bits`` x c chips carry the coded word (1 for repetition, 3 for 32 bits)."""
    return -(-coded_length(n_bits, code) // int(n_bits))


def _trellis():
    """next_state (S, 2) int and outputs (S, 2, n_out) in {-1, +1} of the shift register."""
    states = 1 << (CONSTRAINT - 1)
    s = np.arange(states)[:, None]
    u = np.arange(2)[None, :]
    register = (u << (CONSTRAINT - 1)) | s           # current input in the top bit
    outputs = np.stack([_parity(register & g) for g in GENERATORS], axis=-1)
    return register >> 1, 2.0 * outputs - 1.0


def _parity(x):
    x = np.asarray(x, dtype=np.int64)
    bits = (x[..., None] >> np.arange(CONSTRAINT)) & 1
    return bits.sum(axis=-1) & 1


_NEXT, _OUT = _trellis()


def encode(bits, code):
    """Coded word of payload bits.

    Parameters
    ----------
    bits : (m,) {0, 1}
    code : {"repetition", "convolutional"}

    Returns
    -------
    (coded_length(m, code),) uint8
    """
    bits = np.asarray(bits, dtype=np.int64)
    if code == "repetition":
        return bits.astype(np.uint8)
    coded_length(len(bits), code)   # validates the name
    state, out = 0, []
    for u in np.concatenate([bits, np.zeros(CONSTRAINT - 1, dtype=np.int64)]):
        out.append((_OUT[state, u] > 0).astype(np.uint8))
        state = int(_NEXT[state, u])
    return np.concatenate(out)


def decode_soft(z, n_bits, code):
    """Soft decoding of per-symbol scores.

    Parameters
    ----------
    z : (coded_length(n_bits, code),) float
        Score of each coded symbol, positive for a 1 (the correlator's z).
    n_bits : int
    code : {"repetition", "convolutional"}

    Returns
    -------
    bits : (n_bits,) uint8
    margin : (n_bits,) float
        Per-bit reliability in z units: z itself for the repetition code;
        for the convolutional code half the difference of the best path
        metrics with the bit at 1 and at 0 (max-log-MAP), positive for a 1.
    """
    z = np.asarray(z, dtype=np.float64)
    if len(z) != coded_length(n_bits, code):
        raise ValueError(f"{len(z)} scores for a {code} word of {n_bits} bits")
    if code == "repetition":
        return (z > 0).astype(np.uint8), z.copy()
    steps = n_bits + CONSTRAINT - 1
    gamma = np.einsum("tk,suk->tsu", z.reshape(steps, len(GENERATORS)), _OUT)   # (T, S, 2) branch metrics
    gamma[n_bits:, :, 1] = -np.inf                                               # the tail is all zeros
    states = _NEXT.shape[0]
    alpha = np.full((steps + 1, states), -np.inf)
    alpha[0, 0] = 0.0
    for t in range(steps):
        cand = alpha[t][:, None] + gamma[t]                                      # (S, 2)
        np.maximum.at(alpha[t + 1], _NEXT.ravel(), cand.ravel())
    beta = np.full((steps + 1, states), -np.inf)
    beta[steps, 0] = 0.0
    for t in range(steps - 1, -1, -1):
        beta[t] = (gamma[t] + beta[t + 1][_NEXT]).max(axis=1)
    path = alpha[:n_bits, :, None] + gamma[:n_bits] + beta[1:n_bits + 1][:, _NEXT]   # (m, S, 2)
    best = path.max(axis=1)                                                          # (m, 2)
    margin = 0.5 * (best[:, 1] - best[:, 0])
    return (margin > 0).astype(np.uint8), margin


def chip_groups(n_symbols, n_chips):
    """Symbol of each chip: ``n_chips`` chips shared as evenly as possible, in order.

    With ``n_chips = m * c`` and ``n_symbols = m`` this is the paper's
    repetition (chip i belongs to bit i // c).

    Returns
    -------
    (n_chips,) int in [0, n_symbols)
    """
    if n_chips < n_symbols:
        raise ValueError(f"{n_chips} chips cannot carry {n_symbols} coded symbols; raise chip_rate")
    return (np.arange(n_chips) * n_symbols) // n_chips
