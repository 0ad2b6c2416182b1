"""INRIA 3D Gaussian Splatting PLY: read (binary LE/BE, ascii) and write (binary LE).

Fields: ``x y z``, ``f_dc_0..2``, ``f_rest_*`` (0, 9, 24 or 45 of them: SH degree
0–3, stored channel-major as in the INRIA code), ``opacity`` (logit),
``scale_0..2`` (log), ``rot_0..3`` (wxyz). Nerfstudio splatfacto and gsplat
exports use the same fields. Any other vertex property (normals, labels, ...)
is kept and written back, in its original order and type, so a read followed
by a write reproduces a binary little-endian file byte for byte.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import atomic_write
from phirie_jax.types import GaussianSplatData

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
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
class _Header:
    fmt: str
    vertex_count: int
    properties: tuple[tuple[str, str], ...]  # vertex (name, type token)
    comments: tuple[str, ...]
    data_offset: int
    element_counts: tuple[tuple[str, int], ...]  # every element, in file order


def _read_header(path: Path, raw: bytes) -> _Header:
    if not raw.startswith(b"ply"):
        raise SceneInputError(path, "header", "not a PLY file (expected the magic line 'ply')")
    end = raw.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise SceneInputError(path, "header", "no 'end_header' line (truncated or not a PLY)")
    newline = raw.find(b"\n", end)
    if newline < 0:
        raise SceneInputError(path, "header", "truncated right after 'end_header'")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements, comments = None, [], []
    for number, line in enumerate(lines[1:], start=2):
        tokens = line.split()
        if not tokens:
            continue
        key = tokens[0]
        if key == "format":
            if len(tokens) < 2 or tokens[1] not in FORMATS:
                raise SceneInputError(path, f"header line {number}",
                                      f"format {tokens[1:]} (expected one of {sorted(FORMATS)})")
            fmt = tokens[1]
        elif key in ("comment", "obj_info"):
            comments.append(line)
        elif key == "element":
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise SceneInputError(path, f"header line {number}", f"bad element line {line!r}")
            elements.append((tokens[1], int(tokens[2]), []))
        elif key == "property":
            if not elements:
                raise SceneInputError(path, f"header line {number}", "property before any element")
            if tokens[1] == "list":
                elements[-1][2].append((tokens[-1], "list"))
            elif len(tokens) != 3 or tokens[1] not in PLY_TYPES:
                raise SceneInputError(path, f"header line {number}",
                                      f"bad property line {line!r} (expected 'property TYPE NAME')")
            else:
                elements[-1][2].append((tokens[2], tokens[1]))
    if fmt is None:
        raise SceneInputError(path, "header", "no 'format' line")
    if not elements or elements[0][0] != "vertex":
        raise SceneInputError(path, "element vertex", "expected 'vertex' as the first element")
    _, count, props = elements[0]
    for name, token in props:
        if token == "list":
            raise SceneInputError(path, f"vertex property '{name}'",
                                  "list properties are not Gaussian fields (expected scalars)")
    counts = tuple((name, n) for name, n, _ in elements)
    return _Header(fmt, count, tuple(props), tuple(comments), newline + 1, counts)


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


# --- read -----------------------------------------------------------------------------


def _vertex_table(path: Path, raw: bytes, header: _Header) -> np.ndarray:
    names = [n for n, _ in header.properties]
    duplicates = {n for n in names if names.count(n) > 1}
    if duplicates:
        raise SceneInputError(path, f"vertex property '{sorted(duplicates)[0]}'", "declared twice")
    order = FORMATS[header.fmt]
    if order is not None:
        dtype = np.dtype([(n, order + PLY_TYPES[t]) for n, t in header.properties])
        need = header.vertex_count * dtype.itemsize
        have = len(raw) - header.data_offset
        if have < need:
            raise SceneInputError(
                path, "element vertex",
                f"truncated: header declares {header.vertex_count} vertices × {dtype.itemsize} bytes"
                f" = {need} bytes, file has {have} bytes of data")
        return np.frombuffer(raw, dtype=dtype, count=header.vertex_count, offset=header.data_offset)
    dtype = np.dtype([(n, "=" + PLY_TYPES[t]) for n, t in header.properties])
    text = raw[header.data_offset:].decode("ascii", errors="replace").split("\n")
    rows = [line.split() for line in text if line.strip()][: header.vertex_count]
    if len(rows) < header.vertex_count:
        raise SceneInputError(path, "element vertex",
                              f"truncated: header declares {header.vertex_count} vertices, "
                              f"file has {len(rows)} data lines")
    bad = next((i for i, r in enumerate(rows) if len(r) != len(names)), None)
    if bad is not None:
        raise SceneInputError(path, f"vertex {bad}",
                              f"{len(rows[bad])} values (expected {len(names)}: {' '.join(names)})")
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError as err:
        raise SceneInputError(path, "element vertex", f"unparsable number ({err})") from None
    table = np.empty(header.vertex_count, dtype=dtype)
    for i, name in enumerate(names):
        table[name] = values[:, i]
    return table


def _column_group(path: Path, table: np.ndarray, names: list[str]) -> np.ndarray:
    missing = [n for n in names if n not in table.dtype.names]
    if missing:
        raise SceneInputError(
            path, f"vertex property '{missing[0]}'",
            "missing (a 3DGS PLY needs x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3)")
    dtype = np.result_type(*[table.dtype[n] for n in names], np.float32)
    out = np.stack([table[n].astype(dtype.newbyteorder("=")) for n in names], axis=-1)
    bad_rows = ~np.isfinite(out).all(axis=-1)
    if bad_rows.any():
        row = int(np.argmax(bad_rows))
        col = int(np.argmax(~np.isfinite(out[row])))
        raise SceneInputError(path, f"vertex {row} property '{names[col]}'",
                              f"value {out[row, col]} (expected a finite number; "
                              f"{int(bad_rows.sum())} vertices affected)")
    return out


def read_gaussian_ply(path: str | Path) -> GaussianSplatData:
    """Read an INRIA-format Gaussian PLY; raises ``SceneInputError`` on malformed input."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise SceneInputError(path, None, f"cannot read ({err.strerror})") from None
    header = _read_header(path, raw)
    table = _vertex_table(path, raw, header)
    names = set(table.dtype.names)
    rest_names = sorted((n for n in names if n.startswith("f_rest_")),
                        key=lambda n: int(n[7:]) if n[7:].isdigit() else -1)
    num_rest = len(rest_names)
    if num_rest not in REST_COUNTS or rest_names != _group("f_rest_", num_rest):
        raise SceneInputError(path, "vertex properties 'f_rest_*'",
                              f"{num_rest} fields (expected f_rest_0.. with 0, 9, 24 or 45 fields "
                              "for SH degree 0–3)")
    groups = {key: _column_group(path, table, cols) for key, cols in REQUIRED.items()}
    n, k = header.vertex_count, num_rest // 3 + 1
    dc = groups.pop("sh_dc")
    rest = _column_group(path, table, rest_names) if num_rest else np.zeros((n, 0), dc.dtype)
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
        f.write(("\n".join(lines) + "\n").encode("ascii"))
        f.write(table.tobytes())
