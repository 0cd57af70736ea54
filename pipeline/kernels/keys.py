"""Key-seeded pseudo-random sequences (the paper's PRNS p_i), from HMAC-SHA256.

The master secret never leaves the process that read it: a per-key-id
``key material`` is derived once, and every sequence (per cluster, per axis)
is drawn from that material in counter mode.  The result depends only on the
bytes hashed, so it is the same on every platform and library version.
"""

from __future__ import annotations

import hashlib
import hmac

import numpy as np

__all__ = ["derive_key_material", "key_fingerprint", "new_salt", "pseudo_random_signs", "key_permutation",
           "recipient_payload", "ledger_mac_key", "row_mac", "MIN_SECRET_BYTES"]

MIN_SECRET_BYTES = 16
# scrypt cost of the public key fingerprint: about 50 ms per guess on one core
_SCRYPT = {"n": 1 << 14, "r": 8, "p": 1}


def derive_key_material(secret, key_id):
    """32 bytes of key material for one key id, derived from the master secret.

    Parameters
    ----------
    secret : bytes
    key_id : str

    Returns
    -------
    bytes, length 32
    """
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(f"the master secret is {len(secret)} bytes; at least {MIN_SECRET_BYTES} are needed")
    return hmac.new(secret, b"pointmark/key/" + key_id.encode("utf-8"), hashlib.sha256).digest()


def key_fingerprint(secret, salt):
    """Public fingerprint of the master secret: 16 hex digits of salted scrypt.

    Slow on purpose (about 50 ms per guess) and salted per deployment, so a
    manifest does not make a weak secret cheap to find.

    Parameters
    ----------
    secret : bytes
    salt : str
        Hex salt of the deployment (the ledger's).

    Returns
    -------
    str
    """
    digest = hashlib.scrypt(secret, salt=b"pointmark/key-fingerprint/" + bytes.fromhex(salt),
                            dklen=8, maxmem=64 << 20, **_SCRYPT)
    return digest.hex()


def new_salt():
    """A fresh random deployment salt (32 hex digits)."""
    import secrets

    return secrets.token_hex(16)


def _stream(material, label, n_bytes):
    out = bytearray()
    counter = 0
    while len(out) < n_bytes:
        msg = label.encode("utf-8") + b"/" + counter.to_bytes(8, "big")
        out += hmac.new(material, msg, hashlib.sha256).digest()
        counter += 1
    return np.frombuffer(bytes(out[:n_bytes]), dtype=np.uint8)


def pseudo_random_signs(material, label, length):
    """A +-1 sequence of ``length`` chips for ``label`` (e.g. "cluster=0/axis=1").

    Returns
    -------
    (length,) int8 in {-1, +1}
    """
    bits = np.unpackbits(_stream(material, "signs/" + label, (length + 7) // 8))[:length]
    return (2 * bits.astype(np.int8) - 1).astype(np.int8)


def key_permutation(material, label, length):
    """A key-dependent permutation of ``range(length)`` (for interleaving chips).

    Returns
    -------
    (length,) int64
    """
    keys = _stream(material, "perm/" + label, 8 * length).view(">u8")
    return np.argsort(keys, kind="stable").astype(np.int64)


def recipient_payload(asset_key, recipient, n_bits):
    """The payload issued to one recipient of one asset: n_bits of SHA-256, as HEX.

    Public (no secret): the embedding manifest maps it back to the recipient;
    a scan matches a decoded payload to the nearest issued one.
    """
    digest = hashlib.sha256(f"pointmark/payload/{asset_key}/{recipient}".encode("utf-8")).digest()
    value = int.from_bytes(digest, "big") >> (256 - n_bits)
    return format(value, f"0{(n_bits + 3) // 4}x")


def ledger_mac_key(secret):
    """32 bytes that authenticate ledger rows, derived from the master secret (never the secret itself)."""
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(f"the master secret is {len(secret)} bytes; at least {MIN_SECRET_BYTES} are needed")
    return hmac.new(secret, b"pointmark/ledger-row-mac/v1", hashlib.sha256).digest()


def _canonical(value):
    if isinstance(value, float):
        return {"f": value.hex()}           # exact, and NaN/inf safe
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if hasattr(value, "isoformat"):         # a timestamp
        return {"t": value.isoformat()}
    return value


def row_mac(mac_key, row, fields):
    """HMAC-SHA256 (hex) of one ledger row's ``fields``, in a canonical form.

    Parameters
    ----------
    mac_key : bytes
        From :func:`ledger_mac_key`.
    row : dict
    fields : sequence of str
        The columns covered (every column but the MAC itself).

    Returns
    -------
    str, 64 hex digits
    """
    import json

    body = json.dumps([[f, _canonical(row.get(f))] for f in fields], separators=(",", ":"), ensure_ascii=True)
    return hmac.new(mac_key, body.encode("ascii"), hashlib.sha256).hexdigest()
