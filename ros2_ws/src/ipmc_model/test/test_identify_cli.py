import json
import re

import numpy as np
import pytest

from ipmc_driver.dataio import load_record
from ipmc_model.identify_cli import evaluate_main, identify_main
from ipmc_model.persistence import FORMAT_VERSION, load_model, save_model
from ipmc_model.play import PrandtlIshlinskii


@pytest.fixture(scope="module")
def csvs(tmp_path_factory, hyst_data):
    from ipmc_driver.dataio import Record, save_csv

    u, y = hyst_data
    d = tmp_path_factory.mktemp("data")
    t = np.arange(u.size) * 0.01
    train, test = d / "train.csv", d / "test.csv"
    save_csv(Record(t[:800], u[:800], y[:800]), train)
    save_csv(Record(t[:400], u[800:], y[800:]), test)
    return train, test


def test_identify_and_evaluate_lssvm_narx(tmp_path, csvs, capsys):
    train, test = csvs
    model = tmp_path / "m.json"
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "abc",
                        "--budget", "3x2", "--input-lags", "3", "--output-lags", "3",
                        "--lag-step", "1", "--folds", "1", "--out", str(model)])
    assert rc == 0
    out, err = capsys.readouterr()
    assert "ABC cycle 2/2" in err
    assert "training free-run: RMSE" in out and "training one-step: RMSE" in out
    out_json = tmp_path / "metrics.json"
    plots = tmp_path / "plots"
    rc = evaluate_main(["--model", str(model), "--data", str(test), "--json", str(out_json),
                        "--plots", str(plots)])
    assert rc == 0
    doc = json.loads(out_json.read_text())
    assert set(doc) == {"free_run", "one_step", "units", "samples_skipped",
                        "unlike_identification"}
    for mode in ("free_run", "one_step"):
        assert set(doc[mode]) == {"rmse", "nrmse", "fit_percent", "max_abs"}
    assert doc["units"] == "mm" and doc["samples_skipped"] == 3
    assert {p.name for p in plots.iterdir()} == {"measured_vs_model.png", "error.png",
                                                  "hysteresis.png"}


def test_identify_pi_and_inverse(tmp_path, csvs):
    train, test = csvs
    rc = identify_main(["--data", str(train), "--model", "pi", "--out", str(tmp_path / "pi")])
    assert rc == 0
    assert load_model(tmp_path / "pi.json").inverse() is not None
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--inverse",
                        "--tune", "none", "--C", "100", "--sigma", "2",
                        "--out", str(tmp_path / "inv.json")])
    assert rc == 0
    inv = load_model(tmp_path / "inv.json")
    assert inv.input_lags == 0  # default inverse: no voltage feedback
    u_free = inv.stepper()
    assert np.isfinite(u_free.step(0.5))
    rc = evaluate_main(["--model", str(tmp_path / "inv.json"), "--data", str(test),
                        "--json", str(tmp_path / "inv_metrics.json")])
    assert rc == 0
    assert json.loads((tmp_path / "inv_metrics.json").read_text())["units"] == "V"


def test_identify_bad_data_is_one_clear_error(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,u,y\n0,1,nan\n0.01,1,2\n")
    rc = identify_main(["--data", str(bad), "--model", "pi", "--out", str(tmp_path / "x")])
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ipmc identify: error:") and "\n" not in err


def test_evaluate_corrupt_model_is_one_clear_error(tmp_path, csvs, capsys):
    _, test = csvs
    bad = tmp_path / "model.json"
    bad.write_text("{}")
    rc = evaluate_main(["--model", str(bad), "--data", str(test)])
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert "not an ipmc-ros model file" in err and "\n" not in err


def test_identify_bad_budget_is_usage_error(tmp_path, csvs):
    train, _ = csvs
    with pytest.raises(SystemExit):
        identify_main(["--data", str(train), "--model", "lssvm-narx", "--budget", "lots",
                       "--out", str(tmp_path / "m")])


def test_identify_lag_step_list_and_auto_flags(tmp_path, csvs, capsys):
    train, _ = csvs
    model = tmp_path / "m.json"
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--budget", "2x1",
                        "--lag-step", "1,5", "--folds", "2", "--out", str(model)])
    assert rc == 0
    assert "lag step" in capsys.readouterr().out
    assert load_model(model).lag_step in (1, 5)
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "none",
                        "--lag-step", "auto", "--out", str(model)])
    assert rc == 1
    assert "needs tuning" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        identify_main(["--data", str(train), "--model", "lssvm-narx", "--lag-step", "x",
                       "--out", str(model)])


