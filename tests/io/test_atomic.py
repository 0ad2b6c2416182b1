"""Write-then-rename: what a killed write leaves is recognised by its name and removed by the
next run, and nothing else is."""

from __future__ import annotations

import os

from phirie_jax.io.atomic import TEMPORARY_NAME, _stage, remove_temporaries, write_bytes


def test_the_temporary_a_killed_write_leaves_is_removed_and_nothing_else(tmp_path):
    fd, tmp = _stage(tmp_path, "background.ply")  # what a write killed before its rename leaves
    os.close(fd)
    write_bytes(tmp_path / "background.ply", b"done")
    others = ["background.ply", ".background.ply.tmp", "x.abcdefgh.tmp", ".x.abcdefgh.tmpx", ".x.ABCDEFGH.tmp"]
    for name in others[1:]:
        (tmp_path / name).write_text("theirs")
    (tmp_path / ".sub.abcdefgh.tmp").mkdir()  # a folder named like one is not one
    assert TEMPORARY_NAME.fullmatch(os.path.basename(tmp))
    assert remove_temporaries(tmp_path) == [tmp_path / os.path.basename(tmp)]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(others + [".sub.abcdefgh.tmp"])
    assert remove_temporaries(tmp_path / "missing") == []
