import pytest

from avatar_motor.io.atomic import recover_folder, replace_folder, write_file


def _complete(folder):
    return (folder / "done").exists()


def test_a_failed_write_leaves_the_old_file_and_no_temporary():
    import tempfile
    from pathlib import Path
    d = Path(tempfile.mkdtemp())
    write_file(d / "f.txt", lambda tmp: tmp.write_text("old"))

    def broken(tmp):
        tmp.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_file(d / "f.txt", broken)
    assert (d / "f.txt").read_text() == "old" and [p.name for p in d.iterdir()] == ["f.txt"]


@pytest.mark.parametrize("left,expected", [
    ({"x.tmp": True, "x": True, "x.old": False}, "new"),  # killed after filling, before the swap
    ({"x.tmp": False, "x": True}, "live"),  # killed while filling
    ({"x.tmp": True, "x.old": True}, "new"),  # killed between the two renames
    ({"x.tmp": False, "x.old": True}, "old"),  # the new copy unfinished, the live one moved aside
    ({"x": True, "x.old": True}, "live"),  # killed before removing the old copy
])
def test_recovery_takes_the_newest_complete_copy_and_removes_the_rest(tmp_path, left, expected):
    tags = {"x.tmp": "new", "x": "live", "x.old": "old"}
    for name, done in left.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "tag").write_text(tags[name])
        if done:
            (tmp_path / name / "done").write_text("")
    got = recover_folder(tmp_path / "x", _complete)
    assert got == tmp_path / "x" and (got / "tag").read_text() == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x"]


def test_an_incomplete_fill_keeps_the_old_folder(tmp_path):
    replace_folder(tmp_path / "x", lambda t: (t / "done").write_text("1"), _complete)
    with pytest.raises(RuntimeError, match="incomplete"):
        replace_folder(tmp_path / "x", lambda t: (t / "other").write_text("2"), _complete)
    assert (tmp_path / "x" / "done").read_text() == "1" and sorted(p.name for p in tmp_path.iterdir()) == ["x"]
