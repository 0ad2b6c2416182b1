"""INRIA 3D Gaussian Splatting PLY: read (binary LE/BE, ascii) and write (binary LE).

Fields: ``x y z``, ``f_dc_0..2``, ``f_rest_*`` (0, 9, 24 or 45 of them: SH degree
0–3, stored channel-major as in the INRIA code), ``opacity`` (logit),
``scale_0..2`` (log), ``rot_0..3`` (wxyz). Nerfstudio splatfacto and gsplat
exports use the same fields. Any other vertex property (normals, labels, ...)
is kept and written back, in its original order and type, so a read followed
by a write reproduces a binary little-endian file byte for byte.

The reader checks the whole file against its header (every declared element, no byte or
row more or less) and refuses anything else with one ``SceneInputError`` line naming the
file, the header line, element, property or row, and what was expected. Degenerate
Gaussians in a well-formed file (zero quaternions, absurd scales, NaN) are counted and
dropped by ``phirie_jax.io.gaussian_checks``.
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import atomic_write
from phirie_jax.io.gaussian_checks import FLOAT32_MAX
from phirie_jax.types import GaussianSplatData

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest_* fields → SH degree
MAX_HEADER_BYTES = 1 << 20


def _group(prefix: str, n: int) -> list[str]:
    return [f"{prefix}{i}" for i in range(n)]


REQUIRED = {
    "means": ["x", "y", "z"],
    "sh_dc": _group("f_dc_", 3),
    "opacity_logits": ["opacity"],
    "log_scales": _group("scale_", 3),
    "quats": _group("rot_", 4),
}


def default_layout(sh_degree: int, extra: dict[str, np.ndarray] | None = None) -> tuple:
    """The INRIA property order (normals included, as zeros, for viewers that expect them)."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    names = ["x", "y", "z", "nx", "ny", "nz", *_group("f_dc_", 3), *_group("f_rest_", rest),
             "opacity", *_group("scale_", 3), *_group("rot_", 4)]
    layout = [(n, "float") for n in names]
    for name, values in (extra or {}).items():
        if name not in names:
            layout.append((name, _type_token(values.dtype)))
    return tuple(layout)


def _type_token(dtype: np.dtype) -> str:
    for token, code in PLY_TYPES.items():
        if np.dtype(code) == np.dtype(dtype).newbyteorder("="):
            return token
    raise ValueError(f"no PLY type for dtype {dtype}")


# --- header ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: tuple[tuple[str, str], ...]  # (name, type token); a list is "list COUNT_TYPE ITEM_TYPE"

    @property
    def has_lists(self) -> bool:
        return any(token.startswith("list ") for _, token in self.properties)

    def dtype(self, order: str) -> np.dtype:
        """Row layout of an element of scalar properties; ``order`` is '<', '>' or '='."""
        return np.dtype([(n, order + PLY_TYPES[t]) for n, t in self.properties])


@dataclasses.dataclass(frozen=True)
class _Header:
    fmt: str
    elements: tuple[_Element, ...]  # in file order; the first is 'vertex'
    comments: tuple[str, ...]
    data_offset: int  # first byte after 'end_header\n'
    data_line: int    # file line number of the first data line (for ascii messages)

    @property
    def vertex_count(self) -> int:
        return self.elements[0].count

    @property
    def properties(self) -> tuple[tuple[str, str], ...]:
        return self.elements[0].properties

    @property
    def element_counts(self) -> tuple[tuple[str, int], ...]:
        return tuple((e.name, e.count) for e in self.elements)


def _header_lines(path: Path, raw: bytes) -> tuple[list[bytes], int]:
    """The header's lines after 'ply' and before 'end_header', and the offset of the data."""
    if not (raw.startswith(b"ply\n") or raw.startswith(b"ply\r\n")):
        raise SceneInputError(path, "header", "not a PLY file (expected the magic line 'ply')")
    lines, start = [], raw.index(b"\n") + 1
    while True:
        newline = raw.find(b"\n", start, MAX_HEADER_BYTES)
        if newline < 0:
            rest = raw[start:MAX_HEADER_BYTES].split()
            raise SceneInputError(path, "header", "truncated right after 'end_header'" if rest == [b"end_header"]
                                  else "no 'end_header' line (truncated or not a PLY)")
        line = raw[start:newline].rstrip(b"\r")
        if line.split() == [b"end_header"]:
            return lines, newline + 1
        lines.append(line)
        start = newline + 1


