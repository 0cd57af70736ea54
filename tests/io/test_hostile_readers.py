"""Hostile and malformed point-set files (issue 36): refused before any work, in bounded memory, in one line.

Grouped by cause.  Large files are sparse (``truncate``), so they cost no
disk; the memory-bound tests read them in a child process and check its
peak resident size (``ru_maxrss``) against what the old readers needed.
"""

from __future__ import annotations

import errno
import io
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.io.pcd import lzf_compress
from pipeline.io.pointcloud import InputError, read_points, write_points
from tests.conftest import ROOT

PEAK_MB = 500           # the brief's bound for any refused input of at most 2 GB
GB = 1 << 30


def _ply(n, fmt="binary_little_endian", declared=None, faces=None, list_count=3, face_tail=b""):
    """A PLY of ``n`` double vertices; ``faces`` (f, k) int rows as lists of ``list_count`` items."""
    head = [f"ply", f"format {fmt} 1.0", f"element vertex {n if declared is None else declared}",
            "property double x", "property double y", "property double z"]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    data = ("\n".join(head + ["end_header"]) + "\n").encode()
    pts = np.random.default_rng(0).uniform(-1, 1, (n, 3))
    if fmt == "ascii":
        data += "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist()).encode()
        if faces is not None:
            data += "".join(" ".join(map(str, [len(f)] + list(f))) + "\n" for f in faces).encode()
    else:
        e = "<" if fmt == "binary_little_endian" else ">"
        data += pts.astype(e + "f8").tobytes()
        for f in faces if faces is not None else []:
            data += bytes([len(f)]) + np.asarray(f, dtype=e + "i4").tobytes()
    return data + face_tail


def _pcd(n, encoding="binary", width=None, height="1", points=None, size="4 4 4", count="1 1 1", body=None):
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE {size}\nTYPE F F F\nCOUNT {count}\n"
            f"WIDTH {n if width is None else width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {n if points is None else points}\nDATA {encoding}\n").encode()
    if body is None:
        pts = np.random.default_rng(1).uniform(-1, 1, (n, 3)).astype("<f4")
        body = pts.tobytes() if encoding == "binary" else \
            "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.astype(float).tolist()).encode()
    return head + body


def _las(n=300, compress=False):
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = np.array([0.001] * 3), np.zeros(3)
    las = laspy.LasData(header)
    pts = np.random.default_rng(2).uniform(0, 10, (n, 3))
    las.x, las.y, las.z = pts.T
    buf = io.BytesIO()
    las.write(buf, do_compress=compress)
    return bytearray(buf.getvalue())


def _patched(data, at, fmt, value):
    data = bytearray(data)
    struct.pack_into(fmt, data, at, value)
    return bytes(data)


def _sparse(path, head, size):
    """``head`` then zeros up to ``size`` bytes, without writing the zeros."""
    with open(path, "wb") as f:
        f.write(head)
        f.truncate(size)
    return path


def _write(tmp_path, name, data):
    path = tmp_path / name
    if isinstance(data, tuple):
        return _sparse(path, *data)
    path.write_bytes(data)
    return path


def _read_in_child(paths):
    """Read ``paths`` in a fresh interpreter: ({path: message or 'ok'}, peak resident MB)."""
    code = textwrap.dedent("""
        import json, sys
        from pipeline.io.pointcloud import InputError, read_points
        out = {}
        for p in sys.argv[1:]:
            try:
                read_points(p)
                out[p] = "ok"
            except InputError as exc:
                out[p] = str(exc)
        # VmHWM: this process's own peak since exec (ru_maxrss would also count the parent's
        # resident size at the fork, which is the test runner's)
        peak = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")) / 1024
        print(json.dumps({"messages": out, "peak_mb": peak}))
    """)
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-c", code, *map(str, paths)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    return report["messages"], report["peak_mb"]


