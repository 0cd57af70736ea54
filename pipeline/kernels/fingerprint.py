"""Recipient fingerprints: independent spread-spectrum codes and their scoring.

Every recipient of an asset gets its own +-1 chip vector x_j over all spectral
coefficients (cluster, coefficient, axis) of the asset, drawn from a keyed
extendable-output function of the key material, the asset and the recipient
(Cox et al. 1997; Wang, Wu, Trappe and Liu 2005, independent Gaussian-like
fingerprints with correlation detection).

Detection turns the estimated coefficient differences of a suspect into one
weighted observation vector y (chosen without looking at any fingerprint) and
scores every recipient with the normalised correlation

    s_j = <y, x_j> / ||y||.

For an innocent recipient x_j is independent of y, so given y the chips are
independent Rademacher variables and Hoeffding's inequality gives, for any y,
noisy or noise-free, colluded or not,

    P(s_j >= t) <= exp(-t^2 / 2).

A recipient is accused only when s_j clears sqrt(2 ln(n / epsilon)) for n
recipients checked, so the probability of accusing any innocent among them is
at most epsilon (union bound).  Colluders who average k copies keep about
1/k of their energy each, and still clear the threshold for small k.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["chip_bank", "signs", "quantize", "scores", "cluster_scores", "threshold", "corrected_p", "accuse", "presence",
           "observation"]

_DOMAIN = b"pointmark/fingerprint/v1"


def _field(text):
    raw = text.encode("utf-8")
    return len(raw).to_bytes(4, "big") + raw


def chip_bank(material, label, recipients, length):
    """Packed fingerprint chips of recipients: bit 1 is +1, bit 0 is -1.

    SHAKE-256 keyed by the (secret) key material is a pseudo-random function;
    fields are length-prefixed so no two (label, recipient) pairs collide.

    Parameters
    ----------
    material : bytes
        Key material of one key id (32 bytes).
    label : str
        What the copies are of (asset and generation).
    recipients : sequence of str
    length : int
        Chips per recipient.

    Returns
    -------
    (n_recipients, ceil(length / 8)) uint8
    """
    n_bytes = (int(length) + 7) // 8
    prefix = _DOMAIN + len(material).to_bytes(2, "big") + material + _field(label)
    raw = b"".join(hashlib.shake_256(prefix + _field(r)).digest(n_bytes) for r in recipients)
    return np.frombuffer(raw, dtype=np.uint8).reshape(len(recipients), n_bytes).copy()


def signs(bank, length, dtype=np.float64):
    """Unpacked chips, (n_recipients, length) in {-1, +1} (float64, or e.g. int8 to save memory)."""
    bits = np.unpackbits(np.atleast_2d(bank), axis=1)[:, :length].astype(dtype)
    return 2 * bits - 1


def quantize(y, bits=8):
    """y as integers in [-(2^(bits-1) - 1), 2^(bits-1) - 1], (length,) int64 (zeros stay zeros)."""
    y = np.asarray(y, dtype=np.float64)
    top = float(np.abs(y).max()) if y.size else 0.0
    if top == 0.0:
        return np.zeros(len(y), dtype=np.int64)
    return np.rint(y / top * (2 ** (bits - 1) - 1)).astype(np.int64)


def scores(y, bank, chunk=512, bits=8):
    """Normalised correlation s_j = <q, x_j> / ||q|| of every recipient, q = quantize(y).

    The observation is quantised to ``bits`` bits first; the Hoeffding bound
    holds for any fixed vector, so the scores of q keep it exactly, and q
    differs from y by less than 0.4 % of its largest entry.  Each bit-plane of
    q is a chip mask, and <q, c_j> is a sum of weighted popcounts of c_j AND
    mask: no recipient's chips are unpacked.

    Parameters
    ----------
    y : (length,) float
    bank : (n_recipients, ceil(length / 8)) uint8
    chunk : int
        Recipients per block (keeps a block in cache across the bit-planes).
    bits : int

    Returns
    -------
    (n_recipients,) float; zeros when y is zero
    """
    q = quantize(y, bits)
    norm = float(np.linalg.norm(q))
    if norm == 0.0 or len(bank) == 0:
        return np.zeros(len(bank))
    n_bytes = bank.shape[1]
    pad = (-n_bytes) % 8
    padded = np.zeros(8 * (n_bytes + pad), dtype=np.int64)
    padded[: len(q)] = q
    masks, weights = [], []
    for sign, part in ((1, np.maximum(padded, 0)), (-1, np.maximum(-padded, 0))):
        for b in range(bits - 1):
            masks.append(np.packbits(((part >> b) & 1).astype(np.uint8)).view(np.uint64))
            weights.append(sign * (1 << b))
    masks, weights = np.stack(masks), np.asarray(weights, dtype=np.float64)
    ones = np.empty(len(bank))
    for a in range(0, len(bank), chunk):
        words = np.ascontiguousarray(np.pad(bank[a:a + chunk], ((0, 0), (0, pad)))).view(np.uint64)
        ones[a:a + chunk] = np.bitwise_count(words[:, None, :] & masks[None]).sum(axis=2, dtype=np.int64) @ weights
    return (2.0 * ones - float(padded.sum())) / norm


def cluster_scores(y, chips, n_clusters):
    """Score of one recipient's chips cluster by cluster (for evidence: where the mark was found).

    Parameters
    ----------
    y : (length,) float
    chips : (length,) float in {-1, +1}
    n_clusters : int

    Returns
    -------
    (n_clusters,) float; 0 for a cluster the suspect does not cover
    """
    parts_y = np.split(np.asarray(y, dtype=np.float64), n_clusters)
    parts_x = np.split(np.asarray(chips, dtype=np.float64), n_clusters)
    return np.array([float(a @ b) / float(np.linalg.norm(a)) if np.any(a) else 0.0
                     for a, b in zip(parts_y, parts_x)])


def scores_over_poses(ys, bank):
    """Each recipient's best score over the poses a suspect was read at.

    A part of a near-symmetric shape fits at several poses; the mark is read
    at each.  Every pose is another test of every recipient: the threshold
    must count ``len(ys) * n_recipients`` checks.

    Parameters
    ----------
    ys : sequence of (length,) float
        The observation at each pose (at least one).
    bank : (n_recipients, ceil(length / 8)) uint8

    Returns
    -------
    best : (n_recipients,) float
        The highest score of each recipient.
    pose : (n_recipients,) int
        The index into ``ys`` where it was reached (the first on a tie).
    table : (len(ys), n_recipients) float
        Every score at every pose (for :func:`presence_over_poses`).
    """
    table = np.stack([scores(y, bank) for y in ys])
    pose = np.argmax(table, axis=0)
    return table[pose, np.arange(table.shape[1])], pose, table


def threshold(n_checked, epsilon):
    """Score an innocent exceeds with probability at most epsilon / n_checked."""
    return float(np.sqrt(2.0 * np.log(max(int(n_checked), 1) / float(epsilon))))


def corrected_p(s, n_checked):
    """Bonferroni-corrected Hoeffding p-value: min(1, n exp(-s^2/2)) for s > 0, else 1.

    Parameters
    ----------
    s : float or (k,) float
    n_checked : int
        Every recipient (of every asset and key) the suspect was scored against.

    Returns
    -------
    float or (k,) float
    """
    s = np.asarray(s, dtype=np.float64)
    log_p = np.log(max(int(n_checked), 1)) - 0.5 * np.maximum(s, 0.0) ** 2
    p = np.where(s > 0, np.exp(np.minimum(log_p, 0.0)), 1.0)
    return float(p) if p.ndim == 0 else p


def accuse(s, n_checked, epsilon):
    """Recipients whose scores clear the corrected threshold.

    Parameters
    ----------
    s : (n,) float
        Scores of the recipients of one reference.
    n_checked : int
        Total recipients checked for this suspect (>= n).
    epsilon : float
        Allowed probability of accusing any innocent, per suspect.

    Returns
    -------
    accused : (k,) int, indices into ``s`` by decreasing score
    margin : (k,) float
        Each accused score minus the best score that was not accused
        (minus 0 when every recipient is accused).
    """
    s = np.asarray(s, dtype=np.float64)
    t = threshold(n_checked, epsilon)
    order = np.argsort(-s, kind="stable")
    accused = order[s[order] >= t]
    rest = np.delete(s, accused)
    best_innocent = float(rest.max()) if len(rest) else 0.0
    return accused, s[accused] - best_innocent


def presence(s):
    """p-value of "some recipient's fingerprint is present", from all scores.

    Given y the scores of recipients that are not present are independent,
    mean 0, variance 1 and sub-Gaussian, so sum(s^2) is compared with a
    chi-square of n degrees of freedom.  Used only to say "inconclusive" (a
    mark is there, nobody is named), never to accuse.
    """
    from scipy import special

    s = np.asarray(s, dtype=np.float64)
    if len(s) == 0:
        return 1.0
    return float(special.gammaincc(len(s) / 2.0, float(s @ s) / 2.0))


def presence_over_poses(table):
    """:func:`presence` of a mark at any of the poses read: the best pose's p, Bonferroni over the poses.

    Parameters
    ----------
    table : (n_poses, n_recipients) float
        The scores at each pose (:func:`scores_over_poses`); one pose gives :func:`presence` itself.
    """
    return min(1.0, len(table) * min(presence(s) for s in table))


def observation(deltas, coverage, first, count):
    """One weighted vector y from every cluster's estimated coefficient differences.

    Parameters
    ----------
    deltas : list of (K, 3) float
        r-hat - r per cluster.
    coverage : (k,) float in [0, 1]
        Share of each cluster the suspect covers.
    first, count : int
        The fingerprint occupies coefficients first .. first + count - 1.

    Returns
    -------
    (k * 3 * count,) float
        Cluster by cluster, axis by axis (the layout of :func:`chip_bank` rows).
        Each cluster is weighted by coverage over its mean energy, which
        does not depend on any fingerprint.
    """
    parts = []
    for delta, cov in zip(deltas, coverage):
        d = np.asarray(delta, dtype=np.float64)[first:first + count].T   # (3, count)
        energy = float((d**2).mean()) if d.size else 0.0
        weight = float(np.clip(cov, 0.0, 1.0)) / energy if energy > 0 else 0.0
        parts.append(weight * d.ravel())
    return np.concatenate(parts) if parts else np.zeros(0)
