"""INRIA 3DGS PLY: bit-exact round trips, SH layout, every malformed-input error, degenerate
Gaussians (counted by reason)."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import atomic_write
from phirie_jax.io.gaussian_checks import (
    MAX_ABS_LOG_SCALE,
    REASONS,
    degenerate_counts,
    degenerate_mask,
    degenerate_reasons,
    describe_counts,
)
from phirie_jax.io.ply import is_gaussian_ply, read_gaussian_ply, write_gaussian_ply
from phirie_jax.types import GaussianSplatData
from tests.conftest import shared_data

DONUT_COUNT = 45_624


def make_data(n=50, degree=3, seed=0, extra=None) -> GaussianSplatData:
    rng = np.random.default_rng(seed)
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    return GaussianSplatData(
        means=f32(n, 3), quats=f32(n, 4), log_scales=f32(n, 3), opacity_logits=f32(n),
        sh=f32(n, (degree + 1) ** 2, 3), extra=extra or {},
    )


def header_text(fmt: str, props, count: int) -> str:
    head = ["ply", f"format {fmt} 1.0", f"element vertex {count}"]
    head += [f"property {t} {n}" for n, t in props] + ["end_header"]
    return "\n".join(head) + "\n"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_bit_exact(tmp_path, degree):
    extra = {"label": np.arange(50, dtype=np.uint8), "confidence": np.linspace(0, 1, 50)}
    first = tmp_path / "a.ply"
    write_gaussian_ply(first, make_data(degree=degree, extra=extra))
    data = read_gaussian_ply(first)
    assert data.sh_degree == degree and data.sh.shape == (50, (degree + 1) ** 2, 3)
    assert data.extra["label"].dtype == np.uint8 and data.extra["confidence"].dtype == np.float64
    second = tmp_path / "b.ply"
    write_gaussian_ply(second, data)
    assert first.read_bytes() == second.read_bytes()


def test_sh_coefficients_are_channel_major_like_inria(tmp_path):
    """f_rest_0..K-2 hold red for bands ≥ 1, then green, then blue."""
    data = make_data(n=3, degree=1)
    path = tmp_path / "g.ply"
    write_gaussian_ply(path, data)
    raw = np.frombuffer(path.read_bytes()[path.read_bytes().index(b"end_header\n") + 11:],
                        dtype=np.float32).reshape(3, -1)
    # default layout: x y z nx ny nz f_dc_0..2 f_rest_0..8 ...
    np.testing.assert_array_equal(raw[:, 6:9], data.sh[:, 0, :])
    np.testing.assert_array_equal(raw[:, 9:12], data.sh[:, 1:, 0])   # red
    np.testing.assert_array_equal(raw[:, 15:18], data.sh[:, 1:, 2])  # blue


def test_ascii_and_big_endian_read_the_same_values(tmp_path):
    binary = tmp_path / "bin.ply"
    write_gaussian_ply(binary, make_data(n=7, degree=1))
    ref = read_gaussian_ply(binary)
    raw = binary.read_bytes()
    src = np.frombuffer(raw[raw.index(b"end_header\n") + 11:],
                        dtype=np.dtype([(n, "<f4") for n, _ in ref.layout]))
    big = tmp_path / "big.ply"
    big.write_bytes(header_text("binary_big_endian", ref.layout, 7).encode()
                    + src.astype([(n, ">f4") for n, _ in ref.layout]).tobytes())
    rows = "\n".join(" ".join(repr(float(src[n][i])) for n, _ in ref.layout) for i in range(7))
    asc = tmp_path / "asc.ply"
    asc.write_text(header_text("ascii", ref.layout, 7) + rows + "\n")
    for other in (read_gaussian_ply(big), read_gaussian_ply(asc)):
        for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(other, field), getattr(ref, field))


def test_real_donut_round_trips_bit_exact(tmp_path):
    path = shared_data("gaussians", "donut_fused.ply")
    data = read_gaussian_ply(path)
    assert data.num == DONUT_COUNT and data.sh_degree == 0
    assert is_gaussian_ply(path)
    out = tmp_path / "donut.ply"
    write_gaussian_ply(out, data)
    assert out.read_bytes() == path.read_bytes()


# --- malformed input: each names the file, the field and what was expected -------------


def written(tmp_path, data=None) -> tuple:
    path = tmp_path / "scene.ply"
    write_gaussian_ply(path, data or make_data(n=20, degree=1))
    return path, path.read_bytes()


def test_truncated_file(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw[:-10])
    with pytest.raises(SceneInputError, match=r"scene\.ply: element vertex: truncated: .*20 vertices"):
        read_gaussian_ply(path)


def test_truncated_header(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw[:40])
    with pytest.raises(SceneInputError, match="end_header"):
        read_gaussian_ply(path)


def test_missing_required_property(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw.replace(b"property float scale_2\n", b"property float other_2\n"))
    with pytest.raises(SceneInputError, match=r"scene\.ply: vertex property 'scale_2': missing"):
        read_gaussian_ply(path)


@pytest.mark.parametrize("field,bad", [("log_scales", np.nan), ("means", np.inf),
                                       ("opacity_logits", -np.inf), ("sh", np.nan)])
def test_non_finite_values(tmp_path, field, bad):
    data = make_data(n=20, degree=1)
    arr = getattr(data, field).copy()
    arr.reshape(20, -1)[13, -1] = bad
    path, _ = written(tmp_path, GaussianSplatData(**{**data.__dict__, field: arr}))
    with pytest.raises(SceneInputError, match=r"vertex 13 property '.*'.*expected a finite number"):
        read_gaussian_ply(path)
    kept = read_gaussian_ply(path, allow_non_finite=True)  # what load_scene reads, then drops
    assert np.flatnonzero(degenerate_mask(kept)).tolist() == [13]


def test_wrong_number_of_sh_fields(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw.replace(b"property float f_rest_8\n", b"property float unrelated\n"))
    with pytest.raises(SceneInputError, match=r"f_rest_\*.*8 fields.*0, 9, 24 or 45"):
        read_gaussian_ply(path)


def test_not_a_ply_and_list_properties(tmp_path):
    path = tmp_path / "x.ply"
    path.write_text("solid mesh\n")
    with pytest.raises(SceneInputError, match="magic line 'ply'"):
        read_gaussian_ply(path)
    path.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n1 0\n")
    with pytest.raises(SceneInputError, match="list properties"):
        read_gaussian_ply(path)
    assert not is_gaussian_ply(path)


GAUSSIAN_FIELDS = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                   "rot_0", "rot_1", "rot_2", "rot_3")


def ascii_file(tmp_path, n=4, rows=None, extra_header="", labels=None) -> tuple:
    """An ascii Gaussian PLY (SH degree 0) of ``make_data``'s values; ``rows`` replaces its value
    rows, ``labels`` adds a uchar column."""
    data = make_data(n=n, degree=0)
    layout = [(name, "float") for name in GAUSSIAN_FIELDS] + ([("label", "uchar")] if labels else [])
    values = np.concatenate([data.means, data.sh[:, 0], data.opacity_logits[:, None], data.log_scales,
                             data.quats], axis=1)
    if rows is None:
        rows = [" ".join(repr(float(v)) for v in row) for row in values]
        rows = [f"{r} {v}" for r, v in zip(rows, labels)] if labels else rows
    head = header_text("ascii", layout, n).replace("end_header\n", extra_header + "end_header\n")
    path = tmp_path / "scene.ply"
    path.write_text(head + "\n".join(rows) + "\n")
    return path, rows, data


def refused(path, *fragments) -> str:
    """The one-line message a malformed file is refused with; checks it names the file."""
    with pytest.raises(SceneInputError) as err:
        read_gaussian_ply(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_zero_vertices_is_no_gaussians(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw[: raw.index(b"end_header\n") + 11].replace(b"element vertex 20", b"element vertex 0"))
    refused(path, "element vertex: 0 vertices: no Gaussians")
    path.write_text(header_text("ascii", [("x", "float")], 0))
    refused(path, "vertex property")  # the missing fields are named first


def test_count_smaller_than_the_data_is_trailing_data(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw.replace(b"element vertex 20", b"element vertex 19"))
    refused(path, "element vertex: trailing data beyond the declared count", "after the 19 vertices")
    path.write_bytes(raw + b"\x00")
    refused(path, "1 bytes after the 20 vertices")
    path, rows, _ = ascii_file(tmp_path, n=4)
    path.write_text(path.read_text() + rows[0] + "\n")
    refused(path, "trailing data beyond the declared count: 1 more data line from line 23")


def test_smaller_declared_type_is_refused(tmp_path):
    path, raw = written(tmp_path)  # float written, short declared: the rows no longer fill the file
    path.write_bytes(raw.replace(b"property float opacity", b"property short opacity"))
    refused(path, "trailing data beyond the declared count", "property type smaller")
    path, _, _ = ascii_file(tmp_path, n=2, labels=(7, 300))
    refused(path, "vertex row 1 (line 21) property 'label': 300 (expected a whole number in 0..255")
    path, _, _ = ascii_file(tmp_path, n=2, labels=(7, 2.5))
    refused(path, "vertex row 1 (line 21) property 'label': 2.5 (expected a whole number")
    path, _, _ = ascii_file(tmp_path, n=2, labels=(7, 255))
    assert read_gaussian_ply(path).extra["label"].tolist() == [7, 255]


def test_truncated_ascii(tmp_path):
    path, rows, _ = ascii_file(tmp_path, n=4)
    path.write_text(path.read_text().replace(rows[-1] + "\n", ""))
    refused(path, "element vertex: truncated: header declares 4 vertices, file has 3 data lines")


def test_short_and_long_ascii_rows_name_the_row(tmp_path):
    path, rows, _ = ascii_file(tmp_path, n=4)
    short = rows.copy()
    short[2] = short[2].rsplit(" ", 1)[0]
    ascii_file(tmp_path, n=4, rows=short)
    refused(path, "vertex row 2 (line 21): 13 values (expected 14, one per vertex property)")
    long = rows.copy()
    long[0] += " 1.0"
    ascii_file(tmp_path, n=4, rows=long)
    refused(path, "vertex row 0 (line 19): 15 values (expected 14")


def test_ascii_word_that_is_no_number(tmp_path):
    path, rows, _ = ascii_file(tmp_path, n=4)
    bad = rows.copy()
    bad[3] = " ".join(["1.0", "abc", *bad[3].split()[2:]])
    ascii_file(tmp_path, n=4, rows=bad)
    refused(path, "vertex row 3 (line 22) property 'y': 'abc' (expected a number)")


def test_ascii_values_beyond_float32_are_non_finite(tmp_path):
    path, rows, _ = ascii_file(tmp_path, n=4)
    big = rows.copy()
    big[1] = " ".join(["1e40", *big[1].split()[1:]])
    ascii_file(tmp_path, n=4, rows=big)
    refused(path, "vertex 1 property 'x': value inf (expected a finite number within float32 range")
    data = read_gaussian_ply(path, allow_non_finite=True)
    assert degenerate_counts(data) == {"non-finite mean": 1}


def test_double_values_beyond_float32_are_non_finite(tmp_path):
    data = make_data(n=5, degree=0)
    layout = [(n, "double" if n in "xyz" else "float") for n in GAUSSIAN_FIELDS]
    table = np.zeros(5, [(n, "<f8" if t == "double" else "<f4") for n, t in layout])
    for name, values in (("x", data.means[:, 0]), ("opacity", data.opacity_logits), ("rot_0", data.quats[:, 0])):
        table[name] = values
    table["y"][2] = 1e300
    path = tmp_path / "scene.ply"
    path.write_bytes(header_text("binary_little_endian", layout, 5).encode() + table.tobytes())
    refused(path, "vertex 2 property 'y': value 1e+300 (expected a finite number within float32 range")
    assert degenerate_counts(read_gaussian_ply(path, allow_non_finite=True)) == {"non-finite mean": 1}


@pytest.mark.parametrize("old,new,fragments", [
    (b"property float x\n", b"propertyfloat x\n", ("header line 4: 'propertyfloat x' (expected a 'format'",)),
    (b"property float x\n", b"property half x\n", ("header line 4: 'property half x' (expected 'property TYPE NAME'",)),
    (b"property float x\n", b"property float\n", ("header line 4: 'property float'",)),
    (b"binary_little_endian 1.0", b"binary_middle_endian 1.0", ("header line 2", "expected 'format FORMAT 1.0'")),
    (b"binary_little_endian 1.0", b"ascii 2.0", ("header line 2", "expected 'format FORMAT 1.0'")),
    (b"element vertex 20", b"element vertex 2O", ("header line 3: 'element vertex 2O' (expected 'element NAME COUNT')",)),
    (b"element vertex 20", b"element vertex " + b"9" * 5000, ("header line 3", "expected 'element NAME COUNT'")),
    (b"element vertex 20", b"element vertex -3", ("header line 3",)),
    (b"property float nx\n", b"property float x\n", ("vertex property 'x': declared twice (header lines 4 and 7)",)),
    (b"property float nx\n", b"property list uchar int nx\n", ("vertex property 'nx': list properties",)),
    (b"property float nx\n", b"property float n\xc3\xa9\n", ("header line 7", "printable ASCII")),
    (b"property float nx\n", b"property float n\x00x\n", ("header line 7", "printable ASCII")),
    (b"format binary_little_endian 1.0\n", b"", ("header: no 'format' line",)),
    (b"format binary_little_endian 1.0\n", b"format binary_little_endian 1.0\nformat ascii 1.0\n",
     ("header line 3: a second 'format' line",)),
    (b"element vertex 20\n", b"", ("header line 3: 'property' before any 'element' line",)),
    (b"element vertex 20\n", b"element face 0\nelement vertex 20\n", ("element vertex: expected 'vertex' as the first",)),
    (b"end_header\n", b"element vertex 1\nend_header\n", ("element vertex: declared twice",)),
    (b"property float rot_3\n", b"property float rot3\n", ("vertex property 'rot_3': missing",)),
    (b"property float nx\n", b"property float f_rest_" + b"9" * 5000 + b"\n", ("'f_rest_*': 10 fields",)),
    (b"ply\n", b"plyx\n", ("header: not a PLY file",)),
    (b"end_header\n", b"end_headr\n", ("header: no 'end_header' line",)),
])
def test_broken_header_lines(tmp_path, old, new, fragments):
    path, raw = written(tmp_path)
    assert old in raw
    path.write_bytes(raw.replace(old, new, 1))
    refused(path, *fragments)


def test_header_without_end(tmp_path):
    path, raw = written(tmp_path)
    path.write_bytes(raw[: raw.index(b"end_header") + 10])
    refused(path, "header: truncated right after 'end_header'")
    path.write_bytes(raw.replace(b"end_header\n", b"end_headerX\n"))
    refused(path, "header: no 'end_header' line")


FACE = b"element face 2\nproperty list uchar int vertex_indices\nend_header\n"


def test_declared_elements_after_the_vertices_are_not_trailing_data(tmp_path):
    path, raw = written(tmp_path)
    ref = read_gaussian_ply(path)
    faces = b"".join(bytes([3]) + np.array(f, "<i4").tobytes() for f in ([0, 1, 2], [2, 3, 4]))
    path.write_bytes(raw.replace(b"end_header\n", FACE) + faces)
    np.testing.assert_array_equal(read_gaussian_ply(path).sh, ref.sh)
    path.write_bytes(raw.replace(b"end_header\n", FACE) + faces[:-3])
    refused(path, "element face: truncated: header declares 2 face rows")
    path.write_bytes(raw.replace(b"end_header\n", FACE) + faces + b"\x00\x00")
    refused(path, "element face: trailing data beyond the declared count: 2 bytes after the 2 face rows")
    path, rows, data = ascii_file(tmp_path, n=4, extra_header=FACE.decode().replace("end_header\n", ""))
    path.write_text(path.read_text() + "3 0 1 2\n3 1 2 3\n")
    np.testing.assert_array_equal(read_gaussian_ply(path).means, data.means)
    path.write_text(path.read_text() + "3 0 2 3\n")
    refused(path, "element face: trailing data beyond the declared count: 1 more data line from line 27")


def test_crlf_header_and_utf8_comment_read_and_round_trip(tmp_path):
    path, raw = written(tmp_path)
    ref = read_gaussian_ply(path)
    head, body = raw.split(b"end_header\n", 1)
    path.write_bytes(head.replace(b"\n", b"\r\n") + b"end_header\r\n" + body)
    np.testing.assert_array_equal(read_gaussian_ply(path).quats, ref.quats)
    path.write_bytes(raw.replace(b"element vertex", "comment made in Zürich\nelement vertex".encode()))
    again = tmp_path / "again.ply"
    write_gaussian_ply(again, read_gaussian_ply(path))
    assert again.read_bytes() == path.read_bytes()


# --- degenerate Gaussians: counted by reason, each under its first reason ------------------


def test_degenerate_gaussians_are_counted_by_their_first_reason():
    data = make_data(n=10, degree=1)
    means, quats, scales, sh = data.means.copy(), data.quats.copy(), data.log_scales.copy(), data.sh.copy()
    opacity = data.opacity_logits.copy()
    means[0, 2] = np.nan
    opacity[1] = np.inf
    scales[2, 0] = -np.inf
    quats[3] = 0.0
    quats[4, 1] = np.nan
    scales[5, 1] = MAX_ABS_LOG_SCALE + 1
    scales[6, 2] = -(MAX_ABS_LOG_SCALE + 20)
    sh[7, 3, 1] = np.nan
    quats[8] = 0.0  # and a huge scale too: counted once, as a zero quaternion
    scales[8] = 40.0
    scales[9] = MAX_ABS_LOG_SCALE  # at the bound: still sound
    bad = GaussianSplatData(means=means, quats=quats, log_scales=scales, opacity_logits=opacity, sh=sh)
    assert degenerate_mask(bad).tolist() == [True] * 9 + [False]
    assert degenerate_reasons(bad)[[0, 3, 7, 8]].tolist() == [REASONS.index(r) for r in (
        "non-finite mean", "zero quaternion", "non-finite SH", "zero quaternion")]
    counts = degenerate_counts(bad)
    assert counts == {"non-finite mean": 1, "non-finite opacity": 1, "non-finite scale": 1,
                      "non-finite quaternion": 1, "zero quaternion": 2, "|log-scale| > 20": 2,
                      "non-finite SH": 1}
    assert describe_counts({"zero quaternion": 3, "|log-scale| > 20": 9}) == "3 zero quaternion, 9 |log-scale| > 20"
    assert degenerate_counts(data) == {} and not degenerate_mask(data).any()


def test_failed_write_leaves_the_old_file_untouched(tmp_path):
    path, raw = written(tmp_path)
    with pytest.raises(RuntimeError):
        with atomic_write(path) as f:
            f.write(b"partial")
            raise RuntimeError("interrupted")
    assert path.read_bytes() == raw
    assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]


def test_written_files_get_the_mode_of_an_ordinary_new_file(tmp_path):
    import os
    import stat

    from phirie_jax.io.atomic import write_files, write_text

    old = os.umask(0o022)
    try:
        write_text(tmp_path / "a.json", "{}")
        write_files(tmp_path / "d", {"b.obj": b"v 0 0 0\n"})
        (tmp_path / "plain").write_text("x")
    finally:
        os.umask(old)
    expected = stat.S_IMODE((tmp_path / "plain").stat().st_mode)
    assert expected == 0o644
    for path in (tmp_path / "a.json", tmp_path / "d" / "b.obj"):
        assert stat.S_IMODE(path.stat().st_mode) == expected, path
