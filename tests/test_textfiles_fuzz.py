"""Fuzzing the dataset text parsers: any input gives a parsed result or a SlamkitError, nothing else.

Inputs are near-misses of the real formats (numbers, words, separators, comments, blank lines, CR/LF), free
text and raw bytes. A FormatError must point at a line that exists; a parsed result must satisfy the
format's guarantees (shapes, finite values, strictly increasing timestamps).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slamkit.errors import FormatError, SlamkitError
from slamkit.sources.euroc import read_euroc_groundtruth, read_euroc_images, read_euroc_sensor
from slamkit.sources.kitti import read_kitti_calib, read_kitti_poses, read_kitti_times
from slamkit.sources.sevenscenes import read_pose_matrix, read_sevenscenes_intrinsics
from slamkit.sources.textfiles import parse_float_rows
from slamkit.sources.tum import read_rgb_list, read_tum_trajectory

FUZZ = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-1e4, 1e4, allow_nan=False).map(lambda x: f"{x:.6f}"),
    st.integers(-10, 2**64).map(str),
    st.sampled_from(["0", "1", "-1", "1e-3", "nan", "-inf", "1_0", "0x1", "", "1.2.3", "+5", "١٢"]),
)
words = st.sampled_from(["rgb/1.png", "P0:", "P1:", "Tr:", "#", "# comment", "x", ":", ",", "data: [1, 2]",
                         "intrinsics:", "[", "]", "T_BS:", "resolution: [64, 48]", "\t", "\x00", "é"])
token = st.one_of(numbers, numbers, numbers, words)
separators = st.sampled_from([" ", " ", ",", ", ", "\t", ":"])


@st.composite
def near_miss_lines(draw) -> str:
    lines = []
    for _ in range(draw(st.integers(0, 8))):
        fields = draw(st.lists(token, max_size=18))
        sep = draw(separators)
        prefix = draw(st.sampled_from(["", "", "", "#", "P0: ", "P2: ", "  "]))
        lines.append(prefix + sep.join(fields))
    eol = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    return eol.join(lines) + draw(st.sampled_from(["", eol]))


texts = st.one_of(near_miss_lines(), near_miss_lines(), st.text(max_size=300))
contents = st.one_of(texts.map(lambda s: s.encode("utf-8")), st.binary(max_size=200))


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def run(parser, folder, name: str, content: bytes):
    """Parse ``content`` as file ``name``: the result, or None after a well-formed SlamkitError."""
    path = folder / name
    path.write_bytes(content)
    try:
        return parser(path)
    except FormatError as e:
        assert e.path == path
        assert e.line is None or 1 <= e.line <= len(content.splitlines()), (e.line, content)
        assert str(path) in str(e)
    except SlamkitError as e:
        assert str(path) in str(e), str(e)
    return None


def increasing(t) -> bool:
    t = np.asarray(t)
    return bool(len(t) < 2 or (np.diff(t) > 0).all())


@FUZZ
@given(content=contents)
def test_rgb_txt(scratch, content):
    out = run(read_rgb_list, scratch, "rgb.txt", content)
    if out is not None:
        t, names, lines = out
        assert len(t) == len(names) == len(lines) and np.isfinite(t).all() and increasing(t)


@FUZZ
@given(content=contents)
def test_groundtruth_txt(scratch, content):
    out = run(read_tum_trajectory, scratch, "groundtruth.txt", content)
    if out is not None:
        t, poses = out
        assert poses.shape == (len(t), 4, 4) and np.isfinite(poses).all() and increasing(t)
        R = poses[:, :3, :3]
        assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)


@FUZZ
@given(content=contents)
def test_calib_txt(scratch, content):
    out = run(read_kitti_calib, scratch, "calib.txt", content)
    if out is not None:
        for key, value in out.items():
            assert np.isfinite(value).all()
            if key.startswith("P") and key[1:].isdigit():
                assert value.shape == (3, 4)


@FUZZ
@given(content=contents)
def test_times_txt(scratch, content):
    out = run(read_kitti_times, scratch, "times.txt", content)
    if out is not None:
        assert out.ndim == 1 and np.isfinite(out).all() and increasing(out)


@FUZZ
@given(content=contents)
def test_kitti_poses(scratch, content):
    out = run(read_kitti_poses, scratch, "07.txt", content)
    if out is not None:
        assert out.ndim == 3 and out.shape[1:] == (4, 4) and np.isfinite(out).all()


@FUZZ
@given(content=contents)
def test_sevenscenes_pose_and_intrinsics(scratch, content):
    out = run(read_pose_matrix, scratch, "frame-000000.pose.txt", content)
    if out is not None:
        assert out.shape == (4, 4) and (np.isfinite(out).all() or np.isnan(out).all())
    out = run(read_sevenscenes_intrinsics, scratch, "camera-intrinsics.txt", content)
    if out is not None:
        assert len(out) == 4 and np.isfinite(out).all()


@FUZZ
@given(content=contents)
def test_euroc_csv_and_yaml(scratch, content):
    out = run(read_euroc_images, scratch, "data.csv", content)
    if out is not None:
        t, names = out
        assert t.dtype == np.int64 and len(t) == len(names) and increasing(t)
    out = run(read_euroc_groundtruth, scratch, "gt.csv", content)
    if out is not None:
        t, poses = out
        assert poses.shape == (len(t), 4, 4) and np.isfinite(poses).all() and increasing(t)
    out = run(read_euroc_sensor, scratch, "sensor.yaml", content)
    if out is not None:
        assert np.isfinite(out.T_BS).all() and len(out.intrinsics) == 4


@FUZZ
@given(rows=st.lists(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=3,
                              max_size=3), max_size=20),
       comment_every=st.integers(1, 5))
def test_float_rows_round_trip(scratch, rows, comment_every):
    """Any finite table written with repr() and comments/blank lines in between reads back exactly."""
    text = []
    for i, row in enumerate(rows):
        if i % comment_every == 0:
            text.append("# comment" if i % 2 else "")
        text.append("  ".join(repr(v) for v in row))
    path = scratch / "table.txt"
    path.write_text("\n".join(text))
    values, lines = parse_float_rows(path, 3, return_lines=True)
    assert values.shape == (len(rows), 3)
    assert np.array_equal(values, np.asarray(rows, dtype=np.float64).reshape(-1, 3))
    assert [text[n - 1] for n in lines] == [t for t in text if t and not t.startswith("#")]
