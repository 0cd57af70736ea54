"""Fuzz targets of the readers: seeds from the real files, mutations, and the property checked.

Every target goes through the public API (:func:`pipeline.io.pointcloud.read_points`,
:func:`pipeline.config.load_config`), so it covers whatever reader is in place.
The property: any input ends as a valid cloud (finite (n, 3) coordinates,
n > 0, written back and read again unchanged) or as one clean line
(``InputError`` / ``ConfigError`` naming the file); never another exception,
a warning, a hang, a huge allocation or a file left behind.

Seeds are cut from the real scans of ``../shared/data`` (read there, never
copied into the repository) and from the shipped configs.
"""

from __future__ import annotations

import io
import re
import shutil
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

from pipeline.config import ConfigError, detect_params, load_config, watermark_params
from pipeline.io.ply import PlyData, read_ply, write_ply
from pipeline.io.pointcloud import InputError, read_points, write_points

ROOT = Path(__file__).resolve().parents[2]
SEED_POINTS = 48   # points per seed: small files keep each execution fast


class FuzzFailure(AssertionError):
    """The property does not hold for an input."""


# -- seeds --------------------------------------------------------------------------------------

def _models(data_dir):
    return sorted((data_dir / "models").glob("*.ply"))


def _ply_subset(ply, n, fmt, endian_fmt=None):
    """A valid PLY of the first ``n`` vertices of ``ply``, in ``fmt`` (faces among them kept)."""
    vertices = ply.vertices[:n]
    fmt = endian_fmt or fmt
    header, tail = [], b""
    faces = ply.faces() if len(ply.elements) > 1 else np.zeros((0, 3), dtype=np.int64)
    faces = faces[(faces < n).all(axis=1)][:2 * n]
    for line in ply.header:
        words = line.split()
        if words[:1] == ["format"]:
            line = f"format {fmt} 1.0"
        elif words[:2] == ["element", "vertex"]:
            line = f"element vertex {n}"
        elif words[:2] == ["element", "face"]:
            line = f"element face {len(faces)}"
        header.append(line)
    if len(ply.elements) > 1:
        if fmt == "ascii":
            tail = "".join(f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()).encode()
        else:
            e = "<" if fmt == "binary_little_endian" else ">"
            _, _, props = ply.elements[1]
            count_t, item_t = props[0][2]
            rec = np.zeros(len(faces), dtype=[("n", e + count_t), ("v", e + item_t, (3,))])
            rec["n"], rec["v"] = 3, faces
            tail = rec.tobytes()
    e = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}[fmt]
    vertices = vertices.astype(vertices.dtype.newbyteorder(e)) if fmt != "ascii" else vertices
    data = PlyData(vertices, header, fmt, tail, ply.elements)
    return write_ply(data, data.points)


@lru_cache(maxsize=None)
def _real_plys(data_dir):
    return [(p.name, read_ply(p.read_bytes())) for p in _models(data_dir)] + \
           [("bun_zipper.ply", read_ply((data_dir / "meshes" / "bun_zipper.ply").read_bytes()))]


def seeds_ply_binary(data_dir):
    out = []
    for i, (_, ply) in enumerate(_real_plys(data_dir)):
        fmt = "binary_big_endian" if i % 3 == 2 else "binary_little_endian"
        out.append(_ply_subset(ply, SEED_POINTS, fmt))
    return out


def seeds_ply_ascii(data_dir):
    return [_ply_subset(ply, SEED_POINTS, "ascii") for _, ply in _real_plys(data_dir)[::3]] + \
           [_ply_subset(_real_plys(data_dir)[-1][1], SEED_POINTS, "ascii")]


def _real_points(data_dir):
    return [ply.points[:SEED_POINTS] for _, ply in _real_plys(data_dir)[:6]]


