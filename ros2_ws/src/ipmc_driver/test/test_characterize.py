"""The default simulated plant reproduces the paper's Table 1 (the calibration contract)."""

import json

import pytest

from ipmc_driver.characterize import FREQUENCIES_HZ, characterize, main, paper_row


@pytest.fixture(scope="module")
def records():
    return characterize(seed=0)


def test_nine_conditions_in_the_papers_order(records):
    assert [(r["amplitude_v"], r["frequency_hz"]) for r in records] == [
        (a, f) for a in (1.0, 2.0, 3.0) for f in FREQUENCIES_HZ]


def test_every_range_within_20_percent_of_table_1(records):
    for r in records:
        paper = paper_row(r["amplitude_v"], r["frequency_hz"])[2]
        assert abs(r["range_mm"] - paper) <= 0.2 * paper, (r["amplitude_v"], r["frequency_hz"],
                                                          r["range_mm"], paper)


@pytest.mark.parametrize("amplitude", [2.0, 3.0])
def test_negative_side_larger_than_positive(records, amplitude):
    for r in records:
        if r["amplitude_v"] == amplitude:
            assert -r["lower_mm"] > r["upper_mm"]


@pytest.mark.parametrize("amplitude", [2.0, 3.0])
def test_range_largest_at_1_over_2pi_hz(records, amplitude):
    rows = {r["frequency_hz"]: r["range_mm"] for r in records if r["amplitude_v"] == amplitude}
    assert max(rows, key=rows.get) == FREQUENCIES_HZ[1]


def test_cli_writes_json_with_the_documented_keys(tmp_path, capsys):
    out = tmp_path / "t1.json"
    assert main(["--json", str(out), "--plots", str(tmp_path / "fig")]) == 0
    doc = json.loads(out.read_text())
    assert len(doc["conditions"]) == 9
    assert set(doc["conditions"][0]) == {"amplitude_v", "frequency_hz", "lower_mm", "upper_mm",
                                         "range_mm"}
    assert len(list((tmp_path / "fig").glob("*.png"))) == 10
    assert "paper" in capsys.readouterr().out
