"""The master secret: from a key file or the environment, never from a config.

Only key ids and fingerprints leave this module's callers; the secret itself
is turned into per-key-id material (:func:`pipeline.kernels.keys.derive_key_material`)
in the process that read it.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["SecretError", "load_secret", "ENV_VAR"]

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
    """
    environ = os.environ if environ is None else environ
    if secret_file is not None:
        path = Path(secret_file)
        if not path.is_file():
            raise SecretError(f"{path}: secret file not found")
        secret = path.read_bytes().rstrip(b"\r\n")
        if not secret:
            raise SecretError(f"{path}: secret file is empty")
        return secret
    value = environ.get(ENV_VAR, "")
    if not value:
        raise SecretError(f"no secret: set {ENV_VAR} or pass --secret-file FILE")
    return value.encode("utf-8")
