"""The master secret: from a key file or the environment, never from a config.

Only key ids and salted fingerprints leave this module's callers; the secret
itself is turned into per-key-id material
(:func:`pipeline.kernels.keys.derive_key_material`) in the process that read
it.  No message of this module ever contains the secret or a value that may
be one (a secret pasted where a key-file path belongs is not echoed).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ..kernels.keys import MIN_SECRET_BYTES

__all__ = ["SecretError", "load_secret", "ENV_VAR", "without_secret_env"]

ENV_VAR = "POINTMARK_SECRET"


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
        Defaults to ``os.environ``.

    Returns
    -------
    bytes
        At least ``MIN_SECRET_BYTES`` long.
    """
    environ = os.environ if environ is None else environ
    if secret_file is not None:
        path = Path(secret_file)
        try:
            is_file = path.is_file()
        except (OSError, ValueError):
            is_file = False
        if not is_file:
            # the value may be a secret pasted in the wrong place: never echo it
            raise SecretError("secret file: no such file (the value given is not shown, "
                              "in case it is the secret itself)")
        secret = path.read_bytes().rstrip(b"\r\n")
        return _checked(secret, f"{path}: the secret file")
    value = environ.get(ENV_VAR, "")
    if not value:
        raise SecretError(f"no secret: set {ENV_VAR} or pass --secret-file FILE")
    return _checked(value.encode("utf-8"), ENV_VAR)


def _checked(secret, where):
    if len(secret) < MIN_SECRET_BYTES:
        raise SecretError(f"{where} holds a secret of {len(secret)} bytes; at least {MIN_SECRET_BYTES} "
                          f"are needed (e.g. python -c 'import secrets; print(secrets.token_hex(32))')")
    return secret


@contextlib.contextmanager
def without_secret_env():
    """Hide ``POINTMARK_SECRET`` from processes started inside the block (Dask workers)."""
    value = os.environ.pop(ENV_VAR, None)
    try:
        yield
    finally:
        if value is not None:
            os.environ[ENV_VAR] = value