def seeds_pcd(data_dir):
    out = []
    for i, pts in enumerate(_real_points(data_dir)):
        n = len(pts)
        size, t = (8, "f8") if i % 2 else (4, "f4")
        extra = i % 3 == 0
        fields = "x y z intensity" if extra else "x y z"
        k = 4 if extra else 3
        table = np.column_stack([pts, np.arange(n, dtype=float)]) if extra else pts
        head = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\n"
                f"SIZE {' '.join([str(size)] * k)}\nTYPE {' '.join(['F'] * k)}\nCOUNT {' '.join(['1'] * k)}\n"
                f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n")
        if i % 2 == 0:
            body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in table.astype(t).tolist())
            out.append((head + "DATA ascii\n").encode() + body.encode())
        else:
            out.append((head + "DATA binary\n").encode() + table.astype("<" + t).tobytes())
    return out


def seeds_pcd_compressed(data_dir):
    """binary_compressed (LZF) PCDs, float32 and float64, some with an extra field."""
    from pipeline.io.pcd import read_pcd, write_pcd

    out = []
    for data in seeds_pcd(data_dir):
        if b"DATA binary\n" in data:
            pcd = read_pcd(data)
            pcd.encoding = "binary_compressed"
            out.append(write_pcd(pcd, pcd.points).replace(b"DATA binary\n", b"DATA binary_compressed\n"))
    return out


def seeds_obj(data_dir):
    """OBJ meshes cut from the real PLY meshes: v lines, then 1-based and negative f lines."""
    out = []
    for i, (_, ply) in enumerate(_real_plys(data_dir)[:6]):
        faces = ply.faces() if len(ply.elements) > 1 else np.zeros((0, 3), dtype=np.int64)
        faces = faces[(faces < SEED_POINTS).all(axis=1)][:SEED_POINTS]
        v = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in ply.points[:SEED_POINTS].tolist())
        if i % 2:
            f = "".join(f"f {a - SEED_POINTS} {b - SEED_POINTS} {c - SEED_POINTS}\n" for a, b, c in faces.tolist())
        else:
            f = "".join(f"f {a + 1}//{a + 1} {b + 1} {c + 1}/1\n" for a, b, c in faces.tolist())
        out.append(("# cut from a real scan\n" + v + f).encode())
    return out


def seeds_xyz_pts(data_dir):
    out = []
    for i, pts in enumerate(_real_points(data_dir)):
        rows = [" ".join(repr(float(v)) for v in p) for p in pts.tolist()]
        if i % 2:
            rows = [f"{r} {j % 255} 10 20 30" for j, r in enumerate(rows)]
            out.append((".pts", (f"{len(rows)}\n" + "\n".join(rows) + "\n").encode()))
        else:
            out.append((".xyz", ("\n".join(rows) + "\n").encode()))
    out.append((".xyz", ("\r\n".join(rows) + "\r\n").encode()))        # CRLF is read; CR-only refused
    return out


def seeds_las(data_dir):
    import laspy

    out = []
    for name in ("lidar/vegetation_1_3.las", "lidar/autzen_trim.laz"):
        las = laspy.read(str(data_dir / name))
        for suffix, compress in ((".las", False), (".laz", True)):
            part = laspy.LasData(header=las.header, points=las.points[:SEED_POINTS].copy())
            buf = io.BytesIO()
            part.write(buf, do_compress=compress)
            out.append((suffix, buf.getvalue()))
    return out


def seeds_config(_data_dir=None):
    return [p.read_bytes() for p in sorted((ROOT / "configs").glob("*.yaml"))]


# -- mutations ------------------------------------------------------------------------------------

INTERESTING_NUMBERS = [b"0", b"1", b"-1", b"-1500", b"2", b"3", b"999999", b"1_0", b"+5", b"1.5", b"47", b"49", b"255", b"256", b"65535", b"2147483647",
                       b"4294967295", b"4294967296", b"18446744073709551617", b"99999999999999999999",
                       b"1e308", b"1e-320", b"nan", b"inf", b"-inf", b"-0", b"0.5", b"", b"x"]
INTERESTING_INTS = [0, 1, 2, 3, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 2**63 - 1, 2**64 - 1]
KEYWORDS = [b"float", b"double", b"uchar", b"int", b"uint", b"list", b"char", b"ascii", b"binary",
            b"binary_little_endian", b"binary_big_endian", b"vertex", b"face", b"x", b"y", b"z", b"property",
            b"element", b"end_header", b"F", b"I", b"U", b"8", b"4", b"DATA", b"POINTS", b"WIDTH", b"HEIGHT",
            b"FIELDS", b"binary_compressed", b"\n", b" ", b"\r\n", b"\t", b"#", b"\x00", b"\r", b"|", b"`",
            b"\xff\xfe", b"\x1f\x8b", b"f", b"v", b"nan"]
