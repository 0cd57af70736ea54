"""A table of bad inputs and configs thrown at the command line, and how many are handled cleanly.

    python -m tests.fuzz.bad_inputs [--only CATEGORY] [--verbose]

Every case is run through ``pipeline.cli.main`` in this process.  A refused
case is handled cleanly when the exit status is 2, stderr is exactly one line
``pointmark: error: ...`` holding the expected file, option or key name and
the problem, and nothing was written (no output, no temporary file).  A case
marked ``ok`` must succeed (the documented correct result).  Exit status 0
when every case is handled cleanly.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import tempfile
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SECRET = "bad-inputs-secret-not-for-production"
SMALL = ["--set", "n_bits=24", "--set", "cluster_size=1200", "--set", "n_clusters=2"]


def surface(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v * (1 + 0.15 * np.sin(3 * v[:, :1]))


def ply(pts, fmt="binary_little_endian", coord="double", declared=None, extra_header="", tail=b""):
    t = {"double": "f8", "float": "f4"}[coord]
    e = ">" if fmt == "binary_big_endian" else "<"
    head = (f"ply\nformat {fmt} 1.0\n{extra_header}element vertex {len(pts) if declared is None else declared}\n"
            f"property {coord} x\nproperty {coord} y\nproperty {coord} z\nend_header\n").encode()
    if fmt == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(pts, dtype=t).astype(float).tolist()).encode()
    else:
        body = np.asarray(pts, dtype=e + t).tobytes()
    return head + body + tail


def las(pts, scale=0.001, suffix=".las"):
    import laspy

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([scale] * 3)
    header.offsets = np.floor(pts.min(axis=0))
    data = laspy.LasData(header)
    data.x, data.y, data.z = pts.T
    buf = io.BytesIO()
    data.write(buf, do_compress=suffix == ".laz")
    return buf.getvalue()


def patch(data, at, raw):
    data = bytearray(data)
    data[at: at + len(raw)] = raw
    return bytes(data)


@dataclass
class Case:
    category: str
    name: str
    files: dict                      # name -> bytes (or a str for text, None for a folder)
    argv: list                       # {d} is replaced by the case folder
    needles: tuple = ()
    ok: bool = False                 # the documented result is success
    env: dict = field(default_factory=dict)


def embed(src, out="out.ply", message="c0ffee", *extra):
    return ["embed", "{d}/" + src, "{d}/" + out, "--key-id", "k", "--message", message, *SMALL, *extra]


def cases():
    good = ply(surface())
    pts = surface()
    out = []

    def add(category, name, files, argv, *needles, ok=False, env=None):
        out.append(Case(category, name, files, argv, tuple(needles), ok, env or {}))

    # -- PLY files -------------------------------------------------------------------------------
    P = "PLY file"
    add(P, "valid binary PLY (control)", {"a.ply": good}, embed("a.ply"), ok=True)
    add(P, "valid ASCII PLY (control)", {"a.ply": ply(pts, "ascii")}, embed("a.ply"), ok=True)
    add(P, "garbage bytes", {"a.ply": b"\x00\x01garbage"}, embed("a.ply"), "a.ply", "not a PLY")
    add(P, "empty file", {"a.ply": b""}, embed("a.ply"), "a.ply", "the file is empty")
    add(P, "magic only", {"a.ply": b"ply\n"}, embed("a.ply"), "a.ply", "not a PLY")
    add(P, "no end_header", {"a.ply": good.replace(b"end_header", b"end_headr")}, embed("a.ply"), "a.ply")
    add(P, "unknown format", {"a.ply": good.replace(b"binary_little_endian", b"binary_middle_endian")},
        embed("a.ply"), "a.ply", "unknown PLY format")
    add(P, "negative vertex count", {"a.ply": good.replace(b"vertex 3000", b"vertex -3000")}, embed("a.ply"),
        "a.ply", "bad element line")
    add(P, "fewer vertices declared (binary)", {"a.ply": ply(pts, declared=2500)}, embed("a.ply"), "a.ply",
        "declares 2500 vertices, the body holds 3000")
    add(P, "fewer vertices declared (ascii)", {"a.ply": ply(pts, "ascii", declared=2500)}, embed("a.ply"),
        "a.ply", "declares 2500 vertices")
    add(P, "fewer vertices declared (big endian)", {"a.ply": ply(pts, "binary_big_endian", declared=2999)},
        embed("a.ply"), "a.ply", "declares 2999 vertices")
    add(P, "more vertices declared (binary)", {"a.ply": ply(pts, declared=3001)}, embed("a.ply"), "a.ply",
        "truncated")
    add(P, "more vertices declared (ascii)", {"a.ply": ply(pts, "ascii", declared=3001)}, embed("a.ply"),
        "a.ply", "truncated")
    add(P, "huge vertex count", {"a.ply": ply(pts, declared=10**15)}, embed("a.ply"), "a.ply", "truncated")
    add(P, "5 stray bytes after the vertices", {"a.ply": ply(pts, tail=b"\0" * 5)}, embed("a.ply"), "a.ply",
        "5 bytes follow")
    add(P, "stray line after ascii vertices", {"a.ply": ply(pts, "ascii", tail=b"1 2\n")}, embed("a.ply"),
        "a.ply", "declares 3000 vertices")
    add(P, "face block truncated", {"a.ply": ply(pts, extra_header="", tail=b"")
                                    .replace(b"end_header", b"element face 10\nproperty list uchar int v\nend_header")},
        embed("a.ply"), "a.ply", "truncated")
    add(P, "list property on vertices", {"a.ply": good.replace(b"property double z",
                                                             b"property list uchar int z")},
        embed("a.ply"), "a.ply", "list properties")
    add(P, "missing z", {"a.ply": good.replace(b"property double z\n", b"")}, embed("a.ply"), "a.ply")
    add(P, "x declared twice", {"a.ply": good.replace(b"property double z", b"property double x")},
        embed("a.ply"), "a.ply", "declared twice")
    add(P, "unknown property type", {"a.ply": good.replace(b"double z", b"quad z")}, embed("a.ply"), "a.ply",
        "bad property line")
    add(P, "ascii value 300 for uchar", {"a.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                                   b"property float y\nproperty float z\nproperty uchar red\n"
                                                   b"end_header\n0 0 0 300\n"}, embed("a.ply"), "a.ply", "red")
    add(P, "ascii word instead of a number", {"a.ply": ply(pts, "ascii").replace(b"\n0.", b"\nabc", 1)},
        embed("a.ply"), "a.ply", "is not a number")
    add(P, "NaN coordinates", {"a.ply": ply(np.where(np.arange(3000)[:, None] == 7, np.nan, pts))},
        embed("a.ply"), "a.ply", "NaN or infinite")
    add(P, "infinite coordinates", {"a.ply": ply(np.where(np.arange(3000)[:, None] == 9, np.inf, pts))},
        embed("a.ply"), "a.ply", "NaN or infinite")
    add(P, "zero vertices", {"a.ply": ply(pts[:0])}, embed("a.ply"), "a.ply", "no points")
    add(P, "all points identical", {"a.ply": ply(np.ones((3000, 3)))}, embed("a.ply"), "a.ply",
        "identical")
    t = np.random.default_rng(1).uniform(0, 1000, 1000)
    line = np.column_stack([t, 2 * t + 1, 3 - t])
    add(P, "collinear float64", {"a.ply": ply(line)}, embed("a.ply"), "a.ply", "collinear")
    add(P, "collinear float32", {"a.ply": ply(line, coord="float")}, embed("a.ply"), "a.ply", "collinear")
    add(P, "collinear float32 at offset 1e5", {"a.ply": ply(line + 1e5, coord="float")}, embed("a.ply"),
        "a.ply", "collinear")
    add(P, "every point twice", {"a.ply": ply(np.repeat(pts, 2, axis=0))}, embed("a.ply"), "a.ply",
        "repeat another point")
    add(P, "200 points: payload beyond capacity", {"a.ply": ply(pts[:200])}, embed("a.ply"), "a.ply",
        "capacity")
    add(P, "non-ASCII bytes in a comment", {"a.ply": ply(pts, extra_header="comment caf\xe9\n")
                                            .replace(b"caf\xc3\xa9", b"caf\xe9")}, embed("a.ply"), ok=True)
    add(P, "input is a folder", {"a.ply": None}, embed("a.ply"), "a.ply")
    add(P, "input missing", {}, embed("gone.ply"), "gone.ply", "no such file")
    add(P, "unknown input suffix", {"a.stl": b"solid"}, embed("a.stl", "out.ply"), "a.stl",
        "unknown point-cloud format")
    add(P, "bad suspect for detect", {"a.ply": good, "s.ply": b"ply\nformat ascii 1.0\nend_header\n"},
        ["detect", "{d}/s.ply", "--original", "{d}/a.ply", "--key-id", "k"], "s.ply")
    add(P, "bad original for detect", {"a.ply": ply(pts, declared=10), "s.ply": good},
        ["detect", "{d}/s.ply", "--original", "{d}/a.ply", "--key-id", "k"], "a.ply", "declares 10")

    # -- LAS and LAZ ------------------------------------------------------------------------------
    L = "LAS/LAZ file"
    geo = pts * 3 + [637000.0, 851000.0, 400.0]
    good_las = las(geo)
    add(L, "valid LAS (control)", {"a.las": good_las}, embed("a.las", "out.las"), ok=True)
    add(L, "valid LAZ (control)", {"a.laz": las(geo, suffix=".laz")}, embed("a.laz", "out.laz"), ok=True)
    # a 3 m object at 1 cm steps: the survey rule's amplitude is below the step, so the paper's is set
    add(L, "LAS with 1 cm scale (control)", {"a.las": las(geo, 0.01)},
        embed("a.las", "out.las", "c0ffee", "--set", "amplitude=model", "--set", "max_displacement=null"), ok=True)
    add(L, "truncated LAS", {"a.las": good_las[:-100]}, embed("a.las", "out.las"), "a.las", "truncated")
    add(L, "two records more than declared", {"a.las": good_las + bytes(56)}, embed("a.las", "out.las"),
        "a.las", "declares 3000 points, the file holds 3002")
    add(L, "stray bytes after the points", {"a.las": good_las + b"xyz"}, embed("a.las", "out.las"), "a.las",
        "3 bytes more")
    add(L, "no LASF signature", {"a.las": b"LASX" + good_las[4:]}, embed("a.las", "out.las"), "a.las",
        "LASF")
    add(L, "version 0.3", {"a.las": patch(good_las, 24, b"\x00\x03")}, embed("a.las", "out.las"), "a.las",
        "version 0.3")
    add(L, "4 billion VLRs declared", {"a.las": patch(good_las, 100, b"\xff\xff\xff\xff")},
        embed("a.las", "out.las"), "a.las", "variable-length records")
    add(L, "offset to points past the end", {"a.las": patch(good_las, 96, b"\xff\xff\xff\x7f")},
        embed("a.las", "out.las"), "a.las", "offset to the points")
    add(L, "LAZ with 4 billion points declared", {"a.laz": patch(las(geo, suffix=".laz"), 107, b"\xff" * 4)},
        embed("a.laz", "out.laz"), "a.laz")
    add(L, "empty LAS", {"a.las": b""}, embed("a.las", "out.las"), "a.las")
    add(L, "header only", {"a.las": good_las[:227]}, embed("a.las", "out.las"), "a.las")
    tl = np.random.default_rng(2).uniform(0, 1000, 1000)
    add(L, "collinear on a 1 cm grid", {"a.las": las(np.column_stack([tl + 1000, 2 * tl + 1000, 3 - tl]), 0.01)},
        embed("a.las", "out.las"), "a.las", "collinear")

    # -- PCD, XYZ, PTS ----------------------------------------------------------------------------
    T = "PCD/XYZ/PTS file"
    xyz = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist()).encode()
    add(T, "valid XYZ (control)", {"a.xyz": xyz}, embed("a.xyz", "out.xyz"), ok=True)
    add(T, "empty XYZ", {"a.xyz": b""}, embed("a.xyz", "out.xyz"), "a.xyz")
    add(T, "XYZ with a word", {"a.xyz": xyz.replace(b"\n", b"\nhello 1 2\n", 1)}, embed("a.xyz", "out.xyz"),
        "a.xyz")
    add(T, "XYZ with two columns", {"a.xyz": b"1 2\n3 4\n"}, embed("a.xyz", "out.xyz"), "a.xyz")
    add(T, "XYZ with NaN", {"a.xyz": xyz.replace(b"\n", b"\nnan 1 2\n", 1)}, embed("a.xyz", "out.xyz"), "a.xyz")
    add(T, "PTS without its count line", {"a.pts": xyz}, embed("a.pts", "out.pts"), "a.pts")
    add(T, "PTS count larger than the body", {"a.pts": b"3001\n" + xyz}, embed("a.pts", "out.pts"), "a.pts")
    add(T, "binary junk as PTS", {"a.pts": bytes(range(256))}, embed("a.pts", "out.pts"), "a.pts")
    pcd_head = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3000\nHEIGHT 1\n"
                "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3000\nDATA binary\n").encode()
    pcd = pcd_head + pts.astype("<f4").tobytes()
    add(T, "valid PCD (control)", {"a.pcd": pcd}, embed("a.pcd", "out.pcd"), ok=True)
    add(T, "PCD truncated", {"a.pcd": pcd[:-40]}, embed("a.pcd", "out.pcd"), "a.pcd")
    add(T, "PCD POINTS disagrees with WIDTH", {"a.pcd": pcd.replace(b"POINTS 3000", b"POINTS 2000")},
        embed("a.pcd", "out.pcd"), "a.pcd")
    add(T, "PCD unknown DATA", {"a.pcd": pcd.replace(b"DATA binary", b"DATA zipped")}, embed("a.pcd", "out.pcd"),
        "a.pcd")
    add(T, "PCD garbage", {"a.pcd": b"\x89PNG\r\n"}, embed("a.pcd", "out.pcd"), "a.pcd")

    # -- arguments ---------------------------------------------------------------------------------
    A = "argument"
    for message, needle in [("-1", "not hexadecimal"), (" de_ad ", "not hexadecimal"), ("", "empty"),
                            ("0x", "empty"), ("xyz", "not hexadecimal"), ("+ff", "not hexadecimal"),
                            ("1_0", "not hexadecimal"), ("de ad", "not hexadecimal"), ("\u0663", "not hexadecimal"),
                            ("c0ffee00", "more than the 6"), ("ffffff1", "more than the 6")]:
        add(A, f"--message={message!r}", {"a.ply": good}, embed("a.ply", "out.ply", message), "--message", needle)
    add(A, "--message 0XC0FFEE (control)", {"a.ply": good}, embed("a.ply", "out.ply", "0XC0FFEE"), ok=True)
    add(A, "--expect not hex", {"a.ply": good}, ["detect", "{d}/a.ply", "--original", "{d}/a.ply", "--key-id",
                                                 "k", "--expect", "-1", *SMALL], "--expect")
    add(A, "no secret", {"a.ply": good}, embed("a.ply"), "POINTMARK_SECRET", env={"POINTMARK_SECRET": None})
    add(A, "secret too short", {"a.ply": good}, embed("a.ply"), "POINTMARK_SECRET", env={"POINTMARK_SECRET": "abc"})
    add(A, "secret file missing", {"a.ply": good}, embed("a.ply", "out.ply", "c0ffee", "--secret-file", "{d}/nokey"),
        "secret file")
    add(A, "unknown attack", {"a.ply": good}, ["attack", "{d}/a.ply", "{d}/out.ply", "--attack", "melt"],
        "--attack")
    add(A, "attack strength negative", {"a.ply": good},
        ["attack", "{d}/a.ply", "{d}/out.ply", "--attack", "noise:-1"], "--attack")
    add(A, "attack strength not a number", {"a.ply": good},
        ["attack", "{d}/a.ply", "{d}/out.ply", "--attack", "crop:lots"], "--attack")

    # -- output paths ---------------------------------------------------------------------------------
    O = "output path"
    junk = b"not a point cloud at all"
    add(O, "output is a folder", {"a.ply": junk, "o.ply": None}, embed("a.ply", "o.ply"), "o.ply", "is a folder")
    add(O, "output's parent is a file", {"a.ply": junk, "p": "file"}, embed("a.ply", "p/o.ply"), "p/o.ply",
        "is a file, not a folder")
    add(O, "output == input", {"a.ply": junk}, embed("a.ply", "a.ply"), "a.ply", "overwrite the original")
    add(O, "output == input via ./", {"a.ply": junk}, embed("a.ply", "./a.ply"), "a.ply", "overwrite the original")
    add(O, "output format differs", {"a.ply": junk}, embed("a.ply", "o.las"), "o.las", "differs")
    add(O, "output suffix unknown", {"a.ply": junk}, embed("a.ply", "o.stl"), "o.stl", "unknown point-cloud")
    add(O, "output in a new folder (control)", {"a.ply": good}, embed("a.ply", "new/deeper/o.ply"), ok=True)
    add(O, "attack output is a folder", {"a.ply": junk, "o.ply": None},
        ["attack", "{d}/a.ply", "{d}/o.ply", "--attack", "shuffle"], "o.ply", "is a folder")
    add(O, "attack output == input", {"a.ply": junk},
        ["attack", "{d}/a.ply", "{d}/a.ply", "--attack", "shuffle"], "a.ply", "overwrite")
    add(O, "attack output's parent is a file", {"a.ply": junk, "p": "x"},
        ["attack", "{d}/a.ply", "{d}/p/o.ply", "--attack", "shuffle"], "is a file")

    # -- configs -------------------------------------------------------------------------------------
    C = "config"
    bad_values = [
        ("watermark", "beta", ".nan", "not a finite number"), ("watermark", "beta", ".inf", "not a finite"),
        ("watermark", "beta", "-1", "beta"), ("watermark", "beta", "0", "beta"), ("watermark", "beta", "'x'", "beta"),
        ("watermark", "beta", "1", "beta"), ("watermark", "n_bits", "0", "n_bits"),
        ("watermark", "n_bits", "1000", "n_bits"), ("watermark", "n_bits", "1.5", "n_bits"),
        ("watermark", "n_bits", "'8'", "n_bits"), ("watermark", "chip_rate", "0", "chip_rate"),
        ("watermark", "valence", "-.inf", "not a finite"), ("watermark", "crc_bits", "7", "crc_bits"),
        ("watermark", "on_touch", "maybe", "on_touch"), ("watermark", "seeds", "[[0, 0, .nan]]", "not a finite"),
        ("watermark", "seeds", "[-1]", "seeds"), ("detection", "p_threshold", "1", "p_threshold"),
        ("detection", "p_threshold", "0", "p_threshold"), ("detection", "p_threshold", ".nan", "not a finite"),
        ("detection", "p_threshold", "-1", "p_threshold"), ("detection", "ratio_gate", "2", "ratio_gate"),
        ("detection", "iterations", "0", "iterations"), ("detection", "registration", "magic", "registration"),
        ("detection", "ridge", ".inf", "not a finite"),
    ]
    for section, key, value, needle in bad_values:
        add(C, f"{section}.{key}: {value}", {"c.yaml": f"{section}:\n  {key}: {value}\n"},
            ["validate", "{d}/c.yaml"], "c.yaml", needle)
    add(C, "beta .nan through embed --config", {"a.ply": good, "c.yaml": "watermark:\n  beta: .nan\n"},
        embed("a.ply", "out.ply", "c0ffee", "--config", "{d}/c.yaml"), "c.yaml", "not a finite")
    add(C, "beta=.nan through --set", {"a.ply": good}, embed("a.ply", "out.ply", "c0ffee", "--set", "beta=.nan"),
        "beta", "not a finite")
    add(C, "unknown key", {"c.yaml": "watermark:\n  betta: 0.1\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "betta")
    add(C, "unknown section", {"c.yaml": "watermarks: {}\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "watermarks")
    add(C, "bad indentation", {"c.yaml": "watermark:\n  beta: 0.1\n    n_bits: 8\n"}, ["validate", "{d}/c.yaml"],
        "c.yaml", "not valid YAML")
    add(C, "unclosed bracket", {"c.yaml": "watermark: [\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "not valid YAML")
    add(C, "tab indentation", {"c.yaml": "watermark:\n\tbeta: 0.1\n"}, ["validate", "{d}/c.yaml"], "c.yaml",
        "not valid YAML")
    add(C, "unclosed quote", {"c.yaml": "key:\n  id: 'abc\n"}, ["validate", "{d}/c.yaml"], "c.yaml",
        "not valid YAML")
    add(C, "a list at the top", {"c.yaml": "- 1\n- 2\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "mapping")
    add(C, "empty file (defaults, control)", {"c.yaml": ""}, ["validate", "{d}/c.yaml"], ok=True)
    add(C, "recursive alias", {"c.yaml": "a: &a [*a]\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "itself")
    bomb = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"] + [
        f"{c}: &{c} [" + ", ".join([f"*{p}"] * 10) + "]" for p, c in zip("abcdefgh", "bcdefghi")]
    add(C, "alias bomb", {"c.yaml": "\n".join(bomb) + "\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "more than")
    add(C, "not UTF-8", {"c.yaml": b"\xff\xfe\x00w"}, ["validate", "{d}/c.yaml"], "c.yaml", "UTF-8")
    add(C, "integer key", {"c.yaml": "watermark:\n  1: 2\n"}, ["validate", "{d}/c.yaml"], "c.yaml", "not a string")
    add(C, "python tag", {"c.yaml": "watermark: !!python/object:os.system {}\n"}, ["validate", "{d}/c.yaml"],
        "c.yaml", "not valid YAML")
    add(C, "config missing", {}, ["validate", "{d}/none.yaml"], "none.yaml", "not found")
    add(C, "config is a folder", {"c.yaml": None}, ["validate", "{d}/c.yaml"], "c.yaml")
    add(C, "--set unknown key", {"a.ply": good}, embed("a.ply", "out.ply", "c0ffee", "--set", "bta=1"), "bta")
    add(C, "--set without =", {"a.ply": good}, embed("a.ply", "out.ply", "c0ffee", "--set", "beta"), "--set")
    add(C, "--set bad YAML", {"a.ply": good}, embed("a.ply", "out.ply", "c0ffee", "--set", "beta=[0"), "--set beta")
    add(C, "--set into a scalar section", {"a.ply": good, "c.yaml": "watermark: 3\n"},
        embed("a.ply", "out.ply", "c0ffee", "--config", "{d}/c.yaml", "--set", "beta=0.1"), "not a mapping")
    add(C, "--set ambiguous name", {"a.ply": good}, embed("a.ply", "out.ply", "c0ffee", "--set", "out=x"),
        "ambiguous")
    return out


def _setup(case, folder):
    for name, content in case.files.items():
        path = folder / name
        if content is None:
            path.mkdir(parents=True)
        elif isinstance(content, str):
            path.write_text(content)
        else:
            path.write_bytes(content)


def run_case(case, root):
    """(clean: bool, note: str) for one case."""
    from pipeline.cli import main

    folder = root / f"case{id(case)}"
    folder.mkdir()
    _setup(case, folder)
    before = {p for p in folder.rglob("*")}
    argv = [a.replace("{d}", str(folder)) for a in case.argv]
    saved = {k: os.environ.get(k) for k in case.env}
    for k, v in case.env.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    err, outs = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(outs):
            try:
                code = main(argv)
            except SystemExit as exc:
                code = exc.code
            except BaseException:
                traceback.print_exc()
                code = "traceback"
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    lines = err.getvalue().splitlines()
    written = sorted(str(p.relative_to(folder)) for p in set(folder.rglob("*")) - before)
    if case.ok:
        if code == 0:
            return True, ""
        return False, f"exit {code}, wrote {written}: {' | '.join(lines)[:200]}"
    if code != 2:
        return False, f"exit {code}: {' | '.join(lines)[-200:]}"
    if len(lines) != 1 or not lines[0].startswith("pointmark: error: "):
        return False, f"{len(lines)} stderr lines: {' | '.join(lines)[:200]}"
    missing = [n for n in case.needles if n not in lines[0]]
    if missing:
        return False, f"message lacks {missing}: {lines[0][:200]}"
    if written:
        return False, f"left {written}"
    return True, lines[0]


def run_all(selected=None, verbose=False, stream=sys.stdout):
    """Run the cases; print the table; returns (rows, failures)."""
    os.environ.setdefault("POINTMARK_SECRET", SECRET)
    all_cases = cases() if selected is None else selected
    rows, failures = {}, []
    with tempfile.TemporaryDirectory(prefix="pointmark-bad-inputs-") as tmp:
        for case in all_cases:
            clean, note = run_case(case, Path(tmp))
            tried, ok = rows.get(case.category, (0, 0))
            rows[case.category] = (tried + 1, ok + clean)
            if not clean:
                failures.append(f"{case.category}: {case.name}: {note}")
            if verbose:
                print(f"  [{'clean' if clean else 'NOT CLEAN'}] {case.category}: {case.name}: {note[:160]}",
                      file=stream)
    width = max(len(c) for c in rows) + 2
    print(f"{'category':<{width}}{'tried':>6}{'clean':>7}", file=stream)
    for category, (tried, ok) in rows.items():
        print(f"{category:<{width}}{tried:>6}{ok:>7}", file=stream)
    total = sum(t for t, _ in rows.values()), sum(o for _, o in rows.values())
    print(f"{'total':<{width}}{total[0]:>6}{total[1]:>7}", file=stream)
    for line in failures:
        print(f"NOT CLEAN {line}", file=stream)
    return rows, failures


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="one category")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)
    selected = [c for c in cases() if args.only in (None, c.category)]
    _, failures = run_all(selected, verbose=args.verbose)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