def _assert_refused(cases, tmp_path, peak_mb=PEAK_MB):
    """Write each case, read all in one child; every one refused with its needle, peak < ``peak_mb``."""
    paths = {name: _write(tmp_path, name, data) for name, (data, _) in cases.items()}
    messages, peak = _read_in_child(paths.values())
    for name, (_, needle) in cases.items():
        message = messages[str(paths[name])]
        assert message.startswith(f"{paths[name]}: ") and needle in message and "\n" not in message, \
            (name, message)
    assert peak < peak_mb, f"peak {peak:.0f} MB"
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(paths), left            # nothing written next to the inputs


# -- cause: magic and header checked from the first bytes, before the body is read -----------------

_RANDOM = np.random.default_rng(7).integers(0, 256, 1 << 16, dtype=np.uint8).tobytes()

MAGIC_CASES = {
    "garbage.ply": ((_RANDOM, GB), "not a PLY file"),
    "garbage.pcd": ((_RANDOM, GB), "not a PCD file"),
    "garbage.xyz": ((_RANDOM, GB), "not a text point file"),
    "garbage.pts": ((_RANDOM, GB), "not a text point file"),
    "garbage.obj": ((_RANDOM, GB), "not a text point file"),
    "garbage.las": ((_RANDOM, GB), "not a LAS/LAZ file"),
    "zeros.xyz": ((b"", GB), "a NUL byte at offset 0"),
    "gzip.ply": (b"\x1f\x8b\x08\x00" + _RANDOM[:4000], "gzip-compressed"),
    "zip.xyz": (b"PK\x03\x04" + _RANDOM[:4000], "zip-compressed"),
    "empty.ply": (b"", "the file is empty"),
    "empty.xyz": (b"", "the file is empty"),
    "utf16.xyz": ("1 2 3\n4 5 6\n".encode("utf-16"), "UTF-16"),
    "utf16_nobom.xyz": ("1 2 3\n4 5 6\n".encode("utf-16-le"), "NUL byte"),
    "bom.xyz": (b"\xef\xbb\xbf1 2 3\n4 5 6\n", "byte-order mark"),
    "one_line.xyz": (b"1 " * (3 << 20), "line 1 is longer than"),
    "long_second_line.pts": (b"2\n" + b"1" * (3 << 20) + b"\n", "line 2 is longer than"),
    "no_end_header.ply": (b"ply\nformat ascii 1.0\ncomment " + b"x" * (3 << 20), "no 'end_header' line"),
    "huge_header.ply": ((b"ply\nformat ascii 1.0\n" + b"comment x\n" * 120_000, 2 * GB), "no 'end_header' line"),
    "no_data_line.pcd": ((b"VERSION 0.7\n" + b"# comment\n" * 120_000, GB), "no DATA line"),
    "ply_magic_cut.ply": (b"plyformat ascii 1.0\nend_header\n", "not a PLY file"),
    "control.xyz": (b"1 2 3\n4 5 \x1b[31m6\n", "control byte 0x1b"),
}


@pytest.mark.parametrize("batch", ["all"])
def test_the_magic_and_header_are_checked_before_the_body_is_read(tmp_path, batch):
    _assert_refused(MAGIC_CASES, tmp_path)


# -- cause: declared counts and sizes checked against the file's length before allocating ---------

def _laz_count(factor, drop_table=False):
    data = _las(3000, compress=True)
    count = struct.unpack_from("<I", data, 107)[0]
    struct.pack_into("<I", data, 107, count * factor)
    if drop_table:
        struct.pack_into("<q", data, struct.unpack_from("<I", data, 96)[0], -1)
    return bytes(data)