YAML_VALUES = [".nan", ".inf", "-.inf", "-1", "0", "1", "1e400", "[]", "{}", "~", "'x'", "*a", "&a [*a]",
               "!!binary AA==", "!!python/object:os.system", "0x10", "2024-01-01", "yes", "1_000",
               "[1, 2, 3]", "{a: 1}", "\"\\u0000\"", "-0.0", "1e-320", "99999999999999999999999", "true",
               "[[0, 0, 0]]", "[0, 1, -1]", "&x 1", "? [a]", "|\n  text", "'", "\"", "- a", "null"]


@st.composite
def mutated_bytes(draw, seeds, max_ops=6):
    """A seed with up to ``max_ops`` mutations; sometimes plain random bytes."""
    if draw(st.integers(0, 49)) == 0:
        return draw(st.binary(max_size=512))
    data = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, max_ops))):
        op = draw(st.sampled_from(["flip", "byte", "insert", "delete", "truncate", "copy", "number",
                                   "keyword", "word", "number", "keyword"]))
        n = len(data)
        pos = draw(st.integers(0, max(n - 1, 0)))
        if op == "flip" and n:
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte" and n:
            data[pos] = draw(st.integers(0, 255))
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete":
            del data[pos: pos + draw(st.integers(1, 64))]
        elif op == "truncate":
            del data[pos:]
        elif op == "copy" and n:
            size = draw(st.integers(1, 256))
            chunk = data[pos: pos + size]
            at = draw(st.integers(0, n))
            data[at:at] = chunk
        elif op == "word" and n:
            width = draw(st.sampled_from([1, 2, 4, 8]))
            value = draw(st.sampled_from(INTERESTING_INTS)) % (1 << (8 * width))
            data[pos: pos + width] = value.to_bytes(width, draw(st.sampled_from(["little", "big"])))
        elif op in ("number", "keyword"):
            head = bytes(data[:4096])
            pattern = rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?" if op == "number" else rb"[A-Za-z_]+"
            spans = [m.span() for m in re.finditer(pattern, head)]
            if spans:
                a, b = draw(st.sampled_from(spans))
                pool = INTERESTING_NUMBERS if op == "number" else KEYWORDS
                new = draw(st.sampled_from(pool + [head[a:b]]))
                if op == "number" and draw(st.booleans()) and head[a:b].isdigit():
                    new = str(int(head[a:b]) + draw(st.sampled_from([-1, 1]))).encode()
                data[a:b] = new
    return bytes(data)


@st.composite
def mutated_yaml(draw, seeds):
    """A shipped config with line-level YAML mutations, then perhaps a few byte mutations."""
    text = draw(st.sampled_from(seeds)).decode()
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 5))):
        op = draw(st.sampled_from(["value", "value", "value", "delete", "duplicate", "indent", "insert",
                                   "swap", "text", "dupkey"]))
        if not lines:
            lines = [""]
        i = draw(st.integers(0, len(lines) - 1))
        if op == "value" and ":" in lines[i]:
            key = lines[i].split(":", 1)[0]
            lines[i] = f"{key}: {draw(st.sampled_from(YAML_VALUES))}"
        elif op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "dupkey":            # a key given twice in its mapping, with another value
            keyed = [k for k, line in enumerate(lines) if re.match(r"\s*[A-Za-z_]+:", line)]
            if keyed:
                k = draw(st.sampled_from(keyed))
                key = lines[k].split(":", 1)[0]
                lines.insert(k + 1, f"{key}: {draw(st.sampled_from(YAML_VALUES))}")
        elif op == "indent":
            lines[i] = draw(st.sampled_from(["", " ", "  ", "\t", "    "])) + lines[i].lstrip()
        elif op == "insert":
            lines.insert(i, draw(st.sampled_from(["watermark:", "  beta: .nan", "unknown: 1", "- 1", "a: &a [*a]",
                                                  "detection:", "  p_threshold: 1", "recipients: [a, a]",
                                                  "---", "...", "%YAML 1.1", "key: {", "? [x]"])))
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "text":
            lines[i] += draw(st.text(max_size=12))
    data = ("\n".join(lines) + "\n").encode("utf-8", errors="surrogatepass")
    if draw(st.integers(0, 9)) == 0:
        data = draw(mutated_bytes([data], max_ops=2))
    return data


