"""The master secret: from a key file or the environment, never from a config.

Only key ids and salted fingerprints leave this module's callers; the secret
itself is turned into per-key-id material
(:func:`pipeline.kernels.keys.derive_key_material`) in the process that read
it.  No message of this module ever contains the secret or a value that may
be one: a secret pasted where a key-file path belongs is not echoed, and
neither is the path of a key file that cannot be read (it may be the secret
typed in the wrong place, and a path names where the keys are kept).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ..kernels.keys import MIN_SECRET_BYTES

__all__ = ["SecretError", "load_secret", "ENV_VAR", "without_secret_env", "check_key_id", "MAX_SECRET_BYTES"]

ENV_VAR = "POINTMARK_SECRET"
# a key file is a line of text: a larger "secret file" is the wrong file
MAX_SECRET_BYTES = 4096
# a secret of which one byte value makes up this share or more is a placeholder, not a key
MAX_ONE_BYTE_SHARE = 0.5
# a key id that is this long a part of the secret gives the secret away
MIN_LEAKED_PART = 8


class SecretError(ValueError):
    """No usable master secret."""


def load_secret(secret_file=None, environ=None):
    """Read the master secret.

    Parameters
    ----------
    secret_file : str or Path, optional
        A file whose content (trailing newline stripped) is the secret; wins
        over the environment.
    environ : mapping, optional
        Defaults to ``os.environ``.  A value that is not UTF-8 is taken as
        its bytes (POSIX hands the environment over as bytes).

    Returns
    -------
    bytes
        At least ``MIN_SECRET_BYTES`` long, not blank, not mostly one byte.
    """
    environ = os.environ if environ is None else environ
    if secret_file is not None:
        return _checked(_read_key_file(secret_file), "the secret file")
    value = environ.get(ENV_VAR, "")
    if not value:
        raise SecretError(f"no secret: set {ENV_VAR} or pass --secret-file FILE")
    try:
        secret = value if isinstance(value, bytes) else value.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:
        raise SecretError(f"{ENV_VAR}: not text nor bytes the environment can hold (the value is not shown)") from None
    return _checked(secret, ENV_VAR)


def _read_key_file(secret_file):
    """The key file's bytes, trailing newline stripped; no message names the path."""
    path = Path(secret_file)
    try:
        exists, is_file = path.exists(), path.is_file()
    except (OSError, ValueError):
        exists = is_file = False
    if not is_file:
        # the value may be a secret pasted in the wrong place: never echo it
        what = "not a regular file (a folder, FIFO or device)" if exists else "no such file"
        raise SecretError(f"secret file: {what} (the value given is not shown, in case it is the secret itself)")
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_SECRET_BYTES + 1)
    except OSError as exc:
        raise SecretError(f"secret file: cannot be read ({exc.strerror or type(exc).__name__}; the path is "
                          f"not shown)") from None
    if len(data) > MAX_SECRET_BYTES:
        raise SecretError(f"secret file: more than {MAX_SECRET_BYTES} bytes; a key file holds one line "
                          f"(is it the right file? the path is not shown)")
    return data.rstrip(b"\r\n")


def _checked(secret, where):
    """Refuse a secret that is short, blank or mostly one byte (the message never quotes it)."""
    hint = "(e.g. python -c 'import secrets; print(secrets.token_hex(32))')"
    if len(secret) < MIN_SECRET_BYTES:
        raise SecretError(f"{where} holds a secret of {len(secret)} bytes; at least {MIN_SECRET_BYTES} "
                          f"are needed {hint}")
    if not secret.strip():
        raise SecretError(f"{where} holds only white space; use a random secret {hint}")
    top = max(secret.count(bytes([b])) for b in set(secret))
    if top >= MAX_ONE_BYTE_SHARE * len(secret):
        raise SecretError(f"{where}: {100 * top // len(secret)} % of the secret is one repeated byte; use a "
                          f"random secret {hint}")
    return secret


def check_key_id(key_id, secret, where="--key-id"):
    """Refuse a key id that holds the secret, or a part of it, before it reaches a ledger or a line.

    Parameters
    ----------
    key_id : str
    secret : bytes
    where : str
        Where the key id came from (the option or config key), for the message.

    Returns
    -------
    str
        ``key_id``.
    """
    try:
        text = key_id.encode("utf-8")
    except UnicodeEncodeError:
        raise SecretError(f"{where}: the key id is not valid UTF-8 text (not shown)") from None
    if not key_id or not key_id.isprintable() or len(key_id) > 128:
        raise SecretError(f"{where}: a key id is 1 to 128 printable characters on one line (not shown)")
    if secret in text or (len(text) >= MIN_LEAKED_PART and text in secret):
        raise SecretError(f"{where}: the key id holds the secret or a part of it; a key id is public "
                          f"(it goes into the ledger and onto every line): choose a name (not shown)")
    return key_id


@contextlib.contextmanager
def without_secret_env():
    """Hide ``POINTMARK_SECRET`` from processes started inside the block (Dask workers)."""
    value = os.environ.pop(ENV_VAR, None)
    try:
        yield
    finally:
        if value is not None:
            os.environ[ENV_VAR] = value