def _text(path: Path, number: int, line: bytes) -> str:
    """A header line (other than a comment) as text: printable ASCII, tabs allowed."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        text = "\0"
    if not text.replace("\t", " ").isprintable():
        raise SceneInputError(path, f"header line {number}",
                              f"{line[:60]!r} (expected a printable ASCII header line)")
    return text


def _format(path: Path, number: int, tokens: list[str], seen: str | None) -> str:
    if seen is not None:
        raise SceneInputError(path, f"header line {number}", "a second 'format' line (expected one)")
    if len(tokens) != 3 or tokens[1] not in FORMATS or tokens[2] not in ("1.0", "1"):
        raise SceneInputError(path, f"header line {number}",
                              f"{' '.join(tokens)[:60]!r} (expected 'format FORMAT 1.0' with FORMAT one of "
                              f"{', '.join(FORMATS)})")
    return tokens[1]


def _element(path: Path, number: int, tokens: list[str], elements: list[dict]) -> dict:
    """A new element from 'element NAME COUNT' (its properties follow)."""
    # at most 18 digits: more than any real count, and int() of it cannot hit Python's digit limit
    if len(tokens) != 3 or not tokens[2].isdigit() or len(tokens[2]) > 18:
        raise SceneInputError(path, f"header line {number}",
                              f"{' '.join(tokens)[:60]!r} (expected 'element NAME COUNT')")
    first = next((e for e in elements if e["name"] == tokens[1]), None)
    if first is not None:
        raise SceneInputError(path, f"element {tokens[1]}",
                              f"declared twice (header lines {first['line']} and {number})")
    return {"name": tokens[1], "count": int(tokens[2]), "properties": {}, "line": number}


def _property(path: Path, number: int, tokens: list[str], elements: list[dict]) -> None:
    """Adds 'property TYPE NAME' or 'property list COUNT_TYPE ITEM_TYPE NAME' to the last element."""
    if not elements:
        raise SceneInputError(path, f"header line {number}", "'property' before any 'element' line")
    if len(tokens) == 3 and tokens[1] in PLY_TYPES:
        name, token = tokens[2], tokens[1]
    elif (len(tokens) == 5 and tokens[1] == "list" and tokens[2] in PLY_TYPES and tokens[3] in PLY_TYPES
          and PLY_TYPES[tokens[2]][0] in "iu"):
        name, token = tokens[4], f"list {tokens[2]} {tokens[3]}"
    else:
        raise SceneInputError(path, f"header line {number}",
                              f"{' '.join(tokens)[:60]!r} (expected 'property TYPE NAME' or 'property list "
                              "INT_TYPE TYPE NAME', TYPE one of char uchar short ushort int uint float "
                              "double or int8..float64)")
    element = elements[-1]
    if name in element["properties"]:
        raise SceneInputError(path, f"{element['name']} property '{name}'",
                              f"declared twice (header lines {element['properties'][name][1]} and {number})")
    element["properties"][name] = (token, number)


def _read_header(path: Path, raw: bytes) -> _Header:
    lines, data_offset = _header_lines(path, raw)
    fmt, elements, comments = None, [], []
    for number, line in enumerate(lines, start=2):
        if line.split()[:1] in ([b"comment"], [b"obj_info"]):
            comments.append(line.decode("utf-8", errors="replace"))  # kept, never parsed
            continue
        tokens = _text(path, number, line).split()
        if not tokens:
            continue
        if tokens[0] == "format":
            fmt = _format(path, number, tokens, fmt)
        elif tokens[0] == "element":
            elements.append(_element(path, number, tokens, elements))
        elif tokens[0] == "property":
            _property(path, number, tokens, elements)
        else:
            raise SceneInputError(path, f"header line {number}", f"{' '.join(tokens)[:60]!r} (expected a "
                                  "'format', 'element', 'property' or 'comment' line)")
    if fmt is None:
        raise SceneInputError(path, "header", "no 'format' line (expected e.g. 'format binary_little_endian 1.0')")
    frozen = tuple(_Element(e["name"], e["count"], tuple((n, t) for n, (t, _) in e["properties"].items()))
                   for e in elements)
    if not frozen or frozen[0].name != "vertex":
        raise SceneInputError(path, "element vertex", "expected 'vertex' as the first element")
    for name, token in frozen[0].properties:
        if token.startswith("list "):
            raise SceneInputError(path, f"vertex property '{name}'",
                                  "list properties are not Gaussian fields (expected scalars)")
    return _Header(fmt, frozen, tuple(comments), data_offset, len(lines) + 3)


def read_ply_header_properties(path: str | Path) -> list[str]:
    """Vertex property names of a PLY, from the header alone."""
    path = Path(path)
    with open(path, "rb") as f:
        raw = f.read(65536)
    return [name for name, _ in _read_header(path, raw).properties]


def ply_element_counts(path: str | Path) -> dict[str, int]:
    """Element name → count from the header alone (e.g. a mesh's vertices and faces)."""
    path = Path(path)
    with open(path, "rb") as f:
        raw = f.read(65536)
    return dict(_read_header(path, raw).element_counts)


def is_gaussian_ply(path: str | Path) -> bool:
    """True when the PLY's vertices carry 3DGS fields (a splat, not a mesh or point cloud)."""
    try:
        names = set(read_ply_header_properties(path))
    except (SceneInputError, OSError):
        return False
    return {"f_dc_0", "opacity", "scale_0", "rot_0"} <= names


def _required_fields(path: Path, header: _Header) -> list[str]:
    """Checks, from the header, that every Gaussian field is there; the ``f_rest_*`` names in SH order."""
    names = [n for n, _ in header.properties]
    rest = sorted((n for n in names if n.startswith("f_rest_")),
                  key=lambda n: int(n[7:]) if n[7:].isdigit() and len(n) < 20 else -1)  # no digit-limit error
    if len(rest) not in REST_COUNTS or rest != _group("f_rest_", len(rest)):
        raise SceneInputError(path, "vertex properties 'f_rest_*'",
                              f"{len(rest)} fields (expected f_rest_0.. with 0, 9, 24 or 45 fields "
                              "for SH degree 0–3)")
    missing = [n for cols in REQUIRED.values() for n in cols if n not in names]
    if missing:
        raise SceneInputError(
            path, f"vertex property '{missing[0]}'",
            "missing (a 3DGS PLY needs x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3)")
    return rest


# --- binary data ----------------------------------------------------------------------


def _rows(element: _Element) -> str:
    """'20 vertices' or '3 face rows', for messages."""
    if element.name == "vertex":
        return f"{element.count} {'vertex' if element.count == 1 else 'vertices'}"
    return f"{element.count} {element.name} row{'' if element.count == 1 else 's'}"



def _walk_rows(path: Path, raw: bytes, offset: int, element: _Element, order: str) -> int:
    """End of an element with list properties, whose row lengths are in the data itself.

    Returns an offset past ``len(raw)`` as soon as the data runs out (each row takes at least
    one byte, so the walk never runs longer than the file).
    """
    steps = []
    for _, token in element.properties:
        parts = token.split()
        if parts[0] == "list":
            steps.append((struct.Struct(order + STRUCT_CODES[PLY_TYPES[parts[1]]]),
                          np.dtype(PLY_TYPES[parts[2]]).itemsize))
        else:
            steps.append((None, np.dtype(PLY_TYPES[token]).itemsize))
    for row in range(element.count):
        for counter, size in steps:
            if counter is None:
                offset += size
                continue
            if offset + counter.size > len(raw):
                return len(raw) + 1
            length = counter.unpack_from(raw, offset)[0]
            if length < 0:
                raise SceneInputError(path, f"element {element.name} row {row}",
                                      f"list length {length} (expected ≥ 0)")
            offset += counter.size + length * size
        if offset > len(raw):
            return offset
    return offset


def _binary_end(path: Path, raw: bytes, offset: int, element: _Element, order: str) -> int:
    """Offset just after ``element``'s rows, which start at ``offset``."""
    if element.has_lists:
        end = _walk_rows(path, raw, offset, element, order)
    else:
        end = offset + element.count * element.dtype(order).itemsize
    if end > len(raw):
        if element.has_lists or element.name != "vertex":
            raise SceneInputError(path, f"element {element.name}",
                                  f"truncated: header declares {_rows(element)}, the file ends "
                                  f"{'inside them' if element.has_lists else f'{end - len(raw)} bytes short'}")
        size = element.dtype(order).itemsize
        raise SceneInputError(
            path, "element vertex",
            f"truncated: header declares {element.count} vertices × {size} bytes"
            f" = {element.count * size} bytes, file has {len(raw) - offset} bytes of data")
    return end


def _binary_table(path: Path, raw: bytes, header: _Header) -> np.ndarray:
    order, vertex = FORMATS[header.fmt], header.elements[0]
    offset = header.data_offset
    for element in header.elements:
        offset = _binary_end(path, raw, offset, element, order)
    if offset < len(raw):
        last = header.elements[-1]
        raise SceneInputError(
            path, f"element {last.name}",
            f"trailing data beyond the declared count: {len(raw) - offset} bytes after the "
            f"{_rows(last)} (expected the file to end there; a count or a property type smaller "
            "than the data written gives this)")
    return np.frombuffer(raw, dtype=vertex.dtype(order), count=vertex.count, offset=header.data_offset)


# --- ascii data -----------------------------------------------------------------------


def _data_lines(path: Path, raw: bytes, header: _Header) -> list[tuple[int, str]]:
    """(file line number, text) of the vertex rows; checks the line count of every element."""
    text = raw[header.data_offset:].decode("ascii", errors="replace").split("\n")
    lines = [(header.data_line + i, line) for i, line in enumerate(text) if line.strip()]
    start = 0
    for element in header.elements:
        if len(lines) - start < element.count:
            raise SceneInputError(path, f"element {element.name}",
                                  f"truncated: header declares {_rows(element)}, "
                                  f"file has {len(lines) - start} data lines for them")
        start += element.count
    if start < len(lines):
        last, extra = header.elements[-1], len(lines) - start
        raise SceneInputError(
            path, f"element {last.name}",
            f"trailing data beyond the declared count: {extra} more data line{'s' * (extra > 1)} from "
            f"line {lines[start][0]} (expected the {_rows(last)}, then the end of the file)")
    return lines[: header.vertex_count]


def _row_field(lines: list[tuple[int, str]], row: int, name: str | None = None) -> str:
    field = f"vertex row {row} (line {lines[row][0]})"
    return field if name is None else f"{field} property '{name}'"


def _ascii_numbers(path: Path, lines: list[tuple[int, str]], names: list[str]) -> np.ndarray:
    """(N, P) float64 values of the vertex rows; each row must hold one number per property."""
    rows = [line.split() for _, line in lines]
    for row, values in enumerate(rows):
        if len(values) != len(names):
            raise SceneInputError(path, _row_field(lines, row),
                                  f"{len(values)} values (expected {len(names)}, one per vertex property)")
    try:
        return np.array(rows, dtype=np.float64)
    except ValueError:
        pass
    for row, values in enumerate(rows):
        for name, value in zip(names, values):
            try:
                float(value)
            except ValueError:
                raise SceneInputError(path, _row_field(lines, row, name),
                                      f"{value[:40]!r} (expected a number)") from None
    raise SceneInputError(path, "element vertex", "a value that is not a number (expected numbers)")


def _check_integers(path: Path, lines: list[tuple[int, str]], column: np.ndarray, name: str,
                    token: str) -> None:
    """An integer-typed property must hold whole numbers within its type's range."""
    info = np.iinfo(PLY_TYPES[token])
    with np.errstate(invalid="ignore"):
        bad = ~((column == np.round(column)) & (column >= info.min) & (column <= info.max))
    if bad.any():
        row = int(np.argmax(bad))
        raise SceneInputError(path, _row_field(lines, row, name),
                              f"{column[row]:g} (expected a whole number in {info.min}..{info.max} "
                              f"for type {token})")


def _ascii_table(path: Path, raw: bytes, header: _Header) -> np.ndarray:
    vertex = header.elements[0]
    lines = _data_lines(path, raw, header)
    values = _ascii_numbers(path, lines, [n for n, _ in vertex.properties])
    table = np.empty(vertex.count, dtype=vertex.dtype("="))
    for i, (name, token) in enumerate(vertex.properties):
        if PLY_TYPES[token][0] in "iu":
            _check_integers(path, lines, values[:, i], name, token)
        with np.errstate(over="ignore"):  # beyond float32 becomes inf: counted as non-finite later
            table[name] = values[:, i]
    return table


# --- read -----------------------------------------------------------------------------


def _vertex_table(path: Path, raw: bytes, header: _Header) -> np.ndarray:
    """The vertex rows as a structured array; the whole file is checked against the header."""
    if header.fmt == "ascii":
        return _ascii_table(path, raw, header)
    return _binary_table(path, raw, header)


def _column_group(path: Path, table: np.ndarray, names: list[str], allow_non_finite: bool) -> np.ndarray:
    dtype = np.result_type(*[table.dtype[n] for n in names], np.float32)
    out = np.stack([table[n].astype(dtype.newbyteorder("=")) for n in names], axis=-1)
    if allow_non_finite:
        return out
    bad_rows = ~(np.abs(out) <= FLOAT32_MAX).all(axis=-1)  # NaN compares False
    if bad_rows.any():
        row = int(np.argmax(bad_rows))
        col = int(np.argmax(~(np.abs(out[row]) <= FLOAT32_MAX)))
        raise SceneInputError(path, f"vertex {row} property '{names[col]}'",
                              f"value {out[row, col]} (expected a finite number within float32 range; "
                              f"{int(bad_rows.sum())} vertices affected)")
    return out


def read_gaussian_ply(path: str | Path, allow_non_finite: bool = False) -> GaussianSplatData:
    """Read an INRIA-format Gaussian PLY; raises ``SceneInputError`` on malformed input.

    The whole file is checked against its header: a count smaller than the data, or a property
    type smaller than the one written, is an error like a truncated file. A value that is NaN,
    infinite or beyond float32's range is an error too, unless ``allow_non_finite``: then it is
    returned, for ``phirie_jax.io.gaussian_checks`` to count and drop with the other degenerate
    Gaussians (what ``load_scene`` does).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise SceneInputError(path, None, f"cannot read ({err.strerror})") from None
    header = _read_header(path, raw)
    rest_names = _required_fields(path, header)
    if header.vertex_count == 0:
        raise SceneInputError(path, "element vertex", "0 vertices: no Gaussians (expected at least one)")
    table = _vertex_table(path, raw, header)
    groups = {key: _column_group(path, table, cols, allow_non_finite) for key, cols in REQUIRED.items()}
    n, k = header.vertex_count, len(rest_names) // 3 + 1
    dc = groups.pop("sh_dc")
    rest = (_column_group(path, table, rest_names, allow_non_finite) if rest_names
            else np.zeros((n, 0), dc.dtype))
    sh = np.concatenate([dc[:, None, :], rest.reshape(n, 3, k - 1).transpose(0, 2, 1)], axis=1)
    known = {c for cols in REQUIRED.values() for c in cols} | set(rest_names)
    extra = {name: table[name].astype(table.dtype[name].newbyteorder("="))
             for name, _ in header.properties if name not in known}
    return GaussianSplatData(
        means=groups["means"], quats=groups["quats"], log_scales=groups["log_scales"],
        opacity_logits=groups["opacity_logits"][:, 0], sh=sh, extra=extra,
        layout=header.properties, comments=header.comments,
    )


# --- write ----------------------------------------------------------------------------


def _columns(data: GaussianSplatData) -> dict[str, np.ndarray]:
    n, k = data.num, data.sh.shape[1]
    cols = {name: data.means[:, i] for i, name in enumerate("xyz")}
    cols.update({f"f_dc_{c}": data.sh[:, 0, c] for c in range(3)})
    rest = data.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))
    cols.update({f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])})
    cols["opacity"] = data.opacity_logits
    cols.update({f"scale_{i}": data.log_scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": data.quats[:, i] for i in range(4)})
    cols.update(data.extra)
    return cols


def write_gaussian_ply(path: str | Path, data: GaussianSplatData) -> None:
    """Write binary little-endian, atomically. Keeps ``data.layout`` when it still fits the data."""
    cols = _columns(data)
    layout = data.layout
    if not layout or {n for n, _ in layout} - set(cols) - {"nx", "ny", "nz"} or set(cols) - {
        n for n, _ in layout
    }:
        layout = default_layout(data.sh_degree, data.extra)
    table = np.zeros(data.num, dtype=[(n, "<" + PLY_TYPES[t]) for n, t in layout])
    for name, _ in layout:
        if name in cols:
            table[name] = cols[name]
    lines = ["ply", "format binary_little_endian 1.0", *data.comments,
             f"element vertex {data.num}", *[f"property {t} {n}" for n, t in layout], "end_header"]
    with atomic_write(path) as f:
        f.write(("\n".join(lines) + "\n").encode("utf-8"))  # comments may be UTF-8
        f.write(table.tobytes())