def test_identify_defaults_search_lag_step_with_folds(tmp_path, csvs, capsys):
    from ipmc_model.identify_cli import DEFAULT_LAGS
    from ipmc_model.tuning import DEFAULT_LAG_STEPS

    train, _ = csvs
    model = tmp_path / "m.json"
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--budget", "2x1",
                        "--out", str(model)])
    assert rc == 0
    assert f"ABC cycle {len(DEFAULT_LAG_STEPS)}/{len(DEFAULT_LAG_STEPS)}" in \
        capsys.readouterr().err
    m = load_model(model)
    assert m.lag_step in DEFAULT_LAG_STEPS and m.output_lags == DEFAULT_LAGS
    # --tune none keeps the old default spacing 1
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "none",
                        "--out", str(model)])
    assert rc == 0 and load_model(model).lag_step == 1


def test_identify_inverse_memory_taus(tmp_path, csvs, capsys):
    train, _ = csvs
    base = ["--data", str(train), "--model", "lssvm-narx", "--inverse", "--tune", "none",
            "--C", "100", "--sigma", "2"]
    rc = identify_main(base + ["--memory-taus", "0.5,2", "--out", str(tmp_path / "inv")])
    assert rc == 0
    inv = load_model(tmp_path / "inv.json")
    assert inv.memory_taus_s == (0.5, 2.0)
    assert inv.dt_s == pytest.approx(0.01)  # from the record's rate
    assert np.isfinite(inv.stepper().step(0.5))
    # Tuning sees the same channels as the final fit.
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--inverse",
                        "--budget", "3x2", "--folds", "1", "--lag-step", "2",
                        "--memory-taus", "1", "--out", str(tmp_path / "tuned")])
    assert rc == 0
    assert load_model(tmp_path / "tuned.json").memory_taus_s == (1.0,)
    for bad in ("0", "-1", "x", ""):
        with pytest.raises(SystemExit):
            identify_main(base + ["--memory-taus", bad, "--out", str(tmp_path / "bad")])
    capsys.readouterr()
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "none",
                        "--C", "100", "--sigma", "2", "--memory-taus", "1",
                        "--out", str(tmp_path / "fwd")])
    assert rc == 1
    assert "--inverse" in capsys.readouterr().err


def test_identify_builds_a_forward_model_with_voltage_channels(tmp_path, csvs, capsys):
    train, test = csvs
    out = tmp_path / "fwd.json"
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "none",
                        "--C", "1e4", "--sigma", "2", "--input-memory-taus", "0.3", "0.5",
                        "--no-raw-voltage", "--output-lags", "0", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    stdout = capsys.readouterr().out
    assert "training free-run: RMSE" in stdout
    m = load_model(out)
    assert m.uses_voltage_channels and m.include_voltage is False
    assert tuple(m.input_memory_taus_s) == (0.3, 0.5) and m.dt_s == pytest.approx(0.01)
    assert m.input_lags == 0 and m.output_lags == 0 and m.n_inputs_ == 2
    doc = json.loads(out.read_text())
    assert doc["format_version"] == FORMAT_VERSION
    assert doc["model"]["params"]["input_memory_taus_s"] == [0.3, 0.5]
    # The training free run it reported is the model's own free run of the raw voltage.
    from ipmc_driver.dataio import load_record

    rec = load_record(train)
    rmse = np.sqrt(np.mean((m.simulate(rec.u_v) - rec.y_mm) ** 2))
    assert doc["metadata"]["training_metrics"]["free_run"]["rmse"] == pytest.approx(rmse)
    assert rmse < 0.2 * np.std(rec.y_mm)
    # the kind of input it was identified on, which ipmc diagnose --model checks a record against
    from ipmc_model.excitation import input_kind, model_input_kind

    assert doc["metadata"]["input_kind"] == pytest.approx(input_kind(rec.u_v, rec.rate_hz))
    assert model_input_kind(m) == pytest.approx(doc["metadata"]["input_kind"])
    # Comma lists work too; with the voltage kept, three channels.
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "none",
                        "--C", "1e4", "--sigma", "2", "--input-memory-taus", "0.3,0.5",
                        "--out", str(tmp_path / "fwd3.json")])
    assert rc == 0
    assert load_model(tmp_path / "fwd3.json").n_inputs_ == 3
    assert evaluate_main(["--model", str(out), "--data", str(test)]) == 0


