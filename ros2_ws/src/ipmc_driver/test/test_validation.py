"""Tests of ipmc_driver.validation's output-path checks (as_signal is tested by its users)."""

import pytest

from ipmc_driver.validation import check_output_dir, check_output_file


def test_check_output_file_accepts_a_new_file_and_missing_folders(tmp_path):
    assert check_output_file(tmp_path / "a.csv", option="--out", suffixes=(".csv",)) == \
        tmp_path / "a.csv"
    deep = tmp_path / "x" / "y" / "a.CSV"
    assert check_output_file(deep, option="--out", suffixes=(".csv",)) == deep
    assert not (tmp_path / "x").exists()  # a check creates nothing
    (tmp_path / "old.csv").write_text("t,u,y\n")
    check_output_file(tmp_path / "old.csv", option="--out", suffixes=(".csv",))


@pytest.mark.parametrize(("name", "match"), [
    ("dir", r"^--out .*dir is a folder; give a file name, e.g. .*dir/out\.csv$"),
    ("a.json", r"^--out .*a\.json: expected a \.csv file name$"),
    ("a", r"^--out .*a: expected a \.csv file name$"),
    ("file/a.csv", r"^--out .*file/a\.csv: .*file is a file, not a folder$"),
    ("file/sub/a.csv", r"^--out .*file/sub/a\.csv: .*file is a file, not a folder$"),
])
def test_check_output_file_refuses_in_one_sentence(tmp_path, name, match):
    (tmp_path / "dir").mkdir()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=match):
        check_output_file(tmp_path / name, option="--out", suffixes=(".csv",))


def test_check_output_file_refuses_a_folder_it_cannot_write(tmp_path, monkeypatch):
    # os.access stands in for a read-only folder: root may write anywhere
    import ipmc_driver.validation as v

    monkeypatch.setattr(v.os, "access", lambda path, mode: False)
    with pytest.raises(ValueError, match=r"the folder .* cannot be written$"):
        check_output_file(tmp_path / "a.json", option="--json", suffixes=(".json",))


def test_check_output_dir(tmp_path):
    (tmp_path / "file").write_text("x")
    assert check_output_dir(tmp_path / "new", option="--plots") == tmp_path / "new"
    assert not (tmp_path / "new").exists()
    with pytest.raises(ValueError, match=r"^--plots .*file is a file; give a folder"):
        check_output_dir(tmp_path / "file", option="--plots")
    with pytest.raises(ValueError, match=r"file is a file, not a folder$"):
        check_output_dir(tmp_path / "file" / "sub", option="--plots")
