"""XYZ and PTS: strict column and count checks, comments kept, extra columns verbatim."""

from __future__ import annotations

import pytest

from pipeline.io.pointcloud import InputError, read_points, write_points
from pipeline.io.text import TextFormatError, read_pts, read_xyz, write_text


@pytest.mark.parametrize("data,match", [
    (b"1 2 3\n4 5 6 7\n", r"line 2: 4 columns, the first point line has 3"),
    (b"# c\n\n1 2\n", r"line 3: 2 columns, a point needs x y z"),
    (b"1 2 3\n4 x 6\n", r"line 2: coordinate y \(a 1-character non-numeric value\) is not a number"),
    (b"1,2,3\n", r"line 1: 1 columns"),
])
def test_xyz_errors_name_the_line(data, match):
    with pytest.raises(TextFormatError, match=match):
        read_xyz(data)


@pytest.mark.parametrize("data,match", [
    (b"3\n1 2 3 9\n4 5 6 9\n", r"line 1 declares more points than follow \(1 missing\)"),
    (b"1\n1 2 3 9\n4 5 6 9\n", r"line 3: expected a point count, found '4 5 6 9'"),
    (b"1 2 3\n", r"line 1: expected a point count"),
    (b"2\n1 2 3 9\n4 5 6\n", r"line 3: 3 columns, the first point line has 4"),
    (b"# only a comment\n", r"no point count line"),
])
def test_pts_counts_that_disagree_are_errors(data, match):
    with pytest.raises(TextFormatError, match=match):
        read_pts(data)


def test_comments_and_blank_lines_are_kept_and_hold_no_point():
    data = b"# header\n\n1 2 3 a\n  # indented comment\n4 5 6 b\n"
    table = read_xyz(data)
    assert table.points.tolist() == [[1, 2, 3], [4, 5, 6]]
    out = write_text(table, table.points + [[0.5, 0, 0], [0, 0, 0]])
    assert out == b"# header\n\n1.5 2 3 a\n  # indented comment\n4 5 6 b\n"


def test_pts_blocks_and_crlf():
    data = b"2\r\n1 2 3 -7 1 2 3\r\n4 5 6 -8 4 5 6\r\n1\r\n7 8 9 -9 7 8 9\r\n"
    table = read_pts(data)
    assert table.points[:, 0].tolist() == [1, 4, 7]
    out = write_text(table, table.points * [1, 1, 2])
    assert out == b"2\r\n1 2 6.0 -7 1 2 3\r\n4 5 12.0 -8 4 5 6\r\n1\r\n7 8 18.0 -9 7 8 9\r\n"


def test_full_precision_and_untouched_tokens(tmp_path):
    (tmp_path / "a.xyz").write_text("4000000.123456789012 0.1 -2.5e-3 255 0 0\n")
    cloud = read_points(tmp_path / "a.xyz")
    moved = cloud.points + [1e-9, 0.0, 0.0]
    write_points(cloud, moved, tmp_path / "b.xyz")
    text = (tmp_path / "b.xyz").read_text()
    assert text.split()[1:] == ["0.1", "-2.5e-3", "255", "0", "0"]
    assert read_points(tmp_path / "b.xyz").points[0, 0] == moved[0, 0]


def test_bad_file_error_names_the_file(tmp_path):
    (tmp_path / "scan.pts").write_text("5\n1 2 3\n")
    with pytest.raises(InputError, match=r"scan\.pts: line 1 declares more points than follow"):
        read_points(tmp_path / "scan.pts")
    (tmp_path / "empty.xyz").write_text("# nothing\n")
    with pytest.raises(InputError, match=r"empty\.xyz: the file holds no points"):
        read_points(tmp_path / "empty.xyz")
