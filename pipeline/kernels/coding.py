"""Channel codes for the payload: the paper's repetition and three convolutional codes.

The paper repeats every bit ``chip_rate`` times (eq. 2): a repetition code,
which at equal energy per payload bit gains nothing over sending each bit
once.  The convolutional codes here spread the same number of chips over a
coded word instead:

- ``convolutional``: rate 1/2, constraint length 7, generators 171 and 133
  (octal, the NASA/CCSDS code, free distance 10), terminated with K - 1 zero
  tail bits: 76 symbols for 32 bits.
- ``tailbiting``: rate 1/3, constraint length 9, generators 557, 663 and 711
  (the IS-95 code, free distance 18), tail-biting (the encoder starts in the
  state its last K - 1 bits leave it in, so no tail is sent): 96 symbols for
  32 bits, the chips of chip rate 3.  Its R * d_free at the effective rate
  (32 / 96) is 6, against 4.2 for the terminated code (32 / 76): about
  1.5 dB more at high signal-to-noise ratio.
- ``tailbiting-half``: rate 1/2, constraint length 9, generators 561 and 753
  (free distance 12), tail-biting: 64 symbols for 32 bits, the chips of
  chip rate 2, for bands too narrow for three chips a bit (bench/RESULTS.md,
  "The coded message at chip rate 2").

Decoding is soft: max-log-MAP (the BCJR recursion in the log domain) over
the per-coded-bit z-scores, whose hard decisions are those of the soft
Viterbi decoder and whose margins are per-bit reliabilities.  The
tail-biting word is decoded exactly: one recursion per starting state, the
paths kept whose last state is their first.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["CODES", "CONSTRAINT", "GENERATORS", "TAILBITING_CONSTRAINT", "TAILBITING_GENERATORS",
           "TAILBITING_HALF_GENERATORS", "coded_length",
           "least_chip_rate", "encode", "decode_soft", "chip_groups"]

CODES = ("repetition", "convolutional", "tailbiting", "tailbiting-half")
GENERATORS = (0o171, 0o133)
CONSTRAINT = 7
TAILBITING_GENERATORS = (0o557, 0o663, 0o711)
TAILBITING_CONSTRAINT = 9
TAILBITING_HALF_GENERATORS = (0o561, 0o753)


def coded_length(n_bits, code):
    """Number of coded symbols for ``n_bits`` payload bits (CRC included)."""
    if code == "repetition":
        return int(n_bits)
    if code == "convolutional":
        return len(GENERATORS) * (int(n_bits) + CONSTRAINT - 1)
    if code in _TAILBITING:
        return _TAILBITING[code].out.shape[-1] * int(n_bits)
    raise ValueError(f"unknown code {code!r}; use one of {', '.join(CODES)}")


def least_chip_rate(n_bits, code):
    """Smallest chip rate whose ``n_bits`` x c chips carry the coded word.

    1 for repetition; for 32 bits 3 under ``convolutional`` and ``tailbiting``, 2 under ``tailbiting-half``.
    """
    return -(-coded_length(n_bits, code) // int(n_bits))


def _trellis(generators=GENERATORS, constraint=CONSTRAINT):
    """next_state (S, 2) int and outputs (S, 2, n_out) in {-1, +1} of the shift register."""
    states = 1 << (constraint - 1)
    s = np.arange(states)[:, None]
    u = np.arange(2)[None, :]
    register = (u << (constraint - 1)) | s           # current input in the top bit
    outputs = np.stack([_parity(register & g, constraint) for g in generators], axis=-1)
    return register >> 1, 2.0 * outputs - 1.0


def _parity(x, constraint=CONSTRAINT):
    x = np.asarray(x, dtype=np.int64)
    bits = (x[..., None] >> np.arange(constraint)) & 1
    return bits.sum(axis=-1) & 1


_NEXT, _OUT = _trellis()


class _Tailbiting(NamedTuple):
    """The trellis of a tail-biting code (S = 2^(K - 1) states)."""

    nxt: np.ndarray     # (S, 2) int, the state after each (state, input)
    out: np.ndarray     # (S, 2, n_out) in {-1, +1}, the symbols sent
    came: np.ndarray    # (S, 2) int, the two states that lead into each state
    fed: np.ndarray     # (S, 2) int, and the input that leads from each of them


def _tailbiting_tables(generators):
    nxt, out = _trellis(generators, TAILBITING_CONSTRAINT)
    came, fed = np.divmod(np.argsort(nxt.ravel(), kind="stable").reshape(-1, 2), 2)
    return _Tailbiting(nxt, out, came, fed)


_TAILBITING = {"tailbiting": _tailbiting_tables(TAILBITING_GENERATORS),
               "tailbiting-half": _tailbiting_tables(TAILBITING_HALF_GENERATORS)}


def encode(bits, code):
    """Coded word of payload bits.

    Parameters
    ----------
    bits : (m,) {0, 1}
    code : {"repetition", "convolutional", "tailbiting", "tailbiting-half"}

    Returns
    -------
    (coded_length(m, code),) uint8
    """
    bits = np.asarray(bits, dtype=np.int64)
    if code == "repetition":
        return bits.astype(np.uint8)
    coded_length(len(bits), code)   # validates the name
    if code in _TAILBITING:
        nxt, table = _TAILBITING[code].nxt, _TAILBITING[code].out
        memory = TAILBITING_CONSTRAINT - 1
        state = 0
        for u in np.tile(bits, -(-memory // max(len(bits), 1)))[-memory:]:   # the state the last bits leave
            state = int(nxt[state, u])                     # (a word shorter than the memory, repeated)
        feed = bits
    else:
        state, nxt, table = 0, _NEXT, _OUT
        feed = np.concatenate([bits, np.zeros(CONSTRAINT - 1, dtype=np.int64)])
    out = []
    for u in feed:
        out.append((table[state, u] > 0).astype(np.uint8))
        state = int(nxt[state, u])
    return np.concatenate(out)


def decode_soft(z, n_bits, code):
    """Soft decoding of per-symbol scores.

    Parameters
    ----------
    z : (coded_length(n_bits, code),) float
        Score of each coded symbol, positive for a 1 (the correlator's z).
    n_bits : int
    code : {"repetition", "convolutional", "tailbiting", "tailbiting-half"}

    Returns
    -------
    bits : (n_bits,) uint8
    margin : (n_bits,) float
        Per-bit reliability in z units: z itself for the repetition code;
        for either convolutional code half the difference of the best path
        metrics with the bit at 1 and at 0 (max-log-MAP), positive for a 1.
    """
    z = np.asarray(z, dtype=np.float64)
    if len(z) != coded_length(n_bits, code):
        raise ValueError(f"{len(z)} scores for a {code} word of {n_bits} bits")
    if code == "repetition":
        return (z > 0).astype(np.uint8), z.copy()
    if code in _TAILBITING:
        return _decode_tailbiting(z, n_bits, _TAILBITING[code])
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


def _decode_tailbiting(z, n_bits, trellis):
    """Exact max-log-MAP of the tail-biting word of ``trellis`` (a :class:`_Tailbiting`).

    alpha and beta per starting state, (S0, S) each step; ``z`` is (n_bits * n_out,).
    """
    nxt, out, came, fed = trellis
    states = nxt.shape[0]
    gamma = np.einsum("tk,suk->tsu", z.reshape(n_bits, out.shape[-1]), out)                    # (T, S, 2)
    start = np.where(np.eye(states, dtype=bool), 0.0, -np.inf)                                 # (S0, S)
    alpha = np.empty((n_bits + 1, states, states))
    alpha[0] = start
    for t in range(n_bits):
        alpha[t + 1] = np.maximum(alpha[t][:, came[:, 0]] + gamma[t][came[:, 0], fed[:, 0]],
                                  alpha[t][:, came[:, 1]] + gamma[t][came[:, 1], fed[:, 1]])
    beta = np.empty_like(alpha)
    beta[n_bits] = start                                      # the last state is the first
    for t in range(n_bits - 1, -1, -1):
        beta[t] = np.maximum(gamma[t][:, 0] + beta[t + 1][:, nxt[:, 0]],
                             gamma[t][:, 1] + beta[t + 1][:, nxt[:, 1]])
    best = np.empty((n_bits, 2))
    for t in range(n_bits):
        for u in range(2):
            best[t, u] = (gamma[t][:, u] + (alpha[t] + beta[t + 1][:, nxt[:, u]]).max(axis=0)).max()
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