def _lzf_bomb(n=1000, expand=8 << 20):
    """A binary_compressed PCD declaring n points whose LZF data expands 88-fold to ``expand`` bytes."""
    backref = bytes([0xE0, 255 - 7 + 0, 0])          # 264 bytes copied from distance 1
    lzf = b"\x00\x00" + backref * (expand // 264)
    return _pcd(n, "binary_compressed", body=struct.pack("<II", len(lzf), n * 12) + lzf)


COUNT_CASES = {
    "laz_999x.laz": (_laz_count(999), "more than"),
    "laz_40x.laz": (_laz_count(40), "chunk"),
    "laz_no_table.laz": (_laz_count(40, drop_table=True), "points"),
    "las_record_0.las": (_patched(_las(), 105, "<H", 0), "records of 0 bytes"),
    "las_huge_count.las": (_patched(_las(), 107, "<I", 2**32 - 1), "truncated: the header declares 4294967295"),
    "ply_2e31.ply": (_ply(10, declared=2**31), "the header declares 2147483648 vertices"),
    "ply_ascii_2e31.ply": (_ply(10, "ascii", declared=2**31), "the header declares 2147483648 vertices"),
    "ply_sparse_2e31.ply": ((_ply(10, declared=2**31)[:200], GB), "need at least"),
    "ply_list_255.ply": (_ply(20).replace(b"end_header", b"element face 10\nproperty list uchar int vertex_indices"
                                          b"\nend_header") + b"\xff" + b"\0" * 20, "truncated: face 0 of 10"),
    "ply_list_255_many.ply": (_ply(20).replace(b"end_header", b"element face 1000\nproperty list uchar int "
                                               b"vertex_indices\nend_header") + b"\xff" * 300, "truncated"),
    "pcd_width_neg.pcd": (_pcd(1500, width="-1500", points="-1500"), "WIDTH '-1500' is not a positive integer"),
    "pcd_width_0.pcd": (_pcd(0, width="0"), "WIDTH '0' is not a positive integer"),
    "pcd_width_float.pcd": (_pcd(10, width="10.0"), "not a positive integer"),
    "pcd_height_neg.pcd": (_pcd(10, width="-10", height="-1"), "not a positive integer"),
    "pcd_points_plus.pcd": (_pcd(10, points="+10"), "POINTS '+10' is not a positive integer"),
    "pcd_points_underscore.pcd": (_pcd(10, width="1_0", points="1_0"), "not a positive integer"),
    "pcd_size_0.pcd": (_pcd(10, size="0 4 4"), "unsupported TYPE"),
    "pcd_count_neg.pcd": (_pcd(10, count="-1 1 1"), "unsupported TYPE"),
    "pcd_huge_binary.pcd": (_pcd(10, width=str(10**9), points=str(10**9)), "the body has 120"),
    "pcd_sparse_binary.pcd": ((_pcd(10, width=str(10**8), points=str(10**8)), GB), "the body has"),
    "pcd_packed_beyond.pcd": (_pcd(10, "binary_compressed", body=struct.pack("<II", 10**9, 120) + b"\0" * 50),
                              "the compressed block declares 1000000000 bytes"),
    "pcd_unpacked_lie.pcd": (_pcd(10, "binary_compressed", body=struct.pack("<II", 4, 10**9) + b"\0" * 4),
                             "unpacks to 1000000000 bytes"),
    "pcd_lzf_bomb.pcd": (_lzf_bomb(), "decodes to more than the 12000 bytes"),
    "pcd_lzf_truncated.pcd": (_pcd(10, "binary_compressed", body=struct.pack("<II", 5, 120) + b"\x1f1234"),
                              "corrupt LZF data"),
    "pcd_ascii_huge.pcd": (_pcd(10, "ascii", width=str(10**9), points=str(10**9)), "truncated: POINTS"),
}


def test_declared_counts_beyond_the_file_are_refused_before_allocating(tmp_path):
    _assert_refused(COUNT_CASES, tmp_path)


def _compressed_pcd_of(n, file_bytes):
    """A binary_compressed PCD of ``n`` points whose compressed block fills a sparse file of ``file_bytes``."""
    head = _pcd(n, "binary_compressed", body=b"")
    return head + struct.pack("<II", file_bytes - len(head) - 8, 12 * n), file_bytes


def test_a_compressed_pcd_too_large_to_decode_whole_is_refused_before_reading(tmp_path):
    # LZF is decoded whole: a body unpacking past the bound would cost several times its size
    _assert_refused({"pcd_compressed_2gb.pcd": (_compressed_pcd_of(170_000_000, 2 * GB),
                                                "binary_compressed bodies are read up to 64 MiB unpacked"),
                     "pcd_compressed_100mb.pcd": (_compressed_pcd_of(9_000_000, 100 * 2**20),
                                                  "re-save it as binary")}, tmp_path)


# -- cause: an ASCII PLY body is parsed in C and checked as it goes, never as per-token lists -------

def _big_ascii_ply(n_vertices=800_000, n_faces=800_000, declared_faces=None, bad_last=False):
    head = (f"ply\nformat ascii 1.0\nelement vertex {n_vertices}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {n_faces if declared_faces is None else declared_faces}\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    vertices = b"0.1234567 1.2345678 2.3456789\n" * n_vertices
    faces = b"3 0 1 2\n" * n_faces
    return head + vertices + faces[:-8] + (b"3 0 x 2\n" if bad_last else faces[-8:])


ASCII_CASES = {
    "one_face_missing.ply": (_big_ascii_ply(declared_faces=800_001), "800001 face records, the body holds 800000"),
    "one_face_more.ply": (_big_ascii_ply(declared_faces=799_999), "799999 face records, the body holds 800000"),
    "bad_last_token.ply": (_big_ascii_ply(bad_last=True), "line 1600009, face 799999: a vertex index is not an integer"),
}


def test_a_30_mb_ascii_ply_is_refused_in_bounded_memory(tmp_path):
    _assert_refused(ASCII_CASES, tmp_path)      # the per-token reader peaked at 754 MB on one such file
    assert (tmp_path / "one_face_more.ply").stat().st_size > 30e6


# -- cause: the input is not a regular, readable file --------------------------------------------

def _special(tmp_path, kind):
    path = tmp_path / f"in_{kind}.ply"
    if kind == "folder":
        path.mkdir()
    elif kind == "loop":
        path.symlink_to(path.name)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        path.symlink_to("/dev/zero")
    elif kind == "broken":
        path.symlink_to("gone.ply")
    elif kind == "missing":
        pass
    return path


@pytest.mark.parametrize("kind,needle", [
    ("folder", "is a folder, not a point-set file"), ("loop", "symlink loop"),
    ("fifo", "not a regular file"), ("device", "not a regular file"), ("broken", "a broken link"),
    ("missing", "no such file"),
])
def test_an_input_that_is_not_a_regular_file_is_refused_without_reading(tmp_path, kind, needle, capsys):
    path = _special(tmp_path, kind)
    signal.alarm(10)                              # a FIFO read would block forever
    try:
        code = main(["attack", str(path), str(tmp_path / "out.ply"), "--attack", "noise:0.1%"])
    finally:
        signal.alarm(0)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0] == f"pointmark: error: {path}: {needle}" or \
        (needle in err[0] and f"{path}: " in err[0]), err
    assert not (tmp_path / "out.ply").exists()


def test_an_unreadable_file_is_refused_as_permission_denied(tmp_path):
    from tests.readonly import unprivileged

    path = tmp_path / "secret.xyz"
    path.write_bytes(b"1 2 3\n4 5 6\n7 8 10\n")
    path.chmod(0)
    code = ("from pipeline.io.pointcloud import InputError, read_points\n"
            f"try:\n    read_points({str(path)!r})\nexcept InputError as exc:\n    print(exc)\n")
    run = subprocess.run([*unprivileged(), sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert run.stdout.strip() == f"{path}: permission denied", run.stdout + run.stderr


# -- cause: old-Mac CR-only line endings are refused (CRLF is read) -------------------------------

@pytest.mark.parametrize("name,data", [
    ("cr.xyz", b"1 2 3\r4 5 6\r7 8 10\r"),
    ("cr.pts", b"3\r1 2 3\r4 5 6\r7 8 10\r"),
    ("cr.obj", b"v 1 2 3\rv 4 5 6\rv 7 8 10\rf 1 2 3\r"),
    ("mixed.xyz", b"1 2 3\r\n4 5 6\r7 8 10\r\n"),
    ("cr.pcd", _pcd(3, "ascii").replace(b"DATA ascii\n", b"DATA ascii\n").split(b"DATA ascii\n")[0]
     + b"DATA ascii\n1 2 3\r4 5 6\r7 8 10\r"),
])
def test_cr_line_endings_are_refused_by_name(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(InputError, match="CR line endings .* are not supported"):
        read_points(path)


@pytest.mark.parametrize("name,data", [("crlf.xyz", b"1 2 3\r\n4 5 6\r\n7 8 10\r\n"),
                                       ("crlf.pts", b"3\r\n1 2 3\r\n4 5 6\r\n7 8 10\r\n")])
def test_crlf_text_is_still_read(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    assert read_points(path).points.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 10]]


# -- cause: a failed write names the file and leaves no temporary ------------------------------------

def test_a_failed_write_names_the_file_and_leaves_nothing(tmp_path):
    """RLIMIT_FSIZE makes every write past 4 KiB fail in the OS, as a full disk does (EFBIG for ENOSPC)."""
    code = textwrap.dedent(f"""
        import json, resource, signal, sys
        import numpy as np
        from pathlib import Path
        from pipeline.io.pointcloud import InputError, atomic_write_bytes, read_points, write_array, write_points
        folder = Path({str(tmp_path)!r})
        pts = np.random.default_rng(0).uniform(-1, 1, (3000, 3))
        src = write_array(folder / "src", "src", pts[:10], "ply")
        cloud = read_points(src)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
        out = []
        jobs = [lambda: atomic_write_bytes(folder / "out" / "a.ply", b"x" * 10000),
                lambda: write_array(folder / "out", "b", pts, "xyz"),
                lambda: write_array(folder / "out", "c", pts, "ply-ascii"),
                lambda: write_array(folder / "out", "d", pts, "las"),
                lambda: write_points(cloud, np.repeat(cloud.points, 1, axis=0), folder / "out" / "e.ply")]
        for job in jobs:
            try:
                job()
                out.append("ok")
            except InputError as exc:
                out.append(str(exc))
        print(json.dumps(out))
    """)
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    messages = json.loads(run.stdout)
    names = ["a.ply", "b.xyz", "c.ply", "d.las"]
    assert len(messages) == 5 and messages[4] == "ok"
    for name, message in zip(names, messages):
        assert message == f"{tmp_path / 'out' / name}: cannot write: {os.strerror(errno.EFBIG).lower()}", message
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["e.ply"]   # 10 points fit in 4 KiB


# -- cause: faces that index a vertex the mesh does not have -------------------------------------------

FACE_CASES = [
    ("tri_ascii.ply", _ply(500, "ascii", faces=[[0, 1, 2], [0, 1, 999999]]), "face 1: vertex index 999999"),
    ("tri_le.ply", _ply(500, faces=[[0, 1, 2], [0, 1, 999999]]), "face 1: vertex index 999999"),
    ("tri_be.ply", _ply(500, "binary_big_endian", faces=[[0, 1, 2], [-1, 1, 2]]), "face 1: vertex index -1"),
    ("poly_ascii.ply", _ply(500, "ascii", faces=[[0, 1, 2, 3], [0, 1, 500]]), "face 1: vertex index 500"),
    ("poly_le.ply", _ply(500, faces=[[0, 1, 2, 3], [0, -5, 2]]), "face 1: vertex index -5"),
    ("big.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n", "face vertex index 999999 is out of range"),
    ("neg.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -999\n", "face vertex index -999 is out of range"),
]


@pytest.mark.parametrize("name,data,needle", FACE_CASES, ids=[c[0] for c in FACE_CASES])
def test_faces_beyond_the_vertices_are_refused_before_an_attack(tmp_path, capsys, name, data, needle):
    path = tmp_path / name
    path.write_bytes(data)
    out = tmp_path / f"out{path.suffix}"
    code = main(["attack", str(path), str(out), "--attack", "simplify:200"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"{path}: " in err[0] and needle in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


# -- cause: error text quotes file content only as a short, escaped excerpt ---------------------------

SECRET = "5f1c9a0e7b2d48c3a6e1f09b8d7c6a5e"
QUOTE_CASES = {
    "pipes.pts": b"| a | b |\n`x`\n1 2 3\n",
    "pipes.xyz": b"1 2 3\n4 |`rm -rf`| 6\n",
    "key.xyz": SECRET.encode() + b"\n",
    "key.pts": SECRET.encode() + b"\n",
    "key.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 " + SECRET.encode() + b"\n",
    "key.ply": b"ply\nformat ascii 1.0\n" + SECRET.encode() + b"|" * 300 + b"\nend_header\n",
    "key2.ply": b"ply\nformat " + SECRET.encode() + b" 1.0\nend_header\n",
    "name.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x|`y`\nend_header\n",
    "key.pcd": b"VERSION 0.7\n" + SECRET.encode() + b" |\n",
    "key2.pcd": SECRET.encode() + b"\n",
    "type.pcd": _pcd(2, "ascii").replace(b"TYPE F F F", b"TYPE F F |" + SECRET.encode() + b"|"),
    "fields.pcd": _pcd(2, "ascii").replace(b"FIELDS x y z", b"FIELDS x y |`" + SECRET.encode() + b"`"),
    "ascii_ply_token.ply": _ply(3, "ascii").replace(b"\n0.", b"\n" + SECRET.encode() + b" 0.", 1),
}


def test_messages_never_quote_more_than_a_short_escaped_excerpt(tmp_path):
    paths = {name: _write(tmp_path, name, data) for name, data in QUOTE_CASES.items()}
    for name, path in paths.items():
        with pytest.raises(InputError) as info:
            read_points(path)
        text = str(info.value)[len(str(path)) + 2:]
        assert SECRET not in text and SECRET[:16] not in text, (name, text)
        assert not set("|`\n\r") & set(text), (name, text)
        quoted = [q for q in text.split("'")[1::2]]
        assert all(len(q.encode().decode("unicode_escape")) <= 43 for q in quoted), (name, text)


def test_numeric_looking_values_are_still_quoted():
    from pipeline.io.text import describe_value, excerpt

    assert describe_value(b"1.5e3") == "'1.5e3'" and describe_value(b"nan") == "'nan'"
    assert describe_value(b"six") == "a 3-character non-numeric value"
    assert excerpt("a|b`c\n" * 20) == "'" + "a\\x7cb\\x60c\\x0a" * 6 + "a\\x7cb\\x60...'"


# -- cause: values that are not finite numbers ----------------------------------------------------------

@pytest.mark.parametrize("name,data,needle", [
    ("nan.xyz", b"1 2 3\nnan 5 6\n7 8 9\n", "NaN or infinite"),
    ("inf.pts", b"2\n1 2 3\n4 inf 6\n", "NaN or infinite"),
    ("nan.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                b"end_header\n1 2 3\nnan 1 2\n", "NaN or infinite"),
    ("big.xyz", b"1 2 3\n1e999 5 6\n", "NaN or infinite"),
    ("nan.obj", b"v 0 0 nan\nv 1 0 0\n", "NaN or infinite"),
])
def test_non_finite_values_are_refused(tmp_path, name, data, needle):
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(InputError, match=needle):
        read_points(path)


def test_a_valid_file_still_round_trips_after_the_checks(tmp_path):
    for name, data in [("ok.ply", _ply(50, "ascii", faces=[[0, 1, 2], [3, 4, 5, 6]])), ("ok.pcd", _pcd(50)),
                       ("ok.laz", bytes(_las(400, compress=True))), ("ok.las", bytes(_las(400)))]:
        path = tmp_path / name
        path.write_bytes(data)
        cloud = read_points(path)
        write_points(cloud, cloud.points, tmp_path / f"back_{name}")
        assert np.array_equal(read_points(tmp_path / f"back_{name}").points, cloud.points)
    pcd = read_points(tmp_path / "ok.pcd")
    from pipeline.io.pcd import write_pcd
    pcd.native.encoding = "binary_compressed"
    data = write_pcd(pcd.native, pcd.points).replace(b"DATA binary\n", b"DATA binary_compressed\n")
    (tmp_path / "ok_c.pcd").write_bytes(data)
    assert np.array_equal(read_points(tmp_path / "ok_c.pcd").points, pcd.points)
    assert lzf_compress(b"") == b""


# -- cause: a large text file whose defect sits on its very last line costs bounded memory ----------------

BIG_TEXT_MB = 100            # memory, not time, is what scales: the old readers peaked at several times this
_REAL = b"-12345.678901234567 -12345.678901234567 -12345.678901234567"


def _big_text(path, size_mb=BIG_TEXT_MB):
    """A text point file of about ``size_mb`` MB whose last line holds a bad token: (path, its line number)."""
    fmt = path.suffix[1:]
    prefix = {"obj": b"v "}.get(fmt, b"")
    line = prefix + _REAL + b"\n"
    block = line * ((4 << 20) // len(line))
    repeats = (size_mb << 20) // len(block)
    n = repeats * (len(block) // len(line)) + 1                # points, the bad last one included
    head = {"pts": f"{n}\n".encode(), "pcd": _pcd(n, "ascii", body=b""),
            "ply": _ply(0, "ascii", declared=n)}.get(fmt, b"")
    with open(path, "wb") as f:
        f.write(head)
        for _ in range(repeats):
            f.write(block)
        f.write(prefix + b"1 2 x\n")
    return path, head.count(b"\n") + n


def _peak_over_baseline(path, tmp_path):
    """(message, peak MB of a child reading ``path`` minus that of one reading a 3-point file)."""
    small = tmp_path / f"small{path.suffix}"
    small.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" if path.suffix == ".obj" else
                      _ply(3, "ascii") if path.suffix == ".ply" else _pcd(3, "ascii") if path.suffix == ".pcd"
                      else (b"3\n" if path.suffix == ".pts" else b"") + b"0 0 0\n1 0 0\n0 1 0\n")
    messages, base = _read_in_child([small])
    assert messages[str(small)] == "ok", messages
    messages, peak = _read_in_child([path])
    return messages[str(path)], peak - base


@pytest.mark.parametrize("name", ["big.xyz", "big.pts", "big.obj", "big.pcd", "big.ply"])
def test_a_large_text_file_bad_on_its_last_line_is_refused_in_bounded_memory(tmp_path, name):
    path, last = _big_text(tmp_path / name)
    try:
        message, over = _peak_over_baseline(path, tmp_path)
    finally:
        path.unlink()
    assert message.startswith(f"{path}: line {last}") and "not a number" in message and "\n" not in message, message
    assert over < 100, f"peak {over:.0f} MB over the interpreter's for a {BIG_TEXT_MB} MB file"


# -- cause: binary PLY lists of several lengths whose data ends long before the declared count ----------

def test_a_binary_mesh_of_mixed_lists_cut_short_is_refused_quickly(tmp_path):
    rec = np.zeros(1_000_000, dtype=[("n3", "u1"), ("t", "<i4", (3,)), ("n4", "u1"), ("q", "<i4", (4,))])
    rec["n3"], rec["n4"], rec["q"] = 3, 4, [0, 1, 2, 3]            # triangles and quads, alternating
    data = _ply(10).replace(b"end_header", b"element face 6000000\nproperty list uchar int vertex_indices"
                                           b"\nend_header") + rec.tobytes()
    path = _write(tmp_path, "mixed.ply", data)
    # the child's CPU time, not the wall clock: a loaded machine (tests side by side) does not change it
    code = ("import json, sys, time; from pipeline.io.pointcloud import InputError, read_points\n"
            "t = time.process_time()\n"
            "try:\n    read_points(sys.argv[1]); m = 'ok'\nexcept InputError as e:\n    m = str(e)\n"
            "print(json.dumps([m, time.process_time() - t]))")
    run = subprocess.run([sys.executable, "-c", code, str(path)], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    message, seconds = json.loads(run.stdout)
    assert message == f"{path}: truncated: face 2000000 of 6000000 is cut off", message
    assert seconds < 8, f"{seconds:.1f} CPU s for 2 million records (the per-record reader took about 8)"


# -- cause: a large binary PLY or PCD whose defect sits in its very last record costs bounded memory ------

BIG_BINARY_MB = 120           # the whole-file readers peaked at about 3 times this


def _big_binary(path, defect):
    """A binary PLY (float vertices, triangles) or PCD of about :data:`BIG_BINARY_MB` MB, bad in its last record.

    Written as one block of records repeated, the last copy patched: (path, record count).
    """
    block, rng = 1 << 16, np.random.default_rng(3)
    vertex = np.zeros(block, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = rng.uniform(-1, 1, (3, block))
    face = np.zeros(block, dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    per = vertex.itemsize + (face.itemsize if path.suffix == ".ply" else 0)
    repeats = (BIG_BINARY_MB << 20) // (per * block)
    n = repeats * block
    face["v"] = rng.integers(0, n, (block, 3))
    last_vertex, last_face = vertex.copy(), face.copy()
    if defect == "nan":
        last_vertex["z"][-1] = np.nan
    else:
        last_face["v"][-1, 2] = n
    if path.suffix == ".ply":
        head = _ply(0, declared=n).replace(b"double", b"float").replace(
            b"end_header",
            b"property uchar red\nelement face %d\nproperty list uchar int vertex_indices\nend_header" % n)
        parts = [(vertex, last_vertex), (face, last_face)]
    else:
        head = _pcd(n, size="4 4 4 1", body=b"").replace(b"x y z", b"x y z red").replace(b"F F F", b"F F F U") \
            .replace(b"COUNT 1 1 1", b"COUNT 1 1 1 1")
        parts = [(vertex, last_vertex)]
    with open(path, "wb") as f:
        f.write(head)
        for records, last in parts:
            data = records.tobytes()
            for _ in range(repeats - 1):
                f.write(data)
            f.write(last.tobytes())
    return path, n


@pytest.mark.parametrize("name,defect,needle", [
    ("nan_vertex.ply", "nan", "1 points have NaN or infinite coordinates (first at index {last})"),
    ("bad_face.ply", "face", "face {last}: vertex index {n} is outside the {n} vertices"),
    ("nan_point.pcd", "nan", "1 points have NaN or infinite coordinates (first at index {last})"),
])
def test_a_large_binary_file_bad_in_its_last_record_is_refused_in_bounded_memory(tmp_path, name, defect, needle):
    path, n = _big_binary(tmp_path / name, defect)
    try:
        message, over = _peak_over_baseline(path, tmp_path)
    finally:
        path.unlink()
    assert message == f"{path}: {needle.format(last=n - 1, n=n)}", message
    assert over < 100, f"peak {over:.0f} MB over the interpreter's for a {BIG_BINARY_MB} MB file"


def _mixed_mesh(n_faces=3000, bad_face=None):
    """A binary PLY of triangles, quads and 200-gons (lists that outrun a small window); one bad index maybe."""
    rng = np.random.default_rng(4)
    faces = [list(rng.integers(0, 50, (3, 4, 200)[k % 3])) for k in range(n_faces)]
    if bad_face is not None:
        faces[bad_face][-1] = 50
    return _ply(50, faces=faces)


@pytest.mark.parametrize("window", [64, 1000, 4096])
def test_binary_bodies_read_the_same_whatever_the_window(tmp_path, monkeypatch, window):
    from pipeline.io import pcd as pcd_io, ply as ply_io

    mesh, cloud = _write(tmp_path, "mesh.ply", _mixed_mesh()), _write(tmp_path, "cloud.pcd", _pcd(500))
    bad = _write(tmp_path, "bad.ply", _mixed_mesh(bad_face=2999))
    whole = [read_points(mesh).native, read_points(cloud).native]
    with pytest.raises(InputError) as refused:
        read_points(bad)
    monkeypatch.setattr(ply_io, "CHUNK", window)
    monkeypatch.setattr(pcd_io, "CHUNK", window)
    ply, pcd = read_points(mesh).native, read_points(cloud).native
    assert np.array_equal(ply.vertices, whole[0].vertices) and ply.tail == whole[0].tail
    assert np.array_equal(pcd.records, whole[1].records)
    with pytest.raises(InputError) as windowed:
        read_points(bad)
    assert str(windowed.value) == str(refused.value) == f"{bad}: face 2999: vertex index 50 is outside the 50 vertices"
