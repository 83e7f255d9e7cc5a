import pytest

from hg.atomic import write_atomic


def test_write_atomic_replaces_whole_file_or_nothing(tmp_path):
    target = tmp_path / "results.csv"
    write_atomic(target, "old\n")
    with pytest.raises(TypeError):
        write_atomic(target, object())  # fails while writing: the old file must survive untouched
    assert target.read_text() == "old\n"
    write_atomic(target, b"new\n")
    assert target.read_text() == "new\n"
    assert [p.name for p in tmp_path.iterdir()] == ["results.csv"]  # no temporary file left behind
    assert target.stat().st_mode & 0o777 == 0o644
