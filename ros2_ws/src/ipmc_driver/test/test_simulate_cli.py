"""`ipmc simulate`: the offline plant, its flags (a public interface) and its CSV."""

import numpy as np
import pytest

from ipmc_driver.cli import main as ipmc
from ipmc_driver.dataio import load_record


@pytest.mark.parametrize("kind", ["sine", "random-sine", "steps"])
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
