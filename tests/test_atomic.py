"""The atomic file output every writer goes through."""

from __future__ import annotations

import os
import stat

import pytest

from torchmorph._atomic import atomic_output


def test_writes_the_target_on_success(tmp_path):
    target = tmp_path / "out.txt"
    with atomic_output(target) as temporary:
        assert temporary.parent == tmp_path
        assert temporary.suffix == ".txt"
        assert not temporary.exists()
        temporary.write_text("new")
        assert not target.exists()  # nothing visible before the block ends
    assert target.read_text() == "new"
    assert [item.name for item in tmp_path.iterdir()] == ["out.txt"]


def test_failure_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")

    def write_half_then_fail():
        with atomic_output(target) as temporary:
            temporary.write_text("half")
            raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError, match="writer failed"):
        write_half_then_fail()
    assert target.read_text() == "old"
    assert [item.name for item in tmp_path.iterdir()] == ["out.txt"]


def test_a_writer_that_writes_nothing_is_an_error(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="nothing was written for"), atomic_output(target):
        pass
    assert target.read_text() == "old"


def test_permissions_follow_the_umask_not_tempfile(tmp_path):
    umask = os.umask(0o027)
    try:
        with atomic_output(tmp_path / "out.bin") as temporary:
            temporary.write_bytes(b"x")
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "out.bin").stat().st_mode) == 0o640


def test_suffix_override_and_missing_directory(tmp_path):
    with atomic_output(tmp_path / "out.vtu", suffix=".tmp") as temporary:
        assert temporary.suffix == ".tmp"
        temporary.write_bytes(b"x")
    assert (tmp_path / "out.vtu").read_bytes() == b"x"
    missing = tmp_path / "missing" / "out.vtu"
    with (
        pytest.raises(FileNotFoundError, match="path: directory .*does not exist"),
        atomic_output(missing),
    ):
        pass
