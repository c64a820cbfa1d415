"""`ipmc simulate`: the offline plant, its flags (a public interface) and its CSV."""

import re

import numpy as np
import pytest

from ipmc_driver.cli import main as ipmc
from ipmc_driver.dataio import load_record


@pytest.mark.parametrize("kind", ["sine", "random-sine", "steps", "mixed"])
def test_simulate_writes_t_u_y_in_seconds_volts_mm(tmp_path, kind):
    out = tmp_path / "run.csv"
    assert ipmc(["simulate", "--input", kind, "--amplitude", "2", "--frequency", "0.5",
                 "--seconds", "10", "--seed", "3", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[0] == "t,u,y"
    rec = load_record(out)
    assert len(rec) == 1000
    np.testing.assert_allclose(np.diff(rec.t_s), 0.01, atol=1e-9)
    assert np.abs(rec.u_v).max() <= 2.0 + 1e-9 and np.ptp(rec.u_v) > 1.0
    assert np.ptp(rec.y_mm) > 0.5  # the tip moves, in millimetres


def test_simulate_is_reproducible_by_seed_and_effects_change_the_output(tmp_path):
    def run(name, *extra):
        path = tmp_path / f"{name}.csv"
        assert ipmc(["simulate", "--input", "steps", "--seconds", "60", "--seed", "4",
                     "--out", str(path), *extra]) == 0
        return load_record(path)

    a, b = run("a"), run("b")
    np.testing.assert_array_equal(a.y_mm, b.y_mm)
    both = run("both", "--effect", "creep", "delay")
    repeated = run("repeated", "--effect", "creep", "--effect", "delay")
    np.testing.assert_array_equal(both.y_mm, repeated.y_mm)
    assert np.abs(both.y_mm - a.y_mm).max() > 0.1


def test_simulate_refuses_an_unknown_effect(tmp_path, capsys):
    with pytest.raises(SystemExit):
        ipmc(["simulate", "--effect", "humidity", "--out", str(tmp_path / "x.csv")])
    assert "invalid choice: 'humidity'" in capsys.readouterr().err


def test_mixed_input_has_fast_slow_and_held_parts_in_every_cycle():
    from ipmc_driver.signals import mixed

    t, u = mixed(400.0, 100.0, 2.5, band_hz=(0.02, 0.8), seed=3, cycles=2)
    assert u.size == t.size == 40000 and np.abs(u).max() == pytest.approx(2.5)

    def top_hz(x):  # frequency below which 95 % of the power lies (windows are short)
        p = np.abs(np.fft.rfft(x - x.mean())) ** 2
        f = np.fft.rfftfreq(x.size, 0.01)
        return f[np.searchsorted(np.cumsum(p) / p.sum(), 0.95)]

    for c in range(2):  # each 200 s cycle: fast 100 s, slow 50 s, held 50 s
        cycle = u[c * 20000:(c + 1) * 20000]
        fast, slow, held = cycle[:10000], cycle[10000:15000], cycle[15000:]
        assert 0.3 < top_hz(fast) <= 0.8 and top_hz(slow) <= 0.2
        # Levels held 0.5-5 s: few changes, long runs of one value, high levels reached.
        changes = np.flatnonzero(np.diff(held)).size + 1
        assert 50 / 5 <= changes <= 50 / 0.5
        assert np.abs(held).max() > 1.5
    # The last 30 % (what a chronological split holds out) has held levels too.
    tail = u[28000:]
    assert np.mean(np.diff(tail) == 0) > 0.3
    np.testing.assert_array_equal(u, mixed(400.0, 100.0, 2.5, band_hz=(0.02, 0.8), seed=3,
                                           cycles=2)[1])
    assert not np.array_equal(u, mixed(400.0, 100.0, 2.5, band_hz=(0.02, 0.8), seed=4,
                                       cycles=2)[1])


def test_mixed_input_refuses_a_band_without_a_slow_quarter():
    from ipmc_driver.signals import mixed

    with pytest.raises(ValueError, match="band_hz"):
        mixed(60.0, band_hz=(0.3, 0.8))
    with pytest.raises(ValueError, match="cycles"):
        mixed(60.0, cycles=0)


@pytest.mark.parametrize(("out", "why"), [
    ("folder", r"--out .*folder is a folder; give a file name"),
    ("run.json", r"--out .*run\.json: expected a \.csv file name"),
    ("file/run.csv", r"--out .*file/run\.csv: .*file is a file, not a folder"),
])
def test_simulate_refuses_an_output_it_cannot_write_before_running(tmp_path, capsys, out, why):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("x")
    assert ipmc(["simulate", "--seconds", "5", "--out", str(tmp_path / out)]) == 1
    err = capsys.readouterr().err.strip()
    assert re.match(r"ipmc simulate: error: " + why, err) and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "folder"]
    assert list((tmp_path / "folder").iterdir()) == []


def test_simulate_bad_values_are_one_sentence_and_exit_1(tmp_path, capsys):
    assert ipmc(["simulate", "--rate-hz", "0", "--out", str(tmp_path / "r.csv")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ipmc simulate: error: ") and "\n" not in err
    assert not (tmp_path / "r.csv").exists()


def test_simulate_warns_of_a_record_in_the_wrong_scale(tmp_path, capsys):
    # plant parameters that give the tip in metres (gains 1000 times too small)
    from ipmc_driver.plant import default_params_path

    text = default_params_path().read_text()
    text = text.replace("gain_pos_mm_per_v: 1.89", "gain_pos_mm_per_v: 0.00189")
    text = text.replace("gain_neg_mm_per_v: 0.7953", "gain_neg_mm_per_v: 0.0007953")
    text = text.replace("noise_std_mm: 0.005", "noise_std_mm: 0.0")
    text = text.replace("resolution_mm: 0.01", "resolution_mm: 0.0")
    params = tmp_path / "metres.yaml"
    params.write_text(text)
    out = tmp_path / "r.csv"
    assert ipmc(["simulate", "--seconds", "10", "--params", str(params), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"ipmc simulate: warning: .*r\.csv: y spans .* - looks like metres", err)
    assert out.exists()
