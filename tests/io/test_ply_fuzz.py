"""The Gaussian PLY reader under mutated input: it returns consistent data or refuses the file
with one ``SceneInputError`` line naming it, never another exception (nor a warning).

Small valid files (binary little/big endian and ascii; SH degree 0–3; with or without normals,
extra properties and a face element after the vertices) are mutated the ways broken exports and
damaged copies are: truncated, bytes appended, inserted or overwritten, header counts and
property types changed, header lines deleted, duplicated or garbled, ascii rows cut, lengthened
or given words that are no numbers. Bounded (``max_examples``) so the file runs in seconds.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from phirie_jax.errors import SceneInputError
from phirie_jax.io.gaussian_checks import FLOAT32_MAX, degenerate_mask
from phirie_jax.io.ply import PLY_TYPES, read_gaussian_ply

FORMATS = ("binary_little_endian", "binary_big_endian", "ascii")
FUZZ = settings(max_examples=1000, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
VALID = settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
ODD_WORDS = ("abc", "nan", "-inf", "1e40", "1e400", "-", "0x1F", "300", "-1", "1.5", "1,5", "é", "")


def layout(degree: int, normals: bool, extra: bool) -> list[tuple[str, str]]:
    names = ["x", "y", "z", *(["nx", "ny", "nz"] if normals else []), "f_dc_0", "f_dc_1", "f_dc_2",
             *[f"f_rest_{i}" for i in range(3 * ((degree + 1) ** 2 - 1))], "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    props = [(n, "float") for n in names]
    return props + ([("label", "uchar"), ("confidence", "double")] if extra else [])


def encode(fmt: str, props, table: np.ndarray, faces: np.ndarray | None) -> bytes:
    """A PLY file of ``table`` (structured, one field per property) and optional triangles."""
    head = ["ply", f"format {fmt} 1.0", "comment fuzz", f"element vertex {len(table)}",
            *[f"property {t} {n}" for n, t in props]]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    out = ("\n".join(head + ["end_header"]) + "\n").encode()
    if fmt == "ascii":
        rows = [" ".join(repr(row[n].item()) for n, _ in props) for row in table]
        rows += [" ".join(map(str, [3, *f])) for f in (faces if faces is not None else [])]
        return out + ("\n".join(rows) + "\n").encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    out += table.astype([(n, order + PLY_TYPES[t]) for n, t in props]).tobytes()
    for face in faces if faces is not None else []:
        out += bytes([3]) + np.asarray(face, order + "i4").tobytes()
    return out


@st.composite
def valid_plys(draw) -> tuple[bytes, np.ndarray, int]:
    """(file bytes, the vertex table written, SH degree)."""
    n, degree = draw(st.integers(1, 5)), draw(st.integers(0, 3))
    fmt = draw(st.sampled_from(FORMATS))
    props = layout(degree, draw(st.booleans()), draw(st.booleans()))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    table = np.zeros(n, [(name, PLY_TYPES[t]) for name, t in props])
    for name, token in props:
        table[name] = rng.integers(0, 256, n) if token == "uchar" else rng.normal(size=n)
    faces = rng.integers(0, n, (draw(st.integers(1, 3)), 3)) if draw(st.booleans()) else None
    return encode(fmt, props, table, faces), table, degree


def split(raw: bytes) -> tuple[list[bytes], bytes]:
    """Header lines (with 'end_header') and the data after them."""
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].split(b"\n")[:-1], raw[end:]


def join(lines: list[bytes], data: bytes) -> bytes:
    return b"\n".join(lines) + b"\n" + data


def _position(draw, raw: bytes, end: int) -> int:
    """An offset in the header or (as often) in the data, up to ``len(raw) - end``."""
    data = raw.find(b"end_header\n") + len(b"end_header\n")
    low = draw(st.sampled_from([0, min(data, len(raw) - end)]))
    return draw(st.integers(low, len(raw) - end))


def _truncate(draw, raw):
    return raw[: _position(draw, raw, 1)]


def _append(draw, raw):
    return raw + draw(st.binary(min_size=1, max_size=24))


def _insert(draw, raw):
    at = _position(draw, raw, 0)
    return raw[:at] + draw(st.binary(min_size=1, max_size=8)) + raw[at:]


def _overwrite(draw, raw):
    at = _position(draw, raw, 1)
    patch = draw(st.binary(min_size=1, max_size=8))
    return raw[:at] + patch + raw[at + len(patch):]


def _count(draw, raw):
    lines, data = split(raw)
    picks = [i for i, line in enumerate(lines) if line.startswith(b"element ")]
    if not picks:  # an earlier mutation removed them
        return raw
    i = draw(st.sampled_from(picks))
    count = draw(st.one_of(st.integers(0, 8), st.sampled_from([10**9, 10**17, -1])))
    lines[i] = b" ".join(lines[i].split()[:2] + [str(count).encode()])
    return join(lines, data)


def _type(draw, raw):
    lines, data = split(raw)
    picks = [i for i, line in enumerate(lines) if line.startswith(b"property ")]
    if not picks:  # an earlier mutation removed them
        return raw
    i = draw(st.sampled_from(picks))
    token = draw(st.sampled_from([*PLY_TYPES, "half", "list uchar int", "list float int"]))
    lines[i] = b" ".join([b"property", token.encode(), lines[i].split()[-1]])
    return join(lines, data)


def _header_line(draw, raw):
    lines, data = split(raw)
    i = draw(st.integers(0, len(lines) - 1))
    action = draw(st.sampled_from(["delete", "duplicate", "garble", "swap"]))
    if action == "delete":
        del lines[i]
    elif action == "duplicate":
        lines.insert(i, lines[i])
    elif action == "swap":
        j = draw(st.integers(0, len(lines) - 1))
        lines[i], lines[j] = lines[j], lines[i]
    else:
        lines[i] = draw(st.binary(max_size=20).filter(lambda b: b"\n" not in b))
    return join(lines, data)


def _ascii_row(draw, raw):
    lines, data = split(raw)
    if len(lines) < 2 or b"ascii" not in lines[1]:  # an earlier mutation moved the format line
        return _overwrite(draw, raw)
    rows = data.split(b"\n")
    i = draw(st.integers(0, len(rows) - 1))
    words = rows[i].split()
    action = draw(st.sampled_from(["cut", "lengthen", "word", "drop row", "repeat row"]))
    if action == "cut" and words:
        words.pop(draw(st.integers(0, len(words) - 1)))
    elif action == "lengthen":
        words.append(b"0")
    elif action == "word" and words:
        words[draw(st.integers(0, len(words) - 1))] = draw(st.sampled_from(ODD_WORDS)).encode()
    elif action == "drop row":
        del rows[i]
        return join(lines, b"\n".join(rows))
    elif action == "repeat row":
        rows.insert(i, rows[i])
        return join(lines, b"\n".join(rows))
    rows[i] = b" ".join(words)
    return join(lines, b"\n".join(rows))


MUTATIONS = (_truncate, _append, _insert, _overwrite, _count, _type, _header_line, _ascii_row)


@st.composite
def mutated_plys(draw) -> bytes:
    raw = draw(valid_plys())[0]
    for _ in range(draw(st.integers(1, 3))):
        raw = draw(st.sampled_from(MUTATIONS))(draw, raw)
        if b"end_header\n" not in raw:
            break
    return raw


def read_or_refuse(path, raw: bytes, allow_non_finite: bool):
    """The data read, or None after checking the refusal is one line that names the file."""
    path.write_bytes(raw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy overflow/cast warning is a crack in the reader
        try:
            data = read_gaussian_ply(path, allow_non_finite=allow_non_finite)
        except SceneInputError as err:
            message = str(err)
            assert message.startswith(str(path)) and path.name in message, message
            assert not re.search(r"[\n\r]", message), message
            event(f"refused: {(err.field or 'file').split()[0]}")
            return None
    event("read")
    n = data.num
    assert n >= 1
    assert data.means.shape == (n, 3) and data.quats.shape == (n, 4) and data.log_scales.shape == (n, 3)
    assert data.opacity_logits.shape == (n,)
    assert data.sh.shape[0] == n and data.sh.shape[1] in (1, 4, 9, 16) and data.sh.shape[2] == 3
    assert all(values.shape == (n,) for values in data.extra.values())
    assert len(data.layout) == 3 * data.sh.shape[1] + 11 + len(data.extra)
    if not allow_non_finite:
        for field in (data.means, data.quats, data.log_scales, data.opacity_logits, data.sh):
            assert (np.abs(field) <= FLOAT32_MAX).all()
    assert degenerate_mask(data).shape == (n,)
    return data


@VALID
@given(valid_plys())
def test_valid_files_read_back_the_values_written(tmp_path, case):
    raw, table, degree = case
    data = read_or_refuse(tmp_path / "valid.ply", raw, allow_non_finite=False)
    assert data is not None, "a valid file was refused"
    assert data.num == len(table) and data.sh_degree == degree
    np.testing.assert_array_equal(data.means, np.stack([table[c] for c in "xyz"], axis=1))
    np.testing.assert_array_equal(data.quats[:, 3], table["rot_3"])
    np.testing.assert_array_equal(data.sh[:, 0, 2], table["f_dc_2"])
    if "label" in table.dtype.names:
        np.testing.assert_array_equal(data.extra["label"], table["label"])


@FUZZ
@given(mutated_plys(), st.booleans())
def test_mutated_files_are_read_consistently_or_refused_in_one_line(tmp_path, raw, allow_non_finite):
    read_or_refuse(tmp_path / "mutated.ply", raw, allow_non_finite)