@pytest.mark.parametrize("extra, message", [
    (["--no-raw-voltage"], "--no-raw-voltage needs --input-memory-taus"),
    (["--input-memory-taus", "0.3", "--inverse"], "is for a forward model"),
])
def test_identify_refuses_bad_voltage_channel_options(tmp_path, csvs, capsys, extra, message):
    train, _ = csvs
    argv = ["--data", str(train), "--model", "lssvm-narx", "--tune", "none", "--C", "10",
            "--sigma", "2", "--out", str(tmp_path / "x.json")]
    rc = identify_main(argv + extra)
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ipmc identify: error:") and message in err and "\n" not in err


def test_identify_tunes_a_forward_model_with_voltage_channels(tmp_path, csvs, capsys):
    train, _ = csvs
    out = tmp_path / "fwd.json"
    rc = identify_main(["--data", str(train), "--model", "lssvm-narx", "--tune", "abc",
                        "--budget", "3x2", "--folds", "1", "--input-memory-taus", "0.3", "0.5",
                        "--no-raw-voltage", "--out", str(out)])
    assert rc == 0
    out_text, err = capsys.readouterr()
    assert "ABC cycle 2/2" in err and "tuned: C = " in out_text
    m = load_model(out)
    doc = json.loads(out.read_text())
    assert m.uses_voltage_channels and m.n_inputs_ == 2 and m.output_lags == 0
    assert m.regressor_.C == pytest.approx(doc["metadata"]["tuning"]["C"])
    assert m.regressor_.sigma == pytest.approx(doc["metadata"]["tuning"]["sigma"])


def test_identify_refuses_nonpositive_input_memory_taus(tmp_path, csvs, capsys):
    train, _ = csvs
    with pytest.raises(SystemExit) as info:
        identify_main(["--data", str(train), "--model", "lssvm-narx", "--out",
                       str(tmp_path / "x.json"), "--input-memory-taus", "0.3", "-1"])
    assert info.value.code == 2
    assert "positive seconds" in capsys.readouterr().err


def _augmented(path, csv, dt_s: float, effects):
    """An augmented model file (as ipmc diagnose writes model_after.json) around a small NARX
    fitted on the record ``csv``."""
    from ipmc_driver.dataio import load_record
    from ipmc_model.effects import AugmentedModel, Effect, save_augmented
    from ipmc_model.lssvm import LSSVMRegressor
    from ipmc_model.narx import NarxModel

    rec = load_record(csv)
    base = NarxModel(LSSVMRegressor(C=100.0, sigma=2.0), input_lags=3,
                     output_lags=3).fit(rec.u_v, rec.y_mm)
    return save_augmented(AugmentedModel(base, [Effect(n, **p) for n, p in effects], dt_s),
                          path)


def test_identify_inverse_with_effects_from_writes_the_feedforward(tmp_path, csvs, capsys):
    from ipmc_model.effects import AugmentedInverse, load_any_model

    train, test = csvs
    after = _augmented(tmp_path / "model_after.json", train, 0.01,
                       [("creep", {"tau_s": 2.0, "gain_mm_per_v": -0.2}),
                        ("drift", {"gain_loss_per_min": 0.0, "offset_mm_per_min": 0.5})])
    common = ["--data", str(train), "--model", "lssvm-narx", "--inverse", "--tune", "none",
              "--C", "100", "--sigma", "2"]
    assert identify_main([*common, "--effects-from", str(after),
                          "--out", str(tmp_path / "ff.json")]) == 0
    out, err = capsys.readouterr()
    assert "drift left out of the feedforward: a trend over the identification record" in err
    assert "effects undone: creep: tau_s = 2 s" in err
    assert "training free-run: RMSE" in out and " V," in out
    ff = load_any_model(tmp_path / "ff.json", 0.01)
    assert isinstance(ff, AugmentedInverse)
    assert ff.effect_names == ["creep"] and list(ff.left_out) == ["drift"]
    assert ff.metadata_["feedforward_effects"] == ["creep"]
    # the creep is undone around the inverse: not the plain inverse's voltages
    assert identify_main([*common, "--out", str(tmp_path / "plain.json")]) == 0
    plain = load_model(tmp_path / "plain.json")
    y = np.linspace(0.0, 1.0, 300)
    assert np.max(np.abs(ff.simulate(y) - plain.simulate(y))) > 0.01
    rc = evaluate_main(["--model", str(tmp_path / "ff.json"), "--data", str(test),
                        "--json", str(tmp_path / "m.json")])
    assert rc == 0
    assert json.loads((tmp_path / "m.json").read_text())["units"] == "V"