# -- the property ----------------------------------------------------------------------------------

def _clean_folder(folder):
    for p in folder.iterdir():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def _one_line(exc, path, markup=False):
    """One line naming ``path``; with ``markup``, no table or code markup from the file's content."""
    message = str(exc)
    if "\n" in message or "\r" in message or not message.startswith(f"{path}:"):
        raise FuzzFailure(f"unclean message for {path}: {message!r}")
    if markup and set(message[len(str(path)) + 1:]) & set("|`"):
        raise FuzzFailure(f"the message for {path} quotes markup: {message!r}")


def check_points_file(data, suffix, folder):
    """Read ``data`` as a ``suffix`` file: 'ok' for a valid cloud, 'error' for a clean error."""
    _clean_folder(folder)
    path = folder / f"fuzz{suffix}"
    path.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            cloud = read_points(path)
        except InputError as exc:
            _one_line(exc, path, markup=True)
            return "error"
        pts = cloud.points
        if not (isinstance(pts, np.ndarray) and pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 0
                and pts.dtype == np.float64 and np.isfinite(pts).all()):
            raise FuzzFailure(f"invalid cloud from {path}: {getattr(pts, 'shape', None)}")
        out = folder / f"back{suffix}"
        try:
            write_points(cloud, pts, out)
        except InputError as exc:
            _one_line(exc, out)
            left = sorted(p.name for p in folder.iterdir() if p.name != path.name)
            if left:
                raise FuzzFailure(f"a refused write left {left} behind") from None
            return "error"
        again = read_points(out).points
    left = sorted(p.name for p in folder.iterdir() if p.name not in (path.name, out.name))
    if left:
        raise FuzzFailure(f"files left behind: {left}")
    if again.shape != pts.shape or not np.array_equal(again, pts):
        worst = float(np.abs(again - pts).max()) if again.shape == pts.shape else None
        raise FuzzFailure(f"written back, the {suffix} file reads differently (shape {again.shape}, "
                          f"largest change {worst})")
    return "ok"


def check_config(data, folder):
    """Load ``data`` as a config: 'ok' when valid and usable, 'error' for a clean error."""
    _clean_folder(folder)
    path = folder / "fuzz.yaml"
    path.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            cfg = load_config(path)
        except ConfigError as exc:
            _one_line(exc, path)
            return "error"
        watermark_params(cfg)
        detect_params(cfg)
    return "ok"


@dataclass(frozen=True)
class Target:
    name: str
    seeds: object          # data_dir -> list of bytes, or of (suffix, bytes)
    suffix: str | None     # fixed suffix, or None when the seeds carry theirs
    config: bool = False

    def strategy(self, data_dir):
        seeds = self.seeds(data_dir)
        if self.config:
            return mutated_yaml(seeds)
        if self.suffix is not None:
            return st.tuples(st.just(self.suffix), mutated_bytes(seeds))
        by_suffix = {}
        for suffix, data in seeds:
            by_suffix.setdefault(suffix, []).append(data)
        return st.one_of([st.tuples(st.just(s), mutated_bytes(d)) for s, d in sorted(by_suffix.items())])

    def check(self, example, folder):
        if self.config:
            return check_config(example, folder)
        suffix, data = example
        return check_points_file(data, suffix, folder)


TARGETS = {t.name: t for t in [
    Target("ply_ascii", seeds_ply_ascii, ".ply"),
    Target("ply_binary", seeds_ply_binary, ".ply"),
    Target("pcd", seeds_pcd, ".pcd"),
    Target("pcd_compressed", seeds_pcd_compressed, ".pcd"),
    Target("obj", seeds_obj, ".obj"),
    Target("xyz_pts", seeds_xyz_pts, None),
    Target("las_laz", seeds_las, None),
    Target("config", seeds_config, None, config=True),
]}
