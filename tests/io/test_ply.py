"""INRIA 3DGS PLY: bit-exact round trips, SH layout, every malformed-input error."""

from __future__ import annotations

import numpy as np
import pytest

from phirie_jax.errors import SceneInputError
from phirie_jax.io.atomic import atomic_write
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