@pytest.mark.parametrize("case, message", [
    ("forward", "--effects-from with --model lssvm-narx makes a feedforward: add --inverse"),
    ("no effects", "has no effect a feedforward can undo (effects: delay)"),
    ("rate", "the model was identified at 50 Hz, the data are at 100 Hz"),
])
def test_identify_effects_from_refuses_what_gives_no_feedforward(tmp_path, csvs, capsys, case,
                                                                  message):
    train, _ = csvs
    after = _augmented(tmp_path / "after.json", train, 0.02 if case == "rate" else 0.01,
                       [("delay", {"delay_s": 0.05})] if case == "no effects" else
                       [("creep", {"tau_s": 2.0, "gain_mm_per_v": -0.2})])
    args = ["--data", str(train), "--model", "lssvm-narx", "--tune", "none",
            "--effects-from", str(after), "--out", str(tmp_path / "ff.json")]
    rc = identify_main(args if case == "forward" else [*args, "--inverse"])
    assert rc == 1
    err = capsys.readouterr().err
    assert message in err
    assert not (tmp_path / "ff.json").exists()


@pytest.mark.parametrize(("extra", "expected"), [
    (["--inverse"], {"C": 1e4, "sigma": 2.0, "input_lags": 0, "output_lags": 10,
                     "lag_step": 2, "memory_taus_s": (1.0,)}),
    (["--input-memory-taus", "0.3", "0.5", "--no-raw-voltage"], {"C": 1e6, "sigma": 1.0}),
])
def test_lssvm_narx_options_not_given_are_the_documented_recipe(tmp_path, csvs, capsys, extra,
                                                                 expected):
    train, _ = csvs
    out = tmp_path / "m.json"
    assert identify_main(["--data", str(train), "--model", "lssvm-narx", *extra,
                          "--out", str(out)]) == 0
    assert "ABC" not in capsys.readouterr().err  # no tuning: the recipe's C and sigma
    m = load_model(out)
    assert m.regressor_.C == expected.pop("C") and m.regressor_.sigma == expected.pop("sigma")
    for key, value in expected.items():
        assert getattr(m, key) == value


