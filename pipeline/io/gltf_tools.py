"""The Node tools around glTF: the Khronos validator, and glTF Transform's CLI as file-level attacks.

``make setup`` installs them with npm into the repository's ``node_modules``
(``package.json``); ``$POINTMARK_NODE_MODULES`` points elsewhere.  Each
attack reads one GLB and writes one file, as a marketplace's tool chain
would: ``gltf-draco:14`` (Draco, 14 position bits), ``gltf-quantize``,
``gltf-meshopt``, ``gltf-weld``, ``gltf-reorder``, ``gltf-simplify:0.5``,
``gltf-optimize``, and ``gltf-ply`` / ``gltf-obj`` (conversion through
trimesh).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

__all__ = ["node_modules", "tools_available", "validate", "validate_all", "file_attack", "FILE_ATTACKS", "ToolError",
           "attack_suffix"]

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 300

# name -> (gltf-transform arguments after the command, with {s} the strength, default strength)
FILE_ATTACKS = {
    "gltf-draco": (["draco", "--quantize-position", "{s}"], 14),
    "gltf-quantize": (["quantize"], None),
    "gltf-meshopt": (["meshopt"], None),
    "gltf-weld": (["weld"], None),
    "gltf-reorder": (["reorder"], None),
    "gltf-simplify": (["simplify", "--ratio", "{s}", "--error", "0.01"], 0.5),
    "gltf-optimize": (["optimize", "--texture-compress", "false"], None),
    "gltf-ply": (None, None),
    "gltf-obj": (None, None),
}


class ToolError(RuntimeError):
    """An external tool that is missing or failed (the message says which and why)."""


def node_modules():
    """The folder holding the npm tools: ``$POINTMARK_NODE_MODULES`` or the repository's ``node_modules``."""
    return Path(os.environ.get("POINTMARK_NODE_MODULES", ROOT / "node_modules"))


def tools_available():
    """True when node, glTF Transform's CLI and the validator are installed."""
    modules = node_modules()
    return shutil.which("node") is not None and (modules / ".bin" / "gltf-transform").exists() \
        and (modules / "gltf-validator").is_dir()


# one node process for every file (its start-up is most of a small file's time): one report per file, in order
_VALIDATE = """
const fs = require('fs'); const path = require('path');
const validator = require(process.argv[1]);
const one = (file) => validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
  maxIssues: 0, externalResourceFunction: (uri) => new Promise((ok, fail) => {
    fs.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)), (e, d) => e ? fail(e) : ok(new Uint8Array(d)));
  })
});
(async () => { const out = []; for (const file of process.argv.slice(2)) out.push(await one(file)); return out; })()
  .then((r) => process.stdout.write(JSON.stringify(r))).catch((e) => { console.error(String(e)); process.exit(1); });
"""


def validate(path):
    """The Khronos validator's issues on a file.

    Returns
    -------
    list of (code, severity, pointer)
        Severity 0 error, 1 warning, 2 info, 3 hint.
    """
    return validate_all([path])[0]


def validate_all(paths):
    """:func:`validate` on each of ``paths`` in one node process; one list of issues per path, in order."""
    if not tools_available():
        raise ToolError("gltf-validator is not installed (run `make setup`, which installs node and npm where missing)")
    paths = [str(p) for p in paths]
    if not paths:
        return []
    out = _run(["node", "-e", _VALIDATE, str(node_modules() / "gltf-validator"), *paths], "gltf-validator")
    return [[(m["code"], int(m["severity"]), m.get("pointer", "")) for m in report["issues"]["messages"]]
            for report in json.loads(out)]


def attack_suffix(name):
    """The suffix of what a file attack writes (``.ply``, ``.obj`` or ``.glb``)."""
    return {"gltf-ply": ".ply", "gltf-obj": ".obj"}.get(name, ".glb")


def file_attack(source, target, name, strength=None):
    """Run one file attack on ``source`` (a GLB), writing ``target``.

    Parameters
    ----------
    source, target : str or Path
    name : str
        A key of :data:`FILE_ATTACKS`.
    strength : float, optional
        Position bits (draco) or the ratio of vertices kept (simplify).

    Returns
    -------
    pathlib.Path
    """
    if name not in FILE_ATTACKS:
        raise ValueError(f"unknown file attack {name!r}; known: {', '.join(sorted(FILE_ATTACKS))}")
    args, default = FILE_ATTACKS[name]
    target = Path(target)
    if args is None:
        return _convert(source, target)
    if not tools_available():
        raise ToolError(f"{name}: gltf-transform is not installed (run `make setup`, which installs node and npm where missing)")
    s = default if strength is None else strength
    s = int(s) if name == "gltf-draco" else s
    command = [str(node_modules() / ".bin" / "gltf-transform"), args[0], str(source), str(target),
               *[a.format(s=s) for a in args[1:]]]
    _run(command, f"gltf-transform {args[0]}")
    return target


def _convert(source, target):
    """A GLB to PLY or OBJ through trimesh: one mesh in world space (vertices merged as trimesh does)."""
    import trimesh

    scene = trimesh.load(str(source), force="scene")
    mesh = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    mesh.export(str(target))
    return target


def _run(command, what):
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ToolError(f"{what}: {exc}") from None
    if done.returncode != 0:
        last = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no message"]
        raise ToolError(f"{what} failed (exit {done.returncode}): {last[0][:200]}")
    return done.stdout