def test_identify_effects_from_a_gpi_refits_its_stages_and_inverts_them(tmp_path, csvs, capsys):
    """A diagnosis's model_after (a GPI with a delay, a dead zone and a creep) as the structure
    of a new model and of its feedforward."""
    from ipmc_model.hysteresis import GeneralizedPI, GpiInverse

    train, _ = csvs
    rec = load_record(train)
    src = GeneralizedPI(dt_s=rec.dt_s, delay_s=0.03, dead_zone_v=0.2, output_taus_s=(12.0,),
                        max_nfev=5).fit(rec.u_v, rec.y_mm)
    save_model(src, tmp_path / "after.json")
    out = tmp_path / "ff.json"
    assert identify_main(["--data", str(train), "--inverse", "--effects-from",
                          str(tmp_path / "after.json"), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "delay 0.03 s, dead zone 0.2 V, creep taus 12 s" in err
    ff = load_model(out)
    assert isinstance(ff, GpiInverse)
    m = ff.model
    assert (m.delay_samples_, m.dead_zone_v, m.output_taus_s) == (3, 0.2, (12.0,))


@pytest.mark.parametrize(("out", "why"), [
    ("folder", "--out {d}/folder is a folder; give a model file name"),
    ("named.json", "--out {d}/named.json is a folder"),
    ("file/m.json", "--out {d}/file/m.json: {d}/file is a file, not a folder"),
    ("m.npz", "--out {d}/m.npz: a model file is a .json name"),
])
def test_identify_refuses_an_output_it_cannot_write_before_fitting(tmp_path, csvs, capsys, out,
                                                                   why):
    train, _ = csvs
    d = tmp_path / "d"
    d.mkdir()
    (d / "folder").mkdir()
    (d / "named.json").mkdir()
    (d / "file").write_text("x")
    rc = identify_main(["--data", str(train), "--model", "pi", "--out", str(d / out)])
    assert rc == 1
    err = capsys.readouterr().err
    # refused before the fit: the error is all it printed
    assert err.startswith(f"ipmc identify: error: {why.format(d=d)}") and err.count("\n") == 1
    assert sorted(p.name for p in d.iterdir()) == ["file", "folder", "named.json"]
    assert list((d / "folder").iterdir()) == [] == list((d / "named.json").iterdir())


@pytest.mark.parametrize(("extra", "why"), [
    (["--json", "{d}"], "--json {d} is a folder; give a file name"),
    (["--json", "{d}/m.txt"], "--json {d}/m.txt: expected a .json file name"),
    (["--plots", "{d}/f"], "--plots {d}/f is a file; give a folder"),
])
def test_evaluate_refuses_an_output_it_cannot_write_before_work(tmp_path, csvs, capsys, extra,
                                                                why):
    train, test = csvs
    model = save_model(PrandtlIshlinskii(n_operators=4).fit(*_uy(train)), tmp_path / "pi")
    d = tmp_path / "d"
    d.mkdir()
    (d / "f").write_text("x")
    rc = evaluate_main(["--model", str(model), "--data", str(test),
                        *[e.format(d=d) for e in extra]])
    assert rc == 1
    out, err = capsys.readouterr()
    assert err.startswith(f"ipmc evaluate: error: {why.format(d=d)}") and out == ""
    assert err.count("\n") == 1
    assert sorted(p.name for p in d.iterdir()) == ["f"]


def _uy(path):
    rec = load_record(path)
    return rec.u_v, rec.y_mm


def test_evaluate_writes_its_json_whole(tmp_path, csvs):
    train, test = csvs
    model = save_model(PrandtlIshlinskii(n_operators=4).fit(*_uy(train)), tmp_path / "pi")
    out = tmp_path / "new" / "metrics.json"
    assert evaluate_main(["--model", str(model), "--data", str(test), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["units"] == "mm"
    assert sorted(p.name for p in out.parent.iterdir()) == ["metrics.json"]


@pytest.mark.parametrize("edit", ["offset", "weights"])
def test_evaluate_refuses_an_edited_model_file(tmp_path, csvs, capsys, edit):
    train, test = csvs
    assert identify_main(["--data", str(train), "--model", "pi", "--out",
                          str(tmp_path / "m.json")]) == 0
    path = tmp_path / "m.json"
    if edit == "offset":
        doc = json.loads(path.read_text())
        doc["model"]["offset"] = 1e6
        path.write_text(json.dumps(doc, indent=2))
        why = "the model file was changed or corrupted after it was written"
    else:
        npz = path.with_suffix(".npz")
        npz.write_bytes(npz.read_bytes().replace(b"weights", b"weightz"))
        why = "its arrays file m.npz was changed or corrupted"
    capsys.readouterr()
    assert evaluate_main(["--model", str(path), "--data", str(test)]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err.strip().startswith(f"ipmc evaluate: error: {path}: {why}")
    assert err.count("\n") == 1


def _scaled_csv(tmp_path, csv, name, u_gain=1.0, y_gain=1.0):
    from ipmc_driver.dataio import Record, save_csv

    rec = load_record(csv)
    return save_csv(Record(rec.t_s, rec.u_v * u_gain, rec.y_mm * y_gain), tmp_path / name)


def test_identify_and_evaluate_refuse_volts_no_ipmc_is_driven_at(tmp_path, csvs, capsys):
    train, test = csvs
    volts = _scaled_csv(tmp_path, train, "mv.csv", u_gain=100.0)
    out = tmp_path / "m.json"
    assert identify_main(["--data", str(volts), "--model", "pi", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"ipmc identify: error: {volts}: u reaches 250 V, far beyond the H-bridge's "
                   "3 V (looks like millivolts; ipmc expects V); --allow-implausible accepts it.")
    assert not out.exists()
    assert identify_main(["--data", str(volts), "--model", "pi", "--out", str(out),
                          "--allow-implausible"]) == 0
    assert "ipmc identify: warning: " in capsys.readouterr().err and out.exists()
    assert evaluate_main(["--model", str(out), "--data", str(volts)]) == 1
    assert "u reaches 250 V" in capsys.readouterr().err


def test_identify_and_evaluate_warn_of_a_record_in_metres(tmp_path, csvs, capsys):
    train, test = csvs
    metres = _scaled_csv(tmp_path, test, "metres.csv", y_gain=1e-3)
    model = save_model(PrandtlIshlinskii(n_operators=4).fit(*_uy(train)), tmp_path / "pi")
    assert evaluate_main(["--model", str(model), "--data", str(metres)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"^ipmc evaluate: warning: .*metres\.csv: y spans 0\.\d+ - looks like "
                     r"metres; ipmc expects mm", err, re.M)
